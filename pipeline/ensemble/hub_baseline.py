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

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.ensemble.targets import (DAYS_PER_WEEK, EpiHistory, QuantileForecast,
                                          TargetError)

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


def baseline_quantiles(last_value: float, differences: NDArray[np.float64],
                       horizons: tuple[int, ...], levels: NDArray[np.float64], seed: int,
                       config: HubBaselineConfig = HubBaselineConfig()) -> NDArray[np.float64]:
    """Quantiles ``(H, Q)`` of the hub baseline from the last value and the past differences."""
    diffs = np.asarray(differences, dtype=np.float64)
    diffs = diffs[np.isfinite(diffs)]
    if diffs.size == 0:
        raise TargetError("hub baseline needs at least one past difference")
    if config.symmetrize:
        diffs = symmetrized(diffs)
    lv = np.asarray(levels, dtype=np.float64)
    out = np.empty((len(horizons), lv.size))
    grid = np.quantile(diffs, np.linspace(0.0, 1.0, config.n_samples))   # reichlab's draws
    rng = np.random.default_rng(seed)
    total = np.zeros(config.n_samples)
    max_h = max(horizons)
    sums: dict[int, NDArray[np.float64]] = {}
    for h in range(1, max_h + 1):
        total = total + (grid if h == 1 else rng.permutation(grid))
        if h in horizons and h > 1:
            sums[h] = total - (np.median(total) if config.symmetrize else 0.0)
    for k, h in enumerate(horizons):
        if h == 1:
            out[k] = last_value + np.quantile(diffs, lv)
        else:
            out[k] = last_value + np.quantile(sums[h], lv)
    return np.maximum(out, 0.0)


def i_differences(history: EpiHistory) -> NDArray[np.float64]:
    """I_t − I_{t−7} for every day of the history with a day a week before it."""
    return history.I[DAYS_PER_WEEK:] - history.I[:-DAYS_PER_WEEK]


@dataclass(frozen=True)
class HubBaseline:
    """The hub baseline as a member: each target on its own series (module docstring)."""

    config: HubBaselineConfig = HubBaselineConfig()
    name: str = HUB_BASELINE

    def forecast(self, history: EpiHistory, horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int) -> QuantileForecast:
        weekly = history.weekly_cases()
        if len(history) <= DAYS_PER_WEEK or weekly.size < 2:
            raise TargetError(f"hub baseline at {history.origin.date()}: needs more than one week "
                              f"of history, got {len(history)} days")
        seeds = np.random.SeedSequence(seed).generate_state(2)
        values = {
            "I": baseline_quantiles(float(history.I[-1]), i_differences(history), horizons,
                                    levels, int(seeds[0]), self.config),
            "cases": baseline_quantiles(float(weekly[-1]), np.diff(weekly), horizons, levels,
                                        int(seeds[1]), self.config),
        }
        return QuantileForecast(self.name, history.origin, tuple(horizons),
                                np.asarray(levels, dtype=np.float64), values)
