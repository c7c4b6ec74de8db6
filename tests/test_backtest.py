"""Rolling-origin backtest on synthetic SIR data: persistence, a perfect and a calibrated oracle."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from scipy.integrate import solve_ivp

from pipeline.backtest import (BacktestConfig, BacktestError, PersistenceForecaster,
                               origin_positions, relative_wis, run_backtest, summarize,
                               summary_by_horizon)

N_DAYS = 300
NOISE = 0.002


def _sir_truth(n_days: int = N_DAYS, beta: float = 0.12, gamma: float = 0.05) -> np.ndarray:
    def rhs(_t, x):
        s, i, _r = x
        return [-beta * s * i, beta * s * i - gamma * i, gamma * i]
    sol = solve_ivp(rhs, (0, n_days - 1), [0.99, 0.01, 0.0], t_eval=np.arange(n_days),
                    rtol=1e-10, atol=1e-12)
    return sol.y.T                                                    # (n_days, 3)


def _frame(values: np.ndarray) -> pd.DataFrame:
    dates = pd.date_range("2020-03-01", periods=len(values), freq="D")
    return pd.DataFrame({"date": dates, "S": values[:, 0], "I": values[:, 1], "R": values[:, 2]})


@dataclass(frozen=True)
class OracleForecaster:
    """Knows the noise-free trajectory; adds N(0, noise²) to each sample (0: a point mass)."""

    truth: pd.DataFrame
    noise: float
    name: str = "oracle"

    def forecast(self, history, horizon_days, n_samples, seed):
        start = len(history)
        future = self.truth[["S", "I", "R"]].to_numpy()[start:start + horizon_days]
        rng = np.random.default_rng(seed)
        return future[None] + self.noise * rng.standard_normal((n_samples, horizon_days, 3))


def test_origin_positions_by_hand():
    # 100 days, ≥ 56 days of history (row 55 earliest), 28-day horizon (row 71 latest): 57, 64, 71.
    np.testing.assert_array_equal(origin_positions(100, BacktestConfig()), [57, 64, 71])
    np.testing.assert_array_equal(origin_positions(100, BacktestConfig(max_origins=2)), [64, 71])
    with pytest.raises(BacktestError, match="too short"):
        origin_positions(80, BacktestConfig())


def test_persistence_paths_replay_past_changes():
    values = _sir_truth(120, beta=0.08)  # mild: no path leaves [0, 1], so clipping is idle
    history = _frame(values)
    paths = PersistenceForecaster(symmetrize=False).forecast(history, 28, 500, seed=4)
    assert paths.shape == (500, 28, 3)
    last = values[-1]
    # every path is last + (x[a+h] - x[a]) for one anchor a within the lookback
    changes = paths - last
    anchors = np.arange(120 - 90, 120 - 28)
    candidates = values[anchors[:, None] + np.arange(1, 29)] - values[anchors][:, None, :]
    dist = np.abs(changes[:, None] - candidates[None]).max(axis=(2, 3))
    assert np.all(dist.min(axis=1) < 1e-12)
    sym = PersistenceForecaster().forecast(history, 28, 4000, seed=4)
    # symmetrized: half the paths above the last value, half below (a flat central forecast)
    assert np.mean(sym[:, 6, 1] > last[1]) == pytest.approx(0.5, abs=0.03)
    assert np.mean(sym[:, 6, 1]) == pytest.approx(last[1], abs=0.05 * np.std(sym[:, 6, 1]))


def test_persistence_is_exact_on_a_linear_series():
    # x_t = a + b t: every past h-step change is b·h, so unsymmetrized persistence is exact.
    t = np.arange(150.0)
    values = np.stack([0.9 - 1e-3 * t, 0.01 + 1e-4 * t, 0.09 + 9e-4 * t], axis=1)
    result = run_backtest(_frame(values), [PersistenceForecaster(symmetrize=False)],
                          BacktestConfig(n_samples=50))
    scores = result.scores
    assert len(scores) == len(origin_positions(150, BacktestConfig())) * 4 * 3
    np.testing.assert_allclose(scores["wis"], 0.0, atol=1e-12)
    np.testing.assert_allclose(scores["median"], scores["observed"], atol=1e-12)


def test_perfect_forecaster_beats_persistence_on_sir():
    rng = np.random.default_rng(0)
    truth = _frame(_sir_truth())
    observed = truth.copy()
    observed[["S", "I", "R"]] += NOISE * rng.standard_normal((N_DAYS, 3))
    forecasters = [PersistenceForecaster(), OracleForecaster(truth, noise=0.0, name="perfect")]
    result = run_backtest(observed, forecasters, BacktestConfig(n_samples=200, seed=1))
    s = result.scores
    n_origins = len(origin_positions(N_DAYS, BacktestConfig()))
    assert n_origins == 31
    assert len(s) == 2 * n_origins * 4 * 3
    np.testing.assert_allclose(s["wis"], s["dispersion"] + s["overprediction"]
                               + s["underprediction"], rtol=1e-12)

    rel_perfect = relative_wis(s, "perfect", "persistence")
    by_hand = (s.loc[s["forecaster"] == "perfect", "wis"].sum()
               / s.loc[s["forecaster"] == "persistence", "wis"].sum())
    assert rel_perfect == pytest.approx(by_hand)
    assert rel_perfect < 0.2
    # the point-mass oracle has zero dispersion: its WIS is pure over/under-prediction
    assert s.loc[s["forecaster"] == "perfect", "dispersion"].max() == 0.0

    summary = summarize(result)
    assert summary.loc["persistence", "relative_wis"] == pytest.approx(1.0)
    assert summary.loc["perfect", "relative_wis"] == pytest.approx(rel_perfect)
    by_h = summary_by_horizon(result)
    assert set(by_h["horizon"]) == {1, 2, 3, 4}
    assert (by_h.loc[by_h["forecaster"] == "perfect", "relative_wis"] < 0.5).all()
    # persistence error grows with the horizon on an epidemic curve
    p = by_h[by_h["forecaster"] == "persistence"].set_index("horizon")["mean_wis"]
    assert p[4] > p[1]


def test_calibrated_forecaster_covers_at_nominal_rates():
    # Observations = truth + N(0, σ²); the oracle samples truth + N(0, σ²): calibrated.
    # Cells of successive origins share target days (origin t, horizon h+1 = origin t+7,
    # horizon h), so only ~(origins + 3) × 3 ≈ 400 observations are independent:
    # SE(50%) ≈ 0.025, SE(90%) ≈ 0.015; tolerances are 3 SE.
    n_days = 1000
    rng = np.random.default_rng(0)
    truth = _frame(_sir_truth(n_days, beta=0.06, gamma=0.04))
    observed = truth.copy()
    observed[["S", "I", "R"]] += NOISE * rng.standard_normal((n_days, 3))
    result = run_backtest(observed, [OracleForecaster(truth, noise=NOISE, name="calibrated")],
                          BacktestConfig(n_samples=200, seed=1))
    cal = result.scores
    assert len(cal) == 131 * 4 * 3
    assert cal["covered_50"].mean() == pytest.approx(0.5, abs=0.075)
    assert cal["covered_90"].mean() == pytest.approx(0.9, abs=0.045)
    # PIT: use one horizon (independent days) for the uniformity test
    assert stats.kstest(cal.loc[cal["horizon"] == 1, "pit"], "uniform").pvalue > 0.001


def test_bad_inputs_are_named():
    values = _sir_truth(150)
    with pytest.raises(BacktestError, match="columns"):
        run_backtest(_frame(values).drop(columns="I"), [PersistenceForecaster()])
    gappy = _frame(values).drop(index=40)
    with pytest.raises(BacktestError, match="consecutive.*2020-04-11"):
        run_backtest(gappy, [PersistenceForecaster()])

    @dataclass(frozen=True)
    class Broken:
        name: str = "broken"

        def forecast(self, history, horizon_days, n_samples, seed):
            return np.zeros((n_samples, horizon_days - 1, 3))

    with pytest.raises(BacktestError, match="'broken' at origin .* shape"):
        run_backtest(_frame(values), [Broken()])
    with pytest.raises(BacktestError, match="unique"):
        run_backtest(_frame(values), [PersistenceForecaster(), PersistenceForecaster()])
