"""Estimation API: context layout = the dataset's, σ-regions = pushed base spheres, CLI round trip."""
from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch
from torch import Tensor
from typer.testing import CliRunner

from pipeline.training.datasets import make_windows
from pipeline.errors import ConfigError
from pipeline.inference.estimate import (ObservationWindow, batch_window_context, confidence_regions,
                               estimate, unit_sphere_points)
from pipeline.models.encoders import EncoderConfig
from pipeline.models.estimator import build_estimator, make_estimator_config
from pipeline.inference.rollout import RolloutConfig, propagate_paths
from pipeline.systems.sir import simulate_ensemble
from pipeline.systems.vehicle import simulate_vehicle


def _tiny_estimator(features: int = 3, seed: int = 0):
    config = make_estimator_config(features, features + 1, 5,
                                   EncoderConfig(kind="mlp", embedding_features=4),
                                   layers=2, hidden_features=8)
    stats = SimpleNamespace(context_mean=torch.cat([torch.full((features,), 0.3), torch.zeros(1)]),
                            context_std=torch.full((features + 1,), 0.3),
                            target_mean=torch.full((features,), 0.3),
                            target_std=torch.full((features,), 0.1))
    return build_estimator(config, stats, seed=seed).eval(), config


@pytest.mark.parametrize("direction", ["forward", "backward"])
def test_window_context_matches_the_dataset_windows_exactly(direction: str) -> None:
    ensemble = simulate_ensemble("sir-multi", n_trajectories=2, seed=0)
    kept = torch.ones(ensemble.observations.shape[:2], dtype=torch.bool)
    context, mask, _, traj, target_time = make_windows(
        ensemble.times, ensemble.observations, kept, ensemble.states, None, direction, 5)
    rows = [0, 137, 700]
    windows = []
    for i in rows:
        t = float(target_time[i])
        k = int(round(t))
        idx = np.arange(k - 5, k) if direction == "forward" else np.arange(k + 1, k + 6)
        windows.append(ObservationWindow(times=ensemble.times[idx].numpy(),
                                         values=ensemble.observations[int(traj[i]), idx].numpy(),
                                         target_time=t))
    ours, our_mask = batch_window_context(windows, direction, 5)
    torch.testing.assert_close(ours, context[rows], rtol=0, atol=0)
    assert bool(our_mask.all()) and bool(mask[rows].all())


@pytest.mark.parametrize("direction", ["forward", "backward"])
def test_vehicle_window_context_with_absolute_time_matches_the_dataset(direction: str) -> None:
    ensemble = simulate_vehicle("vehicle-dropout", n=40, seed=3)
    context, _, _, traj, target_time = make_windows(
        ensemble.times, ensemble.observations, ensemble.kept, ensemble.states[..., :2], None,
        direction, 5, absolute_time=True)
    rows = [0, len(traj) // 2, len(traj) - 1]
    windows = []
    for i in rows:
        kept = torch.nonzero(ensemble.kept[int(traj[i])]).flatten()
        t = float(target_time[i])
        at = int(torch.nonzero(ensemble.times[kept] == t)[0])
        idx = kept[at - 5:at] if direction == "forward" else kept[at + 1:at + 6]
        windows.append(ObservationWindow(times=ensemble.times[idx].numpy(),
                                         values=ensemble.observations[int(traj[i]), idx].numpy(),
                                         target_time=t))
    ours, _ = batch_window_context(windows, direction, 5, absolute_time=True)
    torch.testing.assert_close(ours, context[rows], rtol=0, atol=0)


def test_short_windows_are_padded_with_masked_zero_rows_and_long_ones_cut() -> None:
    short = ObservationWindow(times=np.array([1.0, 2.5]), values=np.ones((2, 3)), target_time=4.0)
    context, mask = batch_window_context([short], "forward", 5)
    assert mask.tolist() == [[True, True, False, False, False]]
    assert torch.equal(context[0, 2:], torch.zeros((3, 4)))
    np.testing.assert_allclose(context[0, :2, -1].numpy(), [-3.0, -1.5])
    long = ObservationWindow(times=np.arange(10.0, 17.0), values=np.arange(7.0)[:, None] * [1, 1, 1],
                             target_time=9.0)
    context, _ = batch_window_context([long], "backward", 5)
    np.testing.assert_allclose(context[0, :, 0].numpy(), [0, 1, 2, 3, 4])     # nearest rows kept
    with pytest.raises(ConfigError, match="backward estimate needs"):
        batch_window_context([short], "backward", 5)


class GaussianEstimator:
    """x | context ~ N(m, diag(s²)) — the flow with identity layers over a diagonal base."""

    def __init__(self, mean: list[float], scale: list[float]) -> None:
        self.m, self.s = torch.tensor(mean), torch.tensor(scale)
        self.stats, self.window = SimpleNamespace(target_mean=self.m), 5

    def noise_to_data(self, eps, context, mask):  # noqa: ANN001 - test double
        return self.m + self.s * eps

    def log_prob(self, target, context, mask):  # noqa: ANN001
        return torch.distributions.Normal(self.m, self.s).log_prob(target).sum(-1)


def test_estimate_of_a_known_gaussian() -> None:
    est = GaussianEstimator([1.0, -2.0], [0.5, 2.0])
    window = ObservationWindow(times=np.arange(5.0), values=np.zeros((5, 2)), target_time=5.0)
    result = estimate(est, window, "forward", n_samples=40_000, seed=0, names=("p_x", "p_y"))
    assert result.samples.shape == (40_000, 2)
    torch.testing.assert_close(result.mean, est.m, atol=4 * 2.0 / 200, rtol=0)
    torch.testing.assert_close(result.std, est.s, rtol=0.02, atol=0)
    # quantile 0.84134 ≈ m + 1·s
    q = result.quantiles[result.quantile_levels.index(0.84134)]
    torch.testing.assert_close(q, est.m + est.s, atol=0.03, rtol=0)
    # r-σ regions are ellipses m + r·s·u exactly: extent m ± r s
    for region in result.regions:
        torch.testing.assert_close(region.upper, est.m + region.n_sigma * est.s, atol=1e-3, rtol=0)
        torch.testing.assert_close(region.lower, est.m - region.n_sigma * est.s, atol=1e-3, rtol=0)
    value = torch.tensor([[1.5, 0.0]])
    expected = (-0.5 * (1 + 1) - math.log(0.5 * 2.0) - math.log(2 * math.pi))
    assert float(result.log_density(value)[0]) == pytest.approx(expected, rel=1e-5)
    rows = result.summary_rows()
    assert [r["component"] for r in rows] == ["p_x", "p_y"]
    assert rows[1]["sigma3_upper"] == pytest.approx(4.0, abs=1e-3)


class RecordingEstimator(GaussianEstimator):
    """A GaussianEstimator that keeps the contexts it is given and reads the clock like a
    vehicle model."""

    absolute_time = True

    def __init__(self) -> None:
        super().__init__([0.0, 0.0], [1.0, 1.0])
        self.contexts: list[Tensor] = []

    def noise_to_data(self, eps, context, mask):  # noqa: ANN001
        self.contexts.append(context)
        return super().noise_to_data(eps, context, mask)


def test_estimates_and_rollouts_give_clock_models_the_absolute_time() -> None:
    est = RecordingEstimator()
    window = ObservationWindow(times=np.array([3.0, 3.4, 4.1, 4.5, 5.2]), values=np.zeros((5, 2)),
                               target_time=6.0)
    estimate(est, window, "forward", n_samples=10, seed=0)
    np.testing.assert_allclose(est.contexts[0][0, :, 2].numpy(), window.times - 6.0, atol=1e-6)
    np.testing.assert_allclose(est.contexts[0][0, :, 3].numpy(), window.times, atol=1e-6)
    est.contexts.clear()
    times = torch.tensor([[3.0, 3.4, 4.1, 4.5, 5.2]], dtype=torch.float64)
    propagate_paths(est, times, torch.zeros((1, 5, 2)), torch.tensor([[6.0, 7.0]]), "forward",
                    RolloutConfig(n_paths=3, feedback_noise_sigma=0.0))
    second = est.contexts[1][0]  # after the first prediction (t = 6) was shifted in
    np.testing.assert_allclose(second[:, 3].numpy(), [3.4, 4.1, 4.5, 5.2, 6.0], atol=1e-6)
    np.testing.assert_allclose(second[:, 2].numpy(), np.array([3.4, 4.1, 4.5, 5.2, 6.0]) - 7.0,
                               atol=1e-6)


def test_regions_of_a_real_flow_lie_on_base_spheres() -> None:
    """Pull the pushed r-sphere back through the flow: the base log-density drops by r²/2."""
    estimator, _ = _tiny_estimator()
    window = ObservationWindow(times=np.arange(5.0), values=np.full((5, 3), 0.3), target_time=5.0)
    context, mask = batch_window_context([window], "forward", 5)
    regions = confidence_regions(estimator, context, mask, radii=(0.0, 1.0, 2.0, 3.0), n_points=64)
    embedding = estimator._embed_raw(context, mask)
    base = []
    for points in regions:
        z = estimator.flow.layer_outputs(estimator.standardize_target(points[0]),
                                         embedding.expand(points.shape[1], -1))[-1]
        base.append(estimator.flow.base_log_prob(z, embedding.expand(points.shape[1], -1)))
    for r, log_p in zip((1.0, 2.0, 3.0), base[1:], strict=True):
        torch.testing.assert_close(log_p - base[0], torch.full_like(log_p, -0.5 * r * r),
                                   atol=2e-3, rtol=1e-3)


def test_estimate_with_a_real_flow_is_deterministic_and_finite() -> None:
    estimator, _ = _tiny_estimator()
    window = ObservationWindow(times=np.arange(10.0, 15.0), values=np.full((5, 3), 0.3),
                               target_time=9.0)
    a = estimate(estimator, window, "backward", 200, seed=4)
    b = estimate(estimator, window, "backward", 200, seed=4)
    c = estimate(estimator, window, "backward", 200, seed=5)
    assert torch.equal(a.samples, b.samples) and not torch.equal(a.samples, c.samples)
    assert bool(torch.isfinite(a.samples).all())
    # log_density agrees with the estimator's own log_prob under the same context
    context, mask = batch_window_context([window], "backward", 5)
    direct = estimator.log_prob(a.samples[:3], context.expand(3, -1, -1), mask.expand(3, -1))
    torch.testing.assert_close(a.log_density(a.samples[:3]), direct)


def test_unit_sphere_points_have_unit_norm() -> None:
    for dim in (1, 2, 3, 5):
        points = unit_sphere_points(dim, 50)
        torch.testing.assert_close(points.norm(dim=-1), torch.ones(len(points), dtype=torch.float64))
    # the Fibonacci lattice is balanced: its mean is ~0
    assert float(unit_sphere_points(3, 500).mean(0).norm()) < 0.01


def test_cli_estimate_and_rollout_round_trip(tmp_path: Path) -> None:
    from pipeline.training.checkpoints import save_checkpoint
    from pipeline.cli import _register, app

    _register()
    estimator, config = _tiny_estimator()
    dataset = {"name": "sir-multi", "direction": "forward", "target": "state", "window": 5}
    ckpt = save_checkpoint(tmp_path / "model.pt", estimator, config=config,
                           stats=estimator.stats, extra={"preset": {"dataset": dataset}})
    dates = pd.date_range("2021-01-01", periods=12, freq="D")
    series = pd.DataFrame({"date": dates.strftime("%Y-%m-%d"), "S": np.linspace(0.9, 0.8, 12),
                           "I": np.full(12, 0.05), "R": np.linspace(0.05, 0.15, 12)})
    series.to_csv(tmp_path / "series.csv", index=False)
    series.iloc[-5:].to_csv(tmp_path / "window.csv", index=False)
    runner = CliRunner()
    out = tmp_path / "est.csv"
    res = runner.invoke(app, ["estimate", "--checkpoint", str(ckpt), "--window",
                              str(tmp_path / "window.csv"), "--samples", "50", "--out", str(out)])
    assert res.exit_code == 0, res.output
    samples = pd.read_csv(out)
    summary = pd.read_csv(tmp_path / "est_summary.csv")
    assert list(samples.columns) == ["sample", "S", "I", "R"] and len(samples) == 50
    assert summary["date"].iloc[0] == "2021-01-13"
    assert {"mean", "std", "sigma1_lower", "sigma3_upper", "q0.5"} <= set(summary.columns)
    res = runner.invoke(app, ["rollout", "--checkpoint", str(ckpt), "--series",
                              str(tmp_path / "series.csv"), "--horizon", "4", "--paths", "10",
                              "--window-every", "3", "--out", str(tmp_path / "roll")])
    assert res.exit_code == 0, res.output
    summary = pd.read_csv(tmp_path / "roll" / "summary.csv")
    assert summary["date"].tolist()[:4] == ["2021-01-13", "2021-01-14", "2021-01-15", "2021-01-16"]
    assert len(pd.read_csv(tmp_path / "roll" / "paths.csv")) == 10 * 4
    rolling = pd.read_csv(tmp_path / "roll" / "rolling.csv")
    assert len(rolling) == 12 * 3 and rolling["mean"].isna().sum() == 5 * 3
    res = runner.invoke(app, ["estimate", "--checkpoint", str(ckpt), "--window",
                              str(tmp_path / "window.csv"), "--direction", "backward",
                              "--out", str(out)])
    assert res.exit_code == 1 and "trained for forward" in res.output
    bad = series.drop(columns="I")
    bad.to_csv(tmp_path / "bad.csv", index=False)
    res = runner.invoke(app, ["estimate", "--checkpoint", str(ckpt), "--window",
                              str(tmp_path / "bad.csv"), "--out", str(out)])
    assert res.exit_code == 1 and "missing column" in res.output
