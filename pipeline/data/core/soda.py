"""Reading a Socrata (SODA 2.x) JSON resource page by page: DataSF (data.sfgov.org) and the CDC's
portal (data.cdc.gov: NHSN hospital admissions, NSSP ED visits) speak the same API.

``GET <base>/resource/<id>.json?$limit=<page>&$offset=<k·page>&$order=<fields>`` (plus
``$select``/``$where`` when given), every request through the bounded
:class:`~pipeline.data.core.transport.Transport`. Socrata gives no stable order without ``$order``,
so pages could overlap or skip rows: the order must be *total* (DataSF orders a daily series by
its date; NHSN by week and jurisdiction). Paging stops at the first page shorter than
``$limit``, at the first page whose bytes repeat an earlier one (a server ignoring ``$offset``
was read for 1,000 pages, 1.27 GB, in the probe of issue 22) and when the pages together pass
``max_fetch_bytes``. Every page is decoded at the boundary of :mod:`pipeline.data.core.decoding`.

An app token (``app_token``, else ``$<app_token_env>``) is sent as ``X-App-Token``: a
per-request header, never a session default, only over https or to a loopback mirror.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import requests

from pipeline.data.core.decoding import decode_json_records
from pipeline.data.core.transport import (HTTPStatusError, Transport, TransportConfig, strip_query,
                                          token_allowed)
from pipeline.errors import DataSourceError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SodaConfig(TransportConfig):
    """Paging and size limits of a SODA resource, and its app token (kept out of ``repr``)."""

    page_size: int = 1000              # Socrata's default page
    max_pages: int = 1000              # only stops a runaway loop
    max_body_bytes: int = 2 << 20      # one page
    max_fetch_bytes: int = 16 << 20    # all pages of one resource together (bounds memory)
    app_token: str | None = field(default=None, repr=False)
    app_token_env: str = ""

    def token(self) -> str | None:
        token = self.app_token if self.app_token is not None else (
            os.environ.get(self.app_token_env, "") if self.app_token_env else "")
        return token.strip() or None


@dataclass(frozen=True)
class SodaRows:
    """Every row of one resource (as returned: strings), the exact bytes to cache, and where
    the answer came from after redirects (query string dropped: it only held the paging)."""

    url: str
    rows: list[dict[str, object]]
    payload: bytes
    pages: int
    final_url: str


def resource_url(base_url: str, resource_id: str) -> str:
    return f"{base_url.rstrip('/')}/resource/{resource_id}.json"


@dataclass
class SodaClient:
    """Pages of one Socrata portal (``base_url``), read in a fixed order."""

    config: SodaConfig
    base_url: str
    source: str = "Socrata"
    session: requests.Session | None = None
    sleep: Callable[[float], None] = time.sleep
    clock: Callable[[], float] = time.monotonic

    def transport(self) -> Transport:
        return Transport(self.config, source=self.source, origin=self.base_url,
                         session=self.session, sleep=self.sleep, clock=self.clock)

    def fetch(self, resource_id: str, *, order: Sequence[str], select: Sequence[str] = (),
              where: str | None = None) -> SodaRows:
        """Every row of ``resource_id`` ordered by ``order`` (fields, ascending)."""
        with self.transport() as transport:
            return self._pages(transport, resource_url(self.base_url, resource_id), order,
                               select, where)

    def _pages(self, transport: Transport, url: str, order: Sequence[str],
               select: Sequence[str], where: str | None) -> SodaRows:
        deadline = transport.deadline()
        headers = self._headers(url)
        rows: list[dict[str, object]] = []
        final_url = ""
        ledger = _PageLedger(url, self.config.page_size, self.config.max_fetch_bytes)
        query = {"$order": ", ".join(f"{f} ASC" for f in order),
                 **({"$select": ",".join(select)} if select else {}),
                 **({"$where": where} if where else {})}
        for page in range(self.config.max_pages):
            params = {"$limit": str(self.config.page_size),
                      "$offset": str(page * self.config.page_size), **query}
            try:
                answer = transport.get(url, params=params, headers=headers, deadline=deadline,
                                       max_bytes=self.config.max_body_bytes)
            except HTTPStatusError as exc:
                raise HTTPStatusError(str(exc), status=exc.status, page=page) from exc
            batch = decode_json_records(answer.body, source=answer.url,
                                        max_bytes=self.config.max_body_bytes)
            ledger.add(page, answer.body)
            final_url = final_url or strip_query(answer.url)
            rows.extend(batch)
            if len(batch) < self.config.page_size:
                payload = json.dumps(rows, separators=(",", ":")).encode("utf-8")
                return SodaRows(url, rows, payload, page + 1, final_url)
        raise DataSourceError(f"{url}: more than {self.config.max_pages} pages; stopping")

    def _headers(self, url: str) -> dict[str, str]:
        headers = {"Accept": "application/json"}
        token = self.config.token()
        if token is not None:
            # redirects never leave the origin's scheme and host, so this holds for every hop
            if token_allowed(url):
                headers["X-App-Token"] = token
            else:
                log.warning("%s app token not sent to %s over plain http", self.source, url)
        return headers


class _PageLedger:
    """What the pages of one fetch have cost so far: stops a server that ignores ``$offset``
    at its first repeated page and any fetch whose pages together pass ``max_bytes``."""

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
