"""A growth-rate member learnt across places in real time (``growth-qr``).

At origin t, for each horizon h, the log growth y = log(C_{t+h} + 1) − log(C_t + 1) of the weekly
case count is regressed on the log level, the last ``lags`` weekly log growth rates and the log
growth over the last ``long_lag_weeks`` weeks, over every place of a panel and every past weekly
origin whose target week had ended by t (weighted ridge least squares). Its predictive quantiles
are the fit plus the empirical quantiles of the training residuals of places at a similar level
(``level_groups`` bins: small counts are noisier). Nothing but the counts up to t enters the
forecast at t, in any place.

Why each choice (measured on the cross-county backtest, ``bench/results/backtest_counties.json``,
``variants``):

* pooled across places, because one county's history holds a handful of waves, while every
  county's holds hundreds of weeks of growth and decline: how fast growth decays, how plateaus
  hold;
* every past week, not a recent window: recency-weighted fits chased the current regime and
  overshot at the turns (a 12-origin window was 40 % worse at four weeks);
* rows weighted by √(C_t + 1): the weighted interval score of a count scales with the count, so
  busy weeks should shape the fit more than quiet ones;
* no regional (statewide) growth features: they sharpened the first week and made weeks 3–4
  much worse (momentum of the region, extrapolated, misses its turns).

Before ``min_rows`` training rows exist the forecast is the last count with the spread of the
growth seen so far (zero growth).
"""
from __future__ import annotations

import functools

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.ensemble.combine import EnsembleError
from pipeline.ensemble.members import quantile_forecast_from_weekly_cases
from pipeline.ensemble.targets import DAYS_PER_WEEK, EpiHistory, QuantileForecast, TargetError

GROWTH_QR = "growth-qr"
LEVEL_SCALE = 10.0            # log counts / 10: features of comparable size for the ridge


@dataclass(frozen=True)
class GrowthRegressionConfig:
    lags: int = 2
    long_lag_weeks: int | None = 4
    count_weight_power: float = 0.5
    level_groups: int = 3
    ridge: float = 1.0
    min_rows: int = 100
    min_group_rows: int = 5

    def __post_init__(self) -> None:
        if (self.lags < 1 or self.min_rows < 2 or self.level_groups < 1 or self.ridge < 0
                or self.count_weight_power < 0 or self.min_group_rows < 2
                or (self.long_lag_weeks is not None and self.long_lag_weeks < 2)):
            raise EnsembleError(f"invalid GrowthRegressionConfig {self}")


def _lagged_difference(values: NDArray[np.float64], lag: int) -> NDArray[np.float64]:
    """values[..., t] − values[..., t − lag] (NaN for the first ``lag`` weeks)."""
    out = np.full_like(values, np.nan)
    out[..., lag:] = values[..., lag:] - values[..., :-lag]
    return out


def _shifted(values: NDArray[np.float64], weeks: int) -> NDArray[np.float64]:
    """values[..., t − weeks] (NaN where it does not exist)."""
    if weeks == 0:
        return values
    out = np.full_like(values, np.nan)
    out[..., weeks:] = values[..., :-weeks]
    return out


def features(log_weekly: NDArray[np.float64], config: GrowthRegressionConfig
             ) -> NDArray[np.float64]:
    """``(..., W, F)``: 1, the log level / 10, the last ``lags`` weekly log growth rates and the
    log growth over ``long_lag_weeks`` weeks, at each week (NaN where weeks before are missing)."""
    growth = _lagged_difference(log_weekly, 1)
    columns = [np.ones_like(log_weekly), log_weekly / LEVEL_SCALE]
    columns += [_shifted(growth, k) for k in range(config.lags)]
    if config.long_lag_weeks is not None:
        columns.append(_lagged_difference(log_weekly, config.long_lag_weeks))
    return np.stack(columns, axis=-1)


def _level_edges(levels: NDArray[np.float64], groups: int) -> NDArray[np.float64]:
    if groups <= 1 or levels.size == 0:
        return np.empty(0)
    return np.quantile(levels, np.linspace(0, 1, groups + 1)[1:-1])


def growth_regression_quantiles(weekly_cases: NDArray[np.float64],
                                origin_index: NDArray[np.intp], horizons: tuple[int, ...],
                                levels: NDArray[np.float64],
                                config: GrowthRegressionConfig = GrowthRegressionConfig()
                                ) -> NDArray[np.float64]:
    """Weekly case quantiles ``(C, O, H, Q)``.

    ``weekly_cases (C, W)``: each place's weekly counts on a common calendar of consecutive weeks
    (weeks ending on the origins' weekday; NaN where a place has no data); ``origin_index (O,)``:
    the week each origin ends. The regression at origin week j uses rows (place, week i) with
    i + h ≤ j only, so week j's forecast never sees a count after week j."""
    log_w = np.log(np.maximum(weekly_cases, 0.0) + 1.0)
    x = features(log_w, config)                                             # (C, W, F)
    n_c, n_w, n_f = x.shape
    out = np.empty((n_c, len(origin_index), len(horizons), len(levels)))
    for k, h in enumerate(horizons):
        y = np.full((n_c, n_w), np.nan)
        y[:, :n_w - h] = log_w[:, h:] - log_w[:, :n_w - h]
        for o, j in enumerate(origin_index):
            rows = slice(0, max(0, j - h + 1))
            out[:, o, k] = _forecast(x[:, rows].reshape(-1, n_f), y[:, rows].ravel(),
                                     x[:, j], log_w[:, j], levels, config)
    return np.maximum(out, 0.0)


def _forecast(x_train: NDArray[np.float64], y_train: NDArray[np.float64],
              x_now: NDArray[np.float64], log_now: NDArray[np.float64],
              levels: NDArray[np.float64], config: GrowthRegressionConfig
              ) -> NDArray[np.float64]:
    """Quantiles ``(C, Q)`` of the weekly count at one horizon for every place."""
    usable = np.isfinite(y_train) & np.isfinite(x_train).all(axis=1)
    x_train, y_train = x_train[usable], y_train[usable]
    x_now = np.nan_to_num(x_now)
    if y_train.size < config.min_rows:
        residual = y_train if y_train.size else np.zeros(1)
        spread = np.quantile(residual, levels)
        return np.maximum.accumulate(np.expm1(log_now[:, None] + spread[None]), axis=-1)
    weight = np.exp(config.count_weight_power * LEVEL_SCALE * x_train[:, 1])   # (C_t + 1)^p
    penalty = config.ridge * np.eye(x_train.shape[1])
    penalty[0, 0] = 0.0                                      # the intercept is not shrunk
    weighted = x_train * weight[:, None]
    beta = np.linalg.solve(weighted.T @ x_train + penalty, weighted.T @ y_train)
    residual = y_train - x_train @ beta
    edges = _level_edges(x_train[:, 1], config.level_groups)
    group_train = np.searchsorted(edges, x_train[:, 1])
    spread = np.stack([np.quantile(residual[group_train == g], levels)
                       if (group_train == g).sum() >= config.min_group_rows
                       else np.quantile(residual, levels)
                       for g in range(len(edges) + 1)])                     # (G, Q)
    log_q = log_now[:, None] + (x_now @ beta)[:, None] + spread[np.searchsorted(edges,
                                                                                x_now[:, 1])]
    return np.maximum.accumulate(np.expm1(log_q), axis=-1)


# ----------------------------------------------------------------------- as a weekly member


def weekly_sums_ending(cases: NDArray[np.integer] | NDArray[np.floating], dates: pd.DatetimeIndex, end: pd.Timestamp,
                       n_weeks: int) -> NDArray[np.float64]:
    """Counts of the ``n_weeks`` 7-day weeks ending at ``end``, ``end`` − 7, … (oldest first) of a
    daily series; NaN for weeks not wholly inside the series (or after its last day)."""
    cumulative = np.concatenate([[0.0], np.cumsum(np.asarray(cases, dtype=np.float64))])
    return cumulative_weeks_ending(cumulative, dates[0], end, n_weeks)


def cumulative_weeks_ending(cumulative: NDArray[np.float64], first: pd.Timestamp,
                            end: pd.Timestamp, n_weeks: int) -> NDArray[np.float64]:
    """:func:`weekly_sums_ending` from a series' cumulative counts (a leading 0, then one per
    day from ``first``)."""
    n_days = len(cumulative) - 1
    week_ends = (end - first).days - DAYS_PER_WEEK * np.arange(n_weeks)[::-1]      # day index
    inside = (week_ends - DAYS_PER_WEEK + 1 >= 0) & (week_ends < n_days)
    safe = np.clip(week_ends, DAYS_PER_WEEK - 1, n_days - 1)
    sums = cumulative[safe + 1] - cumulative[safe + 1 - DAYS_PER_WEEK]
    return np.where(inside, sums, np.nan)


@dataclass(frozen=True, eq=False)
class PooledGrowthMember:
    """``growth-qr`` for one place at a time, pooled with ``reference`` places (e.g. California's
    counties for San Francisco). At an origin it sees the history it is given and the reference
    places' counts up to the same origin, nothing later."""

    reference: Sequence[EpiHistory] = ()
    config: GrowthRegressionConfig = GrowthRegressionConfig()
    name: str = GROWTH_QR

    def forecast(self, history: EpiHistory, horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int) -> QuantileForecast:
        own = history.weekly_cases()
        if own.size < 2:
            raise TargetError(f"{self.name} at {history.origin.date()}: needs two complete "
                              f"weeks, got {len(history)} days")
        others = self._reference_weeks_ending(history.origin, own.size)
        weekly = np.vstack([others, own[None]])
        quantiles = growth_regression_quantiles(weekly, np.array([own.size - 1]), horizons,
                                                np.asarray(levels, dtype=np.float64),
                                                self.config)[-1, 0]
        return quantile_forecast_from_weekly_cases(self.name, history.origin, horizons,
                                                   np.asarray(levels, dtype=np.float64),
                                                   quantiles, history.population)

    @functools.cached_property
    def _reference_cumulative(self) -> tuple[tuple[pd.Timestamp, NDArray[np.float64]], ...]:
        """Each reference place's first day and cumulative daily cases (computed once: a week's
        sum reads only its own days, so an origin still sees nothing after it)."""
        return tuple((r.dates[0], np.concatenate([[0.0], np.cumsum(r.cases, dtype=np.float64)]))
                     for r in self.reference)

    def _reference_weeks_ending(self, end: pd.Timestamp, n_weeks: int) -> NDArray[np.float64]:
        """``(P, n_weeks)`` weekly counts of the reference places that began by ``end``, for the
        weeks ending ``end``, ``end`` − 7, … (NaN where a week is not wholly observed)."""
        rows = [cumulative_weeks_ending(cumulative, first, end, n_weeks)
                for first, cumulative in self._reference_cumulative if first <= end]
        return np.vstack(rows) if rows else np.empty((0, n_weeks))

    def forecast_panel(self, weekly_cases: NDArray[np.float64], origin_index: NDArray[np.intp],
                       horizons: tuple[int, ...], levels: NDArray[np.float64]
                       ) -> NDArray[np.float64]:
        """Every place of a panel at every origin at once, ``(C, O, H, Q)`` (the panel is the
        pool; ``reference`` is not used)."""
        return growth_regression_quantiles(weekly_cases, origin_index, horizons, levels,
                                           self.config)
