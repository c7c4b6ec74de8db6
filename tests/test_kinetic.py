"""Kinetic-energy loss: plain likelihood when lambda2 = lambda3 = 0, exact value on a hand-made
flow, consistency with a real backend's layer outputs."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.errors import ConfigError
from pipeline.training.kinetic import KineticWeights, kinetic_loss, kinetic_loss_terms, path_lengths
from pipeline.models.maf import BACKENDS, ConditionalFlow, FlowConfig, build_flow



class ReverseAffineFlow(ConditionalFlow):
    """Layer l: y = a_l * reverse(x) + b_l, base N(0, I) (unconditional, untrained)."""

    def __init__(self, scales: np.ndarray, shifts: np.ndarray) -> None:
        super().__init__(FlowConfig(features=2, context_features=0, layers=len(scales)))
        self.scales = nn.Parameter(torch.tensor(scales))
        self.shifts = nn.Parameter(torch.tensor(shifts))

    def _forward_layer(self, index, x, context):
        y = self.scales[index] * x.flip(-1) + self.shifts[index]
        return y, torch.log(self.scales[index].abs()).sum().expand(x.shape[0])

    def _inverse_layer(self, index, z, context):
        return ((z - self.shifts[index]) / self.scales[index]).flip(-1)


def test_value_matches_a_hand_computation():
    scales = np.array([[2.0, 0.5], [1.5, 3.0], [0.25, 1.0]])
    shifts = np.array([[0.1, -0.2], [1.0, 0.0], [-0.5, 0.3]])
    flow = ReverseAffineFlow(scales, shifts).double()
    x = np.array([[0.3, -1.2], [2.0, 0.7], [-0.4, 0.0]])

    # by hand: f_0 = x, f_l = a_l * reverse(f_{l-1}) + b_l, L = 3
    f = [x]
    for a, b in zip(scales, shifts):
        f.append(a * f[-1][:, ::-1] + b)

    def log_normal(z):
        return -0.5 * (z ** 2).sum(1) - np.log(2 * np.pi)

    nll = -(log_normal(f[3]) + np.log(np.abs(scales)).sum()).mean()
    kinetic = np.mean([np.linalg.norm(f[2] - f[1], axis=1).mean(),    # l = 1
                       np.linalg.norm(f[3] - f[2], axis=1).mean()])   # l = 2 = L - 1
    prior = np.mean([-log_normal(f[1]).mean(), -log_normal(f[2]).mean()])
    weights = KineticWeights(nll=0.7, path_length=0.3, intermediate_nll=0.2)

    with torch.no_grad():
        terms = kinetic_loss_terms(flow, torch.tensor(x), torch.empty(3, 0, dtype=torch.float64),
                                   weights=weights)
    assert float(terms.nll) == pytest.approx(nll, rel=1e-12)
    assert float(terms.path_length) == pytest.approx(kinetic, rel=1e-12)
    assert float(terms.intermediate_nll) == pytest.approx(prior, rel=1e-12)
    assert float(terms.total) == pytest.approx(0.7 * nll + 0.3 * kinetic + 0.2 * prior, rel=1e-12)
    full_path = [np.linalg.norm(f[i + 1] - f[i], axis=1).mean() for i in range(3)]
    assert np.allclose(path_lengths([torch.tensor(v) for v in f]).numpy(), full_path)


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_kinetic_weights_is_exactly_maximum_likelihood(backend):
    torch.manual_seed(0)
    flow = build_flow(FlowConfig(3, 2, layers=3, hidden_features=6, backend=backend))
    x, context = torch.randn(16, 3), torch.randn(16, 2)
    loss = kinetic_loss(flow, x, context, weights=KineticWeights())
    assert torch.equal(loss, -flow.log_prob(x, context).mean())


@pytest.mark.parametrize("backend", BACKENDS)
def test_terms_agree_with_layer_outputs_of_a_real_flow(backend):
    """With a conditional base, the prior term scores f_1..f_{L-1} under the base with the
    sample's own context."""
    torch.manual_seed(1)
    flow = build_flow(FlowConfig(2, 2, layers=4, hidden_features=6, backend=backend)).double()
    x, context = torch.randn(32, 2, dtype=torch.float64), torch.randn(32, 2, dtype=torch.float64)
    outputs = flow.layer_outputs(x, context)
    kinetic = torch.stack([(outputs[l + 1] - outputs[l]).norm(dim=1).mean() for l in (1, 2, 3)])
    prior = torch.stack([-flow.base_log_prob(outputs[l], context).mean() for l in (1, 2, 3)])
    terms = kinetic_loss_terms(flow, x, context, weights=KineticWeights(1.0, 2.0, 3.0))
    assert torch.allclose(terms.path_length, kinetic.mean(), rtol=1e-12)
    assert torch.allclose(terms.intermediate_nll, prior.mean(), rtol=1e-12)
    assert torch.allclose(terms.nll, -flow.log_prob(x, context).mean(), rtol=1e-12)
    terms.total.backward()
    assert all(p.grad is not None and bool(torch.isfinite(p.grad).all())
               for p in flow.parameters())


def test_single_layer_flow_rejects_the_layer_averages():
    flow = build_flow(FlowConfig(2, 0, layers=1))
    with pytest.raises(ConfigError, match="L=1"):
        kinetic_loss(flow, torch.randn(4, 2), torch.empty(4, 0), weights=KineticWeights(1, 1, 0))
    with pytest.raises(ConfigError, match="path_length"):
        KineticWeights(path_length=-1.0)


def test_two_moons_lie_on_their_half_circles():
    from pipeline.demos.kinetic import MOONS_CENTRE, two_moons

    points, label = two_moons(2000, 0.0, np.random.default_rng(0))
    points = points + MOONS_CENTRE
    upper, lower = points[label == 0], points[label == 1]
    assert np.allclose(np.linalg.norm(upper, axis=1), 1.0)
    assert np.allclose(np.linalg.norm(lower - [1.0, 0.5], axis=1), 1.0)
    assert (upper[:, 1] >= 0).all() and (lower[:, 1] <= 0.5).all()
    assert 0.45 < label.mean() < 0.55


def test_kinetic_demo_writes_figure_and_numbers(tmp_path):
    import json

    from pipeline.demos.kinetic import KineticDemoConfig, run_kinetic_demo

    config = KineticDemoConfig(iterations=15, batch_size=64, layers=3, hidden_features=8,
                               eval_points=200, kinetic=KineticWeights(1.0, 1.0, 0.0))
    result = run_kinetic_demo(config, tmp_path)
    stored = json.loads((tmp_path / "kinetic_demo.json").read_text())
    assert (tmp_path / "kinetic_layers.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for run in ("maximum_likelihood", "with_kinetic_term"):
        lengths = stored[run]["per_layer_path_length"]
        assert len(lengths) == 3
        assert stored[run]["path_length_total"] == pytest.approx(sum(lengths))
        assert stored[run]["kinetic_sum"] == pytest.approx(sum(lengths[1:]))
        assert np.isfinite(stored[run]["heldout_nll"])
    assert result["path_length_ratio"] == pytest.approx(
        stored["with_kinetic_term"]["path_length_total"]
        / stored["maximum_likelihood"]["path_length_total"])
