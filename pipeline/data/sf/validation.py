"""Schema and value checks for DataSF daily series, with errors that name field, row and value.

Input is a frame of *strings* as read (JSON API values are strings; CSV read with ``dtype=str``)
whose columns may carry API names, CSV display names or canonical names. Output is a typed,
date-sorted frame with canonical columns plus a :class:`ValidationReport`.

Rules (each violation raises :class:`pipeline.errors.ValidationError` unless noted):

* the payload has at least one row;
* every required field is present (a missing/renamed column is named in the CSV display form and
  the API form, e.g. ``missing column 'New Cases' (API field 'new_cases')``);
* every date parses (one of the spec's formats) — otherwise the row and value are named;
* counts are finite, non-negative integers below :data:`COUNT_BOUND` ("12" and "12.0" are
  accepted; "abc", "1.5", "-3", "inf", "1e19" and empty cells are errors naming column, row and
  date). The bound keeps every count exact in float64 and int64: before it, ``inf`` and ``1e19``
  passed and became INT64_MIN when cast, poisoning the cache;
* the last date is not after the payload's own "data as of" stamp (nor after ``today`` when the
  caller passes it): a series reaching into the future is a broken payload, not news;
* no date appears twice (DataSF publishes one row per day; two rows leave no way to know which
  is right, so this is an error, never a silent pick);
* gaps (missing days inside the date range) are *reported*; with ``GapPolicy.ZERO_FILL``
  (default) the missing days are inserted with count 0 and the cumulative column carried
  forward. Why zero: in these series a day without a row is a day on which nothing was recorded
  (DataSF omitted zero days in early versions). If the missing days in fact had events, the
  cumulative check below exposes it on the first day after the gap (the jump in the cumulative
  column exceeds that day's new count), so a wrong repair cannot pass unreported.
  ``GapPolicy.ERROR`` refuses gaps instead;
* the cumulative column is compared with the running sum of the daily counts; disagreement is
  *reported* (days, largest difference, first date) and logged, never silently fixed: the
  daily counts are what flowcast uses, and DataSF revisions can make the two drift.
"""
from __future__ import annotations

import enum
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from pipeline.data.sf.datasf import DatasetSpec, FieldSpec
from pipeline.errors import ValidationError

log = logging.getLogger(__name__)

# Largest count accepted in any column: 100 million. San Francisco has 873,965 people; its largest
# published count, cumulative tests, reached about 4 million by 2022. Far below 2**53, so every
# accepted count is exact in float64 (how pandas parses them) and in int64.
COUNT_BOUND = 100_000_000


class GapPolicy(str, enum.Enum):
    ZERO_FILL = "zero-fill"
    ERROR = "error"


@dataclass(frozen=True)
class Gap:
    first_missing: pd.Timestamp
    last_missing: pd.Timestamp

    @property
    def days(self) -> int:
        return int((self.last_missing - self.first_missing).days) + 1

    def __str__(self) -> str:
        return f"{self.first_missing.date()}…{self.last_missing.date()} ({self.days} d)"


@dataclass(frozen=True)
class ValidationReport:
    dataset_key: str
    source: str
    row_count: int
    first_date: pd.Timestamp
    last_date: pd.Timestamp
    gaps: tuple[Gap, ...] = ()
    filled_days: int = 0
    cumulative_mismatch_days: int = 0
    cumulative_max_abs_diff: int = 0
    first_cumulative_mismatch: pd.Timestamp | None = None
    final_cumulative: int | None = None
    data_as_of: pd.Timestamp | None = None
    data_loaded_at: pd.Timestamp | None = None
    warnings: tuple[str, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class ValidatedFrame:
    """Typed, sorted, gap-free daily frame: ``date`` (datetime64) + int64 count columns."""

    spec: DatasetSpec
    frame: pd.DataFrame
    report: ValidationReport


def find_column(columns: Sequence[str], spec_field: FieldSpec) -> str | None:
    """The column that carries ``spec_field`` under any of its names (case/space-insensitive)."""
    wanted = {n.strip().lower() for n in spec_field.names()}
    for column in columns:
        if str(column).strip().lower() in wanted:
            return str(column)
    return None


def column_match_count(columns: Sequence[str], spec: DatasetSpec) -> int:
    """How many of ``spec``'s required fields and vintage stamps ``columns`` carries."""
    return sum(find_column(columns, f) is not None for f in (*spec.required, *spec.as_of))


def canonical_columns(raw: pd.DataFrame, spec: DatasetSpec, *, source: str) -> pd.DataFrame:
    """Rename recognized columns to canonical names; error naming every missing required one."""
    renames: dict[str, str] = {}
    missing: list[str] = []
    for spec_field in (*spec.required, *spec.as_of):
        found = find_column(list(raw.columns), spec_field)
        if found is not None:
            renames[found] = spec_field.canonical
        elif spec_field in spec.required:
            aka = "".join(f" or '{a}'" for a in spec_field.aliases)
            missing.append(f"missing column '{spec_field.display}' "
                           f"(API field '{spec_field.api}'{aka})")
    if missing:
        present = ", ".join(repr(str(c)) for c in raw.columns)
        raise ValidationError(f"{source}: {'; '.join(missing)} for {spec.key} "
                              f"({spec.dataset_id}); columns present: {present}")
    return raw.loc[:, list(renames)].rename(columns=renames)


def parse_dates(values: pd.Series, formats: Sequence[str]) -> pd.Series:
    """Parse with the first matching format per value; NaT where none matches."""
    text = values.astype("string").str.strip()
    parsed = pd.Series(pd.NaT, index=values.index, dtype="datetime64[us]")
    for fmt in formats:
        todo = parsed.isna() & text.notna()
        if not todo.any():
            break
        parsed.loc[todo] = pd.to_datetime(text[todo], format=fmt, errors="coerce")
    return parsed


def _row_context(frame: pd.DataFrame, position: int) -> str:
    date = frame["date"].iloc[position] if "date" in frame else None
    return f"row {position + 1}" + (f" (date {date})" if date is not None else "")


def _parse_counts(raw: pd.DataFrame, column: str, spec_field: FieldSpec, source: str
                  ) -> np.ndarray:
    text = raw[column].astype("string").str.strip()
    numbers = pd.to_numeric(text, errors="coerce")
    bad = numbers.isna().to_numpy()
    if bad.any():
        pos = int(np.flatnonzero(bad)[0])
        value = text.iloc[pos]
        what = "empty value" if pd.isna(value) or value == "" else f"non-numeric value {value!r}"
        raise ValidationError(f"{source}: {what} in '{spec_field.display}' at "
                              f"{_row_context(raw, pos)}; {int(bad.sum())} such row(s)")
    values = numbers.to_numpy(dtype=np.float64)
    infinite = ~np.isfinite(values)
    if infinite.any():
        pos = int(np.flatnonzero(infinite)[0])
        raise ValidationError(f"{source}: non-finite count {text.iloc[pos]!r} in "
                              f"'{spec_field.display}' at {_row_context(raw, pos)}; "
                              f"{int(infinite.sum())} such row(s)")
    too_large = np.abs(values) >= COUNT_BOUND
    if too_large.any():
        pos = int(np.flatnonzero(too_large)[0])
        raise ValidationError(f"{source}: count {text.iloc[pos]!r} in '{spec_field.display}' at "
                              f"{_row_context(raw, pos)} is not below the bound {COUNT_BOUND:,}; "
                              f"{int(too_large.sum())} such row(s)")
    fractional = values != np.round(values)
    if fractional.any():
        pos = int(np.flatnonzero(fractional)[0])
        raise ValidationError(f"{source}: non-integer count {text.iloc[pos]!r} in "
                              f"'{spec_field.display}' at {_row_context(raw, pos)}")
    negative = values < 0
    if negative.any():
        pos = int(np.flatnonzero(negative)[0])
        raise ValidationError(f"{source}: negative count {text.iloc[pos]!r} in "
                              f"'{spec_field.display}' at {_row_context(raw, pos)}; "
                              f"{int(negative.sum())} negative row(s)")
    return values.astype(np.int64)


def _find_gaps(dates: pd.Series[pd.Timestamp]) -> tuple[Gap, ...]:
    steps = dates.diff().dt.days.to_numpy()
    where = np.flatnonzero(steps > 1)
    day = pd.Timedelta(days=1)
    return tuple(Gap(dates.iloc[i - 1] + day, dates.iloc[i] - day) for i in where)


def _latest_stamp(frame: pd.DataFrame, column: str) -> pd.Timestamp | None:
    if column not in frame:
        return None
    stamps = parse_dates(frame[column], ("%m/%d/%Y %I:%M:%S %p", "%Y-%m-%dT%H:%M:%S.%f",
                                         "%Y-%m-%dT%H:%M:%S", "%Y/%m/%d", "%Y-%m-%d"))
    return None if stamps.isna().all() else pd.Timestamp(stamps.max())


def validate_frame(raw: pd.DataFrame, spec: DatasetSpec, *, source: str,
                   gap_policy: GapPolicy = GapPolicy.ZERO_FILL,
                   today: pd.Timestamp | None = None) -> ValidatedFrame:
    """Check ``raw`` (strings, any supported column names) against ``spec``; see module doc.

    ``today`` (when given): the last date may not be after it (plus a day for time zones)."""
    if len(raw) == 0:
        raise ValidationError(f"{source}: empty payload (no rows) for {spec.key} "
                              f"({spec.dataset_id})")
    named = canonical_columns(raw, spec, source=source)
    dates = parse_dates(named["date"], spec.date_formats)
    if dates.isna().any():
        pos = int(np.flatnonzero(dates.isna().to_numpy())[0])
        raise ValidationError(f"{source}: unparseable date {named['date'].iloc[pos]!r} in "
                              f"'{spec.date.display}' at row {pos + 1}")
    named = named.assign(date=dates.dt.normalize().dt.date.astype(str))
    typed = pd.DataFrame({"date": dates.dt.normalize()})
    for spec_field in (*spec.counts, *((spec.cumulative,) if spec.cumulative else ())):
        typed[spec_field.canonical] = _parse_counts(named, spec_field.canonical, spec_field,
                                                    source)
    duplicated = typed["date"].duplicated(keep=False)
    if duplicated.any():
        dup_dates = sorted({str(d.date()) for d in typed.loc[duplicated, "date"]})
        raise ValidationError(f"{source}: duplicate date(s) in '{spec.date.display}': "
                              f"{', '.join(dup_dates[:5])}" + (" …" if len(dup_dates) > 5 else ""))
    typed = typed.sort_values("date", ignore_index=True)
    gaps = _find_gaps(typed["date"])
    warnings: list[str] = []
    if gaps:
        listed = ", ".join(str(g) for g in gaps[:5])
        if gap_policy is GapPolicy.ERROR:
            raise ValidationError(f"{source}: {len(gaps)} gap(s) in the daily series: {listed}")
        warnings.append(f"{len(gaps)} gap(s) zero-filled: {listed}")
        typed = _zero_fill(typed, spec)
    report_cum = _cumulative_agreement(typed, spec)
    mismatch_days, max_diff, first_mismatch = report_cum
    if mismatch_days:
        # Days can only disagree when there is a cumulative column, and then the first is known.
        assert spec.cumulative is not None and first_mismatch is not None
        warnings.append(f"cumulative '{spec.cumulative.display}' disagrees with the running sum "
                        f"of '{spec.counts[0].display}' on {mismatch_days} day(s), max |diff| "
                        f"{max_diff}, first {first_mismatch.date()}")
    for message in warnings:
        log.warning("%s: %s", source, message)
    report = ValidationReport(
        dataset_key=spec.key, source=source, row_count=len(raw),
        first_date=typed["date"].iloc[0], last_date=typed["date"].iloc[-1], gaps=gaps,
        filled_days=sum(g.days for g in gaps), cumulative_mismatch_days=report_cum[0],
        cumulative_max_abs_diff=report_cum[1], first_cumulative_mismatch=report_cum[2],
        final_cumulative=(int(typed[spec.cumulative.canonical].iloc[-1])
                          if spec.cumulative else None),
        data_as_of=_latest_stamp(named, "data_as_of"),
        data_loaded_at=_latest_stamp(named, "data_loaded_at"), warnings=tuple(warnings))
    _check_not_future(report, source, today)
    return ValidatedFrame(spec, typed, report)


def _check_not_future(report: ValidationReport, source: str, today: pd.Timestamp | None) -> None:
    """A payload may not hold days after its own vintage stamp (or after today)."""
    last = report.last_date
    if report.data_as_of is not None and last > report.data_as_of.normalize():
        raise ValidationError(f"{source}: last date {last.date()} is after the payload's own "
                              f"'data as of' {report.data_as_of.date()} (dates from the future); "
                              f"refused")
    if today is not None and last > pd.Timestamp(today).normalize() + pd.Timedelta(days=1):
        raise ValidationError(f"{source}: last date {last.date()} is after today "
                              f"({pd.Timestamp(today).date()}); refused")


def _zero_fill(typed: pd.DataFrame, spec: DatasetSpec) -> pd.DataFrame:
    full = pd.date_range(typed["date"].iloc[0], typed["date"].iloc[-1], freq="D")
    filled = typed.set_index("date").reindex(full)
    filled[list(spec.count_columns)] = filled[list(spec.count_columns)].fillna(0)
    if spec.cumulative is not None:
        # Carry the last published total through the gap (consistent with zero new events).
        filled[spec.cumulative.canonical] = filled[spec.cumulative.canonical].ffill()
    filled = filled.astype(np.int64).rename_axis("date").reset_index()
    filled["date"] = filled["date"].astype("datetime64[us]")
    return filled


def _cumulative_agreement(typed: pd.DataFrame, spec: DatasetSpec
                          ) -> tuple[int, int, pd.Timestamp | None]:
    """(days where Δcumulative ≠ new count, max |difference|, first such date)."""
    if spec.cumulative is None or spec.cumulative_of is None or len(typed) < 2:
        return 0, 0, None
    step = np.diff(typed[spec.cumulative.canonical].to_numpy())
    new = typed[spec.cumulative_of].to_numpy()[1:]
    diff = step - new
    bad = np.flatnonzero(diff != 0)
    if bad.size == 0:
        return 0, 0, None
    return int(bad.size), int(np.abs(diff).max()), typed["date"].iloc[int(bad[0]) + 1]
