"""California county series from CDPH's "COVID-19 Time-Series Metrics by County and State".

The file (``covid19cases_test.csv``, published on the California Health and Human Services open
data portal) has one row per area and day from 2020-02-01: ``area_type`` ``County`` (the 58
counties, plus ``Unknown`` and ``Out of state``) or ``State``; one more row per area with an empty
``date`` carries totals without a date and is dropped. Columns this module reads:

* ``cases``: cases by **episode date** (earliest of onset, diagnosis, specimen collection; the
  definition of DataSF's specimen-collection series). Recent days fill in as late reports arrive,
  so every download is a **vintage**: the same days as CDPH knew them on that day;
* ``reported_cases``: cases by the day CDPH reported them (complete on arrival, never revised);
* ``deaths`` (date of death), ``population`` (CDPH's estimate, San Francisco 892,280);
* ``total_tests``, ``positive_tests``: tests by specimen collection date, where the file has
  them. Not gated (the forecast's own series are the cases): an empty, unreadable or negative
  count reads as missing (NaN), and the vintage is kept without them.

Vintages differ in their date format (``M/D/YYYY`` in early 2021, ISO later) and columns (the
cumulative columns came later); both are read. The vintage's date is its last dated row.

A county's series becomes an :class:`~pipeline.panels.history.EpiHistory` with the product's
S/I/R conversion (:func:`pipeline.data.core.sir_counts.sir_counts`: a case is infectious for 7 days,
then removed; deaths are removals), on the county's own population.

Parsing is in two steps. The file itself must be CDPH's (readable as CSV, the required columns,
dated county rows): anything else is a :class:`CDPHFormatError` naming the problem, and the
payload is refused. Every county's rows then pass the validation gate every source shares
(:mod:`pipeline.data.core.gate`, :data:`CDPH_GATE`): counts finite, whole, not negative (except
``reported_cases``, where CDPH books corrections), within a share of the county's 2020 Census
population a day and a week and plausible against the county's own history, the county one of
the 58, its reported population within 25 % of the census figure, its days readable, one row each,
no gap, ending on the file's last day. A county that fails is **skipped** and named in
:attr:`CDPHVintage.skipped`; the others are kept. Empty counts on the last day (CDPH leaves
tests empty there) read as 0 for ``cases``/``deaths``/``reported_cases`` only on the vintage's
last date, where they mean "nothing reported yet".
"""
from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.california.counties import COUNTY_POPULATION_2020
from pipeline.data.core.decoding import PayloadRejectedError, decode_boundary
from pipeline.data.core.gate import GateRules, Places, cases_bound, deaths_bound, gate
from pipeline.data.core.plausibility import DAILY, GrowthRule
from pipeline.data.core.sir_counts import DEFAULT_INFECTIOUS_PERIOD_DAYS, proportions, sir_counts
from pipeline.errors import ValidationError
from pipeline.io import atomic_write_bytes

COUNTY = "County"
REQUIRED_COLUMNS: tuple[str, ...] = ("date", "area", "area_type", "population", "cases",
                                     "deaths", "reported_cases")
COUNT_COLUMNS: tuple[str, ...] = ("cases", "deaths", "reported_cases")
TEST_COLUMNS: tuple[str, ...] = ("total_tests", "positive_tests")
NOT_COUNTIES: frozenset[str] = frozenset({"Unknown", "Out of state"})
DATE_FORMATS: tuple[str, ...] = ("%Y-%m-%d", "%m/%d/%Y")
CALIFORNIA_COUNTIES = 58
CDPH_GATE = GateRules(
    source="CDPH", places=Places("California county", COUNTY_POPULATION_2020, "2020 Census"),
    # CDPH books corrections as negative counts on the report date (down to -5,064 in a day),
    # never on episode or death dates
    counts=(cases_bound("cases"), deaths_bound("deaths"),
            cases_bound("reported_cases", negative_ok=True)),
    step_days=1, jump=DAILY, population_column="population",
    # a slow ramp against the fastest growth of the real vintages (reported cases carry
    # CDPH's negative corrections, so only episode-date cases are held to it)
    growth=GrowthRule(columns=("cases",)))


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
    # by specimen collection date; NaN where the file has none
    total_tests: NDArray[np.float64] | None = None
    positive_tests: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.dates)

    @property
    def last_date(self) -> pd.Timestamp:
        return self.dates[-1]


@dataclass(frozen=True, eq=False)
class CDPHVintage:
    """Every county of one CDPH download. ``as_of``: its last date; ``source``: where it came
    from (a path or a URL)."""

    frame: pd.DataFrame      # date, area, population, cases, deaths, reported_cases, tests
    as_of: pd.Timestamp
    source: str
    skipped: Mapping[str, str] = field(default_factory=dict)  # county -> why the gate dropped it

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
        if rows.empty and area in self.skipped:
            raise CDPHFormatError(f"{area} is skipped in the CDPH vintage of {self.as_of.date()} "
                                  f"({self.source}): {self.skipped[area]}")
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
            deaths=rows["deaths"].to_numpy(np.int64),
            **{c: rows[c].to_numpy(np.float64) for c in TEST_COLUMNS if c in rows})


# ------------------------------------------------------------------------------------ parsing


def _parse_dates(values: pd.Series) -> pd.Series:
    """The dates in the format most of them are in (the file has one); NaT where a date does not
    parse (the gate skips its county, named)."""
    text = values.astype("string").str.strip()
    return max((pd.to_datetime(text, format=f, errors="coerce") for f in DATE_FORMATS),
               key=lambda p: int(p.notna().sum())).dt.normalize()


# Parsed vintages by the bytes' hash: a weekly run reads the same cached vintage in several steps
# (reference counties, nowcast, county skill); parsing a 4 MB file takes most of a second.
_PARSED: dict[str, CDPHVintage] = {}
_PARSED_LIMIT = 16
PARSED_FORMAT = f"flowcast-cdph-parsed-3-{CDPH_GATE.fingerprint()}"


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
             skipped=np.array(json.dumps(dict(vintage.skipped))),
             **{c: vintage.frame[c].to_numpy(np.int64) for c in COUNT_COLUMNS},
             **{c: vintage.frame[c].to_numpy(np.float64) for c in TEST_COLUMNS})
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
                                  **{c: npz[c] for c in (*COUNT_COLUMNS, *TEST_COLUMNS)}})
            as_of = pd.Timestamp(int(npz["as_of"]))
            skipped = json.loads(str(npz["skipped"]))
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None
    return CDPHVintage(frame=frame, as_of=as_of, source=str(path), skipped=skipped)


def _parse(data: bytes, source: str) -> CDPHVintage:
    try:
        with decode_boundary("CSV", source, len(data)):
            raw = pd.read_csv(io.BytesIO(data), dtype=str, keep_default_na=False)
    except PayloadRejectedError as exc:   # any decode failure, named (pipeline.data.core.decoding)
        raise CDPHFormatError(f"{source}: not a CSV file ({exc.__cause__})") from exc
    missing = [c for c in REQUIRED_COLUMNS if c not in raw.columns]
    if missing:
        raise CDPHFormatError(f"{source}: missing column(s) {missing}; columns present: "
                              f"{list(raw.columns)[:20]} (is this CDPH's covid19cases_test.csv?)")
    dated = raw[(raw["date"].str.strip() != "") & (raw["area_type"] == COUNTY)
                & ~raw["area"].isin(list(NOT_COUNTIES))]
    if dated.empty:
        raise CDPHFormatError(f"{source}: no dated county rows")
    rows = pd.DataFrame({"place": dated["area"].str.strip(), "date": _parse_dates(dated["date"]),
                         "population": dated["population"],
                         **{c: dated[c] for c in COUNT_COLUMNS}})
    last = rows["date"].max()
    if pd.isna(last):
        raise CDPHFormatError(f"{source}: no date is YYYY-MM-DD or M/D/YYYY")
    on_last = (rows["date"] == last).to_numpy()
    for column in COUNT_COLUMNS:   # nothing reported yet on the vintage's last day
        empty = on_last & (rows[column].str.strip() == "").to_numpy()
        rows.loc[empty, column] = "0"
    gated = gate(rows, CDPH_GATE, source=source)
    frame = gated.frame.rename(columns={"place": "area"})[
        ["date", "area", "population", *COUNT_COLUMNS]]
    frame = frame.merge(_tests(dated, rows), on=["area", "date"], how="left", validate="1:1")
    frame["area"] = frame["area"].astype(object)
    return CDPHVintage(frame=frame, as_of=pd.Timestamp(last), source=source,
                       skipped=gated.skipped)


def _tests(dated: pd.DataFrame, rows: pd.DataFrame) -> pd.DataFrame:
    """``area``, ``date`` and :data:`TEST_COLUMNS` of the dated county rows: NaN where the file
    has no such column, or a count is empty, unreadable or negative; one row per area and day
    (a repeated day is the gate's to refuse, and reads as missing here)."""
    out = pd.DataFrame({"area": rows["place"], "date": rows["date"]})
    for column in TEST_COLUMNS:
        text = dated[column] if column in dated.columns else pd.Series("", index=dated.index)
        value = pd.to_numeric(text.astype("string").str.strip(), errors="coerce")
        out[column] = value.where(value >= 0).to_numpy(np.float64)
    return out.dropna(subset=["date"]).drop_duplicates(["area", "date"], keep=False)


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
