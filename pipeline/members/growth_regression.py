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

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from pipeline.errors import ConfigError
from pipeline.members.base import ForecastsByPool, PoolGroup
from pipeline.members.hub_baseline import row_quantiles

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
            raise ConfigError(f"invalid GrowthRegressionConfig {self}")


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
        if n_w > h:                         # a series shorter than h weeks has no growth yet
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


# ------------------------------------------------------- one pool, many forecast series at once

# Series forecast per call of the batched regression: each carries its own copy of the pool's
# rows (a few thousand), so a chunk's arrays stay within a few tens of MB.
BATCH_CHUNK = 128


def masked_quantiles(values: NDArray[np.float64], mask: NDArray[np.bool_],
                     levels: NDArray[np.float64]) -> NDArray[np.float64]:
    """Type-7 quantiles ``(B, Q)`` of each row's values where ``mask`` (NaN for an empty row)."""
    counts = mask.sum(axis=1)
    if values.shape[1] == 0:
        return np.full((values.shape[0], len(levels)), np.nan)
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    with np.errstate(invalid="ignore"):             # an empty row's inf - inf, replaced below
        out = row_quantiles(ordered, np.maximum(counts, 1), levels)
    return np.where(counts[:, None] > 0, out, np.nan)


def pooled_growth_quantiles(own_weekly: NDArray[np.float64], pool_weekly: NDArray[np.float64],
                            excluded: NDArray[np.intp], horizons: tuple[int, ...],
                            levels: NDArray[np.float64],
                            config: GrowthRegressionConfig = GrowthRegressionConfig()
                            ) -> NDArray[np.float64]:
    """Weekly case quantiles ``(B, H, Q)`` of B series at their last week, each pooled with the
    same places ``pool_weekly (P, W)`` but ``excluded[b]`` (−1: none; a place's own reference
    series): series b's forecast is :func:`growth_regression_quantiles` of the panel (the pool
    without ``excluded[b]``, then ``own_weekly[b]``) at week W − 1, every series in one batch
    (the K completions of a nowcast, many counties)."""
    out = np.empty((own_weekly.shape[0], len(horizons), len(levels)))
    for start in range(0, own_weekly.shape[0], BATCH_CHUNK):
        chunk = slice(start, start + BATCH_CHUNK)
        out[chunk] = _pooled_chunk(own_weekly[chunk], pool_weekly, excluded[chunk], horizons,
                                   np.asarray(levels, dtype=np.float64), config)
    return out


def _pooled_chunk(own_weekly: NDArray[np.float64], pool_weekly: NDArray[np.float64],
                  excluded: NDArray[np.intp], horizons: tuple[int, ...],
                  levels: NDArray[np.float64], config: GrowthRegressionConfig
                  ) -> NDArray[np.float64]:
    own_log = np.log(np.maximum(own_weekly, 0.0) + 1.0)                     # (B, W)
    pool_log = np.log(np.maximum(pool_weekly, 0.0) + 1.0)                   # (P, W)
    x_own, x_pool = features(own_log, config), features(pool_log, config)
    n_b, n_w = own_log.shape
    n_p, n_f = pool_log.shape[0], x_own.shape[-1]
    x_now, log_now = np.nan_to_num(x_own[:, -1]), own_log[:, -1]
    out = np.empty((n_b, len(horizons), len(levels)))
    for k, h in enumerate(horizons):
        rows = max(0, n_w - h)
        y_pool = pool_log[:, h:] - pool_log[:, :rows]                          # (P, rows)
        y_own = own_log[:, h:] - own_log[:, :rows]
        x = np.concatenate([np.broadcast_to(x_pool[:, :rows].reshape(1, -1, n_f),
                                            (n_b, n_p * rows, n_f)),
                            x_own[:, :rows]], axis=1)                          # (B, N, F)
        y = np.concatenate([np.broadcast_to(y_pool.reshape(1, -1), (n_b, n_p * rows)), y_own],
                           axis=1)
        place = np.concatenate([np.repeat(np.arange(n_p), rows), np.full(rows, -1)])
        usable = (np.isfinite(y) & np.isfinite(x).all(axis=-1)
                  & ((place[None, :] < 0) | (place[None, :] != excluded[:, None])))
        x, y = np.where(usable[..., None], x, 0.0), np.where(usable, y, 0.0)
        fitted = usable.sum(axis=1) >= config.min_rows
        log_q = log_now[:, None] + _fallback_spread(y, usable, levels)
        if fitted.any():
            log_q[fitted] = _fitted_log_quantiles(x[fitted], y[fitted], usable[fitted],
                                                  x_now[fitted], log_now[fitted], levels, config)
        out[:, k] = np.maximum.accumulate(np.expm1(log_q), axis=-1)
    return np.maximum(out, 0.0)


def _fallback_spread(y: NDArray[np.float64], usable: NDArray[np.bool_],
                     levels: NDArray[np.float64]) -> NDArray[np.float64]:
    """Too few rows: the quantiles of the growth seen so far (zero without any)."""
    return np.nan_to_num(masked_quantiles(y, usable, levels))


def _fitted_log_quantiles(x: NDArray[np.float64], y: NDArray[np.float64],
                          usable: NDArray[np.bool_], x_now: NDArray[np.float64],
                          log_now: NDArray[np.float64], levels: NDArray[np.float64],
                          config: GrowthRegressionConfig) -> NDArray[np.float64]:
    """:func:`_forecast`'s fit for each row b of the batch on its usable rows: ``(B, Q)``."""
    weight = np.exp(config.count_weight_power * LEVEL_SCALE * x[..., 1]) * usable
    penalty = config.ridge * np.eye(x.shape[-1])
    penalty[0, 0] = 0.0
    gram = np.einsum("bn,bnf,bng->bfg", weight, x, x) + penalty
    beta = np.linalg.solve(gram, np.einsum("bn,bnf,bn->bf", weight, x, y)[..., None])[..., 0]
    residual = y - np.einsum("bnf,bf->bn", x, beta)
    level = x[..., 1]
    if config.level_groups > 1:
        inner = np.linspace(0, 1, config.level_groups + 1)[1:-1]
        edges = masked_quantiles(level, usable, inner)                        # (B, G - 1)
    else:
        edges = np.empty((x.shape[0], 0))
    group = (level[..., None] > edges[:, None, :]).sum(axis=-1)               # searchsorted left
    overall = masked_quantiles(residual, usable, levels)
    spread = np.stack([np.where(((group == g) & usable).sum(axis=1, keepdims=True)
                                >= config.min_group_rows,
                                masked_quantiles(residual, (group == g) & usable, levels),
                                overall)
                       for g in range(edges.shape[1] + 1)], axis=1)           # (B, G, Q)
    group_now = (x_now[:, 1, None] > edges).sum(axis=-1)
    return (log_now + np.einsum("bf,bf->b", x_now, beta))[:, None] + \
        spread[np.arange(x.shape[0]), group_now]


@dataclass(frozen=True, eq=False)
class PooledGrowthMember(ForecastsByPool):
    """``growth-qr`` (module docstring). A cell's pool is its panel as known at its origin
    (:meth:`~pipeline.panels.panel.Panel.pool`: the references other than its place, then every
    place of the panel), with the cell's own history as its place's row. Cells whose own rows
    are their panel's share one regression per origin (and length); cells with their own
    version of a place's data (a nowcast's completions) are fitted one regression each, in one
    batch."""

    config: GrowthRegressionConfig = GrowthRegressionConfig()
    name: str = GROWTH_QR
    pools: ClassVar[bool] = True          # learns from the cell's panel (the memo keys on it)

    def group_forecast(self, group: PoolGroup, horizons: tuple[int, ...],
                       levels: NDArray[np.float64]) -> NDArray[np.float64]:
        """``(B, H, Q)`` counts of the group's cells: one regression where their rows are
        their panel's, else one each."""
        pool = group.pool
        rows = np.array([group.panel.own_row(place) for place in group.places])
        mine = np.stack(group.own)
        if np.array_equal(pool[rows], mine, equal_nan=True):
            return growth_regression_quantiles(pool, np.array([group.n_weeks - 1]), horizons,
                                               levels, self.config)[rows, 0]
        return pooled_growth_quantiles(mine, pool, rows, horizons, levels, self.config)
