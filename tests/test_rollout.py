"""Rollouts against closed-form k-step predictives of a linear-Gaussian AR(1) conditional.

The "estimator" here is a flow whose parameters we set: x_n | context = a·o_last + q·eps, where
o_last is the context row nearest the target (forward: the latest, backward: the earliest).
Its noise_to_data is exactly what a one-layer affine flow with that conditional base would do,
so the rollout logic (path propagation, feed-back, re-anchoring) is checked against exact answers.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from pipeline.errors import ConfigError
from pipeline.inference.estimate import ObservationWindow
from pipeline.inference.rollout import (RolloutConfig, rolling_anchor_indices, rolling_rollout, rollout)


class AR1Estimator:
    """x = a · (context value nearest the target) + q · eps; tracks which rows it was shown."""

    def __init__(self, a: float, q: float, window: int = 3, dim: int = 1) -> None:
        self.a, self.q, self.window = a, q, window
        self.stats = SimpleNamespace(target_mean=torch.zeros(dim))
        self.calls: list[torch.Tensor] = []

    def _nearest_value(self, context: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        gap = context[..., -1].abs().masked_fill(~mask, float("inf"))
        index = gap.argmin(dim=1)
        return context[torch.arange(len(context)), index, :-1]

    def noise_to_data(self, eps: torch.Tensor, context: torch.Tensor,
                      mask: torch.Tensor) -> torch.Tensor:
        self.calls.append(context.clone())
        last = self._nearest_value(context, mask)[:, None, : eps.shape[-1]]
        return self.a * last + self.q * eps

    def log_prob(self, target, context, mask):  # noqa: ANN001 - test double
        mean = self.a * self._nearest_value(context, mask)
        return torch.distributions.Normal(mean, self.q).log_prob(target).sum(-1)


def _window(values: list[float], start: float = 0.0, target_gap: float = 1.0) -> ObservationWindow:
    times = start + np.arange(len(values), dtype=float)
    return ObservationWindow(times=times, values=np.asarray(values)[:, None],
                             target_time=times[-1] + target_gap)


@pytest.mark.parametrize("feedback_sigma", [0.0, 0.5])
def test_forward_rollout_matches_closed_form_ar1_predictive(feedback_sigma: float) -> None:
    a, q, last, horizon, paths = 0.8, 0.3, 2.0, 6, 40_000
    est = AR1Estimator(a, q)
    result = rollout(est, _window([0.0, 1.0, last]), horizon, 1.0, "forward",
                     RolloutConfig(n_paths=paths, feedback_noise_sigma=feedback_sigma, seed=3))
    assert result.samples.shape == (paths, horizon, 1)
    np.testing.assert_allclose(result.times, 3.0 + np.arange(horizon))
    # x_1 = a·o + q·η; x_k = a·(x_{k-1} + s·ξ) + q·η  =>  mean a^k o, var_k = a² var_{k-1} + a² s² + q²
    k = np.arange(1, horizon + 1)
    mean = a ** k * last
    var = np.empty(horizon)
    var[0] = q ** 2
    for i in range(1, horizon):
        var[i] = a ** 2 * var[i - 1] + a ** 2 * feedback_sigma ** 2 + q ** 2
    got_mean = result.mean[:, 0].double().numpy()
    got_var = result.std[:, 0].double().numpy() ** 2
    # Monte-Carlo errors: sd(mean) = sqrt(var/P); sd(var) ≈ var·sqrt(2/P). 4 sd tolerance.
    assert (np.abs(got_mean - mean) < 4 * np.sqrt(var / paths)).all(), (got_mean, mean)
    assert (np.abs(got_var / var - 1) < 4 * np.sqrt(2 / paths)).all(), (got_var, var)
    assert (np.diff(got_var) > 0).all(), "bands must widen with the horizon"


def test_backward_rollout_conditions_on_earliest_row_and_reports_increasing_times() -> None:
    a, q = 0.5, 0.1
    est = AR1Estimator(a, q)
    window = ObservationWindow(times=np.array([10.0, 11.0, 12.0]),
                               values=np.array([[4.0], [9.0], [9.0]]), target_time=9.0)
    result = rollout(est, window, 3, 1.0, "backward",
                     RolloutConfig(n_paths=20_000, seed=0))
    np.testing.assert_allclose(result.times, [7.0, 8.0, 9.0])
    # predicted in the order t=9, 8, 7: mean a·4, a²·4, a³·4
    np.testing.assert_allclose(result.mean[:, 0].numpy(), [a ** 3 * 4, a ** 2 * 4, a * 4],
                               atol=0.01)
    # first context: rows at 10, 11, 12 relative to 9 -> time channel 1, 2, 3 (increasing order)
    np.testing.assert_allclose(est.calls[0][0, :, -1].numpy(), [1.0, 2.0, 3.0])
    # second step: the predicted row (t=9) is inserted first, relative to t=8: 1, 2, 3 again
    np.testing.assert_allclose(est.calls[1][0, :, -1].numpy(), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(est.calls[1][0, 1:, 0].numpy(), [4.0, 9.0])


def test_rollout_is_deterministic_given_the_seed() -> None:
    est = AR1Estimator(0.9, 0.2)
    window = _window([1.0, 1.0, 1.0])
    first = rollout(est, window, 4, 1.0, config=RolloutConfig(n_paths=50, seed=7,
                                                              feedback_noise_sigma=0.1))
    again = rollout(est, window, 4, 1.0, config=RolloutConfig(n_paths=50, seed=7,
                                                              feedback_noise_sigma=0.1))
    other = rollout(est, window, 4, 1.0, config=RolloutConfig(n_paths=50, seed=8,
                                                              feedback_noise_sigma=0.1))
    assert torch.equal(first.samples, again.samples)
    assert not torch.equal(first.samples, other.samples)


def test_each_path_is_conditioned_on_its_own_predictions() -> None:
    """With q = 0 after the first step, each path's later values are a^k times its own first draw."""
    est = AR1Estimator(a=1.0, q=1.0)
    result = rollout(est, _window([0.0, 0.0, 0.0]), 3, 1.0,
                     config=RolloutConfig(n_paths=100, seed=1))
    first = result.samples[:, 0, 0]
    # x_2 = x_1 + eps_2: the increments are independent of x_1 and x_2 - x_1 has variance 1.
    increments = result.samples[:, 1, 0] - first
    assert abs(float(torch.corrcoef(torch.stack([first, increments]))[0, 1])) < 0.35
    assert float(torch.corrcoef(torch.stack([first, result.samples[:, 2, 0]]))[0, 1]) > 0.4


def test_joint_model_feeds_back_only_the_state_part() -> None:
    est = AR1Estimator(a=1.0, q=0.0, dim=3)  # target = (state, two "parameters")
    window = ObservationWindow(times=np.arange(3.0), values=np.array([[1.0], [2.0], [5.0]]),
                               target_time=3.0)
    result = rollout(est, window, 2, 1.0, config=RolloutConfig(n_paths=4))
    assert result.samples.shape == (4, 2, 3)
    second_context = est.calls[1]
    assert second_context.shape == (4, 3, 2)          # one observed column + the time channel
    np.testing.assert_allclose(second_context[0, :, 0].numpy(), [2.0, 5.0, 5.0])


def test_rolling_anchors_use_observed_rows_at_exact_indices() -> None:
    assert rolling_anchor_indices(20, 3, 7, "forward") == [3, 10, 17]
    assert rolling_anchor_indices(20, 3, 7, "backward") == [16, 9, 2]
    values = np.arange(20, dtype=float)[:, None] * 10.0
    times = np.arange(20, dtype=float)
    est = AR1Estimator(a=1.0, q=0.0)
    result = rolling_rollout(est, times, values, every=7, direction="forward",
                             config=RolloutConfig(n_paths=2))
    assert result.anchors == (3, 10, 17)
    first_context = est.calls[0]                        # (segments·paths, R, C+1)
    # segment 0 starts from observed rows 0,1,2; segment 1 from 7,8,9; segment 2 from 14,15,16
    np.testing.assert_allclose(first_context[::2, :, 0].numpy(),
                               [[0, 10, 20], [70, 80, 90], [140, 150, 160]])
    np.testing.assert_allclose(first_context[::2, :, -1].numpy(), [[-3, -2, -1]] * 3)
    # with q = 0 and a = 1, every prediction repeats the anchor's last observation
    expected = np.full(20, np.nan)
    expected[3:10], expected[10:17], expected[17:20] = 20.0, 90.0, 160.0
    np.testing.assert_allclose(result.samples[0, :, 0].numpy(), expected)


def test_rolling_backward_fills_from_the_end() -> None:
    values = np.arange(12, dtype=float)[:, None]
    est = AR1Estimator(a=1.0, q=0.0)
    result = rolling_rollout(est, np.arange(12.0), values, every=4, direction="backward",
                             config=RolloutConfig(n_paths=1))
    assert result.anchors == (8, 4, 0)
    expected = np.full(12, np.nan)
    expected[5:9], expected[1:5], expected[0] = 9.0, 5.0, 1.0
    np.testing.assert_allclose(result.samples[0, :, 0].numpy(), expected)


def test_summary_frame_and_bands() -> None:
    est = AR1Estimator(0.8, 0.3)
    result = rollout(est, _window([0.0, 1.0, 2.0]), 3, 1.0, config=RolloutConfig(n_paths=500))
    frame = result.summary_frame()
    assert list(frame.columns[:6]) == ["time", "component", "mean", "std", "lower_2sigma",
                                      "upper_2sigma"]
    np.testing.assert_allclose(frame["upper_2sigma"] - frame["mean"], 2 * frame["std"],
                               rtol=1e-5)


def test_bad_inputs_raise_named_errors() -> None:
    est = AR1Estimator(0.8, 0.3)
    with pytest.raises(ConfigError, match="rows"):
        rollout(est, _window([1.0, 2.0]), 3, 1.0)
    with pytest.raises(ConfigError, match="target_time"):
        rollout(est, _window([1.0, 2.0, 3.0]), 3, 1.0, direction="backward")
    with pytest.raises(ConfigError, match="n_paths"):
        RolloutConfig(n_paths=0)
    with pytest.raises(ConfigError, match="NaN"):
        rolling_rollout(est, np.arange(10.0), np.full((10, 1), np.nan), every=2)
