"""The phase of the epidemic a forecast is made in: falling, flat or rising.

A cell's regime is read from the last two weekly counts known at its origin: log growth
g = log(C₀ + ½) − log(C₋₁ + ½) below −0.1 is **falling**, above +0.1 **rising** (±10 % a week),
**flat** between. The combiner may recalibrate per regime, and every backtest reports coverage and
relative WIS per regime beside the total (intervals that hold on average can fail exactly at the
turns).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

N_REGIMES = 3                       # falling, flat, rising
REGIME_NAMES: tuple[str, ...] = ("falling", "flat", "rising")
FLAT_LOG_GROWTH = 0.1               # |log(C_0 / C_-1)| below this is "flat" (±10 % a week)


def growth_regimes(last_weeks: NDArray[np.float64]) -> NDArray[np.intp]:
    """Regime 0 (falling), 1 (flat), 2 (rising) from the last two weekly counts ``(..., 2)``;
    a missing count reads as flat."""
    with np.errstate(invalid="ignore"):
        growth = np.log(last_weeks[..., 1] + 0.5) - np.log(last_weeks[..., 0] + 0.5)
    return np.where(growth < -FLAT_LOG_GROWTH, 0, np.where(growth > FLAT_LOG_GROWTH, 2, 1))
