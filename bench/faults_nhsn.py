"""Fault injection against the NHSN source (data.cdc.gov's Socrata API): a good cache is never lost.

A fake data.cdc.gov on 127.0.0.1 (the threaded server of :mod:`bench.faults`, never any other
address) serves NHSN's Hospital Respiratory Data (``/resource/ua7e-t2fy.json``) and NSSP's ED
visits (``/resource/rdmq-nq56.json``) as Socrata pages (``$limit``/``$offset``, the ``$order``
checked), built from the hub's real vintage of 2025-09-24 (``../shared/data/nhsn/
time-series.parquet``, read in place): jurisdictions as NHSN writes them (``USA``, postal
abbreviations, plus territories and HHS regions, which flowcast drops), counts as strings; NSSP
rows per state name with ``county`` = "All", percentages, plus sub-state rows. Then each fault
in turn, through the real ``requests`` stack: the transport's (HTTP 4xx/5xx, Retry-After,
truncated and damaged bodies, drips, a gzip bomb, redirects, refused connections, a server
ignoring ``$offset``), the payload's (missing fields, shrinking, revisions), and issue 32's
poisoned cells, ramps and made-up places. :func:`pipeline.data.hub.nhsn.load_nhsn` must fall back to
the cached vintage with a note naming the problem and leave every cache file byte-identical (or,
for a ``skipped`` case, take the new payload with that place skipped and named), with no request
thread or socket left. Also the concurrent import of an older and a newer vintage (issue 32,
item 7).

Run as part of ``python -m bench.faults`` (-> ``bench/results/faults.json``); also the harness of
``tests/test_nhsn_source.py``.
"""
from __future__ import annotations

import dataclasses
import functools
import json
from datetime import datetime, timezone
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import parse_qs, urlsplit

import pandas as pd

from bench.faults import (CaseResult, FakeDataSF, Responder, bad_gzip, bytes_lost, cache_bytes,
                          closed_port_url, dropped_mid_body, gzip_bomb, gzipped, header_drip,
                          html_body, ignores_offset, leftovers, load_timed, race,
                          race_case, raw_body, redirect, run_cases, status, trickle,
                          truncated_json)
from pipeline.data.hub.nhsn import ED_COVID, HOSP_COVID, NHSNClientConfig, NHSNConfig, load_nhsn
from pipeline.data.hub.nhsn_vintages import TARGETS

if TYPE_CHECKING:
    from bench.faults import _Handler

NHSN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nhsn"
GOOD_AS_OF = "2025-09-24"
# The fake portal serves the hub's release of 2025-09-24, so every fetch happens that day: a
# fetch dated today would read a release whose newest week is over a year old, a stale release
# (issue 39), and hold it.
RELEASE_NOW = datetime(2025, 9, 24, 18, 0, tzinfo=timezone.utc)
HRD_PATH, NSSP_PATH = "/resource/ua7e-t2fy.json", "/resource/rdmq-nq56.json"
Rows = list[dict[str, str]]


# ------------------------------------------------------------------------------ payloads


@functools.cache
def hub_vintage(target: str, as_of: str = GOOD_AS_OF) -> pd.DataFrame:
    table = pd.read_parquet(NHSN / "time-series.parquet")
    rows = table[(table["target"] == target) & (table["as_of"].astype(str) == as_of)]
    return rows.sort_values(["target_end_date", "location"], ignore_index=True)


def _iso(day: object) -> str:
    return f"{pd.Timestamp(str(day)).date()}T00:00:00.000"


@functools.cache
def _hrd_rows(as_of: str) -> tuple[tuple[tuple[str, str], ...], ...]:
    from pipeline.data.hub.locations import BY_LOCATION
    v = hub_vintage(HOSP_COVID, as_of)
    rows = [{"weekendingdate": _iso(d), "jurisdiction": BY_LOCATION[loc].jurisdiction,
             "totalconfc19newadm": f"{obs:.0f}"}
            for d, loc, obs in zip(v["target_end_date"], v["location"], v["observation"],
                                   strict=True)]
    for week in v["target_end_date"].unique():   # NHSN's other jurisdictions, dropped
        rows += [{"weekendingdate": _iso(week), "jurisdiction": j, "totalconfc19newadm": "7"}
                 for j in ("GU", "VI", "Region 1")]
    rows.sort(key=lambda r: (r["weekendingdate"], r["jurisdiction"]))
    return tuple(tuple(r.items()) for r in rows)


def hrd_rows(as_of: str = GOOD_AS_OF) -> Rows:
    """The hub's admissions vintage as NHSN's HRD rows (sorted as ``$order`` asks)."""
    return [dict(r) for r in _hrd_rows(as_of)]


@functools.cache
def _nssp_rows(as_of: str) -> tuple[tuple[tuple[str, str], ...], ...]:
    from pipeline.data.hub.locations import BY_LOCATION
    v = hub_vintage(ED_COVID, as_of)
    name = {loc: ("United States" if loc == "US" else BY_LOCATION[loc].name)
            for loc in v["location"].unique()}
    rows = [{"week_end": _iso(d), "geography": name[loc], "county": "All",
             "percent_visits_covid": f"{obs * 100:.2f}"}
            for d, loc, obs in zip(v["target_end_date"], v["location"], v["observation"],
                                   strict=True)]
    for week in v["target_end_date"].unique()[-4:]:   # sub-state rows, not the hub's
        rows.append({"week_end": _iso(week), "geography": "California", "county": "Alameda",
                     "percent_visits_covid": "1.5"})
    rows.sort(key=lambda r: (r["week_end"], r["geography"]))
    return tuple(tuple(r.items()) for r in rows)


def nssp_rows(as_of: str = GOOD_AS_OF) -> Rows:
    return [dict(r) for r in _nssp_rows(as_of)]


def send_pages(rows: Rows, order: str) -> Responder:
    """Socrata pages of ``rows``; a request without the expected ``$order`` gets HTTP 400."""
    def respond(h: _Handler) -> None:
        query = {k: v[0] for k, v in parse_qs(urlsplit(h.path).query).items()}
        if query.get("$order") != order:
            h.send_body(400, json.dumps({"message": f"bad order {query.get('$order')}"}).encode())
            return
        offset, limit = int(query.get("$offset", "0")), int(query.get("$limit", "1000"))
        h.send_body(200, json.dumps(rows[offset:offset + limit]).encode())
    return respond


HRD_ORDER = "weekendingdate ASC, jurisdiction ASC"
NSSP_ORDER = "week_end ASC, geography ASC"


class FakeCDC:
    """A fake data.cdc.gov on 127.0.0.1: HRD and NSSP, each replaceable."""

    def __init__(self) -> None:
        self.http = FakeDataSF()
        self.hrd: Responder = send_pages(hrd_rows(), HRD_ORDER)
        self.nssp: Responder = send_pages(nssp_rows(), NSSP_ORDER)
        self.http.respond(lambda h: (self.nssp if h.path.startswith(NSSP_PATH) else self.hrd)(h))

    @property
    def url(self) -> str:
        return self.http.url

    def __enter__(self) -> FakeCDC:
        self.http.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.http.__exit__(*exc)


# ------------------------------------------------------------------------------ the faults


def edited(rows: Rows, change: Callable[[Rows], Rows]) -> Rows:
    return change([dict(r) for r in rows])


def with_cell(column: str, value: str, where: Callable[[dict[str, str]], bool]
              ) -> Callable[[Rows], Rows]:
    def change(rows: Rows) -> Rows:
        for r in rows:
            if where(r):
                r[column] = value
        return rows
    return change


def at(jurisdiction: str, week: str, key: str = "jurisdiction",
       date_key: str = "weekendingdate") -> Callable[[dict[str, str]], bool]:
    return lambda r: r[key] == jurisdiction and r[date_key].startswith(week)


def last_weeks(n: int, rows: Rows, date_key: str = "weekendingdate") -> list[str]:
    return sorted({r[date_key][:10] for r in rows})[-n:]


def ramp(rows: Rows) -> Rows:
    """California's last three weeks at 6,000, 60,000 and 190,000 admissions (each under 0.5 %
    of the state, ten times the week before)."""
    for week, value in zip(last_weeks(3, rows), ("6000", "60000", "190000"), strict=True):
        with_cell("totalconfc19newadm", value, at("CA", week))(rows)
    return rows


def revised_settled(rows: Rows) -> Rows:
    """California's week ending 2025-06-07 (15 weeks settled) times ten."""
    for r in rows:
        if at("CA", "2025-06-07")(r):
            r["totalconfc19newadm"] = str(int(r["totalconfc19newadm"]) * 10)
    return rows


def made_up(rows: Rows, key: str = "jurisdiction", name: str = "ZZ",
            date_key: str = "weekendingdate", column: str = "totalconfc19newadm") -> Rows:
    """A made-up place beside the real ones (a copy of Ohio's or Maryland's rows)."""
    copies = [{**r, key: name} for r in rows if r[key] in ("OH", "Maryland")]
    return sorted(rows + copies, key=lambda r: (r[date_key], r[key]))


def many_poisoned(rows: Rows) -> Rows:
    """Fourteen states (more than a quarter of the 53) with a negative count in one week."""
    from pipeline.data.hub.locations import HUB_LOCATIONS
    week = last_weeks(5, rows)[0]
    states = [h.jurisdiction for h in HUB_LOCATIONS[1:15]]
    for r in rows:
        if r["jurisdiction"] in states and r["weekendingdate"].startswith(week):
            r["totalconfc19newadm"] = "-1"
    return rows


Build = Callable[[Rows], Rows]


@dataclass(frozen=True)
class Fault:
    """One failure served after a good fetch of ``target``: ``respond`` builds the server's
    answer from the good rows and another host (None: ``rows`` edits the good rows);
    ``expect``: text the note must hold; ``skipped``: the place the new payload must skip
    (the outcome is then the new payload, not the cache); ``held_place``: the place the new
    payload must hold, forecast from its accepted series (in the vintage, named in its
    ``held``; issue 49); ``held``: the payload lands in held/."""

    name: str
    expect: str
    respond: Callable[[Rows, FakeCDC], Responder] | None = None
    rows: Build | None = None
    target: str = HOSP_COVID
    config: dict[str, float] = field(default_factory=dict)
    base_url: Callable[[], str] | None = None
    skipped: str | None = None
    held_place: str | None = None
    held: bool = False
    hold_lock: bool = False
    max_seconds: float | None = None
    issue: int = 29


def _cell(column: str, value: str, jurisdiction: str = "CA", week: str = "2025-08-02"
          ) -> Build:
    return with_cell(column, value, at(jurisdiction, week))


ADM = "totalconfc19newadm"


def faults() -> list[Fault]:
    cut = lambda rows: rows[:-2 * 56]  # noqa: E731 - the last two weeks gone
    return [
        # -- the transport and the pager (issues 15 and 22, now on NHSN)
        Fault("http-500", "HTTP 500", lambda r, o: status(500)),
        Fault("http-429-retry-after", "HTTP 429: '{\"error\": true}' (Retry-After 1 s)",
              lambda r, o: status(429, {"Retry-After": "1"}), config={"max_retries": 1}),
        Fault("retry-after-too-long", "NHSN asks to retry after 3600 s",
              lambda r, o: status(503, {"Retry-After": "3600"})),
        Fault("http-404-not-retried", "HTTP 404 from", lambda r, o: status(404)),
        Fault("truncated-json", "truncated or damaged", lambda r, o: truncated_json(r)),
        Fault("html-body", "invalid JSON", lambda r, o: html_body),
        Fault("dropped-mid-body", "ChunkedEncodingError", lambda r, o: dropped_mid_body(r)),
        Fault("bad-gzip", "ContentDecodingError", lambda r, o: bad_gzip),
        Fault("gzip-bomb-404-mib", "body larger than 1,048,576 bytes (after decoding); refused",
              lambda r, o: gzipped(gzip_bomb()), issue=32),
        Fault("body-drip-past-deadline", "within the request deadline",
              lambda r, o: trickle(r), config={"request_deadline_s": 1.0,
                                               "fetch_deadline_s": 2.5}),
        Fault("header-drip-no-thread-or-socket-left", "within the request deadline",
              lambda r, o: header_drip, config={"request_deadline_s": 1.0,
                                                "fetch_deadline_s": 2.5}, issue=32),
        Fault("redirect-to-other-host", "refused, only redirects to the same https host",
              lambda r, o: redirect(o.url + HRD_PATH)),
        Fault("connection-refused", "Connection refused", base_url=closed_port_url,
              max_seconds=1.5),
        Fault("unknown-host", "Failed to resolve 'flowcast-fault.invalid'",
              base_url=lambda: "http://flowcast-fault.invalid", max_seconds=3.0),
        Fault("json-nested-200000-deep", "nested too deeply to decode (RecursionError",
              lambda r, o: raw_body(b"[" * 200_000)),
        Fault("json-5000-digit-integer", "Exceeds the limit (4300 digits)",
              lambda r, o: raw_body(b'[{"totalconfc19newadm": ' + b"9" * 5000 + b"}]")),
        Fault("body-over-size-limit", "body larger than 20,000 bytes (after decoding)",
              lambda r, o: send_pages(r, HRD_ORDER), config={"max_body_bytes": 20_000}),
        Fault("server-ignores-offset", "the page at $offset=100 repeats the page at $offset=0",
              lambda r, o: ignores_offset(r), config={"page_size": 100}),
        Fault("cache-lock-held-by-stuck-run", "fetched but not stored, cache kept",
              hold_lock=True, max_seconds=3.0, issue=32),
        # -- the payload against the cached vintage
        Fault("missing-field", "missing field(s) ['totalconfc19newadm']",
              rows=lambda r: [{k: v for k, v in x.items() if k != ADM} for x in r]),
        Fault("empty-list", "empty payload (no rows)", rows=lambda r: []),
        Fault("last-weeks-missing", "last week moves backwards", rows=cut),
        Fault("first-weeks-missing", "payload shrinks: new vintage starts 2024-11-16",
              rows=lambda r: [x for x in r if not x["weekendingdate"].startswith("2024-11-09")]),
        Fault("location-dropped", "location dropped: 06",
              rows=lambda r: [x for x in r if x["jurisdiction"] != "CA"]),
        Fault("revised-settled-week",
              "revision held for review since the release of 2025-09-24 (its series of "
              "2025-09-24 kept): wk inc covid hosp: revision beyond policy: 'value' changed on "
              "1 settled week(s)", rows=revised_settled, held_place="06"),
        Fault("duplicate-week", "06: two rows for 2025-08-02",
              rows=lambda r: sorted(r + [x for x in r if at("CA", "2025-08-02")(x)],
                                    key=lambda x: (x["weekendingdate"], x["jurisdiction"]))),
        # -- issue 32's poisoned cells, one location each: the vintage of the same date is
        # refused (that location passes in the cached one), the cache kept
        Fault("infinity-admissions", "06: 'totalconfc19newadm' is not finite ('Infinity') on "
              "2025-08-02", rows=_cell(ADM, "Infinity"), issue=32),
        Fault("1e19-admissions", "06: implausible count 1e+19 in 'totalconfc19newadm' in the "
              "week ending 2025-08-02: more than 0.5% of the population 39,512,223",
              rows=_cell(ADM, "1e19"), issue=32),
        Fault("1e300-admissions", "06: implausible count 1e+300", rows=_cell(ADM, "1e300"),
              issue=32),
        Fault("negative-admissions", "06: 'totalconfc19newadm' is negative ('-3')",
              rows=_cell(ADM, "-3"), issue=32),
        Fault("fractional-admissions", "06: 'totalconfc19newadm' is not a whole number of "
              "people ('12.5')", rows=_cell(ADM, "12.5"), issue=32),
        Fault("non-numeric-admissions", "06: 'totalconfc19newadm' is not a number ('12a')",
              rows=_cell(ADM, "12a"), issue=32),
        Fault("ramp-within-the-population-bound", "06: implausible count 60,000 in "
              "'totalconfc19newadm' on 2025-09-13: more than 10× the plausible bracket",
              rows=ramp, issue=32),
        Fault("week-not-on-saturday", "06: week ending 2025-08-01 is a Friday, not a Saturday",
              rows=_cell("weekendingdate", "2025-08-01T00:00:00.000"), issue=32),
        Fault("week-after-the-release", "06: 2031-01-04 is after the vintage's date",
              rows=_cell("weekendingdate", "2031-01-04T00:00:00.000"), issue=32),
        Fault("a-quarter-of-locations-poisoned", "14 of the 53 hub locations fail the "
              "validation gate", rows=many_poisoned, issue=32),
        Fault("made-up-jurisdiction", "'ZZ' is not one of the 53 known hub location names",
              rows=made_up, skipped="ZZ", issue=32),
        # -- the ED-visit share (NSSP)
        Fault("ed-share-above-bound", "06: 'percent_visits_covid' is 80 on 2025-08-02, outside "
              "0 … 50", target=ED_COVID,
              rows=with_cell("percent_visits_covid", "80", at("California", "2025-08-02",
                                                                "geography", "week_end")),
              issue=32),
        Fault("ed-share-infinity", "06: 'percent_visits_covid' is not finite ('Infinity')",
              target=ED_COVID, rows=with_cell("percent_visits_covid", "Infinity",
                                              at("California", "2025-08-02", "geography",
                                                 "week_end")), issue=32),
        Fault("ed-missing-field", "missing field(s) ['percent_visits_covid']", target=ED_COVID,
              rows=lambda r: [{k: v for k, v in x.items() if k != "percent_visits_covid"}
                              for x in r]),
        Fault("ed-made-up-geography", "'Atlantis' is not one of the 53 known hub location "
              "names", target=ED_COVID, skipped="Atlantis", issue=32,
              rows=lambda r: made_up(r, "geography", "Atlantis", "week_end",
                                     "percent_visits_covid")),
    ]


# ------------------------------------------------------------------------------ running cases


def client_config(base_url: str, **overrides: float) -> NHSNClientConfig:
    """Short timeouts, no backoff: every case ends in seconds."""
    return dataclasses.replace(
        NHSNClientConfig(base_url=base_url, timeout_s=2.0, request_deadline_s=5.0,
                         fetch_deadline_s=10.0, max_retries=2, backoff_base_s=0.0),
        **overrides)


def nhsn_config(base_url: str, data_dir: Path, target: str = HOSP_COVID,
                **client: float) -> NHSNConfig:
    return NHSNConfig(targets=(target,), client=client_config(base_url, **client),
                      data_dir=data_dir, lock_timeout_s=0.5)


def held_files(data_dir: Path, target: str) -> list[Path]:
    held = data_dir / "nhsn" / TARGETS[target].dataset_id / "held"
    return sorted(p for p in held.glob("payload-*") if not p.name.endswith(".reason.json")) \
        if held.is_dir() else []


def _responder(fault: Fault, cdc: FakeCDC, other: FakeCDC) -> Responder:
    good, order = ((hrd_rows(), HRD_ORDER) if fault.target == HOSP_COVID
                   else (nssp_rows(), NSSP_ORDER))
    if fault.respond is not None:
        return fault.respond(good, other)
    assert fault.rows is not None
    return send_pages(edited(good, fault.rows), order)


def run_fault(fault: Fault, data_dir: Path) -> CaseResult:
    """Good fetch, then the fault; the loader must fall back to the untouched cache (or take the
    new payload with ``skipped`` named, every file of the good cache still unchanged)."""
    spec = TARGETS[fault.target]
    with FakeCDC() as cdc, FakeCDC() as other:
        load_nhsn(nhsn_config(cdc.url, data_dir, fault.target), now=RELEASE_NOW)
        before = cache_bytes(data_dir)
        answer = _responder(fault, cdc, other) if fault.respond or fault.rows else None
        if answer is not None:
            if fault.target == HOSP_COVID:
                cdc.hrd = answer
            else:
                cdc.nssp = answer
        base = fault.base_url() if fault.base_url is not None else cdc.url
        config = nhsn_config(base, data_dir, fault.target, **fault.config)
        loaded, seconds = load_timed(
            lambda: load_nhsn(config, now=RELEASE_NOW), name=fault.name, source="nhsn", issue=fault.issue,
            data_dir=data_dir, before=before,
            lock=(spec.dataset_id, spec.cache_folder) if fault.hold_lock else None)
        provenance, vintage = loaded.provenance[fault.target], loaded[fault.target]
        left = leftovers(cdc.http.port)
        note = " | ".join(provenance.notes) + left
        after = cache_bytes(data_dir)
        if fault.skipped is None and fault.held_place is None:
            lost = bytes_lost(before, after)
            outcome = provenance.from_cache
        else:
            lost = bytes_lost({k: v for k, v in before.items()
                               if not k.endswith("manifest.json")}, after)
            real = set(hub_vintage(fault.target)["location"])
            outcome = not provenance.from_cache and (
                len(vintage.locations) == len(real - {fault.skipped})
                and fault.expect in vintage.skipped.get(fault.skipped, "")
                if fault.skipped is not None else
                set(vintage.locations) == real
                and fault.expect in vintage.held.get(str(fault.held_place), ""))
        passed = (outcome and fault.expect in note and lost == 0 and not left
                  and bool(held_files(data_dir, fault.target)) == fault.held
                  and not other.http.seen
                  and (fault.max_seconds is None or seconds <= fault.max_seconds))
        return CaseResult(fault.name, passed, seconds, lost, note, source="nhsn",
                          issue=fault.issue)


# ------------------------------------------------------------------------------ concurrent imports


def _import_one(path: Path, as_of: str, data_dir: Path) -> str:
    from pipeline.data.hub.nhsn import import_target_csv
    summary = import_target_csv(path, target=HOSP_COVID, as_of=as_of, data_dir=data_dir)
    return summary.vintages[0].action


def write_target_csv(folder: Path, as_of: str) -> Path:
    v = hub_vintage(HOSP_COVID, as_of)
    path = folder / f"covid-hosp-{as_of}.csv"
    v.rename(columns={"target_end_date": "date", "observation": "value"})[
        ["date", "location", "value"]].to_csv(path, index=False)
    return path


def run_concurrent_imports(data_dir: Path, trials: int = 3) -> CaseResult:
    """Two processes import an older and a newer vintage at the same moment, ``trials`` times
    on fresh caches: both must end where they belong (the newer live, both archived by their
    own dates), never "moves backwards" (issue 32, item 7)."""
    from pipeline.data.hub.nhsn import cached_weekly_vintages
    from pipeline.data.hub.nhsn_vintages import live_manifest

    older, newer = "2025-09-17", GOOD_AS_OF

    def trial(k: int) -> str | None:
        cache = data_dir / f"trial-{k}"
        cache.mkdir(parents=True)
        files = {d: write_target_csv(cache, d) for d in (older, newer)}
        actions = race([functools.partial(_import_one, files[d], d, cache / "data")
                        for d in (newer, older)])
        kept = [str(v.as_of.date()) for v in cached_weekly_vintages(HOSP_COVID, cache / "data")]
        manifest = live_manifest(HOSP_COVID, cache / "data")
        live = manifest.data_as_of if manifest is not None else None
        if kept == [older, newer] and live == newer and actions in (["archived", "live"],
                                                                    ["live", "live"]):
            return None
        return f"trial {k}: actions {actions}, vintages {kept}, live {live}"

    return race_case("nhsn", trial, trials, f"the vintage of {newer} live, {older} and {newer} "
                                            f"both kept by their own dates")


def run_all(scratch: Path) -> list[CaseResult]:
    """Every NHSN case, each on a fresh cache under ``scratch``."""
    return run_cases(scratch, [functools.partial(_in_data, f) for f in faults()]
                     + [run_concurrent_imports])


def _in_data(fault: Fault, folder: Path) -> CaseResult:
    return run_fault(fault, folder / "data")
