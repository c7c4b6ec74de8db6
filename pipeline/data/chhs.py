"""Client of the California Health and Human Services open data portal (data.chhs.ca.gov, CKAN).

CDPH publishes "COVID-19 Time-Series Metrics by County and State" there as CKAN dataset
``covid-19-time-series-metrics-by-county-and-state`` (package id
``f333528b-4d38-4814-bebb-12db1f10f535``); the county file is the resource
``046cdd2b-31e5-4d34-9ed3-b48cdbc4be7a`` whose download URL ends in ``covid19cases_test.csv``
(its CKAN *name* is a title, "Statewide COVID-19 Cases Deaths Tests", so the resource is found by
id, then by the file name of its URL, then by name). A fetch is two requests:

1. ``GET <base>/api/3/action/package_show?id=<dataset>`` → ``{"success": true, "result":
   {"resources": [{"id", "name", "url", "last_modified", ...}, ...]}}``;
2. ``GET <resource url>``: the CSV bytes, parsed by :func:`pipeline.data.cdph.parse_cdph_csv`.

Transport discipline, the same as the DataSF client (:mod:`pipeline.data.datasf`):

* every ``requests``/``urllib3`` failure (refused connection, dropped or truncated body, bad gzip,
  timeouts) and HTTP 429/5xx is retried with exponential backoff (``Retry-After`` honoured, never
  shortened; one longer than ``retry_after_max_s`` gives up at once); after the last attempt a
  :class:`CHHSNetworkError`, on which the loader falls back to the cache;
* wall-clock deadlines per request (headers *and* body; a server dripping bytes cannot hold a
  fetch) and per fetch (both requests and every retry); ``timeout_s`` bounds each socket read;
* bodies are limited (``max_metadata_bytes`` for the JSON, ``max_body_bytes`` for the CSV, counted
  after gzip decoding, so a gzip bomb stops at the limit);
* redirects are followed by hand, only to the same scheme and host (https, or plain http on a
  loopback mirror) as the base URL; the resource URL that CKAN names must be on that host too.
  Anything else is a :class:`CHHSRedirectRefusedError`;
* an HTML page where the CSV belongs (a maintenance or login page) is named as such.

A 4xx other than 429 is not retried (:class:`CHHSHTTPStatusError`). The base URL is
``CHHSClientConfig.base_url``, else ``$FLOWCAST_CHHS_BASE_URL`` (read when a fetch starts, never
at import), else https://data.chhs.ca.gov; one without ``http(s)://host`` is a
:class:`~pipeline.errors.ConfigError` when used.
"""
from __future__ import annotations

import json
import logging
import os
import posixpath
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from urllib.parse import urlencode, urljoin, urlsplit, urlunsplit

import requests

from pipeline.data.datasf import parse_retry_after, redirect_allowed
from pipeline.data.decoding import PayloadRejectedError, decode_boundary
from pipeline.errors import ConfigError, DataSourceError

log = logging.getLogger(__name__)

BASE_URL_ENV = "FLOWCAST_CHHS_BASE_URL"
DEFAULT_BASE_URL = "https://data.chhs.ca.gov"
CACHE_FOLDER = "chhs"


@dataclass(frozen=True)
class CKANResourceSpec:
    """One file of a CKAN dataset. ``key``/``dataset_id``/``cache_folder`` place it in the cache
    (:class:`pipeline.data.cache.DatasetCache`): ``<data dir>/chhs/<dataset_id>/``."""

    key: str
    dataset_id: str           # the CKAN package name (``package_show?id=``)
    resource_name: str        # the file name of the resource's download URL
    title: str
    resource_id: str = ""     # the CKAN resource id, when known (matched first)
    package_uuid: str = ""
    cache_folder: str = CACHE_FOLDER

    def package_show_url(self, base_url: str) -> str:
        return (f"{base_url.rstrip('/')}/api/3/action/package_show?"
                + urlencode({"id": self.dataset_id}))

    def portal_url(self, base_url: str = DEFAULT_BASE_URL) -> str:
        return f"{base_url.rstrip('/')}/dataset/{self.dataset_id}"

    def download_url(self, base_url: str = DEFAULT_BASE_URL) -> str:
        """The usual download address (for messages; fetches ask CKAN for the current one)."""
        return (f"{base_url.rstrip('/')}/dataset/{self.package_uuid or self.dataset_id}/resource/"
                f"{self.resource_id}/download/{self.resource_name}")


CDPH_COUNTIES = CKANResourceSpec(
    key="cdph-counties", dataset_id="covid-19-time-series-metrics-by-county-and-state",
    resource_name="covid19cases_test.csv",
    title="COVID-19 Time-Series Metrics by County and State (CDPH)",
    resource_id="046cdd2b-31e5-4d34-9ed3-b48cdbc4be7a",
    package_uuid="f333528b-4d38-4814-bebb-12db1f10f535")


def resolve_base_url(explicit: str | None = None) -> str:
    """``explicit``, else ``$FLOWCAST_CHHS_BASE_URL``, else data.chhs.ca.gov; checked here (at
    use), so a bad value fails the command that uses it, never an import."""
    value = (explicit if explicit is not None else os.environ.get(BASE_URL_ENV, "")).strip()
    value = value or DEFAULT_BASE_URL
    parts = urlsplit(value)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        where = "CHHSClientConfig.base_url / --chhs-base-url" if explicit is not None \
            else f"${BASE_URL_ENV}"
        raise ConfigError(f"CHHS portal base URL must be http(s)://host[/path], got {value!r} "
                          f"({where})")
    return value


@dataclass(frozen=True)
class CHHSClientConfig:
    """How to talk to the CHHS portal. Tests set ``backoff_base_s`` 0 so retries cost no time."""

    base_url: str | None = None         # None: $FLOWCAST_CHHS_BASE_URL or data.chhs.ca.gov
    timeout_s: float = 30.0             # connect, and each socket read
    request_deadline_s: float = 300.0   # one request, headers and body, wall clock
    fetch_deadline_s: float = 900.0     # metadata + CSV, every retry, wall clock
    max_retries: int = 4
    backoff_base_s: float = 1.0
    backoff_max_s: float = 30.0
    retry_after_max_s: float = 120.0
    max_redirects: int = 5
    max_metadata_bytes: int = 4 << 20
    max_body_bytes: int = 512 << 20     # the county file was 4 MB in 2021, ~20 MB by 2023


@dataclass(frozen=True)
class CKANResource:
    id: str
    name: str
    url: str
    last_modified: str | None


@dataclass(frozen=True)
class CHHSFetch:
    """One download: the resource CKAN named, where the bytes came from, and the bytes."""

    spec: CKANResourceSpec
    package_url: str
    resource: CKANResource
    final_url: str
    payload: bytes


class CHHSNetworkError(DataSourceError):
    """The portal could not be reached (connection, timeout, 429/5xx after every retry)."""


class CHHSHTTPStatusError(DataSourceError):
    """The portal answered with a status retrying cannot fix (a 4xx other than 429)."""

    def __init__(self, message: str, *, status: int) -> None:
        super().__init__(message)
        self.status = status


class CHHSRedirectRefusedError(DataSourceError):
    """A redirect or resource URL to another host or scheme: not followed."""


class CKANResponseError(DataSourceError):
    """package_show answered, but not with the dataset and resource expected."""


class _Retry(Exception):
    """A retryable failure of one attempt (its message goes into the final error)."""


@dataclass(frozen=True)
class _Answer:
    status: int
    headers: Mapping[str, str]
    body: bytes
    url: str


_REDIRECTS = (301, 302, 303, 307, 308)


def _excerpt(body: bytes, limit: int = 200) -> str:
    text = body.decode("utf-8", errors="replace")
    return text[:limit] + ("…" if len(text) > limit else "")


def _strip_query(url: str) -> str:
    p = urlsplit(url)
    return urlunsplit((p.scheme, p.netloc, p.path, "", ""))


def looks_like_html(body: bytes) -> bool:
    head = body[:512].lstrip().lower()
    return head.startswith((b"<!doctype html", b"<html", b"<?xml", b"<head", b"<body"))


@dataclass
class CHHSClient:
    """Two-step CKAN reader (package_show, then the resource download) with the transport rules
    of the module doc. ``sleep``/``clock`` are injectable for tests."""

    config: CHHSClientConfig = field(default_factory=CHHSClientConfig)
    session: requests.Session | None = None
    sleep: Callable[[float], None] = time.sleep
    clock: Callable[[], float] = time.monotonic

    def __post_init__(self) -> None:
        if self.session is None:
            self.session = requests.Session()

    def backoff_delay(self, attempt: int) -> float:
        return min(self.config.backoff_max_s, self.config.backoff_base_s * 2 ** (attempt - 1))

    def fetch(self, spec: CKANResourceSpec = CDPH_COUNTIES) -> CHHSFetch:
        base = resolve_base_url(self.config.base_url)
        deadline = self.clock() + self.config.fetch_deadline_s
        package_url = spec.package_show_url(base)
        answer = self._get(package_url, deadline, limit=self.config.max_metadata_bytes,
                           accept="application/json", origin=base)
        resource = find_resource(parse_package_show(answer.body, package_url), spec, package_url)
        url = urljoin(package_url, resource.url)
        if not redirect_allowed(base, url):
            raise CHHSRedirectRefusedError(
                f"{package_url} names the download {url} for {spec.resource_name}: refused, "
                f"only {urlsplit(base).scheme}://{urlsplit(base).netloc} is trusted (set "
                f"${BASE_URL_ENV} to a mirror that serves both)")
        answer = self._get(url, deadline, limit=self.config.max_body_bytes,
                           accept="text/csv, */*;q=0.5", origin=base)
        if looks_like_html(answer.body):
            raise DataSourceError(f"{answer.url} answered with an HTML page, not the CSV "
                                  f"{spec.resource_name} ({len(answer.body)} bytes): "
                                  f"{_excerpt(answer.body, 120)!r}")
        return CHHSFetch(spec, package_url, resource, _strip_query(answer.url), answer.body)

    # -- one URL, retried ------------------------------------------------------------------

    def _get(self, url: str, deadline: float, *, limit: int, accept: str,
             origin: str) -> _Answer:
        attempts = self.config.max_retries + 1
        last = "no attempt made"
        for attempt in range(1, attempts + 1):
            remaining = deadline - self.clock()
            if remaining <= 0:
                break
            retry_after: float | None = None
            try:
                answer = self._request(url, min(self.config.request_deadline_s, remaining),
                                       limit=limit, accept=accept, origin=origin)
            except _Retry as exc:
                last = str(exc)
            else:
                if answer.status == 200:
                    return answer
                if not (answer.status == 429 or 500 <= answer.status < 600):
                    raise CHHSHTTPStatusError(f"HTTP {answer.status} from {answer.url}: "
                                              f"{_excerpt(answer.body)!r}", status=answer.status)
                last = f"HTTP {answer.status}: {_excerpt(answer.body)!r}"
                retry_after = parse_retry_after(answer.headers.get("Retry-After"))
                if retry_after is not None:
                    last += f" (Retry-After {retry_after:.0f} s)"
            if attempt == attempts:
                break
            if retry_after is not None and retry_after > self.config.retry_after_max_s:
                raise CHHSNetworkError(f"{url}: the portal asks to retry after "
                                       f"{retry_after:.0f} s, more than the "
                                       f"{self.config.retry_after_max_s:.0f} s we wait; last: "
                                       f"{last}")
            delay = max(self.backoff_delay(attempt), retry_after or 0.0)
            if self.clock() + delay >= deadline:
                raise CHHSNetworkError(f"{url}: fetch deadline of "
                                       f"{self.config.fetch_deadline_s:g} s would pass before "
                                       f"retry {attempt} (in {delay:.0f} s); last: {last}")
            log.warning("CHHS %s: %s; retry %d/%d in %.1f s", url, last, attempt,
                        attempts - 1, delay)
            self.sleep(delay)
        if self.clock() >= deadline:
            raise CHHSNetworkError(f"{url}: fetch deadline of {self.config.fetch_deadline_s:g}"
                                   f" s passed; last: {last}")
        raise CHHSNetworkError(f"{url} failed after {attempts} attempts; last: {last}")

    def _request(self, url: str, budget_s: float, *, limit: int, accept: str,
                 origin: str) -> _Answer:
        """One GET, same-origin redirects followed by hand, within ``budget_s`` seconds."""
        until = self.clock() + budget_s
        current = url
        for _hop in range(self.config.max_redirects + 1):
            answer = self._get_once(current, until, budget_s, limit=limit, accept=accept)
            if answer.status not in _REDIRECTS:
                return answer
            location = answer.headers.get("Location")
            if not location:
                raise DataSourceError(f"HTTP {answer.status} from {current} without a Location")
            target = urljoin(current, location)
            if not redirect_allowed(origin, target):
                raise CHHSRedirectRefusedError(
                    f"{current} redirects (HTTP {answer.status}) to {target}: refused, only "
                    f"redirects to the same host ({urlsplit(origin).netloc}, https or a loopback "
                    f"mirror) are followed")
            log.info("CHHS redirect %s -> %s", current, target)
            current = target
        raise DataSourceError(f"{url}: more than {self.config.max_redirects} redirects")

    def _get_once(self, url: str, until: float, budget_s: float, *, limit: int,
                  accept: str) -> _Answer:
        """:meth:`_read` in a worker thread; stop waiting at ``until`` (bounds the header phase
        too). A late worker is told to stop and ends at its next read."""
        outcome: dict[str, object] = {}
        cancel = threading.Event()

        def work() -> None:
            try:
                outcome["answer"] = self._read(url, until, cancel, limit=limit, accept=accept)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                outcome["error"] = exc

        worker = threading.Thread(target=work, name="chhs-request", daemon=True)
        worker.start()
        worker.join(max(0.0, until - self.clock()) + 0.05)
        if worker.is_alive():
            cancel.set()
            raise _Retry(f"no complete answer from {url} within the request deadline of "
                         f"{budget_s:.1f} s")
        error = outcome.get("error")
        if isinstance(error, _Retry | DataSourceError):
            raise error
        if isinstance(error, requests.RequestException | OSError):
            raise _Retry(f"{type(error).__name__}: {error}") from error
        if isinstance(error, BaseException):
            # urllib3 errors raised by read1 below requests (DecodeError, ProtocolError, ...)
            if type(error).__module__.startswith("urllib3"):
                raise _Retry(f"{type(error).__name__}: {error}") from error
            raise error
        answer = outcome["answer"]
        assert isinstance(answer, _Answer)
        return answer

    def _read(self, url: str, until: float, cancel: threading.Event, *, limit: int,
              accept: str) -> _Answer:
        assert self.session is not None
        remaining = max(0.001, until - self.clock())
        timeout = (min(self.config.timeout_s, remaining), min(self.config.timeout_s, remaining))
        with self.session.get(url, headers={"Accept": accept}, timeout=timeout, stream=True,
                              allow_redirects=False) as response:
            chunks: list[bytes] = []
            size = 0
            while response.status_code not in _REDIRECTS:
                if cancel.is_set() or self.clock() > until:
                    raise _Retry(f"no complete answer from {url} within the request deadline "
                                 f"({size} bytes of the body so far)")
                # read1: returns as soon as any bytes arrive (the deadline is checked between
                # dripped bytes); decode_content: gzip decoded here, counted after decoding.
                chunk = response.raw.read1(1 << 16, decode_content=True)
                if not chunk:
                    break
                size += len(chunk)
                if size > limit:
                    raise DataSourceError(f"{url}: body larger than {limit:,} bytes (after "
                                          f"decoding); refused")
                chunks.append(chunk)
            return _Answer(response.status_code, dict(response.headers), b"".join(chunks),
                           response.url)


def parse_package_show(body: bytes, url: str) -> dict[str, object]:
    """The ``result`` of a CKAN ``package_show`` answer; a named error for anything else."""
    try:
        with decode_boundary("CKAN package_show JSON", url, len(body)):
            data = json.loads(body)
    except PayloadRejectedError as rejected:
        exc = rejected.__cause__
        if not isinstance(exc, json.JSONDecodeError | UnicodeDecodeError):
            raise                   # too deep, a huge integer, ...: named by the boundary
        kind = "an HTML page" if looks_like_html(body) else "invalid JSON"
        raise CKANResponseError(f"{url}: {kind} instead of a CKAN package_show answer "
                                f"({len(body)} bytes): {exc}") from exc
    if not isinstance(data, dict) or data.get("success") is not True:
        error = data.get("error") if isinstance(data, dict) else None
        raise CKANResponseError(f"{url}: CKAN package_show did not succeed: "
                                f"{json.dumps(error)[:200] if error else _excerpt(body)}")
    result = data.get("result")
    if not isinstance(result, dict) or not isinstance(result.get("resources"), list):
        raise CKANResponseError(f"{url}: CKAN package_show answer has no result.resources")
    return result


def find_resource(package: dict[str, object], spec: CKANResourceSpec,
                  url: str) -> CKANResource:
    """The spec's resource: by id, else by its download URL's file name, else by name."""
    raw = package.get("resources")
    resources = [r for r in raw if isinstance(r, dict)] if isinstance(raw, list) else []

    def file_name(r: dict[str, object]) -> str:
        return posixpath.basename(urlsplit(str(r.get("url") or "")).path)

    for matches in (lambda r: bool(spec.resource_id) and r.get("id") == spec.resource_id,
                    lambda r: file_name(r) == spec.resource_name,
                    lambda r: r.get("name") == spec.resource_name):
        found = [r for r in resources if matches(r)]
        if found:
            r = found[0]
            if not isinstance(r.get("url"), str) or not str(r.get("url")).strip():
                raise CKANResponseError(f"{url}: resource {r.get('id')!r} has no download url")
            last_modified = r.get("last_modified")
            return CKANResource(id=str(r.get("id") or ""), name=str(r.get("name") or ""),
                                url=str(r["url"]).strip(),
                                last_modified=str(last_modified) if last_modified else None)
    listed = ", ".join(f"{r.get('name')!r} ({file_name(r) or 'no url'})" for r in resources)
    raise CKANResponseError(f"{url}: dataset {spec.dataset_id} has no resource "
                            f"{spec.resource_name} (id {spec.resource_id or 'unknown'}); "
                            f"resources: {listed or 'none'}")
