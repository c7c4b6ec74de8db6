"""Faults that arrive as a NEWER release than the cached one (issue 39), through the live fetch
and the import.

The other catalogues replay each fault on a release of the same date as the cached one, which
takes other code paths. Here the fake data.cdc.gov on 127.0.0.1 (:class:`bench.faults_nhsn.
FakeCDC`) first serves the hub's real release of 2025-09-17, fetched that day; then the release
of 2025-09-24 with one fault, fetched a week later. Each case states what must become of it:

* ``cache``: refused, the cached release used with a note naming the problem, every cache file
  byte-identical (``held``: and the payload kept under ``held/``);
* ``live``: the newer release goes live with ``skipped`` left out and named (a location's own
  fault costs that location alone), every earlier file unchanged but the manifest;
* ``error``: no cache to fall back on: one named error, nothing stored.

The import cases (``source="import"``) run :func:`pipeline.data.hub.target_import` and the CLI
on files built from the real releases (``../shared/data/nhsn``, ``../shared/data/flusight``).
Each of issue 39's problems that lives in the data layer is a case (docs/data.md lists which);
the round's are :mod:`bench.faults_round`, the slow ramp DataSF's and CDPH's catalogues, the
hub config (problems 10 and 11) ``tests/test_release_judgement.py``.
"""
from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Literal

import pandas as pd

from bench.faults import CaseResult, bytes_lost, cache_bytes, leftovers, run_cases
from bench.faults_nhsn import (HRD_ORDER, NHSN, NSSP_ORDER, FakeCDC, Rows, at, edited,
                               held_files, hrd_rows, hub_vintage, nhsn_config, nssp_rows,
                               send_pages, with_cell)
from pipeline.data.hub.nhsn import ED_COVID, HOSP_COVID, load_nhsn
from pipeline.errors import FlowcastError

OLD, NEW = "2025-09-17", "2025-09-24"
OLD_NOW = datetime(2025, 9, 17, 18, 0, tzinfo=timezone.utc)
NEW_NOW = OLD_NOW + timedelta(days=7)
FLUSIGHT = NHSN.parent / "flusight" / "time-series.parquet"
Outcome = Literal["cache", "live", "error"]
ADM, ED = "totalconfc19newadm", "percent_visits_covid"


@dataclass(frozen=True)
class Newer:
    """One fault on the newer release: ``rows`` edits its rows (``old``: start from another real
    release instead); ``expect`` must be in the note (or the skipped reason)."""

    name: str
    expect: str
    rows: Callable[[Rows], Rows]
    outcome: Outcome
    target: str = HOSP_COVID
    skipped: str | None = None
    held_place: str | None = None     # held for review, read from its accepted series (49)
    held: bool = False
    first_fetch: bool = False
    old: str | None = None
    derived: str | None = None


def _keys(target: str) -> tuple[str, str, str]:
    return (("jurisdiction", "weekendingdate", ADM) if target == HOSP_COVID
            else ("geography", "week_end", ED))


def newest_week(rows: Rows, date_key: str) -> str:
    return max(r[date_key][:10] for r in rows)


def set_newest(value: str | Callable[[str], str], target: str = HOSP_COVID,
               where: Callable[[dict[str, str]], bool] = lambda r: True
               ) -> Callable[[Rows], Rows]:
    """Every (chosen) row of the newest week set to ``value`` (or ``value(old)``)."""
    place, day, column = _keys(target)

    def change(rows: Rows) -> Rows:
        week = newest_week(rows, day)
        for r in rows:
            if r[day].startswith(week) and where(r):
                r[column] = value(r[column]) if callable(value) else value
        return rows
    return change


def alone_in_newest_week(place_name: str, target: str = HOSP_COVID) -> Callable[[Rows], Rows]:
    """The newest week kept for one place only: its row is later than everyone else's last
    week, and not in the future."""
    place, day, column = _keys(target)

    def change(rows: Rows) -> Rows:
        week = newest_week(rows, day)
        return [r for r in rows if not r[day].startswith(week) or r[place] == place_name]
    return change


def later_row(place_name: str, week: str, target: str = HOSP_COVID) -> Callable[[Rows], Rows]:
    """One place with a row for ``week``, after everyone else's last week."""
    place, day, column = _keys(target)

    def change(rows: Rows) -> Rows:
        template = next(r for r in rows if r[place] == place_name)
        return rows + [{**template, day: f"{week}T00:00:00.000"}]
    return change


def renamed(names: Callable[[str], str], target: str = HOSP_COVID,
            keep: Callable[[str], bool] = lambda n: False) -> Callable[[Rows], Rows]:
    place = _keys(target)[0]

    def change(rows: Rows) -> Rows:
        for r in rows:
            if not keep(r[place]):
                r[place] = names(r[place])
        return rows
    return change


def _state_name(code: str) -> str:
    from pipeline.data.hub.locations import BY_JURISDICTION
    h = BY_JURISDICTION.get(code)
    return h.name if h is not None and code != "USA" else code


def _postal(name: str) -> str:
    from pipeline.data.hub.locations import BY_NAME
    h = BY_NAME.get(name.casefold())
    return h.abbreviation if h is not None else name


def drop_weeks(n: int, target: str = HOSP_COVID) -> Callable[[Rows], Rows]:
    day = _keys(target)[1]

    def change(rows: Rows) -> Rows:
        weeks = sorted({r[day][:10] for r in rows})[-n:]
        return [r for r in rows if r[day][:10] not in weeks]
    return change


def scale_week(place_name: str, week: str, factor: float | None = None, value: str | None = None
               ) -> Callable[[Rows], Rows]:
    def change(rows: Rows) -> Rows:
        for r in rows:
            if at(place_name, week)(r):
                r[ADM] = value if value is not None else str(int(float(r[ADM]) * (factor or 1)))
        return rows
    return change


def many_revised(rows: Rows) -> Rows:
    """Sixteen states' settled week ending 2025-06-07 times ten (a broken payload)."""
    from pipeline.data.hub.locations import HUB_LOCATIONS
    states = {h.jurisdiction for h in HUB_LOCATIONS[1:17]}
    for r in rows:
        if r["jurisdiction"] in states and r["weekendingdate"].startswith("2025-06-07"):
            r[ADM] = str(int(r[ADM]) * 10 + 200)
    return rows


def _without_states(n: int) -> Callable[[Rows], Rows]:
    """The newer release without the first ``n`` states' rows (a broken payload)."""
    from pipeline.data.hub.locations import HUB_LOCATIONS
    gone = {h.jurisdiction for h in HUB_LOCATIONS[1:1 + n]}
    return lambda rows: [r for r in rows if r["jurisdiction"] not in gone]


def newer_faults() -> list[Newer]:
    nation_name = lambda r: r.get("geography") == "United States"  # noqa: E731
    return [
        # 1. a stale release: its newest week far before its date
        Newer("stale-release-62-weeks-old", "stale release: its newest week ends 2024-11-16",
              lambda r: r, "cache", held=True, old="2024-11-20"),
        Newer("stale-release-last-4-weeks-missing", "stale release: its newest week ends "
              "2025-08-23, 32 days", drop_weeks(4), "cache", held=True),
        Newer("ed-stale-release", "stale release", drop_weeks(4, ED_COVID), "cache",
              target=ED_COVID, held=True),
        # 2. one location's later row refuses that location alone
        Newer("one-location-later-week", "06: a row for 2025-09-20, after the payload's last "
              "date 2025-09-13", alone_in_newest_week("CA"), "live", skipped="06"),
        Newer("one-location-future-week", "06: 2031-01-04 is after the vintage's date",
              later_row("CA", "2031-01-04"), "live", skipped="06"),
        Newer("ed-one-geography-later-week", "06: a row for 2025-09-20, after the payload's "
              "last date 2025-09-13", alone_in_newest_week("California", ED_COVID), "live",
              target=ED_COVID, skipped="06"),
        Newer("one-location-week-after-the-release", "06: 2025-09-27 is after the vintage's "
              "date 2025-09-24", later_row("CA", "2025-09-27"), "live", skipped="06"),
        # 3. implausible whole-release events are held
        Newer("nationwide-drop-to-zero", "every one of the 53 locations reads 0 for the week "
              "ending 2025-09-20", set_newest("0"), "cache", held=True),
        Newer("national-row-falls-80-percent", "the national value falls 82% in the week "
              "ending 2025-09-20", set_newest(lambda v: str(int(int(v) * 0.2)),
                                              where=lambda r: r["jurisdiction"] == "USA"),
              "cache", held=True),
        Newer("ed-nationwide-share-zero", "the national value falls 100%",
              set_newest("0", ED_COVID), "cache", target=ED_COVID, held=True),
        # 4. no known place: one named error, the cache kept
        Newer("full-state-names-for-codes", "52 of the 53 hub locations fail the validation "
              "gate, 52 of them unknown names", renamed(_state_name), "cache"),
        Newer("every-name-unknown", "no row names one of the 53 known hub location names",
              renamed(lambda n: f"{n} State"), "cache"),
        Newer("ed-counties-written-x-county", "no row names one of the 53 known hub location "
              "names", renamed(lambda n: f"{n} County", ED_COVID), "cache", target=ED_COVID),
        # 5. unknown names count toward the broken-payload share
        Newer("ed-postal-codes-for-names", "of the 53 hub locations fail the validation "
              "gate, 50 of them unknown names", renamed(_postal, ED_COVID,
                                                        keep=lambda n: n == "United States"),
              "cache", target=ED_COVID),
        Newer("ed-postal-codes-first-fetch", "50 of them unknown names",
              renamed(_postal, ED_COVID, keep=lambda n: n == "United States"), "error",
              target=ED_COVID, first_fetch=True),
        Newer("fourteen-unknown-names-beside-real-ones", "14 of the 53 hub locations fail",
              lambda r: r + [{**x, "jurisdiction": f"Z{k}"} for k in range(14)
                             for x in r[:1]], "cache"),
        Newer("one-unknown-name-beside-real-ones", "'ZZ' is not one of the 53",
              lambda r: r + [{**x, "jurisdiction": "ZZ"} for x in r if x["jurisdiction"] == "OH"],
              "live", skipped="ZZ"),
        # 6. no national row: admissions take the states' sum; a share cannot (below)
        Newer("no-national-row", "no national row in the release: the national value is the "
              "sum of the 52 states", lambda r: [x for x in r if x["jurisdiction"] != "USA"],
              "live", derived="US"),
        Newer("national-row-poisoned", "US: 'totalconfc19newadm' is not finite ('Infinity') "
              "on 2025-09-20: the national value is the sum of the 52 states",
              set_newest("Infinity", where=lambda r: r["jurisdiction"] == "USA"), "live",
              derived="US"),
        # a share's states go live without the US, which is left out and named (issue 39)
        Newer("ed-no-national-row", "US: no national row in the release; a share cannot be "
              "summed from the states: the national forecast is left out",
              lambda r: [x for x in r if not nation_name(x)], "live", target=ED_COVID,
              skipped="US"),
        # a location missing from a newer release is held alone, its last series kept
        Newer("one-state-missing-from-newer-release", "06: missing from the release of "
              "2025-09-24 (its series of 2025-09-17 kept until it is back)",
              lambda r: [x for x in r if x["jurisdiction"] != "CA"], "live", skipped="06"),
        Newer("ed-one-state-missing-from-newer-release", "06: missing from the release of "
              "2025-09-24 (its series of 2025-09-17 kept until it is back)",
              lambda r: [x for x in r if x["geography"] != "California"], "live",
              target=ED_COVID, skipped="06"),
        Newer("fourteen-states-missing-refused-whole", "14 of the 53 locations are missing from "
              "the release of 2025-09-24 (more than 25%: a broken payload, refused)",
              _without_states(14), "cache"),
        # 8. dates from the future
        Newer("every-location-a-week-in-2031", "is after the vintage's date",
              lambda r: [{**x, "weekendingdate": "2031-01-04T00:00:00.000"}
                         if x["weekendingdate"].startswith("2025-09-20") else x for x in r],
              "cache"),
        # missing weeks cost the week
        Newer("na-week-in-one-location", "", scale_week("CA", "2025-08-02", value=""), "live"),
        Newer("ed-na-week-in-one-geography", "",
              with_cell(ED, "NA", at("California", "2025-08-02", "geography", "week_end")),
              "live", target=ED_COVID),
        # revisions judged per location (issue 37, item 4)
        Newer("settled-count-tenfold-held-alone", "06: revision held for review since the "
              "release of 2025-09-24 (its series of 2025-09-17 kept)",
              scale_week("CA", "2025-06-07", 10), "live", held_place="06"),
        Newer("settled-backfill-zero-to-positive", "", scale_week("VT", "2025-06-07",
                                                                  value="150"), "live",
              old=None),
        Newer("sixteen-locations-revised-held-whole", "of the 53 locations revise settled "
              "weeks beyond the policy (more than 25%: the release is held whole)", many_revised,
              "cache", held=True),
    ]


def _rows(target: str, as_of: str) -> Rows:
    return hrd_rows(as_of) if target == HOSP_COVID else nssp_rows(as_of)


def _serve(cdc: FakeCDC, target: str, rows: Rows) -> None:
    if target == HOSP_COVID:
        cdc.hrd = send_pages(rows, HRD_ORDER)
    else:
        cdc.nssp = send_pages(rows, NSSP_ORDER)


def _zero_first(rows: Rows) -> Rows:
    """The cached release with Vermont's settled week ending 2025-06-07 at 0 (so the newer
    release's value there is a backfill)."""
    return scale_week("VT", "2025-06-07", value="0")(rows)


def run_newer(fault: Newer, folder: Path) -> CaseResult:
    data = folder / "data"
    started = time.monotonic()
    with FakeCDC() as cdc:
        if not fault.first_fetch:
            old = _rows(fault.target, OLD)
            _serve(cdc, fault.target, _zero_first(old) if "backfill" in fault.name else old)
            load_nhsn(nhsn_config(cdc.url, data, fault.target), now=OLD_NOW)
        before = cache_bytes(data)
        _serve(cdc, fault.target, edited(_rows(fault.target, fault.old or NEW), fault.rows))
        try:
            loaded = load_nhsn(nhsn_config(cdc.url, data, fault.target), now=NEW_NOW)
        except FlowcastError as exc:
            after = cache_bytes(data)
            passed = (fault.outcome == "error" and fault.expect in str(exc) and not after)
            return CaseResult(fault.name, passed, time.monotonic() - started,
                              bytes_lost(before, after), f"error: {exc}", source="nhsn",
                              issue=39)
        left = leftovers(cdc.http.port)
    seconds = time.monotonic() - started
    provenance, vintage = loaded.provenance[fault.target], loaded[fault.target]
    after = cache_bytes(data)
    held = bool(held_files(data, fault.target))
    note = " | ".join(provenance.notes)
    if fault.outcome == "cache":
        lost = bytes_lost(before, after)
        ok = (provenance.from_cache and fault.expect in note and held == fault.held)
    else:
        lost = bytes_lost({k: v for k, v in before.items() if not k.endswith("manifest.json")},
                          after)
        why = vintage.skipped.get(fault.skipped, "") if fault.skipped else ""
        if fault.derived is not None:
            why = vintage.derived.get(fault.derived, "")
        if fault.held_place is not None:
            why = vintage.held.get(fault.held_place, "")
        named = (fault.skipped, fault.derived, fault.held_place) != (None, None, None)
        ok = (not provenance.from_cache and provenance.as_of == NEW
              and (not named or fault.expect in why)
              and (fault.skipped is not None or fault.derived is not None
                   or not vintage.skipped)
              and len(vintage.locations) == len(set(hub_vintage(fault.target, NEW)["location"])
                                                - {fault.skipped}))
        note = (why or note)
    passed = ok and lost == 0 and not left and fault.outcome != "error"
    return CaseResult(fault.name, passed, seconds, lost, note + left, source="nhsn", issue=39)


# ------------------------------------------------------------------------------ import cases


def _release_csv(folder: Path, as_of: str, change: Callable[[pd.DataFrame], pd.DataFrame]
                 = lambda f: f) -> Path:
    table = pd.read_parquet(NHSN / "time-series.parquet")
    rows = table[(table["target"] == HOSP_COVID) & (table["as_of"].astype(str) == as_of)]
    frame = change(rows[["target_end_date", "location", "observation"]].rename(
        columns={"target_end_date": "date", "observation": "value"}).reset_index(drop=True))
    path = folder / f"release-{as_of}-{abs(hash(change)) % 10_000}.csv"
    frame.to_csv(path, index=False)
    return path


def _imported(folder: Path) -> Path:
    from pipeline.data.hub.target_import import import_target_csv
    data = folder / "data"
    folder.mkdir(parents=True, exist_ok=True)
    import_target_csv(_release_csv(folder, OLD), target=HOSP_COVID, as_of=OLD, data_dir=data)
    return data


def _case(name: str, check: Callable[[Path], tuple[bool, str]]) -> Callable[[Path], CaseResult]:
    def run(folder: Path) -> CaseResult:
        started = time.monotonic()
        folder.mkdir(parents=True, exist_ok=True)
        try:
            passed, note = check(folder)
        except Exception as exc:  # noqa: BLE001 - a crash is a failed case, reported
            passed, note = False, f"raised {type(exc).__name__}: {exc}"
        return CaseResult(name, passed, time.monotonic() - started, 0, note, source="import",
                          issue=39)
    run.__name__ = name
    return run


def _newest_zero(frame: pd.DataFrame) -> pd.DataFrame:
    return frame.assign(value=frame["value"].where(frame["date"] != frame["date"].max(), 0))


def _future(folder: Path) -> tuple[bool, str]:
    from pipeline.data.hub.target_import import import_target_csv
    data = _imported(folder)
    before = cache_bytes(data)
    done = import_target_csv(_release_csv(folder, NEW), target=HOSP_COVID, as_of="2031-01-01",
                             data_dir=data).vintages[0]
    return (done.action == "refused" and "after today" in done.note
            and bytes_lost(before, cache_bytes(data)) == 0), done.note


def _stale_import(folder: Path) -> tuple[bool, str]:
    from pipeline.data.hub.target_import import import_target_csv
    data = _imported(folder)
    done = import_target_csv(_release_csv(folder, "2024-11-20"), target=HOSP_COVID,
                             as_of=NEW, data_dir=data).vintages[0]
    return done.action == "held" and "stale release" in done.note, done.note


def _zero_import(folder: Path) -> tuple[bool, str]:
    from pipeline.data.hub.target_import import import_target_csv
    data = _imported(folder)
    done = import_target_csv(_release_csv(folder, NEW, _newest_zero), target=HOSP_COVID,
                             as_of=NEW, data_dir=data).vintages[0]
    return done.action == "held" and "reads 0" in done.note, done.note


def _raises(call: Callable[[], object], expect: str) -> tuple[bool, str]:
    try:
        call()
    except FlowcastError as exc:
        return expect in str(exc), f"error: {exc}"
    return False, "no error"


def _unreadable_as_of(folder: Path) -> tuple[bool, str]:
    from pipeline.data.hub.target_import import import_hub_time_series
    table = pd.read_parquet(NHSN / "time-series.parquet").head(200).astype({"as_of": str})
    table.loc[5, "as_of"] = "notadate"
    table.to_parquet(folder / "bad.parquet")
    return _raises(lambda: import_hub_time_series(folder / "bad.parquet", folder / "data"),
                   "unreadable release date in as_of, e.g. 'notadate'")


def _empty(folder: Path) -> tuple[bool, str]:
    from pipeline.data.hub.target_import import import_hub_time_series
    pd.read_parquet(NHSN / "time-series.parquet").head(0).to_parquet(folder / "empty.parquet")
    ok, note = _raises(lambda: import_hub_time_series(folder / "empty.parquet", folder / "data"),
                       "an empty time series (no rows); nothing imported")
    return ok and not (folder / "data").exists(), note


def _unknown_targets(folder: Path) -> tuple[bool, str]:
    from pipeline.data.hub.target_import import import_hub_time_series
    table = pd.read_parquet(NHSN / "time-series.parquet").head(50)
    table.assign(target="wk inc measles hosp").to_parquet(folder / "measles.parquet")
    return _raises(lambda: import_hub_time_series(folder / "measles.parquet", folder / "data"),
                   "no row of a target flowcast knows")


def _cli(args: list[str], expect: str, folder: Path) -> tuple[bool, str]:
    import os
    import subprocess
    import sys
    env = {**os.environ, "FLOWCAST_DATA_DIR": str(folder / "data")}
    done = subprocess.run([sys.executable, "-c", "from flows.cli import main; main()", *args],
                          capture_output=True, text=True, env=env, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    lines = done.stderr.strip().splitlines()
    return (done.returncode == 1 and len(lines) == 1 and expect in lines[0]
            and "Traceback" not in done.stderr), (lines[-1] if lines else done.stdout[-200:])


@functools.cache
def _flusight(folder: Path) -> tuple[object, ...]:
    from pipeline.data.hub.nhsn_vintages import cached_weekly_vintages, revisions_waiting
    from pipeline.data.hub.target_import import import_hub_time_series
    summary = import_hub_time_series(FLUSIGHT, folder / "data")
    return (summary, revisions_waiting("wk inc flu hosp", folder / "data"),
            cached_weekly_vintages("wk inc flu hosp", folder / "data"))


# FluSight's four revisions beyond the policy: (held since, settled by) the release repeating it
FLUSIGHT_HOLDS = {"22": ("2024-11-20", "2024-12-04"), "39": ("2024-11-20", "2024-12-04"),
                  "04": ("2025-02-05", "2025-02-12"), "72": ("2025-03-19", "2025-03-26")}


def _flusight_holds(folder: Path) -> tuple[bool, str]:
    """Each revision holds its location alone, and the next release that repeats it settles
    the hold (issue 49): nothing is left waiting for an operator."""
    from pipeline.data.core.cache import DatasetCache
    from pipeline.data.hub.held_locations import read_holds
    from pipeline.data.hub.nhsn_vintages import target_spec

    summary, waiting, _ = _flusight(folder)
    actions = [v.action for v in summary.vintages]  # type: ignore[attr-defined]
    holds = read_holds(DatasetCache.default(folder / "data").directory(
        target_spec("wk inc flu hosp"))).entries
    spans = {h.location: (h.since, h.until) for h in holds}
    repeated = all("repeats the revision" in (h.settled or "") for h in holds)
    return (actions == ["live"] * 59 and spans == FLUSIGHT_HOLDS and repeated and not waiting,
            f"{actions.count('live')} of 59 releases live; held alone, then settled by the "
            f"release repeating it: {spans}; waiting: {sorted(waiting)}")  # type: ignore[arg-type]


def _flusight_na(folder: Path) -> tuple[bool, str]:
    *_, vintages = _flusight(folder)
    kept = [{"25", "27", "54"} <= set(v.locations) for v in vintages]  # type: ignore[attr-defined]
    return all(kept), f"Massachusetts, Minnesota, West Virginia in {sum(kept)} of {len(kept)}"


def _accept_one(folder: Path) -> tuple[bool, str]:
    from pipeline.data.hub.nhsn_vintages import (accept_location_revisions,
                                                 cached_weekly_vintages, revisions_waiting)
    from pipeline.data.hub.target_import import import_target_csv

    def tenfold(frame: pd.DataFrame) -> pd.DataFrame:
        ca = (frame["location"] == "06") & (frame["date"].astype(str) == "2025-06-07")
        return frame.assign(value=frame["value"].where(~ca, frame["value"] * 10))

    data = _imported(folder)
    import_target_csv(_release_csv(folder, NEW, tenfold), target=HOSP_COVID, as_of=NEW,
                      data_dir=data)
    waiting = list(revisions_waiting(HOSP_COVID, data))
    accept_location_revisions(HOSP_COVID, ["CA"], data)
    newest = cached_weekly_vintages(HOSP_COVID, data)[-1]
    return (waiting == ["06"] and "06" in newest.locations
            and not revisions_waiting(HOSP_COVID, data)), f"held {waiting}, accepted CA alone"


def import_cases() -> list[Callable[[Path], CaseResult]]:
    return [
        _case("import-future-dated-release", _future),
        _case("import-stale-release", _stale_import),
        _case("import-nationwide-zero", _zero_import),
        _case("import-unreadable-as-of-in-parquet", _unreadable_as_of),
        _case("import-empty-time-series", _empty),
        _case("import-only-unknown-targets", _unknown_targets),
        _case("cli-as-of-notadate", lambda f: _cli(
            ["data", "import", str(_release_csv(f, NEW)), "--target", HOSP_COVID, "--as-of",
             "notadate"], "error: --as-of: release date 'notadate' is not a date", f)),
        _case("cli-import-empty-time-series", lambda f: _cli(
            ["data", "import", str(_empty_parquet(f))], "nothing imported", f)),
        _case("flusight-revisions-held-per-location", _flusight_holds),
        _case("flusight-na-weeks-keep-their-states", _flusight_na),
        _case("accept-one-locations-revision", _accept_one),
    ]


def _empty_parquet(folder: Path) -> Path:
    path = folder / "empty.parquet"
    pd.read_parquet(NHSN / "time-series.parquet").head(0).to_parquet(path)
    return path


def run_all(scratch: Path) -> list[CaseResult]:
    """Every newer-release case and every import case, each on a fresh folder."""
    flu = scratch / "flusight"
    flu.mkdir(parents=True, exist_ok=True)
    return run_cases(scratch, [functools.partial(run_newer, f) for f in newer_faults()]
                     + [c for c in import_cases()[:8]]) + run_cases(
        scratch / "flu", [lambda _, c=c: c(flu) for c in import_cases()[8:10]]) + run_cases(
        scratch / "accept", import_cases()[10:])
