"""One validation gate for every source (DataSF, CDPH, NHSN): what may enter a forecast (issue 32).

A source parses its payload into long rows (``place``, ``date``, one column per measure, cells
as the payload wrote them) and hands them to :func:`gate` with its :class:`GateRules`. The gate
checks, vectorized over every row:

* **places** only from the known list (:class:`Places`: California's 58 counties, the hub's 53
  locations, San Francisco), each with its population from a known table in code (census
  figures), never from the payload. An unknown place (the probe's "Atlantis", 1.5 M people) is
  skipped, named;
* **every numeric cell** present, a number, finite; where it counts people a whole number, not
  negative (unless the source books corrections as negative counts) — ``Infinity``, ``1e19`` and
  ``1e300`` used to be stored as −9,223,372,036,854,775,808 and fail every later forecast;
* **physical bounds**: a count of people in one day at most ``per_day`` of the place's
  population, in one week (a weekly row, or any 7 consecutive days) at most ``per_week``; a
  share within 0 … ``maximum``. The probe's ramp (San Francisco 2,800 → 56,000 → 89,000 cases a
  day, 6–10 % of the city daily) passed a 10 %-a-day bound and was published;
* **plausible news**: each count against its own series' history
  (:mod:`pipeline.data.core.plausibility`);
* **dates**: readable, on the source's weekday for weekly data, not after the vintage's date,
  one row per place and date, no gap (a source whose empty cells are missing weeks,
  ``missing_weeks``, may have gaps: the week is dropped, the place stays), every place ending
  on the payload's last date. That date is the one most places end on (ties: the later), never
  one place's odd row: a place with rows after it is skipped alone (issue 39: one state's row
  for a later week used to set the date and refuse all 53 locations);
* **a reported population** (CDPH writes one on every row): a finite whole number, the same on
  every row, within ``population_tolerance`` of the known table's figure.

A place whose rows fail any check is **skipped**: dropped from the result and named, with the
first failure, in :attr:`Gated.skipped`, so a one-cell poisoning of one place never stops other
places (the loaded vintage carries ``skipped`` for the run's log and report). Only what no place
can survive is **one named error** (:class:`GateError`, a
:class:`~pipeline.errors.ValidationError`, so the caller keeps its cache): no known place at all
(full state names where codes belong: that used to crash with numpy's "inhomogeneous shape"),
no place left, or more than ``max_skipped_share`` of the known places failing at once, unknown
names counted among the failures (a broken payload, not a broken place: a flu fetch with postal
codes in NSSP's place column used to be stored with the US alone). The bounds and their measured margins are in docs/data.md ("The validation gate").
"""
from __future__ import annotations

import calendar
import hashlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.core.plausibility import (GrowthRule, JumpRule, describe_jump, growth_sums,
                                             history_bounds)
from pipeline.errors import ValidationError


class GateError(ValidationError):
    """A payload the gate refuses as a whole (no place passes, or too many fail): the cache is
    kept."""


@dataclass(frozen=True)
class Places:
    """The places a source may name (``kind``, e.g. "California county"), each with its
    population from ``figures`` (e.g. "2020 Census")."""

    kind: str
    populations: Mapping[str, int]
    figures: str

    def describe(self) -> str:
        return f"one of the {len(self.populations)} known {self.kind} names"


@dataclass(frozen=True)
class CountBound:
    """A column counting people: at most ``per_day`` (daily rows; None for weekly data) and
    ``per_week`` of the population, never below ``floor`` people (tiny places report lumps)."""

    column: str
    per_day: float | None
    per_week: float
    floor: int = 0
    negative_ok: bool = False


@dataclass(frozen=True)
class ShareBound:
    """A column holding a share (e.g. of ED visits): within 0 … ``maximum``."""

    column: str
    maximum: float


@dataclass(frozen=True)
class GateRules:
    """What one source's rows must satisfy (module doc)."""

    source: str
    places: Places
    counts: tuple[CountBound, ...] = ()
    shares: tuple[ShareBound, ...] = ()
    step_days: int = 1                   # 1: daily rows; 7: weekly rows
    weekday: int | None = None           # weekly rows fall on this weekday (5: Saturday)
    jump: JumpRule | None = None
    population_column: str | None = None  # a population the payload reports on every row
    population_tolerance: float = 0.25
    max_skipped_share: float = 0.25
    missing_weeks: bool = False           # an empty or NA cell is a missing week, not a bad place
    growth: GrowthRule | None = None      # a slow ramp beyond real growth (daily cases)

    @property
    def columns(self) -> tuple[str, ...]:
        return tuple(b.column for b in (*self.counts, *self.shares))

    def fingerprint(self) -> str:
        """Changes whenever a rule does (stored parses are keyed by it)."""
        return hashlib.sha256(repr(self).encode()).hexdigest()[:12]


@dataclass(frozen=True, eq=False)
class Gated:
    """The rows of the places that passed (``place``, ``date``, the measures typed: int64 counts,
    float64 shares; sorted by place and date), the places skipped, each with why, and (sources
    with ``missing_weeks``) the dates each kept place left empty."""

    frame: pd.DataFrame
    skipped: Mapping[str, str]
    missing: Mapping[str, tuple[str, ...]] = field(default_factory=dict)


def pct(share: float) -> str:
    return f"{share * 100:g}%"


def count(value: float) -> str:
    """A count for a message: digits grouped, or 3 significant digits when absurd (1e+300)."""
    return f"{value:,.0f}" if abs(value) < 1e15 else f"{value:.3g}"


# A check: (rows, context) -> mask of failing rows and a message for one failing row.
Message = Callable[[int], str]


class _Rows:
    """The rows under test (sorted by place and date) and what the checks share."""

    def __init__(self, frame: pd.DataFrame, rules: GateRules) -> None:
        self.frame = frame.sort_values(["place", "date"], kind="stable", ignore_index=True)
        self.rules = rules
        self.place = self.frame["place"].to_numpy(dtype=object)
        self.date = pd.DatetimeIndex(self.frame["date"])
        known = rules.places.populations
        self.population = np.array([known.get(p, 0) for p in self.place], dtype=np.float64)
        self.text: dict[str, pd.Series] = {}
        self.value: dict[str, NDArray[np.float64]] = {}
        for column in rules.columns:
            text = self.frame[column].astype("string").str.strip()
            self.text[column] = text
            self.value[column] = pd.to_numeric(text, errors="coerce").to_numpy(np.float64)

    def day(self, i: int) -> str:
        d = self.date[i]
        return "an unreadable date" if pd.isna(d) else str(d.date())

    def raw(self, column: str, i: int) -> str:
        return repr(str(self.text[column].iloc[i]))


def gate(frame: pd.DataFrame, rules: GateRules, *, source: str,
         as_of: pd.Timestamp | None = None) -> Gated:
    """Check ``frame`` (``place``, ``date`` (datetime64, NaT where unreadable), the rules'
    columns as the payload wrote them) against ``rules``; see the module doc."""
    known = rules.places.populations
    if frame.empty:
        raise GateError(f"{source}: empty payload (no rows); refused")
    names = frame["place"].astype("string").fillna("").to_numpy(dtype=object)
    unknown = sorted({str(p) for p in names} - set(known))
    skipped = {p: f"{p!r} is not {rules.places.describe()} ({rules.source})" for p in unknown}
    ours = frame[np.isin(names, list(known))]
    if ours.empty:
        raise GateError(f"{source}: no row names {rules.places.describe()} ({len(unknown)} "
                        f"unknown name(s), e.g. {', '.join(repr(p) for p in unknown[:3])}); "
                        f"refused")
    ours, missing = _missing_weeks(ours, rules)
    rows = _Rows(ours, rules)
    for mask, message in _checks(rows, as_of):
        new = mask & ~np.isin(rows.place, list(skipped))
        for i in _first_per_place(rows.place, new):
            skipped[str(rows.place[i])] = f"{rows.place[i]}: {message(i)}"
    kept = rows.frame[~np.isin(rows.place, list(skipped))]
    _refuse_if_too_many(skipped, known, kept, rules, source)
    return Gated(_typed(kept, rules), dict(sorted(skipped.items())),
                 {p: d for p, d in missing.items() if p not in skipped})


MISSING_TEXT = ("", "na", "nan", "null", "none", "<na>")


def _missing_weeks(frame: pd.DataFrame, rules: GateRules
                   ) -> tuple[pd.DataFrame, dict[str, tuple[str, ...]]]:
    """Rows whose every measure is empty or ``NA`` dropped (sources with ``missing_weeks``): a
    week the source left empty costs that week, not the place (FluSight's Massachusetts,
    Minnesota and West Virginia in the 2024 off-season). Other sources: unchanged."""
    if not rules.missing_weeks or not rules.columns:
        return frame, {}
    empty = np.logical_and.reduce([
        frame[c].astype("string").str.strip().str.lower().fillna("").isin(MISSING_TEXT)
        .to_numpy(bool) for c in rules.columns])
    gone = frame[empty]
    dates = pd.DatetimeIndex(gone["date"])
    missing: dict[str, list[str]] = {}
    for place, day in zip(gone["place"].astype(str), dates, strict=True):
        missing.setdefault(place, []).append("an unreadable date" if pd.isna(day)
                                             else str(day.date()))
    return frame[~empty], {p: tuple(d) for p, d in sorted(missing.items())}


def _refuse_if_too_many(skipped: Mapping[str, str], known: Mapping[str, int],
                        kept: pd.DataFrame, rules: GateRules, source: str) -> None:
    failed = len(skipped)      # unknown names count: a payload of misnamed places is broken
    first = next(iter(skipped.values()), "")
    if kept.empty and len(known) == 1:   # one place (San Francisco): its failure is the error
        raise GateError(f"{source}: {first.split(': ', 1)[-1]}; refused")
    if kept.empty:
        raise GateError(f"{source}: no {rules.places.kind} passes the validation gate "
                        f"({len(skipped)} skipped; e.g. {first}); refused")
    if failed > rules.max_skipped_share * len(known):
        unknown = sum(p not in known for p in skipped)
        names = f", {unknown} of them unknown names" if unknown else ""
        raise GateError(f"{source}: {failed} of the {len(known)} {rules.places.kind}s fail the "
                        f"validation gate{names} (more than {pct(rules.max_skipped_share)}: a "
                        f"broken payload, not a broken place); e.g. {first}; refused")


def _first_per_place(place: NDArray[np.object_], mask: NDArray[np.bool_]) -> list[int]:
    """The first failing row of each place with one (rows are sorted by place and date)."""
    where = np.flatnonzero(mask)
    if where.size == 0:
        return []
    _, first = np.unique(place[where].astype(str), return_index=True)
    return [int(where[k]) for k in first]


def _typed(kept: pd.DataFrame, rules: GateRules) -> pd.DataFrame:
    out = kept[["place", "date"]].reset_index(drop=True)
    out["date"] = pd.DatetimeIndex(out["date"]).as_unit("ns")
    for bound in rules.counts:
        out[bound.column] = pd.to_numeric(kept[bound.column].astype("string").str.strip()
                                          ).to_numpy(np.float64).astype(np.int64)
    for share in rules.shares:
        out[share.column] = pd.to_numeric(kept[share.column].astype("string").str.strip()
                                          ).to_numpy(np.float64)
    if rules.population_column is not None:
        out[rules.population_column] = pd.to_numeric(
            kept[rules.population_column].astype("string").str.strip()).to_numpy(
            np.float64).astype(np.int64)
    return out


# ------------------------------------------------------------------------------ the checks


def _checks(rows: _Rows, as_of: pd.Timestamp | None) -> list[tuple[NDArray[np.bool_], Message]]:
    """Every check as (failing rows, message of a row), in the order a place's first failure is
    named: cells, dates, the population it reports, then bounds and history."""
    rules = rows.rules
    checks = [*_cell_checks(rows), *_date_checks(rows, as_of)]
    if rules.population_column is not None:
        checks += _population_checks(rows, rules.population_column)
    clean = ~np.logical_or.reduce([m for m, _ in checks]) if checks else \
        np.ones(len(rows.frame), dtype=bool)
    checks += _bound_checks(rows)
    if rules.jump is not None:
        checks += _jump_checks(rows, rules.jump, clean)
    if rules.growth is not None:
        checks += _growth_checks(rows, rules.growth, clean)
    return checks


def _cell_checks(rows: _Rows) -> list[tuple[NDArray[np.bool_], Message]]:
    checks: list[tuple[NDArray[np.bool_], Message]] = []
    for column in rows.rules.columns:
        text, value = rows.text[column], rows.value[column]
        empty = (text.isna() | (text == "")).to_numpy()
        unparsed = np.isnan(value) & ~empty
        infinite = np.isinf(value)

        def said(what: str, c: str = column) -> Message:
            return lambda i: f"'{c}' is {what} ({rows.raw(c, i)}) on {rows.day(i)}"

        checks += [(empty, said("empty")), (unparsed, said("not a number")),
                   (infinite, said("not finite"))]
    for bound in rows.rules.counts:
        value = rows.value[bound.column]
        finite = np.isfinite(value)
        whole = finite & (value == np.round(value))
        c = bound.column
        checks.append((finite & ~whole, lambda i, c=c: f"'{c}' is not a whole number of people "
                                                       f"({rows.raw(c, i)}) on {rows.day(i)}"))
        if not bound.negative_ok:
            checks.append((finite & (value < 0), lambda i, c=c: f"'{c}' is negative "
                                                                f"({rows.raw(c, i)}) on "
                                                                f"{rows.day(i)}"))
    return checks


def _date_checks(rows: _Rows, as_of: pd.Timestamp | None
                 ) -> list[tuple[NDArray[np.bool_], Message]]:
    rules, date = rows.rules, rows.date
    unreadable = np.asarray(date.isna())
    checks: list[tuple[NDArray[np.bool_], Message]] = [
        (unreadable, lambda i: "a date could not be read")]
    weekday = rules.weekday
    if weekday is not None:
        wrong = ~unreadable & (np.asarray(date.weekday) != weekday)
        checks.append((wrong, lambda i: f"week ending {rows.day(i)} is a "
                                        f"{date[i].day_name()}, not a "
                                        f"{calendar.day_name[weekday]}"))
    if as_of is not None:
        late = ~unreadable & np.asarray(date > as_of)
        checks.append((late, lambda i: f"{rows.day(i)} is after the vintage's date "
                                       f"{as_of.date()}"))
    same_place = np.concatenate([[False], rows.place[1:] == rows.place[:-1]])
    days = np.asarray(date.values.astype("datetime64[D]").astype(np.int64), dtype=np.float64)
    days[unreadable] = np.nan
    step = np.concatenate([[np.nan], np.diff(days)])
    duplicate = same_place & (step == 0)
    checks.append((duplicate, lambda i: f"two rows for {rows.day(i)}"))
    if not rules.missing_weeks:
        gap = same_place & (step > rules.step_days)
        checks.append((gap, lambda i: f"a gap of {int(step[i]) // rules.step_days - 1} "
                                      f"{'day' if rules.step_days == 1 else 'week'}(s) before "
                                      f"{rows.day(i)}"))
    last_of_place = np.concatenate([rows.place[1:] != rows.place[:-1], [True]])
    end = payload_end(rows.place, days, last_of_place)
    beyond = np.isfinite(days) & (days > end)
    short = last_of_place & (days < end)
    checks.append((beyond, lambda i: f"a row for {rows.day(i)}, after the payload's last "
                                           f"date {pd.Timestamp(end, unit='D').date()} (the "
                                           f"date most places end on)"))
    checks.append((short, lambda i: f"ends on {rows.day(i)}, the payload on "
                                    f"{pd.Timestamp(end, unit='D').date()}"))
    return checks


def payload_end(place: NDArray[np.object_], days: NDArray[np.float64],
                last_of_place: NDArray[np.bool_]) -> float:
    """The payload's last date (days since the epoch): the last date most places end on (ties:
    the later), so one place's odd later row never sets it."""
    ends = days[last_of_place]
    ends = ends[np.isfinite(ends)]
    if ends.size == 0:
        return np.nan
    values, counts = np.unique(ends, return_counts=True)
    return float(values[counts == counts.max()].max())


def _population_checks(rows: _Rows, column: str) -> list[tuple[NDArray[np.bool_], Message]]:
    rules = rows.rules
    text = rows.frame[column].astype("string").str.strip()
    value = pd.to_numeric(text, errors="coerce").to_numpy(np.float64)
    ratio = value / np.where(rows.population > 0, rows.population, np.nan)
    tol = rules.population_tolerance
    bad = ~np.isfinite(value) | (value != np.round(value)) | ~(np.abs(ratio - 1.0) <= tol)
    first_of_place = np.concatenate([[True], rows.place[1:] != rows.place[:-1]])
    first_value = pd.Series(np.where(first_of_place, value, np.nan)).ffill().to_numpy()
    varies = ~bad & (value != first_value)

    def off(i: int) -> str:
        return (f"its population {str(text.iloc[i])!r} is not within {pct(tol)} of the "
                f"{rules.places.figures} figure {rows.population[i]:,.0f}")

    return [(bad, off), (varies, lambda i: f"its population changes to {str(text.iloc[i])!r} "
                                          f"on {rows.day(i)}")]


def _weekly_sums(rows: _Rows, value: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each row's count over the 7 days ending on it (daily rows), or the row itself (weekly)."""
    if rows.rules.step_days >= 7:
        return value
    filled = pd.Series(np.nan_to_num(value, nan=0.0, posinf=0.0, neginf=0.0))
    sums = filled.groupby(rows.place.astype(str)).rolling(7, min_periods=1).sum()
    return sums.reset_index(level=0, drop=True).sort_index().to_numpy()


def _bound_checks(rows: _Rows) -> list[tuple[NDArray[np.bool_], Message]]:
    figures = rows.rules.places.figures
    checks: list[tuple[NDArray[np.bool_], Message]] = []
    for bound in rows.rules.counts:
        value, c = rows.value[bound.column], bound.column
        if bound.per_day is not None:
            day_limit = np.maximum(bound.per_day * rows.population, bound.floor)
            over_day = np.isfinite(value) & (value > day_limit)
            checks.append((over_day, lambda i, c=c, b=bound, v=value: (
                f"implausible count {count(v[i])} in '{c}' on {rows.day(i)}: more than "
                f"{pct(b.per_day or 0)} of the population {rows.population[i]:,.0f} "
                f"({figures}) in one day")))
        week = _weekly_sums(rows, value)
        week_limit = np.maximum(bound.per_week * rows.population, bound.floor)
        over_week = np.isfinite(value) & (week > week_limit)
        span = "in the 7 days ending" if rows.rules.step_days < 7 else "in the week ending"
        checks.append((over_week, lambda i, c=c, b=bound, w=week: (
            f"implausible count {count(w[i])} in '{c}' {span} {rows.day(i)}: more than "
            f"{pct(b.per_week)} of the population {rows.population[i]:,.0f} ({figures}) in "
            f"one week")))
    for share in rows.rules.shares:
        value, c = rows.value[share.column], share.column
        outside = np.isfinite(value) & ((value < 0) | (value > share.maximum))
        checks.append((outside, lambda i, c=c, s=share, v=value: (
            f"'{c}' is {v[i]:g} on {rows.day(i)}, outside 0 … {s.maximum:g}")))
    return checks


@dataclass(frozen=True)
class _PlaceDateGrid:
    """The clean, dated rows (``ok``) laid on a (places × dates) grid: each row's cell."""

    ok: NDArray[np.bool_]
    place_code: NDArray[np.intp]
    date_code: NDArray[np.intp]
    shape: tuple[int, int]

    @classmethod
    def of(cls, rows: _Rows, clean: NDArray[np.bool_]) -> _PlaceDateGrid | None:
        ok = clean & ~np.asarray(rows.date.isna())
        if not ok.any():
            return None
        places, place_code = np.unique(rows.place[ok].astype(str), return_inverse=True)
        dates, date_code = np.unique(rows.date[ok].values, return_inverse=True)
        return cls(ok, place_code, date_code, (len(places), len(dates)))

    def grid(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """``values`` of the rows on the grid, NaN where no clean row is."""
        out = np.full(self.shape, np.nan)
        out[self.place_code, self.date_code] = values[self.ok]
        return out


def _jump_checks(rows: _Rows, rule: JumpRule, clean: NDArray[np.bool_]
                 ) -> list[tuple[NDArray[np.bool_], Message]]:
    """Counts beyond their own history, on a (places × dates) grid of the clean rows."""
    checks: list[tuple[NDArray[np.bool_], Message]] = []
    cells = _PlaceDateGrid.of(rows, clean)
    if cells is None:
        return checks
    ok, place_code, date_code = cells.ok, cells.place_code, cells.date_code
    row_place = np.full(len(rows.frame), -1)
    row_date = np.full(len(rows.frame), -1)
    row_place[ok], row_date[ok] = place_code, date_code
    for bound in rows.rules.counts:
        grid = cells.grid(rows.value[bound.column])
        bounds = history_bounds(grid, rule)
        beyond = np.zeros(len(rows.frame), dtype=bool)
        beyond[ok] = grid[place_code, date_code] > bounds[place_code, date_code]

        def jumped(i: int, c: str = bound.column, grid: NDArray[np.float64] = grid) -> str:
            series, d = grid[row_place[i]], row_date[i]
            seen = ~np.isnan(series)
            return (f"implausible count {count(float(series[d]))} in '{c}' on {rows.day(i)}: "
                    f"{describe_jump(series[seen], int(seen[:d].sum()), rule)}")

        checks.append((beyond, jumped))
    return checks


def _growth_checks(rows: _Rows, rule: GrowthRule, clean: NDArray[np.bool_]
                   ) -> list[tuple[NDArray[np.bool_], Message]]:
    """Counts whose ``rule.days``-row sum grew beyond ``rule`` over the sum before, on a
    (places × dates) grid of the clean rows."""
    checks: list[tuple[NDArray[np.bool_], Message]] = []
    cells = _PlaceDateGrid.of(rows, clean)
    if cells is None:
        return checks
    ok, place_code, date_code = cells.ok, cells.place_code, cells.date_code
    for column in rule.columns:
        grid = cells.grid(rows.value[column])
        now, before = growth_sums(grid, rule)
        at_now, at_before = now[place_code, date_code], before[place_code, date_code]
        beyond = np.zeros(len(rows.frame), dtype=bool)
        beyond[ok] = at_now > rule.factor * (at_before + rule.floor)
        full_now = np.full(len(rows.frame), np.nan)
        full_before = np.full(len(rows.frame), np.nan)
        full_now[ok], full_before[ok] = at_now, at_before

        def grew(i: int, c: str = column, n: NDArray[np.float64] = full_now,
                 b: NDArray[np.float64] = full_before) -> str:
            return (f"implausible growth of '{c}': {count(n[i])} in the {rule.days} days ending "
                    f"{rows.day(i)} after {count(b[i])} in the {rule.days} days before, more than "
                    f"{rule.factor:g}× (the earlier count + {rule.floor:g}); the fastest real "
                    f"growth, in the CDPH vintages, is 5.5×")

        checks.append((beyond, grew))
    return checks


# ------------------------------------------------------------------------------ the bounds
# Shares of the population a count of people may reach; measured maxima in docs/data.md.


def cases_bound(column: str, *, negative_ok: bool = False) -> CountBound:
    """People with a positive test, by day: at most 5 % of the place in a day, 10 % in a week,
    never below 100 people. Largest real shares (of the 2020 Census figures): CDPH 1.7 % in a
    day (Alpine's 21 reported cases of 1,204, 2020-11-21) and 3.7 % in a week (Lassen's
    reported cases, 2020-12-15); San Francisco 0.36 % and 1.9 % (Omicron)."""
    return CountBound(column, per_day=0.05, per_week=0.10, floor=100, negative_ok=negative_ok)


def deaths_bound(column: str) -> CountBound:
    """Deaths: at most 0.5 % of the place in a day and 1 % in a week, never below 20. Largest
    real shares: 0.023 % in a day (Modoc, 2 of 8,700), 0.031 % in a week (Imperial)."""
    return CountBound(column, per_day=0.005, per_week=0.01, floor=20)


def tests_bound(column: str) -> CountBound:
    """Tests (people may test several times): at most 10 % of the place in a day and 50 % in a
    week, never below 100. Largest real: San Francisco 2.3 % in a day, 13 % in a week."""
    return CountBound(column, per_day=0.10, per_week=0.50, floor=100)


def admissions_bound(column: str) -> CountBound:
    """Weekly hospital admissions: at most 0.5 % of the location in a week, never below 50.
    Largest real share in the hub's 44 vintages: 0.048 % (Pennsylvania, week ending 2024-11-16,
    6,124 of 12.8 M)."""
    return CountBound(column, per_day=None, per_week=0.005, floor=50)
