"""Conditional MAF backends: context reaches every output, densities normalise, sampling and
density agree (change of variables, KS), inverses are exact, samples stay finite."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from nflows.transforms.autoregressive import MaskedAffineAutoregressiveTransform
from scipy import stats as sps

from pipeline.errors import ConfigError
from pipeline.models.maf import BACKENDS, FlowConfig, build_flow

BACKEND_PARAMS = pytest.mark.parametrize("backend", BACKENDS)



def make_flow(backend: str, features: int, context: int, layers: int = 3, seed: int = 0,
              double: bool = True, **options):
    torch.manual_seed(seed)
    flow = build_flow(FlowConfig(features, context, layers=layers, hidden_features=8,
                                 backend=backend, **options))
    return flow.double() if double else flow


def detach_base_from_context(flow) -> None:
    """Zero the base MLP's input weights: the base no longer sees the context, so any context
    dependence left must come through the flow layers."""
    with torch.no_grad():
        flow.base.net[0].weight.zero_()


def two_contexts(context: int) -> torch.Tensor:
    return torch.tensor([[1.5] * context, [-1.0] * context], dtype=torch.float64)


# ----------------------------------------------------------------------- context dependence

def test_vanilla_nflows_made_ignores_context_in_first_output():
    """The defect we fix (nflows PR #85): reproduced so the next test is known to detect it."""
    torch.manual_seed(0)
    maf = MaskedAffineAutoregressiveTransform(features=3, hidden_features=8, context_features=2)
    x = torch.randn(1, 3).repeat(2, 1)
    out, _ = maf(x, torch.tensor([[2.0, -1.0], [-3.0, 0.5]]))
    assert torch.equal(out[0, 0], out[1, 0])          # first output: no context at all
    assert not torch.allclose(out[0, 1:], out[1, 1:])  # later outputs see it


@BACKEND_PARAMS
def test_every_layer_output_dimension_depends_on_context(backend):
    """Each [permutation, LU, MAF] layer at a fixed input: every output coordinate (the first
    of the autoregressive order included) moves when only the context changes."""
    flow = make_flow(backend, features=3, context=2, layers=3)
    x = torch.randn(1, 3, dtype=torch.float64).repeat(2, 1)
    contexts = two_contexts(2)
    for index in range(flow.num_layers):
        out, _ = flow._forward_layer(index, x, contexts)
        change = (out[0] - out[1]).abs()
        assert bool((change > 1e-4).all()), f"layer {index}: per-dimension change {change}"


@BACKEND_PARAMS
def test_one_dimensional_target_density_depends_on_context_through_layers(backend):
    """D = 1 isolates dimension 0: with the base blind to the context, log p(x | c) still
    changes with c at every grid point (random init)."""
    flow = make_flow(backend, features=1, context=2)
    detach_base_from_context(flow)
    grid = torch.linspace(-3, 3, 61, dtype=torch.float64)[:, None]
    c1, c2 = two_contexts(2)
    lp1 = flow.log_prob(grid, c1.expand(61, 2))
    lp2 = flow.log_prob(grid, c2.expand(61, 2))
    assert bool(((lp1 - lp2).abs() > 1e-4).all())


def _grid_density_2d(flow, context: torch.Tensor, half_width: float, n: int):
    axis = torch.linspace(-half_width, half_width, n, dtype=torch.float64)
    xx, yy = torch.meshgrid(axis, axis, indexing="ij")
    points = torch.stack([xx.flatten(), yy.flatten()], dim=1)
    with torch.no_grad():
        density = flow.log_prob(points, context.expand(points.shape[0], -1)).exp()
    return axis, density.reshape(n, n)


@BACKEND_PARAMS
def test_every_marginal_of_a_2d_target_depends_on_context_through_layers(backend):
    flow = make_flow(backend, features=2, context=2)
    detach_base_from_context(flow)
    c1, c2 = two_contexts(2)
    axis, p1 = _grid_density_2d(flow, c1, 12.0, 161)
    _, p2 = _grid_density_2d(flow, c2, 12.0, 161)
    h = float(axis[1] - axis[0])
    for dim in (0, 1):
        other = 1 - dim
        m1, m2 = p1.sum(other) * h, p2.sum(other) * h        # marginal densities of ``dim``
        assert float((m1 - m2).abs().sum() * h) > 0.02, f"marginal of dim {dim} unchanged"


# ----------------------------------------------------------------------- normalisation

@BACKEND_PARAMS
def test_one_dimensional_density_integrates_to_one(backend):
    """Trapezoid rule on 4,001 points over [min - 5, max + 5] of 5,000 samples. For a smooth
    density that vanishes at both ends the trapezoid sum converges faster than any power of h
    (Euler-Maclaurin: the boundary terms vanish); measured deviations are < 1e-6, so 1e-4 leaves
    a wide margin while any error in a log-det term (an O(1) factor) fails it."""
    flow = make_flow(backend, features=1, context=2)
    for context in two_contexts(2):
        with torch.no_grad():
            samples = flow.sample(5000, context[None], torch.Generator().manual_seed(1))[0, :, 0]
        grid = torch.linspace(float(samples.min()) - 5, float(samples.max()) + 5, 4001,
                              dtype=torch.float64)
        with torch.no_grad():
            density = flow.log_prob(grid[:, None], context.expand(grid.shape[0], 2)).exp()
        mass = float(torch.trapezoid(density, grid))
        assert abs(mass - 1.0) < 1e-4, mass


@BACKEND_PARAMS
def test_two_dimensional_density_integrates_to_one(backend):
    """Riemann sum on a 161 x 161 grid over [-12, 12]^2 (h = 0.15). The box holds the mass
    (no sample of 5,000 leaves it) and, as in 1-D, the sum of a smooth density vanishing at the
    box edges converges spectrally: measured deviations are < 2e-6 (161, 241 and 401 points
    agree), so 1e-4 is a safe tolerance that a wrong Jacobian term could not meet."""
    flow = make_flow(backend, features=2, context=2)
    for context in two_contexts(2):
        with torch.no_grad():
            samples = flow.sample(5000, context[None], torch.Generator().manual_seed(2))[0]
        assert float(samples.abs().max()) < 10
        axis, density = _grid_density_2d(flow, context, 12.0, 161)
        h = float(axis[1] - axis[0])
        mass = float(density.sum()) * h * h
        assert abs(mass - 1.0) < 1e-4, mass


@BACKEND_PARAMS
def test_unconditional_flow_normalizes(backend):
    flow = make_flow(backend, features=1, context=0)
    empty = torch.empty(1, 0, dtype=torch.float64)
    grid = torch.linspace(-40, 40, 8001, dtype=torch.float64)
    with torch.no_grad():
        mass = float(torch.trapezoid(flow.log_prob(grid[:, None], empty.expand(8001, 0)).exp(),
                                     grid))
    assert abs(mass - 1.0) < 1e-4


# ----------------------------------------------------------------------- sampling vs density

@BACKEND_PARAMS
def test_samples_follow_the_density_ks(backend):
    """KS test of 5,000 samples against the CDF obtained by integrating exp(log_prob)."""
    flow = make_flow(backend, features=1, context=2)
    context = two_contexts(2)[:1]
    with torch.no_grad():
        samples = flow.sample(5000, context, torch.Generator().manual_seed(3))[0, :, 0].numpy()
        grid = torch.linspace(float(samples.min()) - 5, float(samples.max()) + 5, 4001,
                              dtype=torch.float64)
        density = flow.log_prob(grid[:, None], context.expand(4001, 2)).exp().numpy()
    cdf = np.concatenate([[0.0], np.cumsum((density[1:] + density[:-1]) / 2 * np.diff(grid))])
    cdf /= cdf[-1]
    result = sps.kstest(samples, lambda v: np.interp(v, grid.numpy(), cdf))
    assert result.pvalue > 1e-3, result


@BACKEND_PARAMS
def test_log_prob_of_samples_matches_change_of_variables(backend):
    """x = T(eps): log p(x) must equal log N(eps; 0, I) - log|det dT/deps| (autograd Jacobian),
    i.e. the sampler and the density describe the same distribution, point by point."""
    flow = make_flow(backend, features=2, context=2)
    context = two_contexts(2)[:1]
    eps = torch.randn(6, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    for e in eps:
        def push(v):
            return flow.noise_to_data(v.reshape(1, 1, 2), context).reshape(2)
        jacobian = torch.autograd.functional.jacobian(push, e)
        x = push(e).detach()[None]
        expected = (-0.5 * float(e @ e) - math.log(2 * math.pi)
                    - float(torch.linalg.slogdet(jacobian).logabsdet))
        with torch.no_grad():
            assert float(flow.log_prob(x, context)) == pytest.approx(expected, abs=1e-8)


@BACKEND_PARAMS
def test_inverse_of_forward_is_identity(backend):
    flow = make_flow(backend, features=3, context=2)
    x = 2 * torch.randn(64, 3, dtype=torch.float64)
    context = torch.randn(64, 2, dtype=torch.float64)
    z = flow.trajectory(x, context).latent
    assert torch.allclose(flow.inverse(z, context), x, atol=1e-10)


@BACKEND_PARAMS
def test_noise_to_data_agrees_with_sample(backend):
    flow = make_flow(backend, features=3, context=2, double=False)
    context = torch.randn(4, 2)
    drawn = flow.sample(7, context, torch.Generator().manual_seed(5))
    eps = torch.randn((4, 7, 3), generator=torch.Generator().manual_seed(5))
    assert torch.equal(drawn, flow.noise_to_data(eps, context))
    assert drawn.shape == (4, 7, 3)


@BACKEND_PARAMS
def test_layer_outputs_run_from_data_to_base(backend):
    flow = make_flow(backend, features=2, context=2, layers=4)
    x, context = torch.randn(5, 2, dtype=torch.float64), torch.randn(5, 2, dtype=torch.float64)
    trajectory = flow.trajectory(x, context)
    outputs = flow.layer_outputs(x, context)
    assert len(outputs) == 5 and torch.equal(outputs[0], x)
    expected = flow.base_log_prob(outputs[-1], context) + trajectory.log_abs_det
    assert torch.allclose(flow.log_prob(x, context), expected, atol=1e-12)


@BACKEND_PARAMS
def test_samples_stay_finite_early_in_training(backend):
    """Aggressive early training (lr 1e-2, 30 steps) on a badly scaled 3-D conditional target:
    the regime in which stock nflows samples reached 1e10-1e24 (stack.md)."""
    torch.manual_seed(0)
    flow = make_flow(backend, features=3, context=2, layers=5, double=False)
    generator = torch.Generator().manual_seed(6)
    context = torch.randn(256, 2, generator=generator)
    target = torch.randn(256, 3, generator=generator) * torch.tensor([0.01, 1.0, 30.0])
    target = target + 5 * context[:, :1] ** 2
    optimizer = torch.optim.Adam(flow.parameters(), lr=1e-2)
    for _ in range(30):
        loss = -flow.log_prob(target, context).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        samples = flow.sample(100, context[:40], generator)
        log_prob = flow.log_prob(samples.reshape(-1, 3), context[:40].repeat_interleave(100, 0))
    assert bool(torch.isfinite(samples).all())
    assert bool(torch.isfinite(log_prob).all())
    assert float(samples.abs().max()) < 1e6


def test_flow_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="backend"):
        FlowConfig(2, 2, backend="pyro")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="layers"):
        FlowConfig(2, 2, layers=0)
    with pytest.raises(ValueError, match="context must have shape"):
        make_flow("zuko", 2, 3).log_prob(torch.zeros(4, 2, dtype=torch.float64),
                                         torch.zeros(4, 2, dtype=torch.float64))
