"""Client of the California Health and Human Services open data portal (data.chhs.ca.gov, CKAN).

CDPH publishes "COVID-19 Time-Series Metrics by County and State" there as CKAN dataset
``covid-19-time-series-metrics-by-county-and-state`` (package id
``f333528b-4d38-4814-bebb-12db1f10f535``); the county file is the resource
``046cdd2b-31e5-4d34-9ed3-b48cdbc4be7a`` whose download URL ends in ``covid19cases_test.csv``
(its CKAN *name* is a title, "Statewide COVID-19 Cases Deaths Tests", so the resource is found by
id, then by the file name of its URL, then by name). A fetch is two requests:

1. ``GET <base>/api/3/action/package_show?id=<dataset>`` → ``{"success": true, "result":
   {"resources": [{"id", "name", "url", "last_modified", ...}, ...]}}``;
2. ``GET <resource url>``: the CSV bytes, parsed by :func:`pipeline.data.california.cdph.parse_cdph_csv`.

Every request goes through the one bounded transport every source shares
(:mod:`pipeline.data.core.transport`: retries with backoff and ``Retry-After``, wall-clock deadlines
per request and per fetch, same-host redirects only, no request thread or socket outliving its
request, bodies capped after decoding, so a gzip bomb stops at the cap). What is the portal's own
is here: the two-step CKAN read, the resource URL CKAN names having to be on the base URL's host
too, an HTML page where the CSV belongs named as such, and the size caps, set from what the
genuine payloads weigh: the county CSV of 2021-11-04 is 4,092,437 bytes (about 104 bytes per
area-day), so ``max_body_bytes`` is 32 MB (8× that file; at the same bytes per area-day, some
14 years of the 61 areas); the ``package_show`` JSON lists the package's resources (a few KB
each; not measured here), capped at 1 MB.

A 4xx other than 429 is not retried (:class:`~pipeline.data.core.transport.HTTPStatusError`). The
base URL is
``CHHSClientConfig.base_url``, else ``$FLOWCAST_CHHS_BASE_URL`` (read when a fetch starts, never
at import), else https://data.chhs.ca.gov; one without ``http(s)://host`` is a
:class:`~pipeline.errors.ConfigError` when used.
"""
from __future__ import annotations

import json
import logging
import os
import posixpath
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import urlencode, urljoin, urlsplit

import requests

from pipeline.data.core.decoding import PayloadRejectedError, decode_boundary
from pipeline.data.core.transport import (RedirectRefusedError, Transport, TransportConfig,
                                          body_excerpt, redirect_allowed, strip_query)
from pipeline.errors import ConfigError, DataSourceError

log = logging.getLogger(__name__)

BASE_URL_ENV = "FLOWCAST_CHHS_BASE_URL"
DEFAULT_BASE_URL = "https://data.chhs.ca.gov"
CACHE_FOLDER = "chhs"


@dataclass(frozen=True)
class CKANResourceSpec:
    """One file of a CKAN dataset. ``key``/``dataset_id``/``cache_folder`` place it in the cache
    (:class:`pipeline.data.core.cache.DatasetCache`): ``<data dir>/chhs/<dataset_id>/``."""

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
class CHHSClientConfig(TransportConfig):
    """How to talk to the CHHS portal (the shared transport's settings, the base URL and the size
    caps of module doc). Tests set ``backoff_base_s`` 0 so retries cost no time."""

    base_url: str | None = None         # None: $FLOWCAST_CHHS_BASE_URL or data.chhs.ca.gov
    request_deadline_s: float = 300.0   # one request, headers and body, wall clock
    fetch_deadline_s: float = 900.0     # metadata + CSV, every retry, wall clock
    max_metadata_bytes: int = 1 << 20
    max_body_bytes: int = 32 << 20


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


class CKANResponseError(DataSourceError):
    """package_show answered, but not with the dataset and resource expected."""


def looks_like_html(body: bytes) -> bool:
    head = body[:512].lstrip().lower()
    return head.startswith((b"<!doctype html", b"<html", b"<?xml", b"<head", b"<body"))


@dataclass
class CHHSClient:
    """Two-step CKAN reader (package_show, then the resource download) through the shared
    transport. ``sleep``/``clock`` are injectable for tests."""

    config: CHHSClientConfig = field(default_factory=CHHSClientConfig)
    session: requests.Session | None = None
    sleep: Callable[[float], None] = time.sleep
    clock: Callable[[], float] = time.monotonic

    def fetch(self, spec: CKANResourceSpec = CDPH_COUNTIES) -> CHHSFetch:
        base = resolve_base_url(self.config.base_url)
        with Transport(self.config, source="CHHS portal", origin=base, session=self.session,
                       sleep=self.sleep, clock=self.clock) as transport:
            deadline = transport.deadline()
            package_url = spec.package_show_url(base)
            answer = transport.get(package_url, deadline=deadline,
                                   max_bytes=self.config.max_metadata_bytes,
                                   headers={"Accept": "application/json"})
            resource = find_resource(parse_package_show(answer.body, package_url), spec,
                                     package_url)
            url = urljoin(package_url, resource.url)
            if not redirect_allowed(base, url):
                raise RedirectRefusedError(
                    f"{package_url} names the download {url} for {spec.resource_name}: "
                    f"refused, only {urlsplit(base).scheme}://{urlsplit(base).netloc} is trusted "
                    f"(set ${BASE_URL_ENV} to a mirror that serves both)")
            answer = transport.get(url, deadline=deadline, max_bytes=self.config.max_body_bytes,
                                   headers={"Accept": "text/csv, */*;q=0.5"})
        if looks_like_html(answer.body):
            raise DataSourceError(f"{answer.url} answered with an HTML page, not the CSV "
                                  f"{spec.resource_name} ({len(answer.body)} bytes): "
                                  f"{body_excerpt(answer.body, 120)!r}")
        return CHHSFetch(spec, package_url, resource, strip_query(answer.url), answer.body)


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
                                f"{json.dumps(error)[:200] if error else body_excerpt(body, 200)}")
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
