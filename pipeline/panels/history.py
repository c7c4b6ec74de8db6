"""One place's data as a forecaster may see them: daily (:class:`EpiHistory`) or weekly
(:class:`WeeklyHistory`), both cut at an origin by ``up_to``.

Every forecaster receives a history that ends at its origin (the last day or week it sees):
``up_to`` is how the backtest enforces real-time discipline. Both kinds give the weekly count
series the members forecast (``weekly_cases``: the complete weeks ending at the origin, oldest
first) and the susceptible share S the flows' coordinates are bounded by.

* :class:`EpiHistory` — a daily source (DataSF, CDPH): daily reported cases and their S/I/R
  proportions (:mod:`pipeline.data.sf.sir_transform`); its targets are the weekly cases and I, the
  infectious share (with the product's L = 7 days, N·I(t) is the trailing 7-day case count).
* :class:`WeeklyHistory` — a weekly source (NHSN admissions, the NSSP ED share as a rate per
  100,000 visits): one count per week ending on a Saturday; its one target is that count, named
  as the hub names it. S = 1 − (counts so far) / N.
"""
from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.california.cdph import CountySeries, county_sir
from pipeline.fingerprint import fingerprint
from pipeline.panels.targets import (CASES, DAYS_PER_WEEK, SHARE, TargetError)


class History(Protocol):
    """What every member may read of a place's data up to its origin."""

    @property
    def dates(self) -> pd.DatetimeIndex: ...

    @property
    def population(self) -> int: ...

    @property
    def origin(self) -> pd.Timestamp: ...

    @property
    def count_target(self) -> str: ...

    @property
    def targets(self) -> tuple[str, ...]: ...

    def __len__(self) -> int: ...

    def up_to(self, date: pd.Timestamp) -> History: ...

    def weekly_cases(self) -> NDArray[np.float64]: ...

    def susceptible_at_weeks(self) -> NDArray[np.float64]: ...

    def observed(self, origin: pd.Timestamp, horizons: tuple[int, ...]
                 ) -> dict[str, NDArray[np.float64]]: ...

    def observed_at(self, origins: Sequence[pd.Timestamp], horizons: tuple[int, ...]
                    ) -> dict[str, NDArray[np.float64]]: ...

    def fingerprint(self) -> str: ...


def _consecutive(dates: pd.DatetimeIndex, step_days: int) -> bool:
    steps = np.diff(dates.to_numpy(dtype=np.int64))
    return len(dates) < 2 or bool((steps == pd.Timedelta(days=step_days).value).all())


def history_length_up_to(dates: pd.DatetimeIndex, date: pd.Timestamp) -> int:
    """How many of ``dates`` (ascending) fall on or before ``date``."""
    return int(np.searchsorted(dates.as_unit("ns").to_numpy(dtype=np.int64),
                               pd.Timestamp(date).as_unit("ns").value, side="right"))


def _positions(dates: pd.DatetimeIndex, origins: Sequence[pd.Timestamp]) -> NDArray[np.intp]:
    """Each origin's index in ``dates`` (ascending); −1 where it is not one of them."""
    days = dates.as_unit("ns").to_numpy(dtype=np.int64)
    wanted = pd.DatetimeIndex(list(origins)).as_unit("ns").to_numpy(dtype=np.int64)
    pos = np.searchsorted(days, wanted)
    found = (pos < len(days)) & (days[np.minimum(pos, len(days) - 1)] == wanted)
    return np.where(found, pos, -1).astype(np.intp)


def _position(dates: pd.DatetimeIndex, origin: pd.Timestamp) -> int:
    """``origin``'s index in ``dates``; an origin that is not one of them is refused."""
    pos = int(_positions(dates, [origin])[0])
    if pos < 0:
        raise TargetError(f"origin {pd.Timestamp(origin).date()} is not a date of the history")
    return pos


@dataclass(frozen=True, eq=False)
class DailySIR:
    """The daily columns of an S/I/R history on ``dates``: reported ``cases`` and the proportions
    ``S``, ``I``, ``R`` of a place of ``population`` N. One history's are (T,)
    (:class:`EpiHistory`); K histories on the same days hold (K, T) (the nowcast's completions,
    :class:`pipeline.nowcast.completions.CompletedHistories`)."""

    dates: pd.DatetimeIndex
    cases: NDArray[np.int64]
    S: NDArray[np.float64]
    I: NDArray[np.float64]  # noqa: E741 - the compartment's name
    R: NDArray[np.float64]
    population: int


@dataclass(frozen=True, eq=False)
class EpiHistory(DailySIR):
    """A daily series up to and including the origin (its last date).

    ``cases`` are the daily reported case counts the conversion used (ascertainment-adjusted when
    that is on); ``S``, ``I``, ``R`` the proportions; ``population`` N. Dates are consecutive days.
    """

    count_target = CASES
    targets = (SHARE, CASES)

    def __post_init__(self) -> None:
        # nanosecond dates: lookups compare the dates as int64 with Timestamp.value (ns);
        # pandas reads dates as datetime64[us], which would silently shift every lookup
        object.__setattr__(self, "dates", pd.DatetimeIndex(self.dates).as_unit("ns"))
        n = len(self.dates)
        if n == 0:
            raise TargetError("empty history")
        for name in ("cases", "S", "I", "R"):
            if len(getattr(self, name)) != n:
                raise TargetError(f"history column {name} has {len(getattr(self, name))} rows, "
                                  f"dates {n}")
        if not _consecutive(self.dates, 1):
            raise TargetError("history dates must be consecutive days")

    @property
    def origin(self) -> pd.Timestamp:
        return self.dates[-1]

    def __len__(self) -> int:
        return len(self.dates)

    def up_to(self, date: pd.Timestamp) -> EpiHistory:
        """The history a forecaster at origin ``date`` would have seen (nothing after it)."""
        keep = history_length_up_to(self.dates, date)
        if keep == 0:
            raise TargetError(f"no history on or before {pd.Timestamp(date).date()}")
        # The first days of a checked history need no new checks (the backtest cuts thousands).
        head = object.__new__(EpiHistory)
        for name, value in (("dates", self.dates[:keep]), ("cases", self.cases[:keep]),
                            ("S", self.S[:keep]), ("I", self.I[:keep]), ("R", self.R[:keep]),
                            ("population", self.population)):
            object.__setattr__(head, name, value)
        return head

    def weekly_cases(self) -> NDArray[np.float64]:
        """Case counts of the complete 7-day weeks ending at the origin, origin − 7, … (oldest
        first); the incomplete week at the start is dropped."""
        n_weeks = len(self) // DAYS_PER_WEEK
        tail = self.cases[len(self) - n_weeks * DAYS_PER_WEEK:].astype(np.float64)
        return tail.reshape(n_weeks, DAYS_PER_WEEK).sum(axis=1)

    def weekly_I(self) -> NDArray[np.float64]:  # noqa: N802 - the compartment's name
        """I at the origin, origin − 7, … (oldest first), aligned with :meth:`weekly_cases`."""
        n_weeks = len(self) // DAYS_PER_WEEK
        return self.I[len(self) - 1 - DAYS_PER_WEEK * np.arange(n_weeks)[::-1]]

    def susceptible_at_weeks(self) -> NDArray[np.float64]:
        """S at the origin, origin − 7, … (oldest first), aligned with :meth:`weekly_cases`."""
        n_weeks = len(self) // DAYS_PER_WEEK
        return self.S[len(self) - 1 - DAYS_PER_WEEK * np.arange(n_weeks)[::-1]]

    def fingerprint(self) -> str:
        """What a forecaster sees of the history: dates, cases, S, I, R, population (a key of
        the forecast memo and of the refits' training-data digests)."""
        return fingerprint(self.dates, self.cases, self.S, self.I, self.R, self.population)

    def target_history(self, target: str) -> NDArray[np.float64]:
        """The weekly series of ``target`` ending at the origin (what a weekly model fits)."""
        if target == SHARE:
            return self.weekly_I()
        if target == CASES:
            return self.weekly_cases()
        raise TargetError(f"unknown target {target!r}; known: {self.targets}")

    def observed(self, origin: pd.Timestamp, horizons: tuple[int, ...]
                 ) -> dict[str, NDArray[np.float64]]:
        """Truth of each target at ``origin`` + 7h, from this (later) history; NaN where not
        observed."""
        pos = _position(self.dates, origin)
        out = {t: np.full(len(horizons), np.nan) for t in self.targets}
        cumulative = np.concatenate([[0], np.cumsum(self.cases, dtype=np.int64)])
        for k, h in enumerate(horizons):
            end = pos + DAYS_PER_WEEK * h
            if 0 <= end < len(self) and end + 1 >= DAYS_PER_WEEK:
                out[SHARE][k] = self.I[end]
                out[CASES][k] = float(cumulative[end + 1] - cumulative[end + 1 - DAYS_PER_WEEK])
        return out

    def observed_at(self, origins: Sequence[pd.Timestamp], horizons: tuple[int, ...]
                    ) -> dict[str, NDArray[np.float64]]:
        """:meth:`observed` at each of ``origins``, ``(O, H)`` per target; NaN rows where an
        origin is not a day of this history."""
        out = {t: np.full((len(origins), len(horizons)), np.nan) for t in self.targets}
        for o in np.flatnonzero(_positions(self.dates, origins) >= 0):
            for t, values in self.observed(origins[int(o)], horizons).items():
                out[t][o] = values
        return out


@dataclass(frozen=True, eq=False)
class WeeklyHistory:
    """A weekly count series up to and including the origin (its last week's end).

    ``dates``: the weeks' last days, 7 days apart; ``cases``: the week's count (NaN: a week the
    source did not report); ``target``: the count's name (the hub's, e.g. ``wk inc covid
    hosp``); ``population`` N. ``depletes``: whether the counts are people leaving the
    susceptibles (admissions); a rate (the ED share per 100,000 visits) does not, and its S is
    1 — the flows' bound is then the rate's own, N per N."""

    dates: pd.DatetimeIndex
    cases: NDArray[np.float64]
    population: int
    target: str
    depletes: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "dates", pd.DatetimeIndex(self.dates).as_unit("ns"))
        object.__setattr__(self, "cases", np.asarray(self.cases, dtype=np.float64))
        if len(self.dates) == 0:
            raise TargetError(f"empty {self.target} history")
        if len(self.cases) != len(self.dates):
            raise TargetError(f"{self.target}: {len(self.cases)} counts for "
                              f"{len(self.dates)} weeks")
        if not _consecutive(self.dates, DAYS_PER_WEEK):
            raise TargetError(f"{self.target}: weeks must be consecutive (7 days apart)")
        if self.population <= 0:
            raise TargetError(f"{self.target}: population must be positive, got "
                              f"{self.population}")

    @property
    def count_target(self) -> str:
        return self.target

    @property
    def targets(self) -> tuple[str, ...]:
        return (self.target,)

    @property
    def origin(self) -> pd.Timestamp:
        return self.dates[-1]

    def __len__(self) -> int:
        return len(self.dates)

    def up_to(self, date: pd.Timestamp) -> WeeklyHistory:
        keep = history_length_up_to(self.dates, date)
        if keep == 0:
            raise TargetError(f"{self.target}: no week ends on or before "
                              f"{pd.Timestamp(date).date()}")
        head = object.__new__(WeeklyHistory)
        for name, value in (("dates", self.dates[:keep]), ("cases", self.cases[:keep]),
                            ("population", self.population), ("target", self.target),
                            ("depletes", self.depletes)):
            object.__setattr__(head, name, value)
        return head

    def weekly_cases(self) -> NDArray[np.float64]:
        return self.cases

    def susceptible_at_weeks(self) -> NDArray[np.float64]:
        """1 − (counts up to each week) / N: the share never counted (missing weeks add 0);
        1 for a rate."""
        if not self.depletes:
            return np.ones(len(self))
        return 1.0 - np.cumsum(np.nan_to_num(self.cases)) / self.population

    def fingerprint(self) -> str:
        return self._fingerprint

    @functools.cached_property
    def _fingerprint(self) -> str:
        """Hashed once: the memo keys every member's cell of the same history by it."""
        return fingerprint(self.dates, self.cases, self.population, self.target, self.depletes)

    def observed(self, origin: pd.Timestamp, horizons: tuple[int, ...]
                 ) -> dict[str, NDArray[np.float64]]:
        """The count of the week ending ``origin`` + 7h (h may be ≤ 0); NaN where not held."""
        _position(self.dates, origin)            # an origin that is not a week is refused
        return {t: values[0] for t, values in self.observed_at([origin], horizons).items()}

    def observed_at(self, origins: Sequence[pd.Timestamp], horizons: tuple[int, ...]
                    ) -> dict[str, NDArray[np.float64]]:
        """:meth:`observed` at each of ``origins`` at once, ``(O, H)``; NaN rows where an
        origin is not a week of this history (the hub backtests read a truth per round)."""
        pos = _positions(self.dates, origins)
        ends = pos[:, None] + np.asarray(horizons, dtype=np.intp)[None, :]
        inside = (pos[:, None] >= 0) & (ends >= 0) & (ends < len(self))
        values = np.where(inside, self.cases[np.clip(ends, 0, len(self) - 1)], np.nan)
        return {self.target: values.astype(np.float64)}


def history_from_frames(sir_frame: pd.DataFrame, cases: NDArray[np.int64] | pd.Series,
                        population: int) -> EpiHistory:
    """An :class:`EpiHistory` from the S/I/R proportions frame (date, S, I, R) and the daily
    case counts on the same dates."""
    missing = [c for c in ("date", "S", "I", "R") if c not in sir_frame.columns]
    if missing:
        raise TargetError(f"S/I/R frame lacks columns {missing}")
    case_counts = np.asarray(cases, dtype=np.int64)
    if len(case_counts) != len(sir_frame):
        raise TargetError(f"{len(case_counts)} case counts for {len(sir_frame)} S/I/R days")
    return EpiHistory(pd.DatetimeIndex(pd.to_datetime(sir_frame["date"])).normalize(),
                      case_counts, sir_frame["S"].to_numpy(np.float64),
                      sir_frame["I"].to_numpy(np.float64), sir_frame["R"].to_numpy(np.float64),
                      int(population))


def history_from_county(series: CountySeries) -> EpiHistory:
    """A California county's :class:`EpiHistory` (CDPH episode-date cases, its own population)."""
    s, i, r = county_sir(series)
    return EpiHistory(series.dates, series.cases, s, i, r, series.population)
