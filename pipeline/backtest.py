"""Rolling-origin backtest of S/I/R forecasters, scored by WIS, coverage and PIT.

For each weekly origin t (the last day of data the forecaster sees), every forecaster gets the
history up to and including t and returns sample paths for days t+1 … t+28. We score the
23 hub quantiles (from the samples) at t + 7h, h = 1…4, against the observed values.

Relative WIS of model A against baseline B = Σ WIS_A / Σ WIS_B over exactly the same
(origin, compartment, horizon) cells — both forecasters scored on the same forecasts, so
< 1 means A is better. (The hub evaluations' pairwise geometric-mean version reduces to this
ratio of means when there are only two models and a common set of forecasts.)

S, I and R are proportions with very different levels (S ≈ 1, I ≈ 1e-3); pooled sums are
dominated by the compartment with the largest errors, so summaries are also given per
compartment.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.errors import FlowcastError
from pipeline.forecast_hub import COMPARTMENTS, HUB_QUANTILE_LEVELS
from pipeline.progress import ProgressReporter, SilentProgress
from pipeline.scoring import (interval_coverage, pit_values, quantiles_from_samples,
                              weighted_interval_score)


class BacktestError(FlowcastError):
    """Bad series, configuration or forecaster output in a backtest."""


class Forecaster(Protocol):
    """Anything that turns a history of daily S/I/R into sample paths."""

    name: str

    def forecast(self, history: pd.DataFrame, horizon_days: int, n_samples: int,
                 seed: int) -> NDArray[np.float64]:
        """``history``: columns date, S, I, R (daily, ascending, ends at the origin).
        Returns paths ``(n_samples, horizon_days, 3)`` for the days after the last date."""
        ...


@dataclass(frozen=True)
class BacktestConfig:
    """Which origins and horizons to score.

    Origins are every ``origin_step_days`` days, the first one at least ``min_history_days``
    after the series starts (a forecaster sees at least that much), the last one such that
    the longest horizon is still observed.
    """

    horizons_weeks: tuple[int, ...] = (1, 2, 3, 4)
    n_samples: int = 200
    origin_step_days: int = 7
    min_history_days: int = 56
    max_origins: int | None = None   # keep only the latest N origins (None: all)
    quantile_levels: tuple[float, ...] = HUB_QUANTILE_LEVELS
    seed: int = 0

    @property
    def horizon_days(self) -> int:
        return 7 * max(self.horizons_weeks)


@dataclass(frozen=True, eq=False)
class BacktestResult:
    """One row per (forecaster, origin, compartment, horizon) with its scores."""

    scores: pd.DataFrame   # forecaster, origin, compartment, horizon, target_end_date, observed,
    #                        median, wis, dispersion, overprediction, underprediction,
    #                        covered_50, covered_90, pit
    config: BacktestConfig

    @property
    def forecasters(self) -> list[str]:
        return list(dict.fromkeys(self.scores["forecaster"]))


def validate_series(series: pd.DataFrame) -> pd.DataFrame:
    """Columns date, S, I, R; consecutive daily dates; finite values. Returns a sorted copy."""
    missing = [c for c in ("date", *COMPARTMENTS) if c not in series.columns]
    if missing:
        raise BacktestError(f"series lacks columns {missing} (needs date, S, I, R)")
    frame = series[["date", *COMPARTMENTS]].copy()
    frame["date"] = pd.to_datetime(frame["date"]).dt.normalize()
    frame = frame.sort_values("date", ignore_index=True)
    gaps = frame["date"].diff().dt.days.iloc[1:]
    if (gaps != 1).any():
        where = frame["date"].iloc[1:][gaps.to_numpy() != 1].iloc[0].date()
        raise BacktestError(f"series dates must be consecutive days; gap or duplicate at {where}")
    values = frame[list(COMPARTMENTS)].to_numpy(dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise BacktestError("series has NaN or inf in S, I or R")
    return frame


def origin_positions(n_days: int, config: BacktestConfig) -> NDArray[np.intp]:
    """Row indices of the origins (the last history day of each forecast)."""
    first = config.min_history_days - 1
    last = n_days - 1 - config.horizon_days
    if last < first:
        raise BacktestError(f"series of {n_days} days is too short for {config.min_history_days} "
                            f"days of history plus a {config.horizon_days}-day horizon")
    # anchor on the latest possible origin so the most recent weeks are always scored
    positions = np.arange(last, first - 1, -config.origin_step_days)[::-1]
    if config.max_origins is not None:
        positions = positions[-config.max_origins:]
    return positions


def _checked_paths(paths: NDArray[np.float64], name: str, origin: pd.Timestamp,
                   config: BacktestConfig) -> NDArray[np.float64]:
    expected = (config.n_samples, config.horizon_days, len(COMPARTMENTS))
    arr = np.asarray(paths, dtype=np.float64)
    if arr.shape != expected:
        raise BacktestError(f"forecaster {name!r} at origin {origin.date()} returned shape "
                            f"{arr.shape}, expected {expected}")
    if not np.all(np.isfinite(arr)):
        raise BacktestError(f"forecaster {name!r} at origin {origin.date()} returned NaN/inf")
    return arr


def run_backtest(series: pd.DataFrame, forecasters: Sequence[Forecaster],
                 config: BacktestConfig = BacktestConfig(),
                 progress: ProgressReporter | None = None) -> BacktestResult:
    """Forecast from every origin with every forecaster and score what followed."""
    if not forecasters:
        raise BacktestError("no forecasters given")
    names = [f.name for f in forecasters]
    if len(set(names)) != len(names):
        raise BacktestError(f"forecaster names must be unique, got {names}")
    progress = progress or SilentProgress()
    frame = validate_series(series)
    values = frame[list(COMPARTMENTS)].to_numpy(dtype=np.float64)
    origins = origin_positions(len(frame), config)
    steps = 7 * np.asarray(config.horizons_weeks) - 1          # path step of t + 7h
    observed = values[origins[:, None] + steps[None, :] + 1]   # (O, H, 3)

    frames = []
    for forecaster in forecasters:
        at_horizons = np.empty((origins.size, steps.size, len(COMPARTMENTS), config.n_samples))
        for k, pos in enumerate(origins):
            origin = frame["date"].iloc[pos]
            history = frame.iloc[: pos + 1].reset_index(drop=True)
            paths = forecaster.forecast(history, config.horizon_days, config.n_samples,
                                        seed=config.seed + int(pos))
            paths = _checked_paths(paths, forecaster.name, origin, config)
            at_horizons[k] = np.transpose(paths[:, steps, :], (1, 2, 0))
            progress.advance(1, forecaster=forecaster.name, origin=str(origin.date()))
        frames.append(_score_block(forecaster.name, frame["date"].iloc[origins].to_numpy(),
                                   at_horizons, observed, config))
    return BacktestResult(scores=pd.concat(frames, ignore_index=True), config=config)


def _score_block(name: str, origin_dates: NDArray, samples: NDArray[np.float64],
                 observed: NDArray[np.float64], config: BacktestConfig) -> pd.DataFrame:
    """Score samples (O, H, 3, n) against observed (O, H, 3); one row per cell."""
    levels = np.asarray(config.quantile_levels)
    quantiles = quantiles_from_samples(samples, levels)
    parts = weighted_interval_score(levels, quantiles, observed)
    n_o, n_h, n_c = observed.shape
    horizons = np.asarray(config.horizons_weeks)
    origin_col = np.repeat(pd.to_datetime(origin_dates), n_h * n_c)
    horizon_col = np.tile(np.repeat(horizons, n_c), n_o)
    median_idx = int(np.argmin(np.abs(levels - 0.5)))
    return pd.DataFrame({
        "forecaster": name,
        "origin": origin_col,
        "compartment": np.tile(np.array(COMPARTMENTS), n_o * n_h),
        "horizon": horizon_col,
        "target_end_date": origin_col + pd.to_timedelta(7 * horizon_col, unit="D"),
        "observed": observed.reshape(-1),
        "median": quantiles[..., median_idx].reshape(-1),
        "wis": parts.wis.reshape(-1),
        "dispersion": parts.dispersion.reshape(-1),
        "overprediction": parts.overprediction.reshape(-1),
        "underprediction": parts.underprediction.reshape(-1),
        "covered_50": interval_coverage(levels, quantiles, observed, 0.5).reshape(-1),
        "covered_90": interval_coverage(levels, quantiles, observed, 0.9).reshape(-1),
        "pit": pit_values(samples, observed, seed=config.seed).reshape(-1),
    })


def relative_wis(scores: pd.DataFrame, model: str, baseline: str,
                 by: Sequence[str] = ()) -> pd.Series | float:
    """Σ WIS(model) / Σ WIS(baseline) over the cells both scored (optionally grouped by ``by``)."""
    keys = ["origin", "compartment", "horizon"]
    a = scores[scores["forecaster"] == model].set_index(keys)["wis"]
    b = scores[scores["forecaster"] == baseline].set_index(keys)["wis"]
    if a.empty or b.empty:
        raise BacktestError(f"no scores for {model if a.empty else baseline!r}; "
                            f"available: {sorted(set(scores['forecaster']))}")
    joined = pd.concat({"model": a, "baseline": b}, axis=1, join="inner").reset_index()
    if not by:
        return float(joined["model"].sum() / joined["baseline"].sum())
    sums = joined.groupby(list(by))[["model", "baseline"]].sum()
    return sums["model"] / sums["baseline"]


def summarize(result: BacktestResult, baseline: str = "persistence") -> pd.DataFrame:
    """Per forecaster: mean WIS (and parts), relative WIS against ``baseline``, coverage."""
    s = result.scores
    summary = s.groupby("forecaster", sort=False).agg(
        mean_wis=("wis", "mean"), dispersion=("dispersion", "mean"),
        overprediction=("overprediction", "mean"), underprediction=("underprediction", "mean"),
        coverage_50=("covered_50", "mean"), coverage_90=("covered_90", "mean"),
        n_forecasts=("wis", "size"))
    summary.insert(1, "relative_wis", [relative_wis(s, name, baseline) for name in summary.index])
    return summary


def summary_by_horizon(result: BacktestResult, baseline: str = "persistence",
                       compartment: str | None = None) -> pd.DataFrame:
    """Rows (forecaster, horizon): relative WIS, coverage 50/90 — the backtest figure's input."""
    s = result.scores if compartment is None else \
        result.scores[result.scores["compartment"] == compartment]
    cov = s.groupby(["forecaster", "horizon"], sort=False).agg(
        mean_wis=("wis", "mean"), coverage_50=("covered_50", "mean"),
        coverage_90=("covered_90", "mean")).reset_index()
    rel = pd.concat({name: relative_wis(s, name, baseline, by=["horizon"])
                     for name in cov["forecaster"].unique()}, names=["forecaster"])
    rel = rel.rename("relative_wis").reset_index()
    return cov.merge(rel, on=["forecaster", "horizon"])


@dataclass(frozen=True)
class PersistenceForecaster:
    """Last value carried forward, with the empirical spread of past h-step changes.

    Each sample path picks one past anchor day a uniformly among the last ``lookback_days``
    (those with a full horizon after them inside the history) and replays that stretch's
    changes: path(h) = x_T + sign·(x_{a+h} − x_a), h = 1…H. So each day-h marginal is the
    empirical distribution of the history's h-step changes, and paths keep their
    autocorrelation. With ``symmetrize`` (default, as the COVID-19 Forecast Hub baseline does)
    a random sign makes the distribution symmetric, so the median stays the last value —
    a flat forecast. Values are clipped to [0, 1] (proportions).
    """

    name: str = "persistence"
    lookback_days: int = 90
    symmetrize: bool = True

    def forecast(self, history: pd.DataFrame, horizon_days: int, n_samples: int,
                 seed: int) -> NDArray[np.float64]:
        x = history[list(COMPARTMENTS)].to_numpy(dtype=np.float64)      # (T, 3)
        n_days = x.shape[0]
        last_anchor = n_days - 1 - horizon_days
        first_anchor = max(0, n_days - self.lookback_days)
        if last_anchor < first_anchor:
            raise BacktestError(f"persistence needs more than {horizon_days} days of history "
                                f"within the {self.lookback_days}-day lookback; got {n_days}")
        rng = np.random.default_rng(seed)
        anchors = rng.integers(first_anchor, last_anchor + 1, size=n_samples)      # (n,)
        ahead = anchors[:, None] + np.arange(1, horizon_days + 1)[None, :]          # (n, H)
        changes = x[ahead] - x[anchors][:, None, :]                                 # (n, H, 3)
        if self.symmetrize:
            changes = changes * rng.choice([-1.0, 1.0], size=(n_samples, 1, 1))
        return np.clip(x[-1][None, None, :] + changes, 0.0, 1.0)
