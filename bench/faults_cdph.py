"""Benchmark: fault injection against the CDPH source (CKAN portal); a good cache is never lost.

A fake CHHS portal on 127.0.0.1 (the threaded server of :mod:`bench.faults`, never any other
address) answers CKAN's ``/api/3/action/package_show`` with a JSON built here and serves the real
``covid19cases_test.csv`` bytes of the 2021-11-04 vintage (``../shared/data/cdph``, read in place)
at the resource's download URL. Then each fault in turn: HTTP 500 and 429 (with Retry-After), a
Retry-After longer than the client waits, a truncated body (short of its Content-Length, and cut
without one), HTML instead of the CSV or the JSON, a resource missing from the package, a gzip
bomb, a bad gzip body, a missing column, a dropped county, a shrunk date range (a real older
vintage; a later first day), an implausible count, a revision of one county's settled days (that
county held alone, the others live; sixteen counties at once: the file held for review), a
refused connection, a server dripping bytes past the deadline, a redirect to another host and a
download URL on another host. Everything goes through the real ``requests`` stack.

For each case the cache is first filled by a good fetch; then the fault is served and
:func:`pipeline.data.california.cdph_source.load_cdph` must (a) return the cached vintage, (b) say why in a
note naming the problem, (c) leave every cache file byte-identical (``held/`` may gain the refused
payload) and (d) never contact the other host. "bytes of good cache lost" sums the sizes of
cache files that changed or vanished (must be 0).

Run as part of ``python -m bench.faults`` (-> ``bench/results/faults.json``, every source); also
the harness of ``tests/test_cdph.py``.
"""
from __future__ import annotations

import dataclasses
import functools
import gzip
import io
import json
import os
import platform
import socket
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from bench.faults import (CaseResult, FakeDataSF, gzip_bomb, load_timed, race, race_case,
                          run_cases, Responder, bytes_lost, cache_bytes, leftovers,
                          header_drip, redirect, status, trickle)
from pipeline.data.california.cdph_source import SPEC, CDPHConfig
from pipeline.data.california.chhs import CHHSClientConfig
from pipeline.io import atomic_write_json

if TYPE_CHECKING:
    from bench.faults import _Handler

CDPH = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "cdph"
GOOD_VINTAGE = "ofaye98__CSC508_Mentor_Class"              # 2021-11-04
OLDER_VINTAGE = "hhaeri__CA_State_COVID-19_Cases_Deaths_Tests"  # 2021-09-23
CSV_NAME = "covid19cases_test.csv"
DOWNLOAD_PATH = (f"/dataset/{SPEC.package_uuid}/resource/{SPEC.resource_id}/download/"
                 f"{SPEC.resource_name}")
BODY_LIMIT = 32 << 20          # the client's default cap (the real file is 4 MB)


# ------------------------------------------------------------------------------ payloads


@functools.cache
def vintage_bytes(folder: str = GOOD_VINTAGE) -> bytes:
    return (CDPH / folder / CSV_NAME).read_bytes()


@functools.cache
def _good_frame() -> pd.DataFrame:
    return pd.read_csv(io.BytesIO(vintage_bytes()), dtype=str, keep_default_na=False)


def edited(change: Callable[[pd.DataFrame], pd.DataFrame]) -> bytes:
    """The good vintage with ``change`` applied to its rows (all cells strings)."""
    return change(_good_frame().copy()).to_csv(index=False).encode()


def without_county(frame: pd.DataFrame, county: str = "Alpine") -> pd.DataFrame:
    return frame[frame["area"] != county]


def starting_later(frame: pd.DataFrame) -> pd.DataFrame:
    return frame[(frame["date"] == "") | (frame["date"] >= "2020-03-01")]


def with_cell(frame: pd.DataFrame, area: str, day: str, column: str, value: str
              ) -> pd.DataFrame:
    frame.loc[(frame["area"] == area) & (frame["date"] == day), column] = value
    return frame


def revised_settled(frame: pd.DataFrame) -> pd.DataFrame:
    """Los Angeles' cases of 2021-01-04 … 2021-01-10 (ten months settled) times three: within
    the gate's bounds (1.7 % of the county a day at most), beyond the revision policy."""
    days = (frame["area"] == "Los Angeles") & frame["date"].between("2021-01-04", "2021-01-10")
    frame.loc[days, "cases"] = (frame.loc[days, "cases"].astype(float) * 3).map(str)
    return frame


def revised_counties(n: int) -> Callable[[pd.DataFrame], pd.DataFrame]:
    """The ``n`` most populous counties' cases of 2021-01-04 (settled) times three, as
    Los Angeles' in :func:`revised_settled` (within the gate's bounds): a broken payload when
    more than a quarter of the counties."""
    def change(frame: pd.DataFrame) -> pd.DataFrame:
        counties = frame[(frame["area_type"] == "County") & (frame["date"] == "2021-01-04")]
        people = pd.to_numeric(counties["population"], errors="coerce")
        biggest = counties.assign(people=people).nlargest(n, "people")["area"]
        days = frame["area"].isin(list(biggest)) & (frame["date"] == "2021-01-04")
        frame.loc[days, "cases"] = (frame.loc[days, "cases"].astype(float) * 3).map(str)
        return frame
    return change


def ramp(frame: pd.DataFrame, area: str = "San Francisco") -> pd.DataFrame:
    """Issue 32's ramp: the county's last three days at 2,800, 56,000 and 89,000 cases."""
    days = sorted(d for d in frame.loc[frame["area"] == area, "date"].unique() if d)[-3:]
    for day, value in zip(days, ("2800", "56000", "89000"), strict=True):
        frame = with_cell(frame, area, day, "cases", value)
    return frame


def x_county(frame: pd.DataFrame) -> pd.DataFrame:
    """Every county written "X County" (issue 39: no known place used to crash the gate with
    numpy's "inhomogeneous shape", with no cache fallback)."""
    county = frame["area_type"] == "County"
    return frame.assign(area=frame["area"].where(~county, frame["area"] + " County"))


def slow_ramp(frame: pd.DataFrame, area: str = "San Francisco") -> pd.DataFrame:
    """Issue 39's slow ramp: the county's last seven days at 2,000 and then 12,000 cases a day
    (under both population bounds)."""
    days = sorted(d for d in frame.loc[frame["area"] == area, "date"].unique() if d)[-7:]
    for day, value in zip(days, ("2000",) + ("12000",) * 6, strict=True):
        frame = with_cell(frame, area, day, "cases", value)
    return frame


def with_county(frame: pd.DataFrame, name: str = "Atlantis",
                population: str = "1500000") -> pd.DataFrame:
    """A made-up county: a copy of Alameda's rows under another name and population."""
    made_up = frame[frame["area"] == "Alameda"].assign(area=name, population=population)
    return pd.concat([frame, made_up], ignore_index=True)


def package_show(download_url: str, *,
                 resources: Sequence[Mapping[str, object]] | None = None) -> bytes:
    """CKAN's ``package_show`` answer for the CDPH dataset (the fields flowcast reads, plus a
    second resource as on the real portal)."""
    ours = {"id": SPEC.resource_id, "name": "Statewide COVID-19 Cases Deaths Tests",
            "format": "CSV", "url": download_url, "last_modified": "2021-11-04T15:02:11.000000"}
    other = {"id": "0d9be83b-5027-41ff-97b2-6ca70238d778", "name": "Data Dictionary",
             "format": "XLSX", "url": download_url.rsplit("/", 1)[0] + "/dictionary.xlsx"}
    result = {"id": SPEC.package_uuid, "name": SPEC.dataset_id, "title": SPEC.title,
              "resources": list(resources) if resources is not None else [ours, other]}
    return json.dumps({"help": "package_show", "success": True, "result": result}).encode()


# ------------------------------------------------------------------------------ the portal


class FakeCKAN:
    """A fake CHHS portal on 127.0.0.1: package_show and the download, each replaceable."""

    def __init__(self) -> None:
        self.http = FakeDataSF()
        self.package: Responder = lambda h: h.send_body(200, package_show(self.url
                                                                           + DOWNLOAD_PATH))
        self.download: Responder = lambda h: h.send_body(200, vintage_bytes(), "text/csv")
        self.http.respond(self._route)

    def _route(self, h: _Handler) -> None:
        (self.package if h.path.startswith("/api/3/action/package_show") else self.download)(h)

    @property
    def url(self) -> str:
        return self.http.url

    @property
    def seen(self) -> list[str]:
        return [s.path for s in self.http.seen]

    def __enter__(self) -> FakeCKAN:
        self.http.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.http.__exit__(*exc)


# ------------------------------------------------------------------------------ the faults


def body(data: bytes, content_type: str = "text/csv",
         headers: dict[str, str] | None = None) -> Responder:
    return lambda h: h.send_body(200, data, content_type, headers)


def short_of_length(data: bytes) -> Responder:
    """Content-Length of the whole file, then half of it and the connection closed."""
    def respond(handler: _Handler) -> None:
        handler.send_response(200)
        handler.send_header("Content-Type", "text/csv")
        handler.send_header("Content-Length", str(len(data)))
        handler.send_header("Connection", "close")
        handler.end_headers()
        handler.wfile.write(data[:len(data) // 2])
        handler.close_connection = True
    return respond


def cut_without_length(data: bytes) -> Responder:
    """No Content-Length (the body ends when the connection closes), cut at 60 %."""
    def respond(handler: _Handler) -> None:
        handler.send_response(200)
        handler.send_header("Content-Type", "text/csv")
        handler.send_header("Connection", "close")
        handler.end_headers()
        handler.wfile.write(data[:int(len(data) * 0.6)])
        handler.close_connection = True
    return respond


def closed_port() -> str:
    """A loopback URL on which nothing listens (connection refused)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"http://127.0.0.1:{port}"


Build = Callable[["FakeCKAN", "FakeCKAN"], Responder]


@dataclass(frozen=True)
class Fault:
    """One failure served after a good fetch. ``package``/``download`` build the responders
    (None: the good one) from the portal and another host; ``expect``: text the note must hold;
    ``held``: the payload must land in held/; ``base_url``: overrides the portal's URL;
    ``skipped``: the outcome is not the cache but the new payload with that county skipped
    (named with ``expect``); ``hold_lock``: the cache lock is held by a stuck run meanwhile;
    ``max_seconds``: how long the fallback may take; ``issue``: the issue that found it."""

    name: str
    expect: str
    package: Build | None = None
    download: Build | None = None
    config: dict[str, float] = field(default_factory=dict)
    held: bool = False
    base_url: Callable[[], str] | None = None
    skipped: str | None = None
    held_alone: bool = False      # the skipped county is one of the 58, held alone
    hold_lock: bool = False
    max_seconds: float | None = None
    issue: int = 19


def _poisoned(area: str, day: str, column: str, value: str) -> Build:
    return lambda s, o: body(edited(lambda f: with_cell(f, area, day, column, value)))


def faults() -> list[Fault]:
    return [
        Fault("http-500", "HTTP 500", package=lambda s, o: status(500)),
        Fault("http-429-retry-after", "HTTP 429: '{\"error\": true}' (Retry-After 1 s)",
              download=lambda s, o: status(429, {"Retry-After": "1"}), config={"max_retries": 1}),
        Fault("retry-after-too-long", "asks to retry after 3600 s",
              download=lambda s, o: status(503, {"Retry-After": "3600"})),
        Fault("truncated-body", "IncompleteRead",
              download=lambda s, o: short_of_length(vintage_bytes())),
        Fault("truncated-without-length", "county dropped: San Diego, San Francisco",
              download=lambda s, o: cut_without_length(vintage_bytes())),
        Fault("html-instead-of-csv", "answered with an HTML page, not the CSV",
              download=lambda s, o: body(b"<!DOCTYPE html><html><body>Site maintenance"
                                         b"</body></html>", "text/html")),
        Fault("html-instead-of-package-json", "an HTML page instead of a CKAN package_show",
              package=lambda s, o: body(b"<html><body>502 Bad Gateway</body></html>",
                                        "text/html")),
        # issue 22's decode faults, on the CKAN answer: every decode failure is one named
        # rejection (pipeline.data.core.decoding), never a traceback
        Fault("deeply-nested-package-json", "nested too deeply to decode (RecursionError",
              package=lambda s, o: body(b"[" * 200_000, "application/json")),
        Fault("huge-integer-package-json", "ValueError: Exceeds the limit (4300 digits)",
              package=lambda s, o: body(b'{"success": true, "result": ' + b"9" * 5_000 + b"}",
                                        "application/json")),
        Fault("binary-garbage-csv", "not a CSV file",
              download=lambda s, o: body(b"\xff\xfe\x00\x01" * 4_096)),
        Fault("resource-missing", "has no resource covid19cases_test.csv",
              package=lambda s, o: body(package_show(s.url + DOWNLOAD_PATH, resources=[]),
                                        "application/json")),
        Fault("bad-gzip", "ContentDecodingError",
              download=lambda s, o: body(gzip.compress(b"x")[:10] + b"\x00not deflate" * 50,
                                         headers={"Content-Encoding": "gzip"})),
        Fault("missing-column", "missing column(s) ['reported_cases']",
              download=lambda s, o: body(edited(lambda f: f.drop(columns=["reported_cases"])))),
        Fault("county-dropped", "county dropped: Alpine",
              download=lambda s, o: body(edited(without_county))),
        Fault("shrunk-date-range-older-vintage",
              "last date moves backwards: new vintage ends 2021-09-23, the cached copy "
              "2021-11-04", download=lambda s, o: body(vintage_bytes(OLDER_VINTAGE))),
        Fault("shrunk-date-range-later-start",
              "date range shrinks: new vintage starts 2020-03-01",
              download=lambda s, o: body(edited(starting_later))),
        Fault("absurd-count",
              "San Francisco: implausible count 5,000,000 in 'cases' on 2021-06-01: more than "
              "5% of the population 873,965 (2020 Census) in one day",
              download=_poisoned("San Francisco", "2021-06-01", "cases", "5000000.0")),
        # a county revised beyond the policy is held alone, the others go live (issue 39)
        Fault("revised-settled-days",
              "revision beyond policy: 'cases' changed on 7 settled county-day(s)",
              download=lambda s, o: body(edited(revised_settled)), skipped="Los Angeles",
              held_alone=True),
        Fault("sixteen-counties-revised-held-whole", "16 of the 58 counties revise settled "
              "days beyond the policy (more than 25%: the vintage is held whole)",
              download=lambda s, o: body(edited(revised_counties(16))), held=True, issue=39),
        Fault("connection-refused", "Connection refused", base_url=closed_port, max_seconds=1.5),
        Fault("drip-past-deadline", "within the request deadline",
              download=lambda s, o: trickle([{"x": "y" * 100}]),
              config={"request_deadline_s": 1.0, "fetch_deadline_s": 2.5}),
        Fault("redirect-to-other-host", "refused, only redirects to the same https host",
              download=lambda s, o: redirect(o.url + DOWNLOAD_PATH)),
        Fault("download-url-on-other-host", "names the download",
              package=lambda s, o: body(package_show(o.url + DOWNLOAD_PATH),
                                        "application/json")),
        # -- issue 32: the CDPH source held to DataSF's standard, through the one gate
        Fault("infinity-in-a-county", "San Francisco: 'cases' is not finite ('Infinity') on "
              "2021-06-01", download=_poisoned("San Francisco", "2021-06-01", "cases",
                                               "Infinity"), issue=32),
        Fault("1e19-in-a-county", "San Francisco: implausible count 1e+19 in 'cases' on "
              "2021-06-01: more than 5% of the population",
              download=_poisoned("San Francisco", "2021-06-01", "cases", "1e19"), issue=32),
        Fault("1e300-deaths", "Los Angeles: implausible count 1e+300 in 'deaths' on 2021-06-01",
              download=_poisoned("Los Angeles", "2021-06-01", "deaths", "1e300"), issue=32),
        Fault("population-inf", "San Francisco: its population 'inf' is not within 25% of the "
              "2020 Census figure 873,965",
              download=_poisoned("San Francisco", "2021-06-01", "population", "inf"), issue=32),
        Fault("population-1e19", "San Francisco: its population '1e19' is not within 25% of "
              "the 2020 Census figure 873,965",
              download=_poisoned("San Francisco", "2021-06-01", "population", "1e19"),
              issue=32),
        Fault("ramp-under-the-old-daily-limit", "San Francisco: implausible count 56,000 in "
              "'cases' on 2021-11-03: more than 5% of the population 873,965",
              download=lambda s, o: body(edited(ramp)), issue=32),
        Fault("slow-ramp-under-both-population-bounds", "San Francisco: implausible growth of "
              "'cases'", download=lambda s, o: body(edited(slow_ramp)), issue=39),
        Fault("counties-written-x-county", "no row names one of the 58 known California county "
              "names", download=lambda s, o: body(edited(x_county)), issue=39),
        Fault("made-up-county", "'Atlantis' is not one of the 58 known California county "
              "names (CDPH)", download=lambda s, o: body(edited(with_county)),
              skipped="Atlantis", issue=32),
        Fault("gzip-bomb-404-mib", f"body larger than {BODY_LIMIT:,} bytes (after decoding); "
              "refused", download=lambda s, o: body(gzip_bomb(),
                                                    headers={"Content-Encoding": "gzip"}),
              issue=32),
        Fault("header-drip-no-thread-or-socket-left", "within the request deadline",
              download=lambda s, o: header_drip, issue=32,
              config={"request_deadline_s": 1.0, "fetch_deadline_s": 2.5}),
        Fault("cache-lock-held-by-stuck-run", "fetched but not stored, cache kept",
              hold_lock=True, max_seconds=3.0, issue=32),
    ]


# ------------------------------------------------------------------------------ running cases


def client_config(base_url: str, **overrides: float) -> CHHSClientConfig:
    """Short timeouts, no backoff: every case ends in seconds."""
    config = CHHSClientConfig(base_url=base_url, timeout_s=2.0, request_deadline_s=5.0,
                              fetch_deadline_s=10.0, max_retries=2, backoff_base_s=0.0,
                              max_body_bytes=BODY_LIMIT)
    return dataclasses.replace(config, **overrides)


def held_files(data_dir: Path) -> list[Path]:
    from pipeline.data.core.cache import DatasetCache
    held = DatasetCache(data_dir).directory(SPEC) / "held"
    return sorted(p for p in held.glob("payload-*") if not p.name.endswith(".reason.json")) \
        if held.is_dir() else []


def run_fault(fault: Fault, data_dir: Path) -> CaseResult:
    """Good fetch, then the fault; the loader must fall back to the untouched cache (or, for a
    ``skipped`` case, take the new payload with that county skipped and named, every file of the
    good cache still on disk unchanged: only the manifest moves to the new payload)."""
    from pipeline.data.california.cdph_source import load_cdph

    with FakeCKAN() as portal, FakeCKAN() as other:
        load_cdph(CDPHConfig(client=client_config(portal.url), data_dir=data_dir))
        before = cache_bytes(data_dir)
        if fault.package is not None:
            portal.package = fault.package(portal, other)
        if fault.download is not None:
            portal.download = fault.download(portal, other)
        base = fault.base_url() if fault.base_url is not None else portal.url
        config = CDPHConfig(client=client_config(base, **fault.config), data_dir=data_dir,
                            lock_timeout_s=0.5)
        loaded, seconds = load_timed(
            lambda: load_cdph(config), name=fault.name, source="cdph", issue=fault.issue,
            data_dir=data_dir, before=before,
            lock=(SPEC.dataset_id, SPEC.cache_folder) if fault.hold_lock else None)
        left = leftovers(portal.http.port)
        note = " | ".join(loaded.provenance.notes) + left
        after = cache_bytes(data_dir)
        if fault.skipped is None:
            lost = bytes_lost(before, after)
            outcome = loaded.provenance.from_cache and fault.expect in note
        else:
            lost = bytes_lost({k: v for k, v in before.items() if not k.endswith("manifest.json")},
                              after)
            outcome = (not loaded.provenance.from_cache
                       and fault.expect in loaded.vintage.skipped.get(fault.skipped, "")
                       and fault.expect in note
                       and len(loaded.vintage.counties) == 58 - fault.held_alone)
        held_ok = bool(held_files(data_dir)) == fault.held
        passed = (outcome and lost == 0 and held_ok and not left
                  and str(loaded.vintage.as_of.date()) == "2021-11-04" and not other.seen
                  and (fault.max_seconds is None or seconds <= fault.max_seconds))
        return CaseResult(fault.name, passed, seconds, lost, note, source="cdph",
                          issue=fault.issue)


def _import_one(path: Path, data_dir: Path) -> str:
    from pipeline.data.california.cdph_source import import_cdph_exports
    return import_cdph_exports([path], data_dir)[0].action


def run_concurrent_imports(data_dir: Path, trials: int = 3) -> CaseResult:
    """Two processes import the real vintages of 2021-09-23 and 2021-11-04 at the same moment,
    ``trials`` times on fresh caches: the newer must end live, both archived by their own dates;
    before the decision moved under the lock, the older one failed with "last date moves
    backwards" in 3 of 3 trials of the issue-32 probe."""
    from pipeline.data.core.cache import DatasetCache
    from pipeline.data.california.cdph_source import cached_vintages

    def trial(k: int) -> str | None:
        cache = data_dir / f"trial-{k}"
        actions = race([functools.partial(_import_one, CDPH / f / CSV_NAME, cache)
                        for f in (GOOD_VINTAGE, OLDER_VINTAGE)])
        kept = [str(v.as_of.date()) for v in cached_vintages(cache)]
        manifest = DatasetCache(cache).read_manifest(SPEC)
        live = manifest.last_date if manifest is not None else None
        if kept == ["2021-09-23", "2021-11-04"] and live == "2021-11-04" and actions in (
                ["archived", "imported"], ["imported", "imported"]):
            return None
        return f"trial {k}: actions {actions}, vintages {kept}, live {live}"

    return race_case("cdph", trial, trials, "the vintage of 2021-11-04 live, 2021-09-23 and "
                                            "2021-11-04 both kept by their own dates")


def run_all(scratch: Path) -> list[CaseResult]:
    """Every CDPH case, each on a fresh cache under ``scratch``."""
    return run_cases(scratch, [functools.partial(_in_data, f) for f in faults()]
                     + [run_concurrent_imports])


def _in_data(fault: Fault, folder: Path) -> CaseResult:
    return run_fault(fault, folder / "data")
