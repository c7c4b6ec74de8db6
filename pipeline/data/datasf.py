"""DataSF (data.sfgov.org, a Socrata portal) dataset specs and the SODA 2.x JSON client.

Three San Francisco COVID-19 datasets feed the forecast (paper, section "COVID-19 Dataset"):
cases over time ``gyr2-k29z``, deaths over time ``g2di-xufg`` and tests over time ``nfpa-mg4g``.
Each is described by a :class:`DatasetSpec` that knows its field names in both forms DataSF
publishes: the JSON API (snake_case, every value a string) and the full CSV export (display names
such as "Specimen Collection Date", US dates, unsorted rows).

Field names changed between DataSF vintages (the later "COVID-19 Testing Over Time" export has
``DATE, tests, pos, neg, indet``); every name a field has carried is listed on its
:class:`FieldSpec` (``aliases``), so each known schema is read, and an unknown one fails naming the
columns it has and the ones it needs (:func:`describe_schema`).

The client pages with ``$limit``/``$offset`` under a fixed ``$order`` (Socrata gives no stable
order without one, so pages could overlap or skip rows). Transport rules, each because a
fault-injection probe broke the previous client (issue 15):

* every ``requests``/``urllib3`` failure (dropped connection mid-body, bad gzip, timeouts, ...)
  is retried with exponential backoff, as are HTTP 429 and 5xx; after the last attempt a
  :class:`NetworkError`, on which the caller falls back to the cache;
* deadlines are wall-clock: one per request (``request_deadline_s``, headers *and* body, so a
  server trickling a byte a second cannot hold a fetch) and one per dataset fetch
  (``fetch_deadline_s``, all pages and retries); ``timeout_s`` only bounds each socket read;
* ``Retry-After`` (seconds or an HTTP date) is honoured, never shortened by the backoff;
* redirects are followed by hand, only to the same host with the same scheme (https, or plain
  http on a loopback mirror); anything else is refused, so the app token never leaves the host
  it was meant for. The token is a per-request header, never a session default (requests keeps
  session headers across redirects), and is not sent over plain http to a remote host;
* the final URL (after redirects) is returned, and recorded in the cache manifest.

And because the probe of issue 22 broke those: a connection that cannot be made at all
(refused, unknown host, no route) raises :class:`UnreachableError` at once, never retried; a
request past its deadline has its sockets shut so its worker thread ends with it; paging stops
at the first repeated page and when the pages pass ``max_fetch_bytes``; every page is decoded at
the boundary of :mod:`pipeline.data.decoding` (any decoder exception -> one named rejection).

A 4xx other than 429 is not retried: it means the request itself is wrong (bad dataset id, bad
query), so the error names status, URL and body. Base URL and token come from the environment
(``FLOWCAST_DATASF_BASE_URL``, ``FLOWCAST_DATASF_APP_TOKEN``) unless given in
:class:`ClientConfig` (``flowcast data fetch --base-url/--app-token``, the flow's
``datasf_base_url`` parameter).
"""
from __future__ import annotations

import contextlib
import email.utils
import hashlib
import ipaddress
import json
import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any
from urllib.parse import urljoin, urlsplit, urlunsplit

import requests
import requests.adapters
import urllib3.connection
import urllib3.connectionpool
import urllib3.exceptions

from pipeline.data.decoding import MAX_PAYLOAD_BYTES, decode_json_records
from pipeline.data.plausibility import PlausibilityRule
from pipeline.errors import DataSourceError

log = logging.getLogger(__name__)

APP_TOKEN_ENV = "FLOWCAST_DATASF_APP_TOKEN"
BASE_URL_ENV = "FLOWCAST_DATASF_BASE_URL"
DEFAULT_BASE_URL = "https://data.sfgov.org"

# San Francisco's population (2020 Census): the scale of every DataSF count (S/I/R conversion,
# plausibility of a day's count).
SF_POPULATION_2020_CENSUS = 873_965
SF_PLAUSIBILITY = PlausibilityRule(population=SF_POPULATION_2020_CENSUS)

# Date formats seen in DataSF payloads: API floating timestamps, CSV-export US timestamps,
# and the slash-ISO form of the tests export.
API_DATE_FORMATS = ("%Y-%m-%dT%H:%M:%S.%f", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d")
CSV_DATE_FORMATS = ("%m/%d/%Y %I:%M:%S %p", "%Y/%m/%d", "%m/%d/%Y", "%Y-%m-%d")


@dataclass(frozen=True)
class FieldSpec:
    """One column: canonical name used inside flowcast, its API name, its CSV display name, and
    any other name it carried in some DataSF vintage (``aliases``). Matching is case- and
    surrounding-space-insensitive, so ``DATE`` and ``date`` are one name."""

    canonical: str
    api: str
    display: str
    aliases: tuple[str, ...] = ()

    def names(self) -> tuple[str, ...]:
        return (self.canonical, self.api, self.display, *self.aliases)

    def describe(self) -> str:
        """``'New Cases' (new_cases)``; with aliases ``'Indeterminate' (indeterminate|indet)``."""
        others = dict.fromkeys(n for n in (self.api, *self.aliases) if n != self.display)
        return f"'{self.display}'" + (f" ({'|'.join(others)})" if others else "")


@dataclass(frozen=True)
class DatasetSpec:
    """A DataSF daily time series: one row per date, non-negative integer counts.

    ``cumulative`` (when present) is the running total of ``cumulative_of``; validation checks
    the two agree. ``as_of`` is the timestamp DataSF stamps on every row (its data vintage).
    """

    key: str
    dataset_id: str
    title: str
    date: FieldSpec
    counts: tuple[FieldSpec, ...]
    cumulative: FieldSpec | None = None
    cumulative_of: str | None = None
    as_of: tuple[FieldSpec, ...] = ()
    date_formats: tuple[str, ...] = API_DATE_FORMATS + CSV_DATE_FORMATS

    @property
    def required(self) -> tuple[FieldSpec, ...]:
        extra = (self.cumulative,) if self.cumulative is not None else ()
        return (self.date, *self.counts, *extra)

    @property
    def count_columns(self) -> tuple[str, ...]:
        return tuple(f.canonical for f in self.counts)

    def resource_url(self, base_url: str = DEFAULT_BASE_URL) -> str:
        return f"{base_url.rstrip('/')}/resource/{self.dataset_id}.json"

    def export_url(self, base_url: str = DEFAULT_BASE_URL) -> str:
        return f"{base_url.rstrip('/')}/api/views/{self.dataset_id}/rows.csv?accessType=DOWNLOAD"


_AS_OF = FieldSpec("data_as_of", "data_as_of", "Data As Of")
_LOADED = FieldSpec("data_loaded_at", "data_loaded_at", "Data Loaded At")

CASES = DatasetSpec(
    key="cases", dataset_id="gyr2-k29z", title="COVID-19 Cases Over Time",
    date=FieldSpec("date", "specimen_collection_date", "Specimen Collection Date"),
    counts=(FieldSpec("new_cases", "new_cases", "New Cases"),),
    cumulative=FieldSpec("cumulative_cases", "cumulative_cases", "Cumulative Cases"),
    cumulative_of="new_cases", as_of=(_AS_OF, _LOADED))

DEATHS = DatasetSpec(
    key="deaths", dataset_id="g2di-xufg", title="COVID-19 Deaths Over Time",
    date=FieldSpec("date", "date_of_death", "Date of Death"),
    counts=(FieldSpec("new_deaths", "new_deaths", "New Deaths"),),
    cumulative=FieldSpec("cumulative_deaths", "cumulative_deaths", "Cumulative Deaths"),
    cumulative_of="new_deaths", as_of=(_AS_OF, _LOADED))

# The tests export already uses API names for most columns; "pct" is derived (pos/(pos+neg))
# and is recomputed by flowcast, so it is not required. Its later export ("COVID-19 Testing Over
# Time") renamed the date to ``DATE`` and ``indeterminate`` to ``indet`` and dropped ``pct``.
TESTS = DatasetSpec(
    key="tests", dataset_id="nfpa-mg4g", title="COVID-19 Testing Over Time",
    date=FieldSpec("date", "specimen_collection_date", "Specimen Collection Date",
                   aliases=("DATE",)),
    counts=(FieldSpec("tests", "tests", "Tests"),
            FieldSpec("positives", "pos", "Pos"),
            FieldSpec("negatives", "neg", "Neg"),
            FieldSpec("indeterminate", "indeterminate", "Indeterminate", aliases=("indet",))),
    as_of=(FieldSpec("data_as_of", "last_updated_at", "Last Updated At",
                     aliases=("data_as_of", "Data As Of")), _LOADED))

DATASETS: dict[str, DatasetSpec] = {s.key: s for s in (CASES, DEATHS, TESTS)}
DATASETS_BY_ID: dict[str, DatasetSpec] = {s.dataset_id: s for s in DATASETS.values()}


def describe_schema(spec: DatasetSpec) -> str:
    """What ``spec`` needs, every accepted name listed: for errors about unknown schemas."""
    return (f"{spec.key} ({spec.dataset_id}) needs "
            + ", ".join(f.describe() for f in spec.required))


def default_base_url() -> str:
    """``$FLOWCAST_DATASF_BASE_URL`` (a mirror or proxy), else data.sfgov.org."""
    return os.environ.get(BASE_URL_ENV, "").strip() or DEFAULT_BASE_URL


@dataclass(frozen=True)
class ClientConfig:
    """How to talk to DataSF. Tests set ``backoff_base_s`` ~0 so retries cost no time.

    ``app_token`` overrides ``$<app_token_env>``; it is kept out of ``repr`` so it never reaches
    a log line or a provenance file.
    """

    base_url: str = field(default_factory=default_base_url)
    page_size: int = 1000
    timeout_s: float = 30.0            # each socket read (and connect, capped below)
    connect_timeout_s: float = 10.0    # a connect: DataSF answers one in well under a second
    request_deadline_s: float = 120.0  # one request, headers and body, wall clock
    fetch_deadline_s: float = 300.0    # one dataset: every page and retry, wall clock
    max_retries: int = 4
    backoff_base_s: float = 1.0
    backoff_max_s: float = 30.0
    retry_after_max_s: float = 120.0   # a longer Retry-After gives up at once (cache fallback)
    max_redirects: int = 5
    max_body_bytes: int = MAX_PAYLOAD_BYTES  # one body; a daily series is < 1 MB
    max_fetch_bytes: int = MAX_PAYLOAD_BYTES  # all pages of one dataset together (bounds memory)
    app_token_env: str = APP_TOKEN_ENV
    app_token: str | None = field(default=None, repr=False)
    max_pages: int = 1000  # a daily series has < 2,000 rows; this only stops a runaway loop

    def __post_init__(self) -> None:
        parts = urlsplit(self.base_url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            hint = (f"; did you mean 'https://{self.base_url.strip().lstrip('/')}'?"
                    if "://" not in self.base_url and self.base_url.strip() else "")
            raise DataSourceError(f"DataSF base URL must be http(s)://host[/path], got "
                                  f"{self.base_url!r} (--base-url / ${BASE_URL_ENV}){hint}")

    def token(self) -> str | None:
        token = self.app_token if self.app_token is not None else os.environ.get(
            self.app_token_env, "")
        return token.strip() or None


@dataclass(frozen=True)
class FetchResult:
    """All rows of one dataset (as returned, strings) plus the exact bytes to cache.

    ``url`` is the resource asked for; ``final_url`` where the answer came from after redirects
    (query string dropped: it only held the paging)."""

    spec: DatasetSpec
    url: str
    rows: list[dict[str, object]]
    payload: bytes
    pages: int
    final_url: str = ""


@dataclass(frozen=True)
class _Answer:
    status: int
    headers: Mapping[str, str]
    body: bytes
    url: str


class NetworkError(DataSourceError):
    """DataSF could not be reached (connection, timeout, 429/5xx after every retry)."""


class UnreachableError(NetworkError):
    """No connection could be made at all (refused, unknown host, no route, connect timeout):
    not retried, since seconds later the answer is the same; the run uses the cache at once."""


class HTTPStatusError(DataSourceError):
    """DataSF answered with a status that retrying cannot fix (a 4xx other than 429)."""

    def __init__(self, message: str, *, status: int, page: int = 0) -> None:
        super().__init__(message)
        self.status, self.page = status, page


class RedirectRefusedError(DataSourceError):
    """DataSF redirected somewhere the client does not follow (another host, or http)."""


REQUEST_THREAD_NAME = "datasf-request"
_WORKER_GRACE_S = 2.0  # a cancelled worker's last read returns at once; this only bounds a join


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


class _TransportProblem(Exception):
    """A retryable failure of one attempt (carries the message for the final error)."""


_REDIRECTS = (301, 302, 303, 307, 308)


def _retryable_status(status: int) -> bool:
    return status == 429 or 500 <= status < 600


def _body_excerpt(body: bytes, limit: int = 300) -> str:
    text = body.decode("utf-8", errors="replace")
    return text[:limit] + ("…" if len(text) > limit else "")


def _is_loopback(host: str | None) -> bool:
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
    return target.scheme == "https" or _is_loopback(target.hostname)


def token_allowed(url: str) -> bool:
    """The app token travels only over https (or to a loopback mirror)."""
    parts = urlsplit(url)
    return parts.scheme == "https" or _is_loopback(parts.hostname)


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


def _strip_query(url: str) -> str:
    parts = urlsplit(url)
    return urlunsplit((parts.scheme, parts.netloc, parts.path, "", ""))


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


@dataclass
class DataSFClient:
    """Paginated, retrying, deadline-bound reader of DataSF JSON resources.

    ``sleep`` is injectable so tests can check the backoff schedule without waiting.
    """

    config: ClientConfig = field(default_factory=ClientConfig)
    session: requests.Session | None = None
    sleep: Callable[[float], None] = time.sleep
    clock: Callable[[], float] = time.monotonic

    def __post_init__(self) -> None:
        self._owns_session = self.session is None
        if self.session is None:
            self.session = requests.Session()
        # Never a session default: requests would carry it along redirects it follows itself.
        self.session.headers.pop("X-App-Token", None)
        # Requests to the base URL's origin (redirects never leave it) go through sockets the
        # request deadline can shut (see _get_once).
        origin = urlsplit(self.config.base_url)
        prefix = f"{origin.scheme}://{origin.netloc}/".lower()
        if not isinstance(self.session.adapters.get(prefix), _WatchedAdapter):
            self.session.mount(prefix, _WatchedAdapter())

    def backoff_delay(self, attempt: int) -> float:
        """Delay before retry ``attempt`` (1-based): base * 2**(attempt-1), capped."""
        return min(self.config.backoff_max_s, self.config.backoff_base_s * 2 ** (attempt - 1))

    def fetch(self, spec: DatasetSpec) -> FetchResult:
        """Every row of ``spec``'s dataset, ordered by date, in pages of ``page_size``.

        The order field is the date's API name; if DataSF answers the first page with HTTP 400
        (no such column: a later schema renamed it), each alias is tried in turn.
        """
        try:
            return self._fetch_orders(spec)
        finally:
            if self._owns_session:
                assert self.session is not None
                self.session.close()  # no idle keep-alive socket outlives the fetch either

    def _fetch_orders(self, spec: DatasetSpec) -> FetchResult:
        orders = list(dict.fromkeys((spec.date.api, *(a.lower() for a in spec.date.aliases))))
        for order in orders:
            try:
                return self._fetch_ordered(spec, order)
            except HTTPStatusError as exc:
                if exc.status != 400 or exc.page != 0 or order == orders[-1]:
                    raise
                log.warning("DataSF %s: ordering by %s refused (%s); trying %s", spec.key, order,
                            exc, orders[orders.index(order) + 1])
        raise AssertionError("unreachable")  # pragma: no cover

    def _fetch_ordered(self, spec: DatasetSpec, order: str) -> FetchResult:
        url = spec.resource_url(self.config.base_url)
        deadline = self.clock() + self.config.fetch_deadline_s
        rows: list[dict[str, object]] = []
        final_url = ""
        pages = _PageLedger(url, self.config.page_size, self.config.max_fetch_bytes)
        for page in range(self.config.max_pages):
            params = {"$limit": str(self.config.page_size),
                      "$offset": str(page * self.config.page_size),
                      "$order": f"{order} ASC"}
            try:
                batch, answered_from, body = self._get_page(url, params, deadline)
            except HTTPStatusError as exc:
                raise HTTPStatusError(str(exc), status=exc.status, page=page) from exc
            pages.add(page, body)
            final_url = final_url or _strip_query(answered_from)
            rows.extend(batch)
            if len(batch) < self.config.page_size:
                payload = json.dumps(rows, separators=(",", ":")).encode("utf-8")
                return FetchResult(spec, url, rows, payload, page + 1, final_url)
        raise DataSourceError(f"{url}: more than {self.config.max_pages} pages; stopping")

    def _get_page(self, url: str, params: dict[str, str], deadline: float
                  ) -> tuple[list[dict[str, object]], str, bytes]:
        attempts = self.config.max_retries + 1
        last_problem = "no attempt made"
        for attempt in range(1, attempts + 1):
            remaining = deadline - self.clock()
            if remaining <= 0:
                break
            retry_after = None
            try:
                answer = self._request(url, params, min(self.config.request_deadline_s,
                                                        remaining))
            except _TransportProblem as exc:
                last_problem = str(exc)
            else:
                if answer.status == 200:
                    rows = decode_json_records(answer.body, source=answer.url,
                                               max_bytes=self.config.max_body_bytes)
                    return rows, answer.url, answer.body
                if not _retryable_status(answer.status):
                    raise HTTPStatusError(f"HTTP {answer.status} from {answer.url}: "
                                          f"{_body_excerpt(answer.body)!r}", status=answer.status)
                last_problem = f"HTTP {answer.status}: {_body_excerpt(answer.body)!r}"
                retry_after = parse_retry_after(answer.headers.get("Retry-After"))
                if retry_after is not None:
                    last_problem += f" (Retry-After {retry_after:.0f} s)"
            if attempt == attempts:
                break
            delay = max(self.backoff_delay(attempt), retry_after or 0.0)
            if retry_after is not None and retry_after > self.config.retry_after_max_s:
                raise NetworkError(f"{url}: DataSF asks to retry after {retry_after:.0f} s, more "
                                   f"than the {self.config.retry_after_max_s:.0f} s we wait; "
                                   f"last: {last_problem}")
            if self.clock() + delay >= deadline:
                raise NetworkError(f"{url}: fetch deadline of {self.config.fetch_deadline_s:.0f}"
                                   f" s would pass before retry {attempt} (in {delay:.0f} s); "
                                   f"last: {last_problem}")
            log.warning("DataSF %s (offset %s): %s; retry %d/%d in %.1f s", url,
                        params["$offset"], last_problem, attempt, attempts - 1, delay)
            self.sleep(delay)
        if self.clock() >= deadline:
            raise NetworkError(f"{url}: fetch deadline of {self.config.fetch_deadline_s:.0f} s "
                               f"passed; last: {last_problem}")
        raise NetworkError(f"{url} failed after {attempts} attempts; last: {last_problem}")

    def _request(self, url: str, params: dict[str, str], budget_s: float) -> _Answer:
        """One GET with hand-followed, same-origin redirects, within ``budget_s`` seconds."""
        current = requests.Request("GET", url, params=params).prepare().url or url
        until = self.clock() + budget_s
        token = self.config.token()
        for _hop in range(self.config.max_redirects + 1):
            headers = {"Accept": "application/json"}
            if token is not None:
                if token_allowed(current):
                    headers["X-App-Token"] = token
                else:
                    log.warning("DataSF app token not sent to %s over plain http", current)
            answer = self._get_once(current, headers, until, budget_s)
            if answer.status not in _REDIRECTS:
                return answer
            location = answer.headers.get("Location")
            if not location:
                raise DataSourceError(f"HTTP {answer.status} from {current} without a Location")
            target = urljoin(current, location)
            if not redirect_allowed(url, target):
                raise RedirectRefusedError(
                    f"{current} redirects (HTTP {answer.status}) to {target}: refused, only "
                    f"redirects to the same https host ({urlsplit(url).netloc}) are followed; the "
                    f"app token was not sent there")
            log.info("DataSF redirect %s -> %s", current, target)
            current = target
        raise DataSourceError(f"{url}: more than {self.config.max_redirects} redirects")

    def _get_once(self, url: str, headers: dict[str, str], until: float,
                  budget_s: float) -> _Answer:
        """Run :meth:`_read` in a worker thread and stop waiting at ``until``.

        The body loop checks the deadline itself; the thread also bounds the header phase, which
        ``requests`` reads with per-read timeouts only. A late worker is told to stop and ends at
        its next read (at most ``timeout_s`` later); its answer is discarded.
        """
        outcome: dict[str, object] = {}
        watch = _RequestWatch()

        def work() -> None:
            _current_watch.watch = watch
            try:
                outcome["answer"] = self._read(url, headers, until, watch.cancelled)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                outcome["error"] = exc
            finally:
                _current_watch.watch = None

        worker = threading.Thread(target=work, name=REQUEST_THREAD_NAME, daemon=True)
        worker.start()
        worker.join(max(0.0, until - self.clock()) + 0.05)
        if worker.is_alive():
            # Shut its sockets: a read blocked on a server that drips bytes (headers included,
            # which requests reads with per-read timeouts only) returns at once, so the worker
            # ends now instead of living on after the fetch gave up (issue 22: 4 threads and
            # their sockets 15 s later).
            watch.cancel()
            worker.join(_WORKER_GRACE_S)
            if worker.is_alive():
                log.warning("DataSF request thread for %s still running %.0f s after its "
                            "deadline (blocked outside a socket read)", url, _WORKER_GRACE_S)
            raise _TransportProblem(f"no complete answer from {url} within the request deadline "
                                    f"of {budget_s:.0f} s")
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
        assert isinstance(answer, _Answer)
        return answer

    def _read(self, url: str, headers: dict[str, str], until: float,
              cancel: threading.Event) -> _Answer:
        assert self.session is not None
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
                if size > self.config.max_body_bytes:
                    raise DataSourceError(f"{url}: body larger than "
                                          f"{self.config.max_body_bytes} bytes; refused")
                chunks.append(chunk)
            return _Answer(response.status_code, dict(response.headers), b"".join(chunks),
                           response.url)


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


def _as_requests_error(exc: BaseException) -> BaseException:
    for low, high in _BODY_ERRORS:
        if isinstance(exc, low):
            return high(exc)
    return exc


class _PageLedger:
    """What the pages of one fetch have cost so far: stops a server that ignores ``$offset``
    at its first repeated page (it would otherwise serve the same page until ``max_pages``,
    1.27 GB in the probe) and any fetch whose pages together pass ``max_bytes``."""

    def __init__(self, url: str, page_size: int, max_bytes: int) -> None:
        self.url, self.page_size, self.max_bytes = url, page_size, max_bytes
        self.first_page_of: dict[str, int] = {}
        self.total = 0

    def add(self, page: int, body: bytes) -> None:
        self.total += len(body)
        if self.total > self.max_bytes:
            raise DataSourceError(f"{self.url}: pages 0…{page} hold {self.total:,} bytes, more "
                                  f"than the {self.max_bytes:,} one dataset may have; stopping")
        digest = hashlib.sha256(body).hexdigest()
        earlier = self.first_page_of.setdefault(digest, page)
        if earlier != page and body.strip() not in (b"[]", b""):
            raise DataSourceError(
                f"{self.url}: the page at $offset={page * self.page_size} repeats the page at "
                f"$offset={earlier * self.page_size} (the server ignores $offset?); stopping")
