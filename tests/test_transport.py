"""The one bounded HTTP transport (``pipeline.data.core.transport``), once, through the real
``requests`` stack against a tiny threaded HTTP server on 127.0.0.1 built here: retries and
Retry-After, same-origin redirects only, the request deadline over a server that drips its
headers (no thread and no socket left), a gzip bomb stopped at the cap after decoding, a refused
connection learned at once. Every source (DataSF, the CHHS portal, NHSN) fetches through it."""
from __future__ import annotations

import gzip
import socket
import threading
import time
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from bench.faults import client_sockets_to
from pipeline.data.core.transport import (REQUEST_THREAD_NAME, NetworkError, RedirectRefusedError,
                                          Transport, TransportConfig, UnreachableError)
from pipeline.errors import DataSourceError

Reply = Callable[[BaseHTTPRequestHandler], None]


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - quiet
        pass

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        server = self.server
        assert isinstance(server, _Server)
        server.paths.append(self.path)
        try:
            server.replies.pop(0)(self) if len(server.replies) > 1 else server.replies[0](self)
        except (BrokenPipeError, ConnectionResetError):
            pass


class _Server(ThreadingHTTPServer):
    daemon_threads = True

    def __init__(self, replies: list[Reply]) -> None:
        super().__init__(("127.0.0.1", 0), _Handler)
        self.replies, self.paths = replies, []

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}"


@pytest.fixture
def serve() -> Iterator[Callable[..., _Server]]:
    servers: list[_Server] = []

    def start(*replies: Reply) -> _Server:
        server = _Server(list(replies))
        threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05},
                         daemon=True).start()
        servers.append(server)
        return server

    yield start
    for server in servers:
        server.shutdown()
        server.server_close()


def send(status: int, body: bytes = b"ok", headers: dict[str, str] | None = None) -> Reply:
    def reply(h: BaseHTTPRequestHandler) -> None:
        h.send_response(status)
        h.send_header("Content-Length", str(len(body)))
        h.send_header("Connection", "close")
        for key, value in (headers or {}).items():
            h.send_header(key, value)
        h.end_headers()
        h.wfile.write(body)
        h.close_connection = True
    return reply


def drip_headers(h: BaseHTTPRequestHandler) -> None:
    h.wfile.write(b"HTTP/1.1 200 OK\r\nX-Drip: ")
    for _ in range(60):  # bounded: 6 s, far past the deadline
        h.wfile.write(b"x")
        h.wfile.flush()
        time.sleep(0.1)


FAST = TransportConfig(timeout_s=2.0, request_deadline_s=1.0, fetch_deadline_s=5.0,
                       max_retries=2, backoff_base_s=0.0)


def transport(server: _Server, **config: float) -> Transport:
    from dataclasses import replace
    return Transport(replace(FAST, **config), source="test portal", origin=server.url)


def test_retries_honour_retry_after_then_return_the_body(serve):
    server = serve(send(503, b"busy", {"Retry-After": "3"}), send(200, b"[1, 2]"))
    slept: list[float] = []
    with Transport(FAST, source="test portal", origin=server.url,
                   sleep=slept.append) as t:
        answer = t.get(server.url + "/data", params={"$limit": "2"}, deadline=t.deadline(),
                       max_bytes=100)
    assert answer.body == b"[1, 2]" and slept == [3.0]  # not the 0 s backoff
    assert server.paths == ["/data?%24limit=2", "/data?%24limit=2"]


def test_a_retry_after_longer_than_we_wait_gives_up_at_once(serve):
    server = serve(send(429, b"later", {"Retry-After": "3600"}))
    with transport(server) as t, pytest.raises(
            NetworkError, match=r"test portal asks to retry after 3600 s, more than the 120 s"):
        t.get(server.url + "/data", deadline=t.deadline(), max_bytes=100)
    assert len(server.paths) == 1


def test_same_origin_redirects_are_followed_and_others_refused(serve):
    other = serve(send(200, b"elsewhere"))
    server = serve(send(302, b"", {"Location": "/moved"}), send(200, b"here"),
                   send(302, b"", {"Location": other.url + "/x"}))
    with transport(server) as t:
        assert t.get(server.url + "/a", deadline=t.deadline(), max_bytes=100).body == b"here"
        with pytest.raises(RedirectRefusedError, match=r"refused, only redirects to the same "
                                                       r"https host \(127\.0\.0\.1:\d+\)"):
            t.get(server.url + "/b", deadline=t.deadline(), max_bytes=100)
    assert server.paths == ["/a", "/moved", "/b"] and other.paths == []


def test_a_header_drip_ends_at_the_deadline_leaving_no_thread_and_no_socket(serve):
    server = serve(drip_headers)
    started = time.monotonic()
    with transport(server, fetch_deadline_s=2.5) as t, pytest.raises(
            NetworkError, match=r"within the request deadline of \d\.\d s"):
        t.get(server.url + "/drip", deadline=t.deadline(), max_bytes=100)
    assert time.monotonic() - started < 3.5
    assert [x for x in threading.enumerate() if x.name == REQUEST_THREAD_NAME] == []
    assert client_sockets_to(server.server_address[1]) == 0
    assert len(server.paths) >= 2  # retried, each attempt bounded


def test_a_gzip_bomb_stops_at_the_cap_after_decoding(serve):
    bomb = gzip.compress(b"0" * (8 << 20), compresslevel=9)  # 8 KB on the wire
    server = serve(send(200, bomb, {"Content-Encoding": "gzip"}))
    with transport(server) as t, pytest.raises(
            DataSourceError, match=r"body larger than 1,048,576 bytes \(after decoding\)"):
        t.get(server.url + "/bomb", deadline=t.deadline(), max_bytes=1 << 20)
    assert len(bomb) < 10_000


def test_a_refused_connection_is_not_retried():
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    started = time.monotonic()
    with Transport(FAST, source="test portal", origin=url) as t, pytest.raises(
            UnreachableError, match=r"cannot connect to 127\.0\.0\.1:\d+ .*not retried"):
        t.get(url + "/x", deadline=t.deadline(), max_bytes=100)
    assert time.monotonic() - started < 1.0
