"""Import a forecast hub's target data into the NHSN cache: every vintage it records.

* a hubverse ``time-series.parquet`` (``target-data/time-series.parquet`` of a hub; columns
  ``target_end_date, location, observation, as_of, target``): every (target, ``as_of``) is one
  vintage. The real one in ``../shared/data/nhsn`` holds 44 vintages of ``wk inc covid hosp``
  (2024-11-20 … 2025-09-24) and 15 of ``wk inc covid prop ed visits``;
* a plain target-data CSV (``date`` or ``target_end_date``, ``location``, ``value`` or
  ``observation``; a location as the hub's code or a postal abbreviation) with the target and
  its as-of date given.

Every vintage is read and passed through the validation gate before any is stored (a file whose
vintage no location passes changes nothing); then they are stored oldest first, each under the
cache lock (:func:`pipeline.data.hub.nhsn_vintages.commit_weekly`): live if newer and within the
revision policy, archived if older than the live one, held for review if it revises settled
weeks beyond the policy (the import goes on with the next). The cache keeps each as the
canonical target CSV (``target_end_date, location, value``).

Sizes are checked before decoding, from what the genuine file weighs: the hub's design-period
parquet is 68,938 bytes, 170,540 rows, 223,946 bytes uncompressed; a file may have 16 MB, 2 M rows
and 64 MB uncompressed (the hub's full history for years to come), else it is refused unread.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import date
from pathlib import Path
from typing import Literal

import pandas as pd

from pipeline.data.core.cache import DatasetCache, RevisionRefusedError
from pipeline.data.core.decoding import PayloadRejectedError, decode_boundary, decode_csv_frame
from pipeline.data.hub.held_locations import read_holds
from pipeline.data.hub.locations import JURISDICTION_LOCATION
from pipeline.data.hub.release import ReleaseDateError, release_date
from pipeline.data.hub.nhsn_vintages import (MAX_CSV_BYTES, TARGETS, WeeklyVintage, canonical_csv,
                                             commit_weekly, parse_vintage, skipped_note,
                                             target_spec)
from pipeline.errors import ValidationError

TIME_SERIES = "time-series.parquet"
MAX_PARQUET_BYTES = 16 << 20
MAX_PARQUET_ROWS = 2_000_000
MAX_PARQUET_UNCOMPRESSED = 64 << 20
Action = Literal["live", "archived", "held", "refused", "skipped"]


@dataclass(frozen=True)
class VintageImport:
    """What became of one imported vintage."""

    target: str
    as_of: str
    action: Action
    rows: int
    first_week: str
    last_week: str
    note: str = ""


@dataclass(frozen=True)
class HubImportSummary:
    path: Path
    vintages: tuple[VintageImport, ...]
    unknown_targets: tuple[str, ...] = ()

    def targets(self) -> dict[str, list[VintageImport]]:
        out: dict[str, list[VintageImport]] = {}
        for v in self.vintages:
            out.setdefault(v.target, []).append(v)
        return out

    def lines(self) -> list[str]:
        """One line per target (what the CLI prints), then one per vintage with a note."""
        out = []
        for target, done in self.targets().items():
            counts = {a: sum(v.action == a for v in done) for a in
                      ("live", "archived", "held", "refused", "skipped")}
            said = ", ".join(f"{n} {a}" for a, n in counts.items() if n)
            out.append(f"{target}: {len(done)} vintage(s) {done[0].as_of} … {done[-1].as_of} "
                       f"from {self.path.name} ({said})")
            out += [f"  {v.as_of} {v.action}: {v.note}" for v in done if v.note]
        if self.unknown_targets:
            out.append(f"not imported (targets flowcast does not know): "
                       f"{', '.join(self.unknown_targets)}")
        return out


def hub_time_series_file(path: str | os.PathLike[str]) -> Path:
    """``path`` itself, or the time series of a hub folder (``<hub>/target-data/`` or the folder
    itself holding ``time-series.parquet``)."""
    p = Path(path)
    if p.is_dir():
        for candidate in (p / TIME_SERIES, p / "target-data" / TIME_SERIES):
            if candidate.is_file():
                return candidate
        raise ValidationError(f"{p} is a folder without a hub {TIME_SERIES} (looked for "
                              f"{p / TIME_SERIES} and {p / 'target-data' / TIME_SERIES})")
    return p


def read_hub_time_series(path: Path) -> pd.DataFrame:
    """The parquet's rows, sizes checked before anything is decoded."""
    import pyarrow.parquet as pq

    size = path.stat().st_size
    if size > MAX_PARQUET_BYTES:
        raise PayloadRejectedError(f"{path}: {size:,} bytes, more than the "
                                   f"{MAX_PARQUET_BYTES:,} a hub time series may have; refused "
                                   f"unread")
    with decode_boundary("parquet", str(path), size):
        meta = pq.ParquetFile(path).metadata
        unpacked = sum(meta.row_group(i).total_byte_size for i in range(meta.num_row_groups))
        if meta.num_rows > MAX_PARQUET_ROWS or unpacked > MAX_PARQUET_UNCOMPRESSED:
            raise PayloadRejectedError(
                f"{path}: {meta.num_rows:,} rows, {unpacked:,} bytes uncompressed, more than "
                f"the {MAX_PARQUET_ROWS:,} rows / {MAX_PARQUET_UNCOMPRESSED:,} bytes a hub "
                f"time series may have; refused unread")
        table = pq.read_table(path).to_pandas()
    missing = [c for c in ("target_end_date", "location", "observation", "target")
               if c not in table.columns]
    if missing:
        raise ValidationError(f"{path}: missing column(s) {missing} of a hubverse time series; "
                              f"columns present: {list(table.columns)}")
    return table


def _canonical(frame: pd.DataFrame, dates: str, values: str) -> pd.DataFrame:
    location = frame["location"].astype("string").str.strip()
    return pd.DataFrame({"target_end_date": frame[dates].astype("string").str.strip().str[:10],
                         "location": location.str.upper().map(JURISDICTION_LOCATION)
                         .fillna(location),
                         "value": frame[values]})


@dataclass(frozen=True)
class _Checked:
    vintage: WeeklyVintage
    payload: bytes


def _check(target: str, as_of: date, rows: pd.DataFrame, source: str) -> _Checked:
    payload = canonical_csv(rows)
    spec = target_spec(target)
    return _Checked(parse_vintage(spec, payload, suffix="csv", as_of=as_of, source=source),
                    payload)


def _store(checked: Sequence[_Checked], *, source: str, data_dir: str | os.PathLike[str] | None,
           if_empty: bool, accept_revisions: bool) -> list[VintageImport]:
    cache = DatasetCache.default(data_dir)
    ordered = sorted(checked, key=lambda c: (c.vintage.target, c.vintage.as_of))
    had = {t: cache.has(target_spec(t)) for t in {c.vintage.target for c in ordered}}
    out = []
    for c in ordered:
        v = c.vintage
        action: Action = "skipped"
        note = "the cache already holds this target (--if-empty)"
        if not (if_empty and had[v.target]):
            try:
                done = commit_weekly(cache, v, c.payload, suffix="csv", source_kind="csv-import",
                                     source=source, older="archive",
                                     accept_revisions=accept_revisions)
                action, note = done.action, ""
                if done.action == "archived":
                    note = f"older than the live vintage of {done.live_as_of}: archived"
                note = "; ".join(filter(None, (note, _holds_opened(cache, v))))
            except RevisionRefusedError as exc:
                action, note = ("held" if exc.hold else "refused"), str(exc)
            except ReleaseDateError as exc:
                action, note = "refused", str(exc)
            note = "; ".join(filter(None, (note, *skipped_note(v))))
        frame = v.frame
        out.append(VintageImport(v.target, str(v.as_of.date()), action, len(frame),
                                 str(frame["target_end_date"].min().date()),
                                 str(v.last_week.date()), note))
    return out


def _holds_opened(cache: DatasetCache, vintage: WeeklyVintage) -> str:
    """The locations this release left held for review (the others went live)."""
    since = str(vintage.as_of.date())
    opened = [h for h in read_holds(cache.directory(target_spec(vintage.target))).entries
              if h.since == since]
    if not opened:
        return ""
    return (f"held for review, their cached series kept: "
            f"{', '.join(h.location for h in opened)} ({opened[0].reason})")


def import_hub_time_series(path: str | os.PathLike[str],
                           data_dir: str | os.PathLike[str] | None = None, *,
                           as_of: date | str | None = None, if_empty: bool = False,
                           accept_revisions: bool = False) -> HubImportSummary:
    """Every vintage of a hub's ``time-series.parquet`` (or a hub folder) into the cache (module
    doc). A file without ``as_of`` holds one vintage, dated ``as_of``."""
    file = hub_time_series_file(path)
    table = read_hub_time_series(file)
    if table.empty:
        raise ValidationError(f"{file}: an empty time series (no rows); nothing imported")
    if "as_of" not in table.columns:
        if as_of is None:
            raise ValidationError(f"{file} has no as_of column: give the vintage's date "
                                  f"(`flowcast data import FILE --as-of YYYY-MM-DD`)")
        table = table.assign(as_of=str(release_date(as_of, where="--as-of")))
    table = table.assign(as_of=_release_dates(table["as_of"], file))
    known = table["target"].isin(list(TARGETS))
    if not known.any():
        raise ValidationError(f"{file}: no row of a target flowcast knows (targets in the file: "
                              f"{', '.join(map(str, table['target'].unique()[:6]))}); nothing "
                              f"imported")
    unknown = tuple(sorted(table.loc[~known, "target"].astype(str).unique()))
    source = str(file.resolve())
    checked = [_check(str(target), date.fromisoformat(str(when)),
                      _canonical(rows, "target_end_date", "observation"),
                      f"{source} ({target}, as of {when})")
               for (target, when), rows in table[known].groupby(["target", "as_of"], sort=True)]
    return HubImportSummary(file, tuple(_store(checked, source=source, data_dir=data_dir,
                                               if_empty=if_empty,
                                               accept_revisions=accept_revisions)), unknown)


def _release_dates(column: pd.Series, file: Path) -> pd.Series:
    """The ``as_of`` column as ``YYYY-MM-DD`` text; any unreadable value is one named error."""
    text = column.astype("string").str.strip().str[:10]
    parsed = pd.to_datetime(text, format="%Y-%m-%d", errors="coerce")
    bad = text[parsed.isna()]
    if len(bad):
        raise ReleaseDateError(f"{file}: {len(bad)} row(s) with an unreadable release date in "
                               f"as_of, e.g. {str(column[parsed.isna()].iloc[0])!r} (YYYY-MM-DD "
                               f"expected); nothing imported")
    return parsed.dt.strftime("%Y-%m-%d")


def import_target_csv(path: str | os.PathLike[str], *, target: str, as_of: date | str,
                      data_dir: str | os.PathLike[str] | None = None,
                      accept_revisions: bool = False) -> HubImportSummary:
    """One vintage of ``target`` from a plain target-data CSV (module doc)."""
    when = release_date(as_of, where="--as-of")
    file = Path(path)
    raw = decode_csv_frame(file.read_bytes(), source=str(file), max_bytes=MAX_CSV_BYTES)
    dates = next((c for c in ("date", "target_end_date") if c in raw.columns), None)
    values = next((c for c in ("value", "observation") if c in raw.columns), None)
    if dates is None or values is None or "location" not in raw.columns:
        raise ValidationError(f"{file}: a target CSV needs columns date (or target_end_date), "
                              f"location and value (or observation); columns present: "
                              f"{list(raw.columns)[:10]}")
    source = str(file.resolve())
    checked = _check(target_spec(target).target, when, _canonical(raw, dates, values),
                     f"{source} (as of {when})")
    return HubImportSummary(file, tuple(_store([checked], source=source, data_dir=data_dir,
                                               if_empty=False,
                                               accept_revisions=accept_revisions)))


def is_hub_time_series(path: str | os.PathLike[str]) -> bool:
    """A parquet file, or a folder holding a hub's time series."""
    p = Path(path)
    if p.is_dir():
        return any((p / sub / TIME_SERIES).is_file() for sub in ("", "target-data"))
    return p.suffix == ".parquet"


def is_target_csv(columns: Sequence[str]) -> bool:
    """Does a CSV header look like a hub target CSV (a location, a date and a value column)?"""
    names = {str(c).strip().lower() for c in columns}
    return "location" in names and bool(names & {"date", "target_end_date"}) \
        and bool(names & {"value", "observation"})
