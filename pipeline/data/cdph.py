"""California county series from CDPH's "COVID-19 Time-Series Metrics by County and State".

The file (``covid19cases_test.csv``, published on the California Health and Human Services open
data portal) has one row per area and day from 2020-02-01: ``area_type`` ``County`` (the 58
counties, plus ``Unknown`` and ``Out of state``) or ``State``; one more row per area with an empty
``date`` carries totals without a date and is dropped. Columns this module reads:

* ``cases``: cases by **episode date** (earliest of onset, diagnosis, specimen collection; the
  definition of DataSF's specimen-collection series). Recent days fill in as late reports arrive,
  so every download is a **vintage**: the same days as CDPH knew them on that day;
* ``reported_cases``: cases by the day CDPH reported them (complete on arrival, never revised);
* ``deaths`` (date of death), ``population`` (CDPH's estimate, San Francisco 892,280).

Vintages differ in their date format (``M/D/YYYY`` in early 2021, ISO later) and columns (the
cumulative columns came later); both are read. The vintage's date is its last dated row.

A county's series becomes an :class:`~pipeline.panels.history.EpiHistory` with the product's
S/I/R conversion (:func:`pipeline.data.sir_transform.sir_counts`: a case is infectious for 7 days,
then removed; deaths are removals), on the county's own population.

Parsing is strict and every problem is a :class:`CDPHFormatError` naming the column, row and
value: a missing column, an unparseable date, a fractional count or a negative one (allowed
only in ``reported_cases``, where CDPH books corrections) on a dated row of a real county, a county with a gap or a duplicate day. Empty counts on the last day (CDPH leaves
tests empty there) read as 0 for ``cases``/``deaths``/``reported_cases`` only on the vintage's
last date, where they mean "nothing reported yet"; anywhere else they are an error.
"""
from __future__ import annotations

import dataclasses
import hashlib
import io
import os
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.decoding import PayloadRejectedError, decode_boundary
from pipeline.data.sir_transform import DEFAULT_INFECTIOUS_PERIOD_DAYS, proportions, sir_counts
from pipeline.errors import ValidationError
from pipeline.io import atomic_write_bytes

COUNTY = "County"
REQUIRED_COLUMNS: tuple[str, ...] = ("date", "area", "area_type", "population", "cases",
                                     "deaths", "reported_cases")
COUNT_COLUMNS: tuple[str, ...] = ("cases", "deaths", "reported_cases")
CORRECTED_BY_NEGATIVE_COUNTS: frozenset[str] = frozenset({"reported_cases"})
NOT_COUNTIES: frozenset[str] = frozenset({"Unknown", "Out of state"})
DATE_FORMATS: tuple[str, ...] = ("%Y-%m-%d", "%m/%d/%Y")
CALIFORNIA_COUNTIES = 58


class CDPHFormatError(ValidationError):
    """A CDPH export that is not the county time series (columns, dates, counts, gaps)."""


@dataclass(frozen=True, eq=False)
class CountySeries:
    """One county's daily series in one vintage (consecutive days, oldest first)."""

    area: str
    population: int
    dates: pd.DatetimeIndex
    cases: NDArray[np.int64]            # by episode date (revised as reports arrive)
    reported_cases: NDArray[np.int64]   # by report date (final on arrival)
    deaths: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.dates)

    @property
    def last_date(self) -> pd.Timestamp:
        return self.dates[-1]


@dataclass(frozen=True, eq=False)
class CDPHVintage:
    """Every county of one CDPH download. ``as_of``: its last date; ``source``: where it came
    from (a path or a URL)."""

    frame: pd.DataFrame      # date, area, population, cases, deaths, reported_cases (counties)
    as_of: pd.Timestamp
    source: str

    @property
    def counties(self) -> tuple[str, ...]:
        return tuple(sorted(self.frame["area"].unique()))

    def populations(self) -> dict[str, int]:
        first = self.frame.groupby("area", sort=True)["population"].first()
        return {str(a): int(p) for a, p in first.items()}

    def counties_with_population(self, minimum: int) -> tuple[str, ...]:
        """Counties with at least ``minimum`` people, by name."""
        return tuple(a for a, p in self.populations().items() if p >= minimum)

    def county(self, area: str) -> CountySeries:
        rows = self.frame[self.frame["area"] == area]
        if rows.empty:
            close = [c for c in self.counties if c.lower() == area.strip().lower()]
            hint = f"; did you mean {close[0]!r}?" if close else \
                f"; known: {', '.join(self.counties)}"
            raise CDPHFormatError(f"no county {area!r} in the CDPH vintage of "
                                  f"{self.as_of.date()} ({self.source}){hint}")
        return CountySeries(
            area=area, population=int(rows["population"].iloc[0]),
            dates=pd.DatetimeIndex(rows["date"]).as_unit("ns"),
            cases=rows["cases"].to_numpy(np.int64),
            reported_cases=rows["reported_cases"].to_numpy(np.int64),
            deaths=rows["deaths"].to_numpy(np.int64))


# ------------------------------------------------------------------------------------ parsing


def _parse_dates(values: pd.Series, source: str) -> pd.Series:
    text = values.astype("string").str.strip()
    for fmt in DATE_FORMATS:
        parsed = pd.to_datetime(text, format=fmt, errors="coerce")
        if parsed.notna().all():
            return parsed.dt.normalize()
    best = max((pd.to_datetime(text, format=f, errors="coerce") for f in DATE_FORMATS),
               key=lambda p: int(p.notna().sum()))
    bad = int(np.flatnonzero(best.isna().to_numpy())[0])
    raise CDPHFormatError(f"{source}: date {text.iloc[bad]!r} on data row {bad + 1} is neither "
                          "YYYY-MM-DD nor M/D/YYYY")


def _parse_counts(frame: pd.DataFrame, column: str, last_date: pd.Timestamp,
                  source: str) -> NDArray[np.int64]:
    # CDPH books corrections as negative counts on the report date (down to -5,064 in a day),
    # never on episode or death dates
    may_be_negative = column in CORRECTED_BY_NEGATIVE_COUNTS
    values = pd.to_numeric(frame[column], errors="coerce").to_numpy(np.float64)
    raw = frame[column].astype("string")
    unparseable = np.isnan(values) & raw.notna().to_numpy() & (raw.str.strip() != "").to_numpy()
    missing = np.isnan(values) & ~unparseable
    allowed_missing = (frame["date"] == last_date).to_numpy()
    problems = [("not a number", unparseable), ("empty", missing & ~allowed_missing),
                ("negative", (values < 0) & (not may_be_negative)), ("not a whole number",
                                            np.isfinite(values) & (values != np.round(values)))]
    for what, mask in problems:
        if mask.any():
            i = int(np.flatnonzero(mask)[0])
            row = frame.iloc[i]
            raise CDPHFormatError(f"{source}: {column} is {what} ({raw.iloc[i]!r}) for "
                                  f"{row['area']} on {pd.Timestamp(row['date']).date()}")
    return np.nan_to_num(values, nan=0.0).astype(np.int64)


def _check_days(frame: pd.DataFrame, source: str) -> None:
    """Each county: no duplicate day, no gap, the same last day as the vintage."""
    last = frame["date"].max()
    for area, dates in frame.groupby("area", sort=True)["date"]:
        steps = np.diff(dates.to_numpy(dtype="datetime64[D]").astype(np.int64))
        if (steps != 1).any():
            k = int(np.flatnonzero(steps != 1)[0])
            what = "a duplicate" if steps[k] == 0 else f"a gap of {int(steps[k]) - 1} days"
            raise CDPHFormatError(f"{source}: {area} has {what} after "
                                  f"{pd.Timestamp(dates.iloc[k]).date()}")
        if dates.iloc[-1] != last:
            raise CDPHFormatError(f"{source}: {area} ends on {pd.Timestamp(dates.iloc[-1]).date()}"
                                  f", the file on {pd.Timestamp(last).date()}")


# Parsed vintages by the bytes' hash: a weekly run reads the same cached vintage in several steps
# (reference counties, nowcast, county skill); parsing a 4 MB file takes most of a second.
_PARSED: dict[str, CDPHVintage] = {}
_PARSED_LIMIT = 16
PARSED_FORMAT = "flowcast-cdph-parsed-1"


def parse_cdph_csv(data: bytes, source: str, parsed_dir: Path | None = None) -> CDPHVintage:
    """A :class:`CDPHVintage` from the bytes of ``covid19cases_test.csv`` (module docstring);
    the same bytes are parsed once per process, and once ever with ``parsed_dir`` (a cache's
    folder of parsed vintages, ``<sha256>.npz``: the six vintages of a weekly run take 2 s to
    parse and milliseconds to read back)."""
    digest = hashlib.sha256(data).hexdigest()
    if digest not in _PARSED:
        stored = None if parsed_dir is None else _read_parsed(parsed_dir / f"{digest}.npz")
        if stored is None:
            stored = _parse(data, source)
            if parsed_dir is not None:
                _write_parsed(parsed_dir / f"{digest}.npz", stored)
        if len(_PARSED) >= _PARSED_LIMIT:
            _PARSED.pop(next(iter(_PARSED)))
        _PARSED[digest] = stored
    return dataclasses.replace(_PARSED[digest], source=source)


def _write_parsed(path: Path, vintage: CDPHVintage) -> None:
    areas, codes = np.unique(vintage.frame["area"].to_numpy(str), return_inverse=True)
    buffer = io.BytesIO()
    np.savez(buffer, allow_pickle=False, format=np.array(PARSED_FORMAT),
             as_of=np.array(vintage.as_of.value), areas=areas, area_codes=codes,
             date=vintage.frame["date"].to_numpy("datetime64[ns]").astype(np.int64),
             population=vintage.frame["population"].to_numpy(np.int64),
             **{c: vintage.frame[c].to_numpy(np.int64) for c in COUNT_COLUMNS})
    try:
        atomic_write_bytes(path, buffer.getvalue())
    except OSError:
        pass    # a cache of a cache: the next run parses again


def _read_parsed(path: Path) -> CDPHVintage | None:
    """The stored parse, or None (absent, or unreadable: then parsed again and rewritten)."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            if str(npz["format"]) != PARSED_FORMAT:
                return None
            areas, codes = npz["areas"], npz["area_codes"]
            frame = pd.DataFrame({"date": pd.to_datetime(npz["date"]).as_unit("ns"),
                                  "area": areas[codes].astype(object),
                                  "population": npz["population"],
                                  **{c: npz[c] for c in COUNT_COLUMNS}})
            as_of = pd.Timestamp(int(npz["as_of"]))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None
    return CDPHVintage(frame=frame, as_of=as_of, source=str(path))


def _parse(data: bytes, source: str) -> CDPHVintage:
    try:
        with decode_boundary("CSV", source, len(data)):
            raw = pd.read_csv(io.BytesIO(data), dtype=str, keep_default_na=False)
    except PayloadRejectedError as exc:   # any decode failure, named (pipeline.data.decoding)
        raise CDPHFormatError(f"{source}: not a CSV file ({exc.__cause__})") from exc
    missing = [c for c in REQUIRED_COLUMNS if c not in raw.columns]
    if missing:
        raise CDPHFormatError(f"{source}: missing column(s) {missing}; columns present: "
                              f"{list(raw.columns)[:20]} (is this CDPH's covid19cases_test.csv?)")
    dated = raw[(raw["date"].str.strip() != "") & (raw["area_type"] == COUNTY)
                & ~raw["area"].isin(list(NOT_COUNTIES))].copy()
    if dated.empty:
        raise CDPHFormatError(f"{source}: no dated county rows")
    dated["date"] = _parse_dates(dated["date"], source)
    dated = dated.sort_values(["area", "date"], kind="stable").reset_index(drop=True)
    last = dated["date"].max()
    population = pd.to_numeric(dated["population"], errors="coerce")
    if population.isna().any() or (population <= 0).any():
        bad = dated.loc[population.isna() | (population <= 0), "area"].iloc[0]
        raise CDPHFormatError(f"{source}: {bad} has no positive population")
    frame = pd.DataFrame({"date": dated["date"], "area": dated["area"].astype(str),
                          "population": population.round().astype(np.int64)})
    for column in COUNT_COLUMNS:
        frame[column] = _parse_counts(dated, column, last, source)
    _check_days(frame, source)
    return CDPHVintage(frame=frame, as_of=pd.Timestamp(last), source=source)


def read_cdph_csv(path: str | os.PathLike[str]) -> CDPHVintage:
    """A vintage from a downloaded ``covid19cases_test.csv``."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise CDPHFormatError(f"cannot read CDPH export {p}: {exc.strerror or exc}") from exc
    return parse_cdph_csv(data, str(p))


def read_vintages(paths: Sequence[str | os.PathLike[str]]) -> list[CDPHVintage]:
    """Vintages from several downloads, oldest first (by their last date)."""
    return sorted((read_cdph_csv(p) for p in paths), key=lambda v: v.as_of)


def find_vintage_files(root: str | os.PathLike[str]) -> list[Path]:
    """Every ``covid19cases_test.csv`` under ``root`` (a folder of archived downloads)."""
    return sorted(Path(root).rglob("covid19cases_test.csv"))


# ------------------------------------------------------------------------- to the S/I/R series


def county_sir(series: CountySeries,
               infectious_period_days: int = DEFAULT_INFECTIOUS_PERIOD_DAYS
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """S, I, R proportions of a county by the product's conversion (module docstring)."""
    s, i, r = sir_counts(series.cases, series.deaths, cases_before=0, deaths_before=0,
                         population=series.population,
                         infectious_period_days=infectious_period_days)
    return proportions(s, i, r, series.population)
