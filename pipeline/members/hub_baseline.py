"""The COVID-19 Forecast Hub baseline (reichlab ``covidModels::quantile_baseline``, symmetrized).

Definition, per target on that target's own series x_1..x_T (T = the origin):

* differences: ``I`` — the one-week differences of the daily I series, I_t − I_{t−7}, over the
  whole history (overlapping weeks); ``cases`` — consecutive differences of the weekly case
  series ending at the origin. Symmetrized: the differences and their negatives (so the median
  difference is 0).
* h = 1: the quantiles are x_T + the type-7 quantiles of the symmetrized differences (exact, as
  reichlab computes them: "for horizon 1 ... we can extract exact quantiles").
* h ≥ 2: reichlab's resampling. ``n_samples`` draws d = Q_diff(linspace(0, 1, n_samples)) (the
  type-7 quantile function of the differences on an even grid); a trajectory adds an independent
  random permutation of them each week; the week-h sums are shifted so their median is 0
  ("force median difference = 0"); quantiles of x_T + sum (type 7).
* median = x_T (last observed value); every quantile is clipped at 0 (incidence is non-negative).

Deterministic given ``seed``. Reference: reichlab/covidModels ``R/quantile_baseline.R``
(``new_quantile_baseline``, ``fit_quantile_baseline``, ``predict.quantile_baseline``), the model
``COVIDhub-baseline`` (Cramer et al. 2022, PNAS 119(15): e2113561119).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.members.base import MemberForecast
from pipeline.panels.history import EpiHistory
from pipeline.panels.panel import Cells
from pipeline.panels.targets import DAYS_PER_WEEK, SHARE, TargetError

HUB_BASELINE = "hub-baseline"


@dataclass(frozen=True)
class HubBaselineConfig:
    """``n_samples``: trajectories for h ≥ 2 (reichlab resamples; 100,000 keeps the Monte Carlo
    error of the 1 %/99 % quantiles near 1 % of the spread)."""

    n_samples: int = 100_000
    symmetrize: bool = True

    def __post_init__(self) -> None:
        if self.n_samples < 2:
            raise TargetError(f"HubBaselineConfig.n_samples={self.n_samples} must be >= 2")


def symmetrized(differences: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.concatenate([differences, -differences])


def row_quantiles(sorted_rows: NDArray[np.float64], counts: NDArray[np.intp],
                   q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Type-7 quantiles ``(B, K)`` of each row's first ``counts[b]`` (sorted) values."""
    position = q[None, :] * (counts[:, None] - 1)
    low = np.floor(position).astype(np.intp)
    high = np.minimum(low + 1, counts[:, None] - 1)
    frac = position - low
    below = np.take_along_axis(sorted_rows, low, axis=1)
    above = np.take_along_axis(sorted_rows, high, axis=1)
    return below + frac * (above - below)


# Rows drawn at once: each holds a few arrays of n_samples draws (3,551 cells of FluSight's
# backtest at 10,000 draws took 21 GB in one batch); rows are independent, so chunks change
# nothing.
CHUNK_ROWS = 256


def baseline_quantiles_batch(last_values: NDArray[np.float64],
                             differences: Sequence[NDArray[np.float64]],
                             horizons: tuple[int, ...], levels: NDArray[np.float64],
                             seeds: Sequence[int], config: HubBaselineConfig = HubBaselineConfig()
                             ) -> NDArray[np.float64]:
    """Quantiles ``(B, H, Q)`` of B baselines (module docstring), each from its last value, its
    own past differences and its own seed: row b never depends on another row's data."""
    last = np.asarray(last_values, dtype=np.float64)
    chunks = [_baseline_rows(last[i:i + CHUNK_ROWS], differences[i:i + CHUNK_ROWS], horizons,
                             levels, seeds[i:i + CHUNK_ROWS], config)
              for i in range(0, len(differences), CHUNK_ROWS)]
    return np.concatenate(chunks) if chunks else np.empty((0, len(horizons), len(levels)))


def _baseline_rows(last_values: NDArray[np.float64], differences: Sequence[NDArray[np.float64]],
                   horizons: tuple[int, ...], levels: NDArray[np.float64],
                   seeds: Sequence[int], config: HubBaselineConfig) -> NDArray[np.float64]:
    rows = [np.asarray(d, dtype=np.float64) for d in differences]
    rows = [d[np.isfinite(d)] for d in rows]
    if any(d.size == 0 for d in rows):
        raise TargetError("hub baseline needs at least one past difference")
    if config.symmetrize:
        rows = [symmetrized(d) for d in rows]
    counts = np.array([d.size for d in rows], dtype=np.intp)
    padded = np.full((len(rows), int(counts.max())), np.inf)
    for b, d in enumerate(rows):
        padded[b, :d.size] = np.sort(d)
    lv = np.asarray(levels, dtype=np.float64)
    grid = row_quantiles(padded, counts, np.linspace(0.0, 1.0, config.n_samples))  # (B, S)
    generators = [np.random.default_rng(seed) for seed in seeds]
    out = np.empty((len(rows), len(horizons), lv.size))
    total = np.zeros_like(grid)
    for h in range(1, max(horizons) + 1):
        # one week's draws: reichlab's grid, then an independent permutation each later week
        total = total + (grid if h == 1 else np.stack(
            [g.permutation(row) for g, row in zip(generators, grid)]))
        if h not in horizons:
            continue
        k = horizons.index(h)
        if h == 1:
            out[:, k] = row_quantiles(padded, counts, lv)
            continue
        centred = total - (np.median(total, axis=1, keepdims=True) if config.symmetrize else 0.0)
        out[:, k] = np.quantile(centred, lv, axis=1).T
    return np.maximum(np.asarray(last_values, dtype=np.float64)[:, None, None] + out, 0.0)


def baseline_quantiles(last_value: float, differences: NDArray[np.float64],
                       horizons: tuple[int, ...], levels: NDArray[np.float64], seed: int,
                       config: HubBaselineConfig = HubBaselineConfig()) -> NDArray[np.float64]:
    """Quantiles ``(H, Q)`` of the hub baseline from the last value and the past differences."""
    return baseline_quantiles_batch(np.array([last_value]), [differences], horizons, levels,
                                    [seed], config)[0]


def i_differences(history: EpiHistory) -> NDArray[np.float64]:
    """I_t − I_{t−7} for every day of the history with a day a week before it."""
    return history.I[DAYS_PER_WEEK:] - history.I[:-DAYS_PER_WEEK]


def _last_finite(weekly: NDArray[np.float64]) -> float:
    """The latest reported week (a weekly source may miss its newest weeks)."""
    finite = weekly[np.isfinite(weekly)]
    return float(finite[-1]) if finite.size else float("nan")


@dataclass(frozen=True)
class HubBaseline:
    """The hub baseline as a member: each target on its own series (module docstring); a
    daily history's I from its daily I series."""

    config: HubBaselineConfig = HubBaselineConfig()
    name: str = HUB_BASELINE

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Quantiles ``(B, H, Q)`` of every cell, cell b drawn from ``cells.seeds[b]`` (two
        streams: I, then the count), so a cell's numbers never depend on the others."""
        histories = cells.histories
        weekly = [h.weekly_cases() for h in histories]
        short = [h for h, w in zip(histories, weekly) if np.isfinite(w).sum() < 2]
        if short:
            raise TargetError(f"hub baseline at {short[0].origin.date()}: needs two reported "
                              f"weeks, got {np.isfinite(short[0].weekly_cases()).sum()}")
        streams = np.array([np.random.SeedSequence(s).generate_state(2) for s in cells.seeds])
        count = baseline_quantiles_batch(np.array([_last_finite(w) for w in weekly]),
                                         [np.diff(w) for w in weekly], horizons, levels,
                                         streams[:, 1].tolist(), self.config)
        extra = {}
        if all(isinstance(h, EpiHistory) for h in histories):
            daily = [h for h in histories if isinstance(h, EpiHistory)]
            extra[SHARE] = baseline_quantiles_batch(
                np.array([h.I[-1] for h in daily]), [i_differences(h) for h in daily], horizons,
                levels, streams[:, 0].tolist(), self.config)
        return MemberForecast(count, extra)
