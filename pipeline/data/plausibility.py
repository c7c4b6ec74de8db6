"""Is every daily count plausible against its own history and the population? (issue 22)

Validation bounds a count only by :data:`pipeline.data.validation.COUNT_BOUND` (1e8, exactness in
float64). The fault probe served 99,999,999 new cases on one day of the open revision window: it
passed, replaced the cache, and every later run failed ("I + R exceeds the population"). A count
must also be plausible as *news*, so each daily count column is checked, day by day, against two
bounds; a day above either is refused with :class:`ImplausibleCountError` and the cache is kept:

* **population**: at most ``max_daily_share`` (10 %) of the population in one day. San
  Francisco's largest daily counts are 3,161 new cases and 20,443 tests (0.4 % and 2.3 % of
  873,965); a tenth of the city in a day is a broken payload in any column;
* **history**: at most ``jump_factor`` × (median + ``mad_scale`` × 1.4826 × MAD + ``floor``) of
  the previous ``window_days`` days. The robust centre and spread ignore one odd day, and the
  floor keeps days after a run of zeros (the start of a series) from being refused for a few
  events. On the real SF series the largest ratio to the bracket is 4.1 (positives at the start
  of the Omicron wave, 2021-12-28: 2,325 after a median of 148); a factor of 20 leaves five
  times that margin. Because an epidemic's onset (or a report-date backlog) outruns any 28-day
  median, the bracket is at least ``growth_factor`` × (the largest count of the previous
  ``growth_window_days`` days + ``floor``): on the six real CDPH vintages (every county, every
  count column) the largest ratio of a real count to the combined bound is 0.43 (San Diego's
  report-date backlog of 5,277 on 2020-05-13), and Los Angeles' first wave (2,126 reported on
  2020-03-28 after a 28-day median of 4) passes.

Only daily columns are checked (cumulative columns are compared with the daily counts by
validation). The rule is source-agnostic: any daily series with a known population (DataSF, a
state portal) calls :func:`check_plausible` before the payload may replace its cache.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.lib.stride_tricks import sliding_window_view

from pipeline.errors import ConfigError, ValidationError

MAD_TO_SIGMA = 1.4826  # MAD of a normal sample × this = its standard deviation


class ImplausibleCountError(ValidationError):
    """A daily count far beyond its own history or the population: the payload is refused."""


@dataclass(frozen=True)
class PlausibilityRule:
    """Bounds on a daily count (see module doc). ``population`` is the place's, people."""

    population: int
    max_daily_share: float = 0.10
    window_days: int = 28
    jump_factor: float = 20.0
    mad_scale: float = 3.0
    floor: int = 50
    growth_factor: float = 20.0
    growth_window_days: int = 7

    def __post_init__(self) -> None:
        if (self.population < 1 or self.window_days < 1 or self.jump_factor <= 1.0
                or not 1 <= self.growth_window_days <= self.window_days):
            raise ConfigError(f"plausibility rule needs population >= 1, window_days >= 1 and "
                              f"jump_factor > 1, got {self}")

    @property
    def population_bound(self) -> float:
        return self.max_daily_share * self.population


def history_bounds(values: np.ndarray, rule: PlausibilityRule) -> np.ndarray:
    """Per day, the largest count its previous ``window_days`` days make plausible (inf on the
    first day, which has no history)."""
    history = np.concatenate([np.full(rule.window_days, np.nan), values.astype(np.float64)])
    # Window i holds the window_days days before day i (NaN where the series had not begun).
    windows = sliding_window_view(history, rule.window_days)[:len(values)]
    bounds = np.full(len(values), np.inf)
    seen = ~np.isnan(windows).all(axis=1)
    if seen.any():
        past = windows[seen]
        median = np.nanmedian(past, axis=1)
        mad = np.nanmedian(np.abs(past - median[:, None]), axis=1)
        bounds[seen] = rule.jump_factor * (median + rule.mad_scale * MAD_TO_SIGMA * mad
                                           + rule.floor)
    recent = sliding_window_view(history, rule.window_days)[:len(values),
                                                             -rule.growth_window_days:]
    recent_max = np.where(np.isnan(recent).all(axis=1), np.inf,
                          np.nanmax(np.where(np.isnan(recent), -np.inf, recent), axis=1))
    return np.maximum(bounds, rule.growth_factor * (np.maximum(recent_max, 0.0) + rule.floor))


def check_plausible(frame: pd.DataFrame, columns: Sequence[str], rule: PlausibilityRule, *,
                    source: str) -> None:
    """Raise :class:`ImplausibleCountError` naming the first implausible day of any column of
    ``frame`` (daily rows sorted by ``date``; ``columns`` the daily count columns)."""
    for column in columns:
        values = frame[column].to_numpy(dtype=np.float64)
        by_population = values > rule.population_bound
        by_history = values > history_bounds(values, rule)
        bad = by_population | by_history
        if not bad.any():
            continue
        first = int(np.flatnonzero(bad)[0])
        day = pd.Timestamp(frame["date"].iloc[first]).date()
        if by_population[first]:
            why = (f"more than {rule.max_daily_share:.0%} of the population "
                   f"{rule.population:,} in one day")
        else:
            past = values[max(0, first - rule.window_days):first]
            why = (f"more than {rule.jump_factor:g}× the plausible bracket of the previous "
                   f"{len(past)} day(s) (median {np.median(past):,.0f}, largest of the last "
                   f"{rule.growth_window_days} {past[-rule.growth_window_days:].max():,.0f}, bound "
                   f"{history_bounds(values, rule)[first]:,.0f})")
        raise ImplausibleCountError(
            f"{source}: implausible count {values[first]:,.0f} in '{column}' on {day}: {why}; "
            f"{int(bad.sum())} such day(s); refused")
