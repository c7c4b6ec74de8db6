"""Flow-seeded rollouts (the flow's estimate at the anchor carried on by the prior's dynamics)
against answers worked out by hand.

The "flow" is a point mass (or a narrow Gaussian) at a chosen (S, I, R, β), so what the rollout
does after the anchor is the prior's dynamics alone, set to cases with closed forms: no
transmission (the window empties a day at a time), full reversion (β is the prior's level after
one day), and the negative-binomial reporting noise's mean and variance.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from pipeline.errors import ConfigError
from pipeline.inference.rollout import rolling_anchor_indices
from pipeline.inference.seeded_rollout import (SeededRolloutConfig, daily_reports, seeded_paths,
                                               seeded_rolling_rollout)
from pipeline.systems.waves import WavePrior

POPULATION = 100_000
L = 7


class PointJointEstimator:
    """A joint (S, I, R, β) "flow" whose draws are ``mean`` with β spread by ``scale · eps``,
    whatever the context; it records the contexts it was shown."""

    def __init__(self, mean: list[float], scale: float = 0.0, window: int = 3) -> None:
        self.mean = torch.tensor(mean, dtype=torch.float64)
        self.scale, self.window = scale, window
        self.stats = SimpleNamespace(target_mean=torch.zeros(4))
        self.contexts: list[torch.Tensor] = []

    def noise_to_data(self, eps, context, mask):  # noqa: ANN001 - test double
        self.contexts.append(context.clone())
        spread = torch.zeros_like(eps, dtype=torch.float64)
        spread[..., 3] = self.scale * eps[..., 3].double()
        return self.mean + spread


def _prior(**changes: object) -> WavePrior:
    quiet = dict(population=POPULATION, reproduction_mean=(1.0, 1.0), reversion_per_day=(0.0, 0.0),
                 volatility_per_day=(0.0, 0.0), jump_rate_per_day=0.0,
                 importation=(1e-15, 1e-15), dispersion=(50.0, 50.0))
    return WavePrior(**(quiet | changes))  # type: ignore[arg-type]


def _flat_series(days: int, reports_per_day: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """An S/I/R series with the same number of reports every day (I = the last L days')."""
    share = reports_per_day / POPULATION
    removed0 = 0.05
    t = np.arange(days, dtype=np.float64)
    infectious = np.full(days, L * share)
    removed = removed0 + share * t
    return t, np.stack([1.0 - infectious - removed, infectious, removed], axis=1)


def test_without_transmission_the_window_empties_a_day_at_a_time() -> None:
    times, values = _flat_series(40)
    i0 = 0.007
    flow = PointJointEstimator([0.9, i0, 0.093, 1e-12])
    paths = seeded_paths(flow, times, values, [20], 10, _prior(),
                         SeededRolloutConfig(n_paths=4, reporting_noise=False))
    infectious = paths[0, :, :, 1].double().numpy()
    # flat reports: each of the L days holds I0/L; day k has lost k of them
    expected = i0 * np.clip(L - np.arange(10), 0, None) / L
    np.testing.assert_allclose(infectious, np.broadcast_to(expected, infectious.shape),
                               atol=1e-9)
    s, i, r = (paths[..., c].double() for c in range(3))
    np.testing.assert_allclose((s + i + r).numpy(), 1.0, atol=1e-6)   # S + I + R = 1 throughout
    np.testing.assert_allclose(s.numpy(), 0.9, atol=1e-6)              # nobody is infected


def test_full_reversion_puts_beta_at_the_priors_level_after_one_day() -> None:
    times, values = _flat_series(40)
    flow = PointJointEstimator([0.9, 0.007, 0.093, 0.4])
    prior = _prior(reversion_per_day=(1.0, 1.0), reproduction_mean=(0.7, 0.7))
    paths = seeded_paths(flow, times, values, [20, 30], 5, prior,
                         SeededRolloutConfig(n_paths=3, reporting_noise=False))
    beta = paths[..., 3].double().numpy()
    np.testing.assert_allclose(beta[:, :, 0], 0.4, rtol=1e-6)           # day 0: the flow's draw
    np.testing.assert_allclose(beta[:, :, 1:], 0.7 / L, rtol=1e-6)      # then R̄ / L


def test_new_infections_follow_the_renewal_step() -> None:
    """One day with β > 0: new = S (1 − exp(−β I)), S falls by it, I gains it and loses the
    oldest day."""
    times, values = _flat_series(40)
    s0, i0, beta = 0.9, 0.007, 0.2
    flow = PointJointEstimator([s0, i0, 1 - s0 - i0, beta])
    paths = seeded_paths(flow, times, values, [20], 2, _prior(),
                         SeededRolloutConfig(n_paths=2, reporting_noise=False)).double()
    new = s0 * -np.expm1(-beta * i0)
    np.testing.assert_allclose(paths[0, :, 1, 0].numpy(), s0 - new, rtol=1e-6)
    np.testing.assert_allclose(paths[0, :, 1, 1].numpy(), i0 - i0 / L + new, rtol=1e-6)


def test_reported_infectious_share_has_the_negative_binomial_moments() -> None:
    """Reported I = NB(N·I, L·k)/N; with fewer than 14 days of reports before the anchor, k is
    the prior's middle dispersion (here 50)."""
    times, values = _flat_series(40)
    i0, paths_n = 0.007, 40_000
    flow = PointJointEstimator([0.9, i0, 0.093, 1e-12])
    paths = seeded_paths(flow, times, values, [10], 2, _prior(),
                         SeededRolloutConfig(n_paths=paths_n, seed=5)).double()
    reported = paths[0, :, 1, 1].numpy() * POPULATION
    mean = (i0 - i0 / L) * POPULATION                                    # the window lost a day
    var = mean + mean ** 2 / (L * 50.0)
    assert abs(reported.mean() - mean) < 4 * np.sqrt(var / paths_n)
    assert abs(reported.var() / var - 1) < 4 * np.sqrt(2 / paths_n)


def test_rolling_segments_see_only_the_days_before_their_anchor() -> None:
    times, values = _flat_series(60)
    flow = PointJointEstimator([0.9, 0.007, 0.093, 0.15], scale=0.02)
    prior = _prior(reversion_per_day=(0.02, 0.05), volatility_per_day=(0.01, 0.03))
    config = SeededRolloutConfig(n_paths=8, seed=3)
    first = seeded_rolling_rollout(flow, times, values, 14, prior, config)
    assert first.anchors == tuple(rolling_anchor_indices(60, L + 1, 14, "forward"))
    assert first.samples.shape == (8, 60, 4)
    assert torch.isnan(first.samples[:, :L + 1]).all()
    assert torch.isfinite(first.samples[:, L + 1:]).all()
    changed = values.copy()
    changed[first.anchors[1]:, 1] *= 3.0            # the future of the first segment
    second = seeded_rolling_rollout(flow, times, changed, 14, prior, config)
    segment = slice(first.anchors[0], first.anchors[1])
    torch.testing.assert_close(first.samples[:, segment], second.samples[:, segment])
    # the contexts are the 3 rows before each anchor, time relative to the target
    context = flow.contexts[0]
    np.testing.assert_allclose(context[0, :, :3].numpy(), values[L - 2:L + 1], rtol=1e-6)
    np.testing.assert_allclose(context[0, :, 3].numpy(), [-3.0, -2.0, -1.0])


def test_daily_reports_are_the_fall_of_s() -> None:
    _, values = _flat_series(5, reports_per_day=250.0)
    np.testing.assert_allclose(daily_reports(values, POPULATION)[1:], 250.0)
    assert np.isnan(daily_reports(values, POPULATION)[0])


@pytest.mark.parametrize("case, message", [
    ("gap", "consecutive days"), ("five", "joint \\(S, I, R, beta\\) flow"),
    ("early", "anchors must lie"), ("nan", "missing values")])
def test_bad_inputs_raise_named_errors(case: str, message: str) -> None:
    times, values = _flat_series(40)
    flow = PointJointEstimator([0.9, 0.007, 0.093, 0.1])
    anchors = [20]
    if case == "gap":
        times = times * 2.0
    elif case == "five":
        flow.stats = SimpleNamespace(target_mean=torch.zeros(5))
    elif case == "early":
        anchors = [2]
    elif case == "nan":
        values[5, 1] = np.nan
    with pytest.raises(ConfigError, match=message):
        seeded_paths(flow, times, values, anchors, 5, _prior())
