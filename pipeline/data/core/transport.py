"""The one bounded HTTP transport every source fetches through (DataSF, the CHHS portal, NHSN).

A source keeps only what is its own (URLs, paging, parsing); *how* a GET is made is decided
here once, each rule because a fault-injection probe broke an earlier client (issues 15, 22, 32):

* **retries**: every ``requests``/``urllib3`` failure (a connection dropped mid-body, a bad gzip
  body, timeouts, ...) and HTTP 429/5xx is retried with exponential backoff
  (``backoff_base_s·2^(attempt−1)``, capped); ``Retry-After`` (seconds or an HTTP date) is
  honoured, never shortened, and one longer than ``retry_after_max_s`` gives up at once; after the
  last attempt a :class:`NetworkError`, on which the caller falls back to its cache. A 4xx other
  than 429 is not retried (:class:`HTTPStatusError`: the request itself is wrong);
* **unreachable**: a connection that cannot be made at all (refused, unknown host, no route)
  raises :class:`UnreachableError` at once; seconds later the answer would be the same;
* **deadlines**, all wall-clock: ``timeout_s`` bounds each socket read (``connect_timeout_s`` a
  connect), ``request_deadline_s`` one request, headers *and* body, and the caller's fetch
  deadline (``fetch_deadline_s`` from :meth:`Transport.deadline`) every request and retry of one
  fetch. The request runs in a worker thread so the header phase (which ``requests`` bounds per
  read only) is bounded too;
* **no thread or socket outlives its request**: the worker's sockets are registered with a
  :class:`_RequestWatch`; when the deadline passes they are shut (a read blocked on a server that
  drips its headers returns at once) and the worker is joined. The CHHS client's own copy of this
  loop lacked it and left 3 threads and their sockets alive 15 s after a header drip (issue 32);
* **bounded reads**: the body is streamed with urllib3's ``read1`` (the deadline is checked
  between trickled bytes) and counted *after* decoding, so a gzip bomb stops at the caller's
  ``max_bytes`` (each source sets it from what its genuine payloads weigh);
* **redirects** are followed by hand, only to the origin's scheme, host and port (https, or plain
  http on a loopback mirror): anything else is a :class:`RedirectRefusedError`, so no header (an
  app token) ever reaches another host.

The cache-side counterpart (a held cache lock falls back to the cache, like an unreachable host)
is :mod:`pipeline.data.core.fallback`.
"""
from __future__ import annotations

import contextlib
import email.utils
import ipaddress
import logging
import socket
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any
from urllib.parse import urljoin, urlsplit, urlunsplit

import requests
import requests.adapters
import urllib3.connection
import urllib3.connectionpool
import urllib3.exceptions

from pipeline.errors import DataSourceError

log = logging.getLogger(__name__)

REQUEST_THREAD_NAME = "flowcast-request"
_WORKER_GRACE_S = 2.0  # a cancelled worker's last read returns at once; this only bounds a join
_REDIRECTS = (301, 302, 303, 307, 308)


@dataclass(frozen=True)
class TransportConfig:
    """How patiently a source is asked. Tests set ``backoff_base_s`` 0 so retries cost no time;
    each source's config extends this one (and may change a default)."""

    timeout_s: float = 30.0            # each socket read (and connect, capped below)
    connect_timeout_s: float = 10.0    # a connect: a portal answers one in well under a second
    request_deadline_s: float = 120.0  # one request, headers and body, wall clock
    fetch_deadline_s: float = 300.0    # one fetch: every request and retry, wall clock
    max_retries: int = 4
    backoff_base_s: float = 1.0
    backoff_max_s: float = 30.0
    retry_after_max_s: float = 120.0   # a longer Retry-After gives up at once (cache fallback)
    max_redirects: int = 5


@dataclass(frozen=True)
class Answer:
    """One HTTP answer: status, headers, the decoded body and the URL it came from."""

    status: int
    headers: Mapping[str, str]
    body: bytes
    url: str


class NetworkError(DataSourceError):
    """The source could not be reached (connection, timeout, 429/5xx after every retry)."""


class UnreachableError(NetworkError):
    """No connection could be made at all (refused, unknown host, no route): not retried, since
    seconds later the answer is the same; the caller uses its cache at once."""


class HTTPStatusError(DataSourceError):
    """The source answered with a status retrying cannot fix (a 4xx other than 429)."""

    def __init__(self, message: str, *, status: int, page: int = 0) -> None:
        super().__init__(message)
        self.status, self.page = status, page


class RedirectRefusedError(DataSourceError):
    """A redirect to another host, port or scheme (or to plain http): not followed."""


class _TransportProblem(Exception):
    """A retryable failure of one attempt (carries the message for the final error)."""


# ------------------------------------------------------------------------------ URL rules


def is_loopback(host: str | None) -> bool:
    if host in (None, ""):
        return False
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def redirect_allowed(origin_url: str, target_url: str) -> bool:
    """Same host and port, same scheme; https, or plain http only on a loopback mirror."""
    origin, target = urlsplit(origin_url), urlsplit(target_url)
    if (target.scheme, target.netloc.lower()) != (origin.scheme, origin.netloc.lower()):
        return False
    return target.scheme == "https" or is_loopback(target.hostname)


def token_allowed(url: str) -> bool:
    """A credential travels only over https (or to a loopback mirror)."""
    parts = urlsplit(url)
    return parts.scheme == "https" or is_loopback(parts.hostname)


def strip_query(url: str) -> str:
    parts = urlsplit(url)
    return urlunsplit((parts.scheme, parts.netloc, parts.path, "", ""))


def body_excerpt(body: bytes, limit: int = 300) -> str:
    text = body.decode("utf-8", errors="replace")
    return text[:limit] + ("…" if len(text) > limit else "")


def parse_retry_after(value: str | None, now: datetime | None = None) -> float | None:
    """Seconds to wait from a ``Retry-After`` header (delta-seconds or HTTP date); None if absent
    or unreadable."""
    if value is None or not value.strip():
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return max(0.0, (when - (now or datetime.now(UTC))).total_seconds())


def backoff_delay(config: TransportConfig, attempt: int) -> float:
    """Delay before retry ``attempt`` (1-based): base * 2**(attempt-1), capped."""
    return min(config.backoff_max_s, config.backoff_base_s * 2 ** (attempt - 1))


def _retryable_status(status: int) -> bool:
    return status == 429 or 500 <= status < 600


# ------------------------------------------------------------------------------ socket watch


class _RequestWatch:
    """The sockets one request's worker opened or reused, so the caller can shut them when the
    request deadline passes (a socket opened after that is shut as soon as it is registered)."""

    def __init__(self) -> None:
        self.cancelled = threading.Event()
        self._lock = threading.Lock()
        self._sockets: list[socket.socket] = []

    def add(self, sock: socket.socket | None) -> None:
        if sock is None:
            return
        with self._lock:
            self._sockets.append(sock)
            if self.cancelled.is_set():
                _shut(sock)

    def cancel(self) -> None:
        with self._lock:
            self.cancelled.set()
            for sock in self._sockets:
                _shut(sock)


def _shut(sock: socket.socket) -> None:
    # socket.socket's own shutdown, also for an SSLSocket: it acts on the descriptor, so the
    # worker's blocked read returns, and leaves the TLS state to the worker that owns it.
    with contextlib.suppress(OSError):
        socket.socket.shutdown(sock, socket.SHUT_RDWR)


_current_watch = threading.local()  # .watch: the _RequestWatch of this worker thread


def _register_socket(sock: socket.socket | None) -> None:
    watch = getattr(_current_watch, "watch", None)
    if watch is not None:
        watch.add(sock)


class _WatchedHTTPConnection(urllib3.connection.HTTPConnection):
    def connect(self) -> None:
        super().connect()
        _register_socket(self.sock)


class _WatchedHTTPSConnection(urllib3.connection.HTTPSConnection):
    def connect(self) -> None:
        super().connect()
        _register_socket(self.sock)


# (The ignores: urllib3 declares ConnectionCls as a Protocol type its own classes do not match
# to pyright's letter either; ours only add a line to connect.)
class _WatchedHTTPPool(urllib3.connectionpool.HTTPConnectionPool):
    ConnectionCls = _WatchedHTTPConnection  # pyright: ignore[reportAssignmentType]

    def _get_conn(self, timeout: float | None = None) -> Any:
        conn = super()._get_conn(timeout)
        _register_socket(getattr(conn, "sock", None))  # a reused keep-alive connection
        return conn


class _WatchedHTTPSPool(urllib3.connectionpool.HTTPSConnectionPool):
    ConnectionCls = _WatchedHTTPSConnection  # pyright: ignore[reportAssignmentType]

    def _get_conn(self, timeout: float | None = None) -> Any:
        conn = super()._get_conn(timeout)
        _register_socket(getattr(conn, "sock", None))
        return conn


class _WatchedAdapter(requests.adapters.HTTPAdapter):
    """requests' adapter with connection pools whose sockets a :class:`_RequestWatch` sees."""

    def init_poolmanager(self, *args: Any, **kwargs: Any) -> None:
        super().init_poolmanager(*args, **kwargs)
        self.poolmanager.pool_classes_by_scheme = {"http": _WatchedHTTPPool,
                                                   "https": _WatchedHTTPSPool}


# What a failing body read raises below requests (we read with urllib3's read1, see _read), and
# what requests would have wrapped it in: the names users know from requests.
_BODY_ERRORS: tuple[tuple[type[BaseException], type[requests.RequestException]], ...] = (
    (urllib3.exceptions.DecodeError, requests.exceptions.ContentDecodingError),
    (urllib3.exceptions.ReadTimeoutError, requests.exceptions.ConnectionError),
    (urllib3.exceptions.SSLError, requests.exceptions.SSLError),
    (urllib3.exceptions.ProtocolError, requests.exceptions.ChunkedEncodingError),
    (urllib3.exceptions.HTTPError, requests.exceptions.ConnectionError),
    (OSError, requests.exceptions.ConnectionError),
)


def _as_requests_error(exc: BaseException) -> BaseException:
    for low, high in _BODY_ERRORS:
        if isinstance(exc, low):
            return high(exc)
    return exc


def _connect_failure(error: requests.RequestException) -> str | None:
    """Why no connection could be made when the answer is definite (refused, unknown host, no
    route), or None for any other failure. A connect *timeout* is not definite (an overloaded
    host drops SYNs too), so it is retried like the rest, each try bounded by
    ``connect_timeout_s``."""
    for arg in error.args:
        # requests wraps urllib3's MaxRetryError, whose reason is the connection's own error
        # (NameResolutionError is a NewConnectionError).
        reason = getattr(arg, "reason", None)
        if isinstance(reason, urllib3.exceptions.NewConnectionError):
            return str(reason)
    return None


# ------------------------------------------------------------------------------ the transport


class Transport:
    """GETs to one origin (a source's base URL) under the rules of the module doc.

    ``source`` names the publisher in messages ("DataSF", "CHHS portal", "NHSN"). ``sleep`` and
    ``clock`` are injectable so tests can check the backoff schedule without waiting. A
    transport that created its own session closes it in :meth:`close` (no idle keep-alive socket
    outlives a fetch); a session passed in is the caller's to close."""

    def __init__(self, config: TransportConfig, *, source: str, origin: str,
                 session: requests.Session | None = None,
                 sleep: Callable[[float], None] = time.sleep,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config, self.source, self.origin = config, source, origin
        self.sleep, self.clock = sleep, clock
        self._owns_session = session is None
        self.session = session if session is not None else requests.Session()
        # Never a session default: requests would carry it along redirects it follows itself.
        self.session.headers.pop("X-App-Token", None)
        # Requests to the origin (redirects never leave it) go through sockets the request
        # deadline can shut (see _get_once).
        parts = urlsplit(origin)
        prefix = f"{parts.scheme}://{parts.netloc}/".lower()
        if not isinstance(self.session.adapters.get(prefix), _WatchedAdapter):
            self.session.mount(prefix, _WatchedAdapter())

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._owns_session:
            self.session.close()

    def deadline(self) -> float:
        """The wall-clock end of a fetch that starts now."""
        return self.clock() + self.config.fetch_deadline_s

    def backoff_delay(self, attempt: int) -> float:
        return backoff_delay(self.config, attempt)

    def get(self, url: str, *, deadline: float, max_bytes: int,
            params: Mapping[str, str] | None = None,
            headers: Mapping[str, str] | None = None) -> Answer:
        """The 200 answer to ``GET url?params``, retried as the module doc says; its body at most
        ``max_bytes`` after decoding."""
        full = requests.Request("GET", url, params=dict(params or {})).prepare().url or url
        attempts = self.config.max_retries + 1
        last_problem = "no attempt made"
        for attempt in range(1, attempts + 1):
            remaining = deadline - self.clock()
            if remaining <= 0:
                break
            retry_after = None
            try:
                answer = self._request(full, dict(headers or {}), max_bytes,
                                       min(self.config.request_deadline_s, remaining))
            except _TransportProblem as exc:
                last_problem = str(exc)
            else:
                if answer.status == 200:
                    return answer
                if not _retryable_status(answer.status):
                    raise HTTPStatusError(f"HTTP {answer.status} from {answer.url}: "
                                          f"{body_excerpt(answer.body)!r}", status=answer.status)
                last_problem = f"HTTP {answer.status}: {body_excerpt(answer.body)!r}"
                retry_after = parse_retry_after(answer.headers.get("Retry-After"))
                if retry_after is not None:
                    last_problem += f" (Retry-After {retry_after:.0f} s)"
            if attempt == attempts:
                break
            self._wait_before_retry(url, attempt, retry_after, deadline, last_problem)
        if self.clock() >= deadline:
            raise NetworkError(f"{url}: fetch deadline of {self.config.fetch_deadline_s:g} s "
                               f"passed; last: {last_problem}")
        raise NetworkError(f"{url} failed after {attempts} attempts; last: {last_problem}")

    def _wait_before_retry(self, url: str, attempt: int, retry_after: float | None,
                           deadline: float, last_problem: str) -> None:
        if retry_after is not None and retry_after > self.config.retry_after_max_s:
            raise NetworkError(f"{url}: {self.source} asks to retry after {retry_after:.0f} s, "
                               f"more than the {self.config.retry_after_max_s:.0f} s we wait; "
                               f"last: {last_problem}")
        delay = max(self.backoff_delay(attempt), retry_after or 0.0)
        if self.clock() + delay >= deadline:
            raise NetworkError(f"{url}: fetch deadline of {self.config.fetch_deadline_s:g} s "
                               f"would pass before retry {attempt} (in {delay:.0f} s); last: "
                               f"{last_problem}")
        log.warning("%s %s: %s; retry %d/%d in %.1f s", self.source, url, last_problem, attempt,
                    self.config.max_retries, delay)
        self.sleep(delay)

    def _request(self, url: str, headers: dict[str, str], max_bytes: int,
                 budget_s: float) -> Answer:
        """One GET with hand-followed, same-origin redirects, within ``budget_s`` seconds."""
        until = self.clock() + budget_s
        current = url
        for _hop in range(self.config.max_redirects + 1):
            answer = self._get_once(current, headers, max_bytes, until, budget_s)
            if answer.status not in _REDIRECTS:
                return answer
            location = answer.headers.get("Location")
            if not location:
                raise DataSourceError(f"HTTP {answer.status} from {current} without a Location")
            target = urljoin(current, location)
            if not redirect_allowed(self.origin, target):
                raise RedirectRefusedError(
                    f"{current} redirects (HTTP {answer.status}) to {target}: refused, only "
                    f"redirects to the same https host ({urlsplit(self.origin).netloc}) are "
                    f"followed; nothing was sent there")
            log.info("%s redirect %s -> %s", self.source, current, target)
            current = target
        raise DataSourceError(f"{url}: more than {self.config.max_redirects} redirects")

    def _get_once(self, url: str, headers: dict[str, str], max_bytes: int, until: float,
                  budget_s: float) -> Answer:
        """Run :meth:`_read` in a worker thread and stop waiting at ``until``.

        The body loop checks the deadline itself; the thread also bounds the header phase, which
        ``requests`` reads with per-read timeouts only. A late worker has its sockets shut, so
        it ends at once; its answer is discarded.
        """
        outcome: dict[str, object] = {}
        watch = _RequestWatch()

        def work() -> None:
            _current_watch.watch = watch
            try:
                outcome["answer"] = self._read(url, headers, max_bytes, until, watch.cancelled)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                outcome["error"] = exc
            finally:
                _current_watch.watch = None

        worker = threading.Thread(target=work, name=REQUEST_THREAD_NAME, daemon=True)
        worker.start()
        worker.join(max(0.0, until - self.clock()) + 0.05)
        if worker.is_alive():
            # Shut its sockets: a read blocked on a server that drips bytes (headers included)
            # returns at once, so the worker ends now instead of living on after the fetch gave
            # up (issues 22 and 32: threads and their sockets alive 15 s later).
            watch.cancel()
            worker.join(_WORKER_GRACE_S)
            if worker.is_alive():
                log.warning("%s request thread for %s still running %.0f s after its deadline "
                            "(blocked outside a socket read)", self.source, url, _WORKER_GRACE_S)
            raise _TransportProblem(f"no complete answer from {url} within the request deadline "
                                    f"of {budget_s:.1f} s")
        return self._outcome(url, outcome)

    @staticmethod
    def _outcome(url: str, outcome: dict[str, object]) -> Answer:
        error = outcome.get("error")
        if isinstance(error, _TransportProblem | DataSourceError):
            raise error
        if isinstance(error, requests.RequestException):
            failure = _connect_failure(error)
            if failure is not None:
                raise UnreachableError(f"cannot connect to {urlsplit(url).netloc} ({failure}); "
                                       f"not retried") from error
            raise _TransportProblem(f"{type(error).__name__}: {error}") from error
        if isinstance(error, BaseException):
            raise error
        answer = outcome["answer"]
        assert isinstance(answer, Answer)
        return answer

    def _read(self, url: str, headers: dict[str, str], max_bytes: int, until: float,
              cancel: threading.Event) -> Answer:
        remaining = max(0.001, until - self.clock())
        timeout = (min(self.config.connect_timeout_s, self.config.timeout_s, remaining),
                   min(self.config.timeout_s, remaining))
        with self.session.get(url, headers=headers, timeout=timeout, stream=True,
                              allow_redirects=False) as response:
            chunks: list[bytes] = []
            size = 0
            while response.status_code not in _REDIRECTS:
                if cancel.is_set() or self.clock() > until:
                    raise _TransportProblem(f"no complete answer from {url} within the request "
                                            f"deadline ({size} bytes of the body so far)")
                try:
                    # read1 returns as soon as any bytes arrive, so the deadline is checked
                    # between trickled bytes too (read(n) would block until n bytes).
                    # decode_content: with stream=True requests leaves gzip/deflate to the
                    # reader (its iter_content passes True); a bad body raises DecodeError here.
                    chunk = response.raw.read1(1 << 16, decode_content=True)
                except Exception as exc:
                    raise _as_requests_error(exc) from exc
                if not chunk:
                    break
                size += len(chunk)
                if size > max_bytes:
                    raise DataSourceError(f"{url}: body larger than {max_bytes:,} bytes (after "
                                          f"decoding); refused")
                chunks.append(chunk)
            return Answer(response.status_code, dict(response.headers), b"".join(chunks),
                          response.url)
