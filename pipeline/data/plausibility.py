"""Is a daily count plausible against the series' own recent history and its population?

Generic: any daily count series of one place (a CDPH county, DataSF's San Francisco series). A
count is *implausible* when it is above

* ``max_population_share`` of the population in one day (default 5 %), or
* ``max(floor, max_ratio × the largest count of the previous history_days days)``
  (default max(1,000, 50 × the 28-day maximum)).

The defaults were measured on six real CDPH vintages (2021-04-28 … 2021-11-04, 58 counties,
453 days each): the largest single-day share of a population is 1.9 % (Alpine, 21 reported
cases of 1,117 people); the largest day above 500 relative to the previous 28-day maximum is
2.1× for episode-date ``cases`` and 22.6× for ``reported_cases`` (San Diego's backlog of 5,277
on 2020-05-13). So no real day is flagged, while a poisoned count (a population-sized number, a
count 100× the recent peak) is. Negative counts (CDPH's corrections) are never implausible here:
whether a column may be negative is the parser's rule.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class PlausibilityLimits:
    history_days: int = 28
    max_ratio: float = 50.0
    floor: int = 1_000
    max_population_share: float = 0.05


DEFAULT_LIMITS = PlausibilityLimits()


@dataclass(frozen=True)
class Implausible:
    """The first implausible day of a series: its position, value, the limit it broke and why."""

    index: int
    value: int
    limit: float
    why: str


def count_limits(values: ArrayLike, population: int | None = None,
                 limits: PlausibilityLimits = DEFAULT_LIMITS) -> NDArray[np.float64]:
    """The largest plausible count of every day (see module doc)."""
    counts = pd.Series(np.asarray(values, dtype=np.float64))
    recent = (counts.clip(lower=0).shift(1)
              .rolling(limits.history_days, min_periods=1).max().fillna(0.0))
    bound = np.maximum(float(limits.floor), limits.max_ratio * recent.to_numpy())
    if population is not None and population > 0:
        bound = np.minimum(bound, limits.max_population_share * population)
    return bound


def first_implausible(values: ArrayLike, population: int | None = None,
                      limits: PlausibilityLimits = DEFAULT_LIMITS) -> Implausible | None:
    """The first day whose count is above its plausible limit; None when every day is fine."""
    counts = np.asarray(values, dtype=np.float64)
    if counts.size == 0:
        return None
    bound = count_limits(counts, population, limits)
    bad = np.flatnonzero(counts > bound)
    if bad.size == 0:
        return None
    i = int(bad[0])
    share_limit = (limits.max_population_share * population
                   if population is not None and population > 0 else np.inf)
    why = (f"more than {limits.max_population_share:.0%} of the population ({population:,}) in "
           f"one day" if bound[i] >= share_limit else
           f"more than max({limits.floor:,}, {limits.max_ratio:g} × the largest count of the "
           f"previous {limits.history_days} days)")
    return Implausible(index=i, value=int(counts[i]), limit=float(bound[i]), why=why)
