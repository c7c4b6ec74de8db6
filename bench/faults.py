"""Benchmark: fault injection against every source's fetch path; a good cache must never be lost.

``python -m bench.faults`` runs the whole catalogue: the DataSF cases below, the CDPH (CKAN)
cases of :mod:`bench.faults_cdph` and the NHSN (data.cdc.gov) cases of :mod:`bench.faults_nhsn`,
and writes ``bench/results/faults.json`` (per case: source, the issue that found it, pass,
seconds, bytes of good cache lost, the note; totals per source and per issue).

A fake DataSF (:class:`FakeDataSF`, a threaded ``http.server`` on 127.0.0.1, never any other
address) serves the real cases export (``../shared/data/datasf``) as Socrata JSON pages, then each
failure of issue 15 in turn: HTTP 429/500, truncated JSON, an HTML body, renamed, negative,
infinite and 1e19 counts, an empty list, a short series, a last date that moves backwards, dates
ten years past the payload's own "data as of", a revision of settled days, a connection dropped
mid-body (``ChunkedEncodingError``), a bad gzip body (``ContentDecodingError``), a server that
trickles a byte at a time, a ``Retry-After`` longer than the client waits, and a redirect to
plain http on another host. Everything goes through the real ``requests`` stack.

Issue 22 added: a body of 200,000 nested ``[`` and a 5,000-digit integer (decoder exceptions
other than ``JSONDecodeError``), 99,999,999 new cases on a day of the open revision window and a
spike far above the series' own history (plausibility), a server that drips its *headers* (no
request thread may be left running), a body over the size limit, a server that ignores
``$offset``, connection refused and an unresolvable host (no retries: seconds, not a backoff
schedule), and a cache lock held by a stuck run; and, through the command line (one named error,
no traceback, cache untouched): a base URL without a scheme in the environment, ``--out`` naming
a directory for ``smc filter``, ``data sir`` and ``simulate`` and an existing file for
``data plot``, and ``final_url`` in ``data sir``'s provenance file.

For each case the cache is first filled by a good fetch; then the fault is served and
:func:`pipeline.data.sf.series.load_dataset` must (a) still return the cached data, (b) say why in a
note that names the problem, (c) leave every cache file byte-identical and (d) leave no request
thread running. "bytes of good cache lost" sums the sizes of cache files that changed or vanished
(must be 0).

Also the harness of ``tests/test_faults.py``.
"""
from __future__ import annotations

import contextlib
import functools
import gzip
import io
import json
import os
import platform
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import pandas as pd

from pipeline.data.sf.datasf import CASES, ClientConfig
from pipeline.io import atomic_write_json

RESULT_PATH = Path(__file__).parent / "results" / "faults.json"
DATASF = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "datasf"
TOKEN = "secret-app-token"
TRICKLE_MAX_BYTES = 40       # bounded: a trickling handler stops after this many bytes
TRICKLE_DELAY_S = 0.1
HEADER_DRIP_MAX_BYTES = 80   # bounded too: 8 s of header bytes, far past the request deadline

Rows = list[dict[str, str]]


# ------------------------------------------------------------------------------ the payload


EXPORTS = {"cases": "AndrewCorry__data_wrangling_1/COVID-19_Cases_Over_Time.csv",
           "deaths": "Yi-Angela__sf-covid-animation/COVID-19_Deaths_Over_Time.csv",
           "tests": "Yi-Angela__sf-covid-animation/Covid-19_Tests.csv"}


def api_rows(key: str = "cases", datasf_dir: Path = DATASF) -> Rows:
    """A real export as DataSF API rows: snake_case names, string values, ISO timestamps,
    sorted by date (what ``/resource/<id>.json?$order=<date field> ASC`` returns)."""
    from pipeline.data.sf.datasf import DATASETS
    from pipeline.data.sf.validation import find_column

    spec = DATASETS[key]
    raw = pd.read_csv(datasf_dir / EXPORTS[key], dtype=str, keep_default_na=False)
    out = pd.DataFrame(index=raw.index)
    for spec_field in (*spec.required, *spec.as_of):
        column = find_column(list(raw.columns), spec_field)
        if column is None:
            continue
        values = raw[column]
        if spec_field is spec.date or spec_field in spec.as_of:
            stamps = pd.to_datetime(values, format="%m/%d/%Y %I:%M:%S %p", errors="coerce")
            stamps = stamps.fillna(pd.to_datetime(values, format="%Y/%m/%d", errors="coerce"))
            values = stamps.dt.strftime("%Y-%m-%dT%H:%M:%S.000")
        out[spec_field.api] = values
    out = out.sort_values(spec.date.api, ignore_index=True)
    return [{str(k): v for k, v in r.items()} for r in out.to_dict(orient="records")]


def cases_api_rows() -> Rows:
    return api_rows("cases")


# ------------------------------------------------------------------------------ the server

Responder = Callable[["_Handler"], None]


@dataclass
class Seen:
    path: str
    headers: dict[str, str]


class _Handler(BaseHTTPRequestHandler):
    server: _Server  # pyright: ignore[reportIncompatibleVariableOverride] - the real type
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - quiet
        pass

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        self.server.seen.append(Seen(self.path, {k: v for k, v in self.headers.items()}))
        try:
            self.server.responder(self)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client gave up (deadline): fine

    # -- building blocks -------------------------------------------------------------------
    def send_body(self, status: int, body: bytes, content_type: str = "application/json",
                  headers: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Connection", "close")
        for key, value in (headers or {}).items():
            self.send_header(key, value)
        self.end_headers()
        self.wfile.write(body)
        self.close_connection = True

    def send_rows(self, rows: Rows) -> None:
        """One Socrata page of ``rows`` per ``$limit``/``$offset``."""
        query = parse_qs(urlsplit(self.path).query)
        limit = int(query.get("$limit", ["1000"])[0])
        offset = int(query.get("$offset", ["0"])[0])
        self.send_body(200, json.dumps(rows[offset:offset + limit]).encode())


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _Handler)
        self.seen: list[Seen] = []
        self.responder: Responder = lambda h: h.send_body(404, b"[]")


class FakeDataSF:
    """A fake DataSF on 127.0.0.1 (random port), in-process, one thread per connection."""

    def __init__(self) -> None:
        self._server = _Server()
        self._thread = threading.Thread(target=self._server.serve_forever,
                                        kwargs={"poll_interval": 0.05}, daemon=True)

    @property
    def url(self) -> str:
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}"

    @property
    def port(self) -> int:
        return int(self._server.server_address[1])

    @property
    def seen(self) -> list[Seen]:
        return self._server.seen

    def respond(self, responder: Responder) -> None:
        self._server.responder = responder

    def serve_rows(self, rows: Rows) -> None:
        self.respond(lambda h: h.send_rows(rows))

    def __enter__(self) -> FakeDataSF:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5)


# ------------------------------------------------------------------------------ the faults


def html_body(h: _Handler) -> None:
    h.send_body(200, b"<html><body>Service maintenance</body></html>", "text/html")


def status(code: int, headers: dict[str, str] | None = None) -> Responder:
    return lambda h: h.send_body(code, b'{"error": true}', headers=headers)


def truncated_json(rows: Rows) -> Responder:
    return lambda h: h.send_body(200, json.dumps(rows).encode()[:5000])


def dropped_mid_body(rows: Rows) -> Responder:
    """Chunked transfer, one chunk of a promised 4 kB, then the connection is cut."""
    def respond(h: _Handler) -> None:
        h.send_response(200)
        h.send_header("Content-Type", "application/json")
        h.send_header("Transfer-Encoding", "chunked")
        h.end_headers()
        h.wfile.write(b"1000\r\n" + json.dumps(rows).encode()[:1000])
        h.wfile.flush()
        h.connection.shutdown(socket.SHUT_RDWR)
        h.close_connection = True
    return respond


def bad_gzip(h: _Handler) -> None:
    """Claims gzip, sends bytes that are not (the gzip magic, then garbage)."""
    body = gzip.compress(b"[]")[:10] + b"\x00garbage, not deflate" * 20
    h.send_body(200, body, headers={"Content-Encoding": "gzip"})


def trickle(rows: Rows) -> Responder:
    """Headers at once, then one byte every TRICKLE_DELAY_S (bounded to TRICKLE_MAX_BYTES)."""
    def respond(h: _Handler) -> None:
        body = json.dumps(rows).encode()
        h.send_response(200)
        h.send_header("Content-Type", "application/json")
        h.send_header("Content-Length", str(len(body)))
        h.send_header("Connection", "close")
        h.end_headers()
        for i in range(min(TRICKLE_MAX_BYTES, len(body))):
            h.wfile.write(body[i:i + 1])
            h.wfile.flush()
            time.sleep(TRICKLE_DELAY_S)
        h.close_connection = True
    return respond


def header_drip(h: _Handler) -> None:
    """A status line, then one header byte every TRICKLE_DELAY_S: the header phase never ends
    (requests bounds each socket read, not the whole header)."""
    h.wfile.write(b"HTTP/1.1 200 OK\r\nX-Drip: ")
    for _ in range(HEADER_DRIP_MAX_BYTES):
        h.wfile.write(b"x")
        h.wfile.flush()
        time.sleep(TRICKLE_DELAY_S)
    h.close_connection = True


BOMB_BYTES = 404 << 20   # issue 32's gzip bomb: 404 MiB decoded, 1.8 MB on the wire


@functools.cache
def gzip_bomb(decoded_bytes: int = BOMB_BYTES) -> bytes:
    """``decoded_bytes`` of zeros, gzip-compressed in chunks (never held whole in memory)."""
    out = io.BytesIO()
    with gzip.GzipFile(fileobj=out, mode="wb", compresslevel=1) as gz:
        chunk = b"0" * (1 << 20)
        for _ in range(decoded_bytes >> 20):
            gz.write(chunk)
    return out.getvalue()


def gzipped(data: bytes) -> Responder:
    return lambda h: h.send_body(200, data, headers={"Content-Encoding": "gzip"})


def raw_body(body: bytes) -> Responder:
    return lambda h: h.send_body(200, body)


def ignores_offset(rows: Rows) -> Responder:
    """Every page is the first page, whatever ``$offset`` says."""
    def respond(h: _Handler) -> None:
        limit = int(parse_qs(urlsplit(h.path).query).get("$limit", ["1000"])[0])
        h.send_body(200, json.dumps(rows[:limit]).encode())
    return respond


def closed_port_url() -> str:
    """A loopback URL nobody listens on (the port was just free): connection refused."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    return f"http://127.0.0.1:{port}"


@contextlib.contextmanager
def held_cache_lock(data_dir: Path, dataset_id: str = "gyr2-k29z",
                    folder: str = "datasf") -> Iterator[None]:
    """The dataset's cache lock held, as by a stuck run (flock on its own open file, which
    conflicts with any other open of it, in this process too)."""
    import fcntl

    path = data_dir / folder / ".locks" / f"{dataset_id}.lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the flock


def _racer(job: Callable[[], str], start: Any, results: Any) -> None:
    start.wait()
    try:
        results.put(job())
    except Exception as exc:  # noqa: BLE001 - reported to the parent: the failure tested
        results.put(f"{type(exc).__name__}: {exc}")


def race(jobs: list[Callable[[], str]], timeout_s: float = 60.0) -> list[str]:
    """Run each job in its own forked process, all released at the same moment (a barrier);
    their results (or "<Error>: message"), sorted."""
    import multiprocessing

    context = multiprocessing.get_context("fork")
    start, results = context.Barrier(len(jobs)), context.Queue()
    workers = [context.Process(target=_racer, args=(job, start, results)) for job in jobs]
    for w in workers:
        w.start()
    for w in workers:
        w.join(timeout_s)
    return sorted(results.get(timeout=5) for _ in workers)


def race_case(source: str, trial: Callable[[int], str | None], trials: int,
              success: str) -> CaseResult:
    """Issue 32, item 7, on one source: ``trial(k)`` races two imports on a fresh cache and
    returns what went wrong (None: both landed where they belong)."""
    started = time.monotonic()
    problems = [p for p in (trial(k) for k in range(trials)) if p is not None]
    note = "; ".join(problems) or f"{trials} of {trials} trials: {success}"
    return CaseResult("concurrent-imports-older-and-newer", not problems,
                      time.monotonic() - started, 0, note, source=source, issue=32)


class CaseCrashed(Exception):
    """A load that raised: the case failed (its result says how)."""

    def __init__(self, result: CaseResult) -> None:
        super().__init__(result.note)
        self.result = result


def load_timed(load: Callable[[], Any], *, name: str, source: str, issue: int, data_dir: Path,
               before: dict[str, bytes], lock: tuple[str, str] | None = None
               ) -> tuple[Any, float]:
    """``load()`` (with the cache lock of ``lock`` = (dataset id, folder) held by a "stuck run"
    meanwhile) and its seconds; a crash raises :class:`CaseCrashed` carrying the failed case."""
    started = time.monotonic()
    try:
        with held_cache_lock(data_dir, *lock) if lock else contextlib.nullcontext():
            return load(), time.monotonic() - started
    except Exception as exc:  # noqa: BLE001 - a crash is a failed case, reported
        raise CaseCrashed(CaseResult(name, False, time.monotonic() - started,
                                     bytes_lost(before, cache_bytes(data_dir)),
                                     f"raised {type(exc).__name__}: {exc}", source=source,
                                     issue=issue)) from exc


def run_cases(scratch: Path, cases: Sequence[Callable[[Path], CaseResult]]) -> list[CaseResult]:
    """Each case on its own fresh folder under ``scratch``, printed as it ends."""
    results = []
    for k, case in enumerate(cases):
        try:
            results.append(show(case(scratch / f"case-{k}")))
        except CaseCrashed as crashed:
            results.append(show(crashed.result))
    return results


def live_request_threads() -> list[threading.Thread]:
    from pipeline.data.core.transport import REQUEST_THREAD_NAME

    return [t for t in threading.enumerate() if t.name == REQUEST_THREAD_NAME and t.is_alive()]


def client_sockets_to(port: int) -> int:
    """Sockets this process holds whose peer is ``port`` (the client side of a connection to a
    fake portal; its server side has ``port`` as the local port): from /proc (Linux)."""
    inodes = set()
    for fd in Path("/proc/self/fd").iterdir():
        try:
            target = fd.readlink().as_posix()
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found = 0
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if int(fields[2].rsplit(":", 1)[1], 16) == port and fields[9] in inodes:
                found += 1
    return found


def leftovers(port: int) -> str:
    """What a fetch left running: request threads and sockets to the portal ("" when none)."""
    threads, sockets = len(live_request_threads()), client_sockets_to(port)
    return (f" | {threads} request thread(s) and {sockets} socket(s) to the portal still open"
            if threads or sockets else "")


def redirect(location: str) -> Responder:
    return lambda h: h.send_body(302, b"", headers={"Location": location})


def with_value(rows: Rows, column: str, value: str, index: int = 100) -> Rows:
    changed = [dict(r) for r in rows]
    changed[index][column] = value
    return changed


def renamed(rows: Rows) -> Rows:
    return [{("new_kases" if k == "new_cases" else k): v for k, v in r.items()} for r in rows]


def future_last_date(rows: Rows, years: int = 10) -> Rows:
    """The last row moved ``years`` later (after the payload's own data_as_of)."""
    changed = [dict(r) for r in rows]
    last = pd.Timestamp(changed[-1]["specimen_collection_date"]) + pd.DateOffset(years=years)
    changed[-1]["specimen_collection_date"] = last.strftime("%Y-%m-%dT%H:%M:%S.000")
    return changed


def revised_settled_days(rows: Rows) -> Rows:
    """Days 300..309 (settled: a year before the end) multiplied by three; cumulative kept
    consistent so only the revision policy can object (tenfold, the gate's growth rule refuses
    the series itself: 19,670 cases in 7 days after 1,623)."""
    changed = [dict(r) for r in rows]
    total = 0
    for i, row in enumerate(changed):
        new = int(row["new_cases"]) * (3 if 300 <= i < 310 else 1)
        total = (int(rows[0]["cumulative_cases"]) - int(rows[0]["new_cases"]) if i == 0
                 else total) + new
        row["new_cases"], row["cumulative_cases"] = str(new), str(total)
    return changed


@dataclass(frozen=True)
class Fault:
    """One failure served after a good fetch: what the server does and the note expected.

    ``config`` overrides the client's settings, ``series`` the loader's; ``base_url`` points the
    faulted fetch elsewhere (a closed port, an unknown host); ``hold_lock`` holds the cache lock
    meanwhile; ``max_seconds`` bounds how long the fallback may take."""

    name: str
    responder: Callable[[Rows, FakeDataSF], Responder]
    expect: str
    config: dict[str, float] = field(default_factory=dict)
    series: dict[str, float] = field(default_factory=dict)
    base_url: Callable[[], str] | None = None
    hold_lock: bool = False
    max_seconds: float | None = None
    issue: int = 15


def ramp(rows: Rows) -> Rows:
    """Issue 32's ramp: the last three days at 2,800, 56,000 and 89,000 cases (6-10 % of San
    Francisco a day, each under the old 10 %-a-day limit)."""
    changed = [dict(r) for r in rows]
    for row, value in zip(changed[-3:], ("2800", "56000", "89000"), strict=True):
        row["new_cases"] = value
    return changed


def slow_ramp(rows: Rows) -> Rows:
    """Issue 39's slow ramp: 2,000 and then 12,000 cases a day for six days (1.4 % of the city a
    day, 8.2 % in the week: under both population bounds, and each day under 20× its
    history)."""
    changed = [dict(r) for r in rows]
    for row, value in zip(changed[-7:], ("2000",) + ("12000",) * 6, strict=True):
        row["new_cases"] = value
    return changed


ISSUE_22 = {"json-nested-200000-deep", "json-5000-digit-integer", "99999999-cases-in-open-window",
            "spike-far-above-history", "header-drip", "body-over-size-limit",
            "server-ignores-offset", "connection-refused", "unknown-host"}


def faults() -> list[Fault]:
    return [replace(f, issue=22) if f.name in ISSUE_22 else f for f in _faults()]


def _faults() -> list[Fault]:
    s = lambda build: (lambda rows, other: (lambda h: h.send_rows(build(rows))))  # noqa: E731
    return [
        Fault("http-429", lambda rows, _: status(429), "HTTP 429"),
        Fault("http-500", lambda rows, _: status(500), "HTTP 500"),
        Fault("truncated-json", lambda rows, _: truncated_json(rows), "invalid JSON"),
        Fault("html-body", lambda rows, _: html_body, "invalid JSON"),
        Fault("renamed-column", s(renamed), "missing column 'New Cases'"),
        Fault("negative-count", s(lambda r: with_value(r, "new_cases", "-3")),
              "negative count '-3'"),
        Fault("inf-count", s(lambda r: with_value(r, "new_cases", "inf")),
              "non-finite count 'inf'"),
        Fault("1e19-count", s(lambda r: with_value(r, "cumulative_cases", "1e19")),
              "count '1e19' in 'Cumulative Cases' at row 101 (date 2020-06-11) is not below "
              "the bound 100,000,000"),
        Fault("empty-list", s(lambda r: []), "empty payload (no rows)"),
        Fault("short-series-60-of-744", s(lambda r: r[-60:]), "payload shrinks: new 60 rows"),
        Fault("last-date-backwards", s(lambda r: r[:-10]), "last date moves backwards"),
        Fault("dates-past-data-as-of", s(future_last_date),
              "last date 2032-03-16 is after the payload's own 'data as of' 2022-03-21"),
        Fault("revised-settled-days", s(revised_settled_days),
              "revision beyond policy: 'new_cases' changed on 10 settled day(s)"),
        Fault("dropped-mid-body", lambda rows, _: dropped_mid_body(rows),
              "ChunkedEncodingError"),
        Fault("bad-gzip", lambda rows, _: bad_gzip, "ContentDecodingError"),
        Fault("trickle", lambda rows, _: trickle(rows), "within the request deadline",
              {"request_deadline_s": 1.0, "fetch_deadline_s": 2.5}),
        Fault("retry-after-too-long", lambda rows, _: status(503, {"Retry-After": "3600"}),
              "asks to retry after 3600 s"),
        Fault("redirect-to-http-other-host",
              lambda rows, other: redirect(f"{other.url}/resource/gyr2-k29z.json"),
              "refused, only redirects to the same https host"),
        # -- issue 22
        Fault("json-nested-200000-deep", lambda rows, _: raw_body(b"[" * 200_000),
              "nested too deeply to decode (RecursionError"),
        Fault("json-5000-digit-integer",
              lambda rows, _: raw_body(b'[{"new_cases": ' + b"9" * 5000 + b"}]"),
              "Exceeds the limit (4300 digits) for integer string conversion"),
        Fault("99999999-cases-in-open-window",
              s(lambda r: with_value(r, "new_cases", "99999999", index=len(r) - 10)),
              "implausible count 99,999,999 in 'new_cases' on 2022-03-07: more than 5% of the "
              "population 873,965 (2020 Census) in one day"),
        Fault("spike-far-above-history",
              s(lambda r: with_value(r, "new_cases", "30000", index=len(r) - 5)),
              "implausible count 30,000 in 'new_cases' on 2022-03-12: more than 20× the "
              "plausible bracket of the previous 28 day(s)"),
        Fault("header-drip", lambda rows, _: header_drip, "within the request deadline",
              {"request_deadline_s": 1.0, "fetch_deadline_s": 2.5}),
        Fault("body-over-size-limit", lambda rows, _: lambda h: h.send_rows(rows),
              "body larger than 20,000 bytes (after decoding); refused", {"max_body_bytes": 20_000}),
        Fault("server-ignores-offset", lambda rows, _: ignores_offset(rows),
              "the page at $offset=100 repeats the page at $offset=0", {"page_size": 100}),
        Fault("connection-refused", lambda rows, _: status(500), "Connection refused",
              base_url=closed_port_url, max_seconds=1.5),
        Fault("unknown-host", lambda rows, _: status(500), "Failed to resolve "
              "'flowcast-fault.invalid'", base_url=lambda: "http://flowcast-fault.invalid",
              max_seconds=3.0),
        Fault("cache-lock-held-by-stuck-run", lambda rows, _: lambda h: h.send_rows(rows),
              "fetched but not stored, cache kept", series={"lock_timeout_s": 0.5},
              hold_lock=True, max_seconds=3.0, issue=22),
        # -- issue 32, on DataSF too (one place: a failing count refuses the payload)
        Fault("infinity-count", s(lambda r: with_value(r, "new_cases", "Infinity")),
              "non-finite count 'Infinity' in 'New Cases' at row 101", issue=32),
        Fault("1e300-count", s(lambda r: with_value(r, "new_cases", "1e300")),
              "count '1e300' in 'New Cases' at row 101 (date 2020-06-11) is not below the bound",
              issue=32),
        Fault("ramp-under-the-old-daily-limit", s(ramp),
              "implausible count 56,000 in 'new_cases' on 2022-03-15: more than 5% of the "
              "population 873,965 (2020 Census) in one day", issue=32),
        Fault("gzip-bomb-404-mib", lambda rows, _: gzipped(gzip_bomb()),
              "body larger than 2,097,152 bytes (after decoding); refused", issue=32),
        Fault("slow-ramp-under-both-population-bounds", s(slow_ramp),
              "implausible growth of 'new_cases': 14,366 in the 7 days ending 2022-03-11 after "
              "698 in the 7 days before, more than 11×", issue=39),
    ]


# ------------------------------------------------------------------------------ running cases


def client_config(server: FakeDataSF, **overrides: float) -> ClientConfig:
    """Short timeouts and no backoff: every case ends in seconds."""
    base: dict[str, object] = dict(base_url=server.url, page_size=1000, timeout_s=2.0,
                                   request_deadline_s=5.0, fetch_deadline_s=10.0, max_retries=2,
                                   backoff_base_s=0.0, app_token=TOKEN)
    return ClientConfig(**{**base, **overrides})  # type: ignore[arg-type]


def cache_bytes(root: Path) -> dict[str, bytes]:
    """Every cache file except lock files (coordination, not content)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and ".locks" not in p.parts and "held" not in p.parts} \
        if root.exists() else {}


def bytes_lost(before: dict[str, bytes], after: dict[str, bytes]) -> int:
    return sum(len(data) for name, data in before.items() if after.get(name) != data)


@dataclass
class CaseResult:
    name: str
    passed: bool
    seconds: float
    bytes_lost: int
    note: str
    source: str = "datasf"
    issue: int = 15
    detail: dict[str, object] = field(default_factory=dict)   # e.g. a round's published/dropped


def run_fault(fault: Fault, rows: Rows, data_dir: Path) -> CaseResult:
    """Good fetch, then the fault; the loader must fall back to the untouched cache."""
    from pipeline.data.sf.series import SFDataConfig, load_dataset

    with FakeDataSF() as server, FakeDataSF() as other:
        other.serve_rows(rows)
        server.serve_rows(rows)
        good = SFDataConfig(datasets=("cases",), data_dir=data_dir,
                            client=client_config(server))
        load_dataset(CASES, good)
        before = cache_bytes(data_dir)
        server.respond(fault.responder(rows, other))
        client = client_config(server, **fault.config)
        if fault.base_url is not None:
            client = replace(client, base_url=fault.base_url())
        config = SFDataConfig(datasets=("cases",), data_dir=data_dir, client=client,
                              **fault.series)  # type: ignore[arg-type]
        started = time.monotonic()
        try:
            with held_cache_lock(data_dir) if fault.hold_lock else contextlib.nullcontext():
                validated, provenance = load_dataset(CASES, config)
        except Exception as exc:  # noqa: BLE001 - a crash is a failed case, reported
            return CaseResult(fault.name, False, time.monotonic() - started,
                              bytes_lost(before, cache_bytes(data_dir)),
                              f"raised {type(exc).__name__}: {exc}", issue=fault.issue)
        seconds = time.monotonic() - started
        left = leftovers(server.port)
        note = " | ".join(provenance.notes) + left
        lost = bytes_lost(before, cache_bytes(data_dir))
        passed = (provenance.from_cache and fault.expect in note and lost == 0
                  and len(validated.frame) == 744 and not other.seen and not left
                  and (fault.max_seconds is None or seconds <= fault.max_seconds))
        return CaseResult(fault.name, passed, seconds, lost, note, issue=fault.issue)


# ------------------------------------------------------------------------------ command line


def fill_cache_from_api(data_dir: Path) -> None:
    """All three datasets fetched from a fake DataSF (so manifests carry a final_url)."""
    from pipeline.data.sf.datasf import DATASETS
    from pipeline.data.sf.series import SFDataConfig, load_sf_series

    by_id = {spec.dataset_id: api_rows(key) for key, spec in DATASETS.items()}
    with FakeDataSF() as server:
        server.respond(lambda h: h.send_rows(by_id[h.path.split("/")[2].split(".")[0]]))
        load_sf_series(SFDataConfig(data_dir=data_dir, client=client_config(server)))


@dataclass(frozen=True)
class CommandFault:
    """A command run against a filled cache: it must end in one named error line (no
    traceback) or succeed as ``check`` says, and leave the cache untouched."""

    name: str
    args: Callable[[Path], list[str]]     # the scratch directory -> command-line arguments
    expect: str                           # in the output
    succeeds: bool = False
    check: Callable[[Path], bool] = lambda tmp: True
    env: dict[str, str] = field(default_factory=dict)


def _provenance_has_final_url(tmp: Path) -> bool:
    provenance = json.loads((tmp / "sir.csv.provenance.json").read_text())
    urls = [d.get("final_url") for d in provenance["datasets"]]
    return len(urls) == 3 and all(u and u.startswith("http://127.0.0.1:") for u in urls)


def command_faults() -> list[CommandFault]:
    def existing_dir(tmp: Path) -> Path:
        (tmp / "outdir").mkdir(exist_ok=True)
        return tmp / "outdir"

    def observations(tmp: Path) -> Path:
        path = tmp / "obs.csv"
        path.write_text("time,S,I,R\n0,0.99,0.01,0\n1,0.98,0.015,0.005\n")
        return path

    def existing_file(tmp: Path) -> Path:
        path = tmp / "figures.png"
        path.write_bytes(b"not a directory")
        return path

    return [
        CommandFault("base-url-without-scheme", lambda tmp: ["data", "fetch"],
                     "error: DataSF base URL must be http(s)://host[/path], got "
                     "'data.sfgov.org' (--base-url / $FLOWCAST_DATASF_BASE_URL); did you mean "
                     "'https://data.sfgov.org'?", env={"FLOWCAST_DATASF_BASE_URL":
                                                       "data.sfgov.org"}),
        CommandFault("smc-filter-out-is-a-directory",
                     lambda tmp: ["smc", "filter", "--observations", str(observations(tmp)),
                                  "--out", str(existing_dir(tmp))],
                     "is a directory; --out names the file to write"),
        CommandFault("data-sir-out-is-a-directory",
                     lambda tmp: ["data", "sir", "--offline", "--out", str(existing_dir(tmp))],
                     "is a directory; --out names the file to write"),
        CommandFault("simulate-out-is-a-directory",
                     lambda tmp: ["simulate", "sir-single", "--out", str(existing_dir(tmp))],
                     "is a directory; --out names the file to write"),
        CommandFault("data-plot-out-is-an-existing-file",
                     lambda tmp: ["data", "plot", "--offline", "--out", str(existing_file(tmp))],
                     "is a file; --out names a directory"),
        CommandFault("data-sir-provenance-has-final-url",
                     lambda tmp: ["data", "sir", "--offline", "--out", str(tmp / "sir.csv")],
                     "wrote", succeeds=True, check=_provenance_has_final_url,
                     env={"FLOWCAST_DATASF_BASE_URL": "data.sfgov.org"}),
    ]


def run_command_fault(fault: CommandFault, tmp: Path) -> CaseResult:
    """The command through typer's runner (in process), FLOWCAST_DATA_DIR = a filled cache."""
    from typer.testing import CliRunner

    from pipeline.cli import app, build_command

    build_command()  # registers every command module
    data_dir = tmp / "data"
    if not data_dir.exists():
        fill_cache_from_api(data_dir)
    before = cache_bytes(data_dir)
    started = time.monotonic()
    result = CliRunner().invoke(app, fault.args(tmp), prog_name="flowcast",
                                env={"FLOWCAST_DATA_DIR": str(data_dir), "COLUMNS": "200",
                                     "NO_COLOR": "1", **fault.env})
    seconds = time.monotonic() - started
    lost = bytes_lost(before, cache_bytes(data_dir))
    output = " ".join(result.output.split())  # rich wraps long lines
    clean_exit = result.exception is None or isinstance(result.exception, SystemExit)
    ok = (result.exit_code == 0) == fault.succeeds and fault.check(tmp)
    passed = clean_exit and ok and " ".join(fault.expect.split()) in output and lost == 0
    note = output[-300:] if clean_exit else f"raised {result.exception!r}"
    return CaseResult(fault.name, passed, seconds, lost, note, issue=22)


@contextlib.contextmanager
def _scratch() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="flowcast-faults-") as tmp:
        yield Path(tmp)


def show(result: CaseResult) -> CaseResult:
    print(f"{'PASS' if result.passed else 'FAIL'} {result.source:6s} {result.name:38s} "
          f"{result.seconds:5.2f} s lost {result.bytes_lost} B — {result.note[:140]}",
          flush=True)
    return result


def run_all(scratch: Path) -> list[CaseResult]:
    """Every DataSF case (each on a fresh cache under ``scratch``) and the command-line cases."""
    rows = cases_api_rows()
    results = [show(run_fault(fault, rows, scratch / f"case-{k}" / "data"))
               for k, fault in enumerate(faults())]
    commands = scratch / "commands"  # one filled cache for every command case
    commands.mkdir()
    results += [show(run_command_fault(command, commands)) for command in command_faults()]
    return results


def _totals(results: list[CaseResult]) -> dict[str, int]:
    passed, lost = sum(r.passed for r in results), sum(r.bytes_lost for r in results)
    return {"total": len(results), "passed": passed, "bytes_lost": lost,
            "cases_tried": len(results), "cases_passed": passed, "bytes_of_good_cache_lost": lost}


SOURCES = ("datasf", "cdph", "nhsn", "hub_round", "import", "replay")
# Issue 39's round cases (round_published, dropped per case, bench.faults_round)
HUB_ROUND_NOTE = ("rounds on the tiny preset from the cache after a faulted newer release of "
                  "admissions or the ED share; each records whether the round was published "
                  "and what it left out (per target: location -> why, or the target itself)")


def main() -> int:
    """The whole catalogue: DataSF, CDPH (CKAN) and NHSN (data.cdc.gov), every case."""
    import logging

    from bench import faults_cdph, faults_nhsn, faults_release, faults_replay, faults_round

    logging.basicConfig(level=logging.ERROR)
    started = time.monotonic()
    results: list[CaseResult] = []
    for run in (run_all, faults_cdph.run_all, faults_nhsn.run_all, faults_release.run_all,
                faults_round.run_all, faults_replay.run_all):
        with _scratch() as tmp:
            results += run(tmp)
    sources = sorted({r.source for r in results} | set(SOURCES))
    summary = {
        **_totals(results),
        "by_source": {s: _totals([r for r in results if r.source == s]) for s in sources},
        "hub_round": {"note": HUB_ROUND_NOTE, "rounds": [
            {"name": r.name, "passed": r.passed, **r.detail} for r in results
            if r.source == "hub_round"]},
        "by_issue": {str(i): _totals([r for r in results if r.issue == i])
                     for i in sorted({r.issue for r in results})},
        "seconds": round(time.monotonic() - started, 1),
        "cases": [asdict(r) for r in results],
        "machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                    "cpus": os.cpu_count()},
        "command": "python -m bench.faults",
        "date": time.strftime("%Y-%m-%d"),
    }
    atomic_write_json(RESULT_PATH, summary)
    print(f"cases tried {summary['cases_tried']}, passed {summary['cases_passed']}, bytes of good "
          f"cache lost {summary['bytes_of_good_cache_lost']} ("
          + ", ".join(f"{s} {t['cases_passed']}/{t['cases_tried']}"
                      for s, t in summary["by_source"].items()) + f") -> {RESULT_PATH}")
    return 0 if summary["cases_passed"] == summary["cases_tried"] else 1


if __name__ == "__main__":
    sys.exit(main())
