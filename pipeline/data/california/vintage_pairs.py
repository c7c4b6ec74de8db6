"""Revision observations: the same county-day as two vintages counted it.

A CDPH vintage counts cases by episode date, and a day's count grows as late reports arrive. Two
vintages v₁ < v₂ of the same county give, for every day d within ``max_lag`` days of v₁, the count
known at lag L₁ = v₁ − d and the count known at the longer lag L₂ = v₂ − d. Under independent
arrivals the earlier count is a binomial thinning of the later one with probability
F(d, L₁) / F(d, L₂), where F is the completeness of day d at a lag (the share of its final count
that had arrived). That ratio is what :mod:`pipeline.data.california.delays` fits; the later vintage need not
be final (F(d, L₂) < 1 when L₂ is short), so every pair of vintages is usable, not only pairs
with the latest one.

Each observation also records the weekday of its day (reporting slows at weekends, so
completeness depends on which weekdays the lags cross), its county and its *era*: the earlier
vintage's date, near which the day's reports arrived (delays lengthen in surges).

Counts that fell between the vintages (CDPH deduplicates and moves cases between days: 14 % of
county-days of the large counties fell by the latest vintage) cannot be a binomial thinning; the
earlier count is capped at the later one and the number capped is kept (:attr:`RevisionPairs.capped`).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.california.cdph import CDPHVintage
from pipeline.errors import ValidationError

DEFAULT_MAX_LAG = 56


class VintagePairError(ValidationError):
    """Vintages that cannot be paired (fewer than two, or no common county-days)."""


@dataclass(frozen=True, eq=False)
class RevisionPairs:
    """One row per (earlier vintage, later vintage, county, day) with 0 ≤ L₁ ≤ ``max_lag``.

    ``county`` indexes ``counties``; ``era`` indexes ``eras`` (the earlier vintage's date);
    ``weekday`` is the day's weekday (0 = Monday); ``early``/``late`` the counts at lags
    ``lag_early`` < ``lag_late``; ``early`` is capped at ``late`` (``capped`` rows were)."""

    counties: tuple[str, ...]
    eras: tuple[pd.Timestamp, ...]
    county: NDArray[np.int64]
    era: NDArray[np.int64]
    later: NDArray[np.int64]          # index into ``vintage_dates`` of the later vintage
    vintage_dates: tuple[pd.Timestamp, ...]
    weekday: NDArray[np.int64]
    lag_early: NDArray[np.int64]
    lag_late: NDArray[np.int64]
    early: NDArray[np.int64]
    late: NDArray[np.int64]
    capped: int
    max_lag: int

    def __len__(self) -> int:
        return len(self.county)

    def select(self, keep: NDArray[np.bool_]) -> RevisionPairs:
        """The rows where ``keep`` is True (same county and era indices)."""
        return RevisionPairs(
            self.counties, self.eras, self.county[keep], self.era[keep], self.later[keep],
            self.vintage_dates, self.weekday[keep], self.lag_early[keep], self.lag_late[keep],
            self.early[keep], self.late[keep], self.capped, self.max_lag)

    def without_era(self, era_date: pd.Timestamp) -> RevisionPairs:
        """Every pair whose earlier vintage is not ``era_date`` (a held-out vintage)."""
        return self.select(self.era != self.eras.index(pd.Timestamp(era_date)))

    def known_at(self, date: pd.Timestamp) -> RevisionPairs:
        """The pairs whose later vintage existed on ``date`` (real time: no later download)."""
        dates = np.array([d.value for d in self.vintage_dates])
        return self.select(dates[self.later] <= pd.Timestamp(date).value)


def _window(vintage: CDPHVintage, counties: Sequence[str], max_lag: int) -> pd.DataFrame:
    frame = vintage.frame
    first = vintage.as_of - pd.Timedelta(days=max_lag)
    rows = frame[(frame["date"] >= first) & frame["area"].isin(list(counties))]
    return rows[["area", "date", "cases"]]


def revision_pairs(vintages: Sequence[CDPHVintage], *, max_lag: int = DEFAULT_MAX_LAG,
                   counties: Sequence[str] | None = None,
                   consecutive: bool = False) -> RevisionPairs:
    """Every ordered pair of ``vintages`` (distinct dates), every county-day within ``max_lag``
    days of the earlier one; ``counties`` (default: those in every vintage).

    ``consecutive``: only each vintage and the next one. That is the likelihood of all of them
    together: a day's counts grow along the vintages, and under thinning P(c₁, …, c_{n−1} | c_n)
    = Π P(c_i | c_{i+1}), so the chain of consecutive pairs carries every vintage's information
    once (all pairs would count the same arrivals several times). The delay model fits on this;
    held-out checks score every pair."""
    ordered = sorted({v.as_of: v for v in vintages}.values(), key=lambda v: v.as_of)
    if len(ordered) < 2:
        raise VintagePairError(f"revision pairs need at least two vintages with different dates, "
                               f"got {len(ordered)}")
    if max_lag < 1:
        raise VintagePairError(f"max_lag={max_lag} must be >= 1")
    common = sorted(set.intersection(*(set(v.counties) for v in ordered)))
    names = tuple(sorted(counties)) if counties is not None else tuple(common)
    missing = sorted(set(names) - set(common))
    if missing:
        raise VintagePairError(f"counties {missing} are not in every vintage")
    index = {c: k for k, c in enumerate(names)}
    parts = []
    for i, early in enumerate(ordered[:-1]):
        window = _window(early, names, max_lag)
        for j in range(i + 1, i + 2 if consecutive else len(ordered)):
            late = ordered[j].frame[["area", "date", "cases"]]
            both = window.merge(late, on=["area", "date"], suffixes=("_early", "_late"))
            both = both.assign(era=i, later=j,
                               lag_early=(early.as_of - both["date"]).dt.days,
                               lag_late=(ordered[j].as_of - both["date"]).dt.days)
            parts.append(both)
    rows = pd.concat(parts, ignore_index=True)
    if rows.empty:
        raise VintagePairError("the vintages share no county-days within "
                               f"{max_lag} days of an earlier vintage")
    early_counts = rows["cases_early"].to_numpy(np.int64)
    late_counts = rows["cases_late"].to_numpy(np.int64)
    capped = int((early_counts > late_counts).sum())
    return RevisionPairs(
        counties=names, eras=tuple(v.as_of for v in ordered[:-1]),
        county=rows["area"].map(index).to_numpy(np.int64),
        era=rows["era"].to_numpy(np.int64), later=rows["later"].to_numpy(np.int64),
        vintage_dates=tuple(v.as_of for v in ordered),
        weekday=pd.DatetimeIndex(rows["date"]).weekday.to_numpy(np.int64),
        lag_early=rows["lag_early"].to_numpy(np.int64),
        lag_late=rows["lag_late"].to_numpy(np.int64),
        early=np.minimum(early_counts, late_counts), late=late_counts, capped=capped,
        max_lag=max_lag)
