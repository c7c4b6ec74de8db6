"""FluSight's targets derived from the joint sample paths of weekly admissions.

**Rate change** (``wk flu hosp rate change``): FluSight's own definition (its model-output
README, "rate-trend forecast specifications"; the same bins as ``reichlab/idmodels``'
``get_flusight_bin_endpoints``). The change at hub horizon h is the week ending
``reference_date + 7h`` minus the most recent week of data (horizon −1, the week ending
``reference_date − 7``). Its five categories have the endpoints ``base ± max(m · population /
100,000, 9.5)``, intervals ``(lower, upper]``, with a stable and a large multiplier m per
horizon: a change of fewer than 10 admissions is always stable. The multipliers changed
between seasons (:data:`RATE_CHANGE_RULES`); the 2024-25 ones hold from then on (FluSight's
2026 ``locations.csv`` lists exactly their counts, ``count_rate0p3`` … ``count_rate5``). The
pmf of a path set is the share of paths whose change falls in each category, computed from
the joint paths so a path's base and its later weeks move together.

**Peak** (``peak inc flu hosp``, ``peak week inc flu hosp``): the season's highest weekly count
and its week. A path's season is joined from three parts: the weeks its vintage reports before
the forecast weeks, the path's own weeks (hub horizons −1 … 3), and beyond them, the weeks the
paths do not reach, a draw of the rest of an earlier season (the highest rate per 100,000 of
the weeks after the same season week, and its week, of one location-season of the earlier
seasons in the vintage). The season's weeks are FluSight's: the 27 Saturdays from the one in
16–22 November (2025-26: 2025-11-22 … 2026-05-23, the config's peak-week categories).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

RATE_CHANGE_CATEGORIES: tuple[str, ...] = ("large_decrease", "decrease", "stable", "increase",
                                           "large_increase")
MIN_COUNT_CHANGE = 9.5          # a change of < 10 admissions is stable (FluSight)
SEASON_WEEKS = 27               # Saturdays of a season's peak-week categories
PER = 100_000.0
PSEUDO_COUNT = 0.5              # of a path, given to every category of a pmf (Jeffreys)


@dataclass(frozen=True)
class RateChangeRule:
    """One season's multipliers per 100,000 people: horizon → (stable bound, large bound)."""

    first_season: int           # the season's starting year (2024: 2024-25)
    multipliers: Mapping[int, tuple[float, float]]


RATE_CHANGE_RULES: tuple[RateChangeRule, ...] = (
    RateChangeRule(2023, {0: (1.0, 2.0), 1: (1.0, 3.0), 2: (2.0, 4.0), 3: (2.5, 5.0)}),
    RateChangeRule(2024, {0: (0.3, 1.7), 1: (0.5, 3.0), 2: (0.7, 4.0), 3: (1.0, 5.0)}),
)


def season_of(day: pd.Timestamp) -> int:
    """A season's starting year: August … December belong to that year's season."""
    day = pd.Timestamp(day)
    return day.year if day.month >= 8 else day.year - 1


def rate_change_rule(reference: pd.Timestamp) -> RateChangeRule:
    """The rule of the round's season (the latest rule starting at or before it)."""
    season = season_of(reference)
    rules = [r for r in RATE_CHANGE_RULES if r.first_season <= season]
    return rules[-1] if rules else RATE_CHANGE_RULES[0]


def category_edges(base: NDArray[np.float64], population: NDArray[np.float64],
                   horizon: int, rule: RateChangeRule) -> NDArray[np.float64]:
    """``(..., 4)`` the four inner endpoints of the five categories around ``base``."""
    stable, large = rule.multipliers[horizon]
    pop = np.asarray(population, dtype=np.float64) / PER
    small = np.maximum(stable * pop, MIN_COUNT_CHANGE)
    big = np.maximum(large * pop, MIN_COUNT_CHANGE)
    b = np.asarray(base, dtype=np.float64)
    return np.stack([b - big, b - small, b + small, b + big], axis=-1)


def categorize(value: NDArray[np.float64], edges: NDArray[np.float64]) -> NDArray[np.int64]:
    """The category index 0 … 4 of ``value`` (intervals ``(lower, upper]``); -1 where NaN."""
    v = np.asarray(value, dtype=np.float64)
    index = np.sum(v[..., None] > edges, axis=-1)
    return np.where(np.isfinite(v) & np.isfinite(edges).all(axis=-1), index, -1)


def rate_change_pmf(paths: NDArray[np.float64], horizons: Sequence[int],
                    population: NDArray[np.float64], rule: RateChangeRule,
                    rate_horizons: Sequence[int] = (0, 1, 2, 3),
                    pseudo_count: float = PSEUDO_COUNT) -> NDArray[np.float64]:
    """``(C, len(rate_horizons), 5)`` the pmf of each location's change from its paths
    ``(C, n, H)`` at hub ``horizons`` (the base: each path's horizon −1), every category given
    ``pseudo_count`` of a path (a finite number of paths leaves a rare category at 0, and a
    category given 0 that happens scores an infinite log score)."""
    base = paths[:, :, list(horizons).index(-1)]
    out = np.empty((paths.shape[0], len(rate_horizons), len(RATE_CHANGE_CATEGORIES)))
    for k, h in enumerate(rate_horizons):
        edges = category_edges(base, np.asarray(population)[:, None], h, rule)
        cats = categorize(paths[:, :, list(horizons).index(h)], edges)
        counts = (cats[..., None] == np.arange(len(RATE_CHANGE_CATEGORIES))).sum(axis=1)
        out[:, k] = (counts + pseudo_count) / (counts.sum(axis=-1, keepdims=True)
                                               + pseudo_count * len(RATE_CHANGE_CATEGORIES))
    return out


def observed_rate_change(truth: NDArray[np.float64], horizons: Sequence[int],
                         population: NDArray[np.float64], rule: RateChangeRule,
                         rate_horizons: Sequence[int] = (0, 1, 2, 3)) -> NDArray[np.int64]:
    """``(C, len(rate_horizons))`` the observed category from ``truth (C, H)``; -1 unknown."""
    base = truth[:, list(horizons).index(-1)]
    return np.stack([categorize(truth[:, list(horizons).index(h)],
                                category_edges(base, population, h, rule))
                     for h in rate_horizons], axis=1)


def season_weeks(reference: pd.Timestamp) -> pd.DatetimeIndex:
    """The 27 Saturdays of the round's season, from the one in 16–22 November."""
    start = pd.Timestamp(season_of(reference), 11, 16)
    start += pd.Timedelta(days=(5 - start.weekday()) % 7)
    return pd.date_range(start, periods=SEASON_WEEKS, freq="7D")


@dataclass(frozen=True)
class SeasonTails:
    """Earlier seasons' rest-of-season: for each location-season ``(S,)`` and each season week
    ``(S, W)``, the highest rate per 100,000 after that week and the week it falls on (-1:
    nothing after the season's last week)."""

    rate: NDArray[np.float64]
    week: NDArray[np.int64]

    def draw(self, after: int, size: tuple[int, ...], rng: np.random.Generator
             ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """``size`` draws of (rate, week) of the weeks after season week ``after``."""
        pick = rng.integers(0, len(self.rate), size=size)
        if after >= SEASON_WEEKS - 1:
            return np.full(size, -np.inf), np.full(size, -1)
        return self.rate[pick, after + 1], self.week[pick, after + 1]


def season_tails(history: Mapping[str, pd.Series], population: Mapping[str, float],
                 before: pd.Timestamp) -> SeasonTails | None:
    """The :class:`SeasonTails` of every complete season ending before ``before`` in
    ``history`` (location → weekly counts indexed by Saturday); None when there is none."""
    rates, weeks = [], []
    for season in range(2000, season_of(before)):
        days = season_weeks(pd.Timestamp(season, 12, 1))
        if days[-1] >= before:
            continue
        for place, series in history.items():
            values = series.reindex(days).to_numpy(dtype=np.float64)
            if not np.isfinite(values).all():
                continue
            rate = values / population[place] * PER
            # position w: the highest of weeks w … W-1 and where it falls (draw(after=w-1))
            rev_max = np.maximum.accumulate(rate[::-1])[::-1]
            rev_arg = np.array([w + int(np.argmax(rate[w:])) for w in range(SEASON_WEEKS)])
            rates.append(rev_max)
            weeks.append(rev_arg)
    if not rates:
        return None
    return SeasonTails(np.stack(rates), np.stack(weeks))


@dataclass(frozen=True)
class PeakForecast:
    """A location's peak: draws of the season's highest count ``(n,)`` and its week index."""

    intensity: NDArray[np.float64]
    week: NDArray[np.int64]


def peak_draws(known: NDArray[np.float64], paths: NDArray[np.float64], path_weeks: Sequence[int],
               tails: SeasonTails | None, population: float, rng: np.random.Generator
               ) -> PeakForecast:
    """One location's peak from its season joined (module docstring): ``known (W,)`` the
    vintage's counts of the season's weeks (NaN: not reported or forecast), ``paths (n, H)``
    its paths at the season weeks ``path_weeks`` (-1: outside the season)."""
    n = paths.shape[0]
    season = np.broadcast_to(known, (n, SEASON_WEEKS)).copy()
    inside = [(k, w) for k, w in enumerate(path_weeks) if 0 <= w < SEASON_WEEKS]
    for k, w in inside:
        season[:, w] = paths[:, k]
    last = max([w for _, w in inside], default=int(np.max(np.flatnonzero(
        np.isfinite(known)), initial=-1)))
    if tails is not None and last < SEASON_WEEKS - 1:
        rate, week = tails.draw(last, (n,), rng)
        tail = rate * population / PER
        season[:, last + 1:] = np.nan
        ahead = tail[:, None] * (np.arange(SEASON_WEEKS) == week[:, None])
        season = np.where(np.arange(SEASON_WEEKS) > last, np.where(ahead > 0, ahead, np.nan),
                          season)
    filled = np.where(np.isfinite(season), season, -np.inf)
    return PeakForecast(filled.max(axis=1), filled.argmax(axis=1).astype(np.int64))


def peak_week_pmf(week: NDArray[np.int64], pseudo_count: float = PSEUDO_COUNT
                  ) -> NDArray[np.float64]:
    """``(W,)`` the pmf of the peak week from its draws, every week given ``pseudo_count`` of a
    draw (so that no week the data could still make the peak has probability 0)."""
    counts = np.bincount(week[week >= 0], minlength=SEASON_WEEKS).astype(np.float64)
    counts += pseudo_count
    return counts / counts.sum()


def observed_peak(values: NDArray[np.float64]) -> tuple[float, int]:
    """The season's highest count and its week (the first, on a tie) from ``values (W,)``;
    (NaN, -1) when a week is missing."""
    if not np.isfinite(values).all():
        return float("nan"), -1
    return float(values.max()), int(values.argmax())
