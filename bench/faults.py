"""Benchmark: fault injection against the DataSF fetch path; a good cache must never be lost.

A fake DataSF (:class:`FakeDataSF`, a threaded ``http.server`` on 127.0.0.1, never any other
address) serves the real cases export (``../shared/data/datasf``) as Socrata JSON pages, then each
failure of issue 15 in turn: HTTP 429/500, truncated JSON, an HTML body, renamed, negative,
infinite and 1e19 counts, an empty list, a short series, a last date that moves backwards, dates
ten years past the payload's own "data as of", a revision of settled days, a connection dropped
mid-body (``ChunkedEncodingError``), a bad gzip body (``ContentDecodingError``), a server that
trickles a byte at a time, a ``Retry-After`` longer than the client waits, and a redirect to
plain http on another host. Everything goes through the real ``requests`` stack.

For each case the cache is first filled by a good fetch; then the fault is served and
:func:`pipeline.data.series.load_dataset` must (a) still return the cached data, (b) say why in a
note that names the problem, and (c) leave every cache file byte-identical. "bytes of good cache
lost" sums the sizes of cache files that changed or vanished (must be 0).

Run: ``python -m bench.faults`` -> ``bench/results/faults.json``. Also the harness of
``tests/test_faults.py``.
"""
from __future__ import annotations

import contextlib
import gzip
import json
import os
import platform
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import pandas as pd

from pipeline.data.datasf import CASES, ClientConfig
from pipeline.io import atomic_write_json

RESULT_PATH = Path(__file__).parent / "results" / "faults.json"
DATASF = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "datasf"
TOKEN = "secret-app-token"
TRICKLE_MAX_BYTES = 40       # bounded: a trickling handler stops after this many bytes
TRICKLE_DELAY_S = 0.1

Rows = list[dict[str, str]]


# ------------------------------------------------------------------------------ the payload


EXPORTS = {"cases": "AndrewCorry__data_wrangling_1/COVID-19_Cases_Over_Time.csv",
           "deaths": "Yi-Angela__sf-covid-animation/COVID-19_Deaths_Over_Time.csv",
           "tests": "Yi-Angela__sf-covid-animation/Covid-19_Tests.csv"}


def api_rows(key: str = "cases", datasf_dir: Path = DATASF) -> Rows:
    """A real export as DataSF API rows: snake_case names, string values, ISO timestamps,
    sorted by date (what ``/resource/<id>.json?$order=<date field> ASC`` returns)."""
    from pipeline.data.datasf import DATASETS
    from pipeline.data.validation import find_column

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
    return out.to_dict(orient="records")


def cases_api_rows() -> Rows:
    return api_rows("cases")


# ------------------------------------------------------------------------------ the server

Responder = Callable[["_Handler"], None]


@dataclass
class Seen:
    path: str
    headers: dict[str, str]


class _Handler(BaseHTTPRequestHandler):
    server: _Server
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
    """Days 300..309 (settled: a year before the end) multiplied by ten; cumulative kept
    consistent so only the revision policy can object."""
    changed = [dict(r) for r in rows]
    total = 0
    for i, row in enumerate(changed):
        new = int(row["new_cases"]) * (10 if 300 <= i < 310 else 1)
        total = (int(rows[0]["cumulative_cases"]) - int(rows[0]["new_cases"]) if i == 0
                 else total) + new
        row["new_cases"], row["cumulative_cases"] = str(new), str(total)
    return changed


@dataclass(frozen=True)
class Fault:
    """One failure served after a good fetch: what the server does and the note expected."""

    name: str
    responder: Callable[[Rows, FakeDataSF], Responder]
    expect: str
    config: dict[str, float] = field(default_factory=dict)


def faults() -> list[Fault]:
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


def run_fault(fault: Fault, rows: Rows, data_dir: Path) -> CaseResult:
    """Good fetch, then the fault; the loader must fall back to the untouched cache."""
    from pipeline.data.series import SFDataConfig, load_dataset

    with FakeDataSF() as server, FakeDataSF() as other:
        other.serve_rows(rows)
        server.serve_rows(rows)
        good = SFDataConfig(datasets=("cases",), data_dir=data_dir,
                            client=client_config(server))
        load_dataset(CASES, good)
        before = cache_bytes(data_dir)
        server.respond(fault.responder(rows, other))
        config = SFDataConfig(datasets=("cases",), data_dir=data_dir,
                              client=client_config(server, **fault.config))
        started = time.monotonic()
        try:
            validated, provenance = load_dataset(CASES, config)
        except Exception as exc:  # noqa: BLE001 - a crash is a failed case, reported
            return CaseResult(fault.name, False, time.monotonic() - started,
                              bytes_lost(before, cache_bytes(data_dir)),
                              f"raised {type(exc).__name__}: {exc}")
        seconds = time.monotonic() - started
        note = " | ".join(provenance.notes)
        lost = bytes_lost(before, cache_bytes(data_dir))
        passed = (provenance.from_cache and fault.expect in note and lost == 0
                  and len(validated.frame) == 744 and not other.seen)
        return CaseResult(fault.name, passed, seconds, lost, note)


@contextlib.contextmanager
def _scratch() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="flowcast-faults-") as tmp:
        yield Path(tmp)


def main() -> int:
    import logging

    logging.basicConfig(level=logging.ERROR)
    rows = cases_api_rows()
    results = []
    for fault in faults():
        with _scratch() as tmp:
            result = run_fault(fault, rows, tmp / "data")
        results.append(result)
        print(f"{'PASS' if result.passed else 'FAIL'} {result.name:30s} {result.seconds:5.2f} s "
              f"lost {result.bytes_lost} B — {result.note[:150]}")
    summary = {
        "cases_tried": len(results),
        "cases_passed": sum(r.passed for r in results),
        "bytes_of_good_cache_lost": sum(r.bytes_lost for r in results),
        "cases": [asdict(r) for r in results],
        "machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                    "cpus": os.cpu_count()},
        "command": "python -m bench.faults",
        "date": time.strftime("%Y-%m-%d"),
    }
    atomic_write_json(RESULT_PATH, summary)
    print(f"cases tried {summary['cases_tried']}, passed {summary['cases_passed']}, bytes of good "
          f"cache lost {summary['bytes_of_good_cache_lost']} -> {RESULT_PATH}")
    return 0 if summary["cases_passed"] == summary["cases_tried"] else 1


if __name__ == "__main__":
    sys.exit(main())
