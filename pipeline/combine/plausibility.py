"""The changes a forecast may imply: no faster than the data's own history has shown.

A quantile q at h weeks from a cell whose last week counted x₀ implies the change
log(1 + q) − log(1 + x₀) over h weeks. The bound of a cell at horizon h is the ``tail`` and
1 − ``tail`` quantiles of the h-week changes of log(1 + x) its panel had shown by the cell's
origin, over every place and every week that started within a factor ``level_ratio`` of x₀
(small counts swing more than large ones, so a cell is held only to weeks at its own level).
Each side asks for evidence of its own kind: the lower band reads the weeks at the level only
where at least ``min_rows`` of them were followed by a fall over h weeks, the upper band only
where as many were followed by a rise; otherwise every week of the panel. Quantiles beyond the
bound are moved onto it (:func:`bounded`), which keeps them ordered.

Why: the weekly SF forecast of 2022-03-12 (589 cases) put its 5 % quantile at 10 cases four
weeks on, a fall of 98 % in a month that no place of California had shown at that level.

Why each side counts its own kind: a level first reached in a surge has been seen mostly on the
way up, and a bound read from those weeks holds a fall to the few small falls among them.
California's large counties first stood that high in the winter of 2020-21. At the origin of
2021-01-23 the bound held Orange, Riverside, San Bernardino and San Diego to no less than
37-46 % of their week's count four weeks on; they fell to 15-21 %. With every week at the
level counted, the counties' worst window of 15 origins was that one (2021-01-23 … 05-01), at
1.062 times the uncalibrated WIS; with each side counting its own kind, the worst is 1.026
(2021-05-08 … 08-14; bench/results/backtest_counties.json).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.combine.average import EnsembleError
from pipeline.members.growth_regression import masked_quantiles
from pipeline.panels.panel import Cells, Panel


@dataclass(frozen=True)
class PlausibilityConfig:
    """``tail``: the share of the panel's changes at a cell's level left beyond the bound on
    each side; ``level_ratio``: how far a past week's count may be from the cell's (a factor);
    ``min_rows``: fewer past falls (for the lower band; rises for the upper) at the level than
    this and the whole panel's weeks count;
    ``bound_rises``: False bounds falls only (a new variant may grow faster than any week
    before it: San Francisco's cases did at Omicron's onset, December 2021)."""

    tail: float = 0.001
    level_ratio: float = 2.0
    min_rows: int = 50
    bound_rises: bool = True

    def __post_init__(self) -> None:
        if not 0 <= self.tail < 0.5 or self.level_ratio <= 1 or self.min_rows < 1:
            raise EnsembleError(f"invalid PlausibilityConfig {self}")


# The published bound (CombineConfig.bounded): falls only. Bounding the rises too cost San
# Francisco 1.7 % of WIS (0.705 against 0.693), all of it at Omicron's onset (the origins of
# 2021-12-04 to 2021-12-25), when cases rose faster than any week before; falls alone cost
# 0.09 % there and 0.1 % on the counties (bench/results/backtest*.json, variants).
FALLS_BOUND = PlausibilityConfig(bound_rises=False)


def _changes(pool: NDArray[np.float64], h: int) -> tuple[NDArray[np.float64],
                                                          NDArray[np.float64]]:
    """The start level log(1 + x_t) and the h-week change of every (place, week) held."""
    logs = np.log1p(np.maximum(pool, 0.0))
    if logs.shape[1] <= h:
        return np.empty(0), np.empty(0)
    start, change = logs[:, :-h].reshape(-1), (logs[:, h:] - logs[:, :-h]).reshape(-1)
    held = np.isfinite(start) & np.isfinite(change)
    return start[held], change[held]


def _group_bands(panel: Panel, place: str, origin: pd.Timestamp, n_weeks: int,
                 last: NDArray[np.float64], horizons: Sequence[int],
                 config: PlausibilityConfig) -> NDArray[np.float64]:
    """``(B, H, 2)`` bounds on log(1 + q) − log(1 + x₀) of cells at one origin of one panel."""
    pool = panel.pool(place, origin, n_weeks)
    level = np.log1p(np.maximum(last, 0.0))
    out = np.full((len(last), len(horizons), 2), np.nan)
    for k, h in enumerate(horizons):
        start, change = _changes(pool, h)
        if change.size < config.min_rows:
            continue                      # too little history to say what is implausible
        near = np.abs(start[None, :] - level[:, None]) <= np.log(config.level_ratio)
        values = np.broadcast_to(change, near.shape)
        for side, (tail, seen) in enumerate(((config.tail, change < 0),
                                             (1.0 - config.tail, change > 0))):
            enough = (near & seen).sum(axis=1) >= config.min_rows
            rows = np.where(enough[:, None], near, True)
            out[:, k, side] = masked_quantiles(values, rows, np.array([tail]))[:, 0]
    if not config.bound_rises:
        out[..., 1] = np.nan
    return out


def plausible_bands(cells: Cells, horizons: Sequence[int], config: PlausibilityConfig
                    ) -> NDArray[np.float64]:
    """``(B, H, 2)`` the lowest and highest count each cell may forecast at each horizon
    (module docstring); NaN where the panel's history is too short to bound it."""
    last = np.array([_last_held(h.weekly_cases()) for h in cells.histories])
    out = np.full((len(cells), len(horizons), 2), np.nan)
    for (_, origin, n, _), index in cells.pool_groups().items():
        b0 = index[0]
        log_change = _group_bands(cells.panels[b0], cells.places[b0], origin, n,
                                  last[index], horizons, config)
        out[index] = np.expm1(np.log1p(np.maximum(last[index], 0.0))[:, None, None]
                              + log_change)
    return out


def _last_held(weekly: NDArray[np.float64]) -> float:
    held = weekly[np.isfinite(weekly)]
    return float(held[-1]) if held.size else np.nan


def bounded(quantiles: NDArray[np.float64], bands: NDArray[np.float64]) -> NDArray[np.float64]:
    """``quantiles (..., Q)`` moved into ``bands (..., 2)`` (NaN bands: left alone)."""
    low = np.nan_to_num(bands[..., :1], nan=-np.inf)
    high = np.nan_to_num(bands[..., 1:], nan=np.inf)
    return np.clip(quantiles, low, high)


def share_beyond(quantiles: NDArray[np.float64], bands: NDArray[np.float64]) -> float:
    """The share of finite quantiles beyond their bands (of those with a band on either
    side; a bound on falls alone has no upper band)."""
    low, high = bands[..., :1], bands[..., 1:]
    held = np.isfinite(quantiles) & (np.isfinite(low) | np.isfinite(high))
    beyond = (quantiles < low) | (quantiles > high)          # NaN compares False: no bound
    return float((beyond & held).sum() / max(held.sum(), 1))
