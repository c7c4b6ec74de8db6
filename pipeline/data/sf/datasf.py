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

The client reads each dataset through the shared SODA pager (:mod:`pipeline.data.core.soda`: paging
under a fixed ``$order``, a repeated page or too many bytes stop it) and the one bounded HTTP
transport (:mod:`pipeline.data.core.transport`: retries with backoff and ``Retry-After``, wall-clock
deadlines, same-host redirects only, no request thread or socket outliving its request, bodies
capped after decoding). What is DataSF's own is here: the dataset specs, the base URL, the app
token's environment variable, and ordering by a renamed date column when the first is refused.

A 4xx other than 429 is not retried: it means the request itself is wrong (bad dataset id, bad
query), so the error names status, URL and body. Base URL and token come from the environment
(``FLOWCAST_DATASF_BASE_URL``, ``FLOWCAST_DATASF_APP_TOKEN``) unless given in
:class:`ClientConfig` (``flowcast data fetch --base-url/--app-token``, the flow's
``datasf_base_url`` parameter).
"""
from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import urlsplit

import requests

import pandas as pd

from pipeline.data.california.counties import SAN_FRANCISCO
from pipeline.data.core.gate import GateRules, Places, cases_bound, deaths_bound, gate, tests_bound
from pipeline.data.core.plausibility import DAILY, GrowthRule, JumpRule
from pipeline.data.core.soda import SodaClient, SodaConfig
from pipeline.data.core.transport import (REQUEST_THREAD_NAME, HTTPStatusError, NetworkError,
                                          RedirectRefusedError, UnreachableError, backoff_delay,
                                          parse_retry_after, redirect_allowed, token_allowed)
from pipeline.errors import DataSourceError

log = logging.getLogger(__name__)

APP_TOKEN_ENV = "FLOWCAST_DATASF_APP_TOKEN"
BASE_URL_ENV = "FLOWCAST_DATASF_BASE_URL"
DEFAULT_BASE_URL = "https://data.sfgov.org"

# San Francisco's population (2020 Census): the scale of every DataSF count (S/I/R conversion,
# the validation gate's bounds).
SF_POPULATION_2020_CENSUS = 873_965
SF_PLACES = Places("San Francisco", {SAN_FRANCISCO: SF_POPULATION_2020_CENSUS}, "2020 Census")

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


# The gate's bound of each daily count column (pipeline.data.core.gate: cases, deaths, tests)
_BOUNDS = {"new_cases": cases_bound, "positives": cases_bound, "new_deaths": deaths_bound,
           "tests": tests_bound, "negatives": tests_bound, "indeterminate": tests_bound}


def gate_rules(spec: DatasetSpec, jump: JumpRule = DAILY) -> GateRules:
    """The validation gate's rules for one DataSF dataset (San Francisco, its daily counts)."""
    cases = tuple(c for c in spec.count_columns if c in ("new_cases", "positives"))
    return GateRules(source=f"DataSF {spec.key}", places=SF_PLACES,
                     counts=tuple(_BOUNDS[c](c) for c in spec.count_columns), jump=jump,
                     growth=GrowthRule(columns=cases) if cases else None)


def check_gate(frame: pd.DataFrame, spec: DatasetSpec, *, source: str,
               jump: JumpRule = DAILY) -> None:
    """A validated daily frame of ``spec`` through the validation gate; San Francisco is the
    only place, so a failure refuses the payload (:class:`~pipeline.data.core.gate.GateError`
    naming the count, the day and the bound)."""
    rows = frame.assign(place=SAN_FRANCISCO)[["place", "date", *spec.count_columns]]
    gate(rows, gate_rules(spec, jump), source=source)


def describe_schema(spec: DatasetSpec) -> str:
    """What ``spec`` needs, every accepted name listed: for errors about unknown schemas."""
    return (f"{spec.key} ({spec.dataset_id}) needs "
            + ", ".join(f.describe() for f in spec.required))


def default_base_url() -> str:
    """``$FLOWCAST_DATASF_BASE_URL`` (a mirror or proxy), else data.sfgov.org."""
    return os.environ.get(BASE_URL_ENV, "").strip() or DEFAULT_BASE_URL


@dataclass(frozen=True)
class ClientConfig(SodaConfig):
    """How to talk to DataSF (the transport's and SODA paging's settings, plus DataSF's base URL).

    ``app_token`` overrides ``$FLOWCAST_DATASF_APP_TOKEN``; it is kept out of ``repr`` so it never
    reaches a log line or a provenance file. The size limits come from what DataSF's genuine
    payloads weigh: the largest series, tests (788 rows), is 169,934 bytes as one JSON array, so
    a page of 1,000 rows is about 216 KB; a page may have 2 MB (9×), all pages of one dataset
    4 MB (24× the largest series).
    """

    base_url: str = field(default_factory=default_base_url)
    app_token_env: str = APP_TOKEN_ENV
    max_body_bytes: int = 2 << 20
    max_fetch_bytes: int = 4 << 20

    def __post_init__(self) -> None:
        parts = urlsplit(self.base_url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            hint = (f"; did you mean 'https://{self.base_url.strip().lstrip('/')}'?"
                    if "://" not in self.base_url and self.base_url.strip() else "")
            raise DataSourceError(f"DataSF base URL must be http(s)://host[/path], got "
                                  f"{self.base_url!r} (--base-url / ${BASE_URL_ENV}){hint}")


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


@dataclass
class DataSFClient:
    """DataSF's datasets through the shared SODA pager and bounded transport.

    ``sleep`` is injectable so tests can check the backoff schedule without waiting.
    """

    config: ClientConfig = field(default_factory=ClientConfig)
    session: requests.Session | None = None
    sleep: Callable[[float], None] = time.sleep
    clock: Callable[[], float] = time.monotonic

    def soda(self) -> SodaClient:
        return SodaClient(self.config, self.config.base_url, source="DataSF",
                          session=self.session, sleep=self.sleep, clock=self.clock)

    def backoff_delay(self, attempt: int) -> float:
        """Delay before retry ``attempt`` (1-based): base * 2**(attempt-1), capped."""
        return backoff_delay(self.config, attempt)

    def fetch(self, spec: DatasetSpec) -> FetchResult:
        """Every row of ``spec``'s dataset, ordered by date, in pages of ``page_size``.

        The order field is the date's API name; if DataSF answers the first page with HTTP 400
        (no such column: a later schema renamed it), each alias is tried in turn.
        """
        orders = list(dict.fromkeys((spec.date.api, *(a.lower() for a in spec.date.aliases))))
        for order in orders:
            try:
                got = self.soda().fetch(spec.dataset_id, order=(order,))
            except HTTPStatusError as exc:
                if exc.status != 400 or exc.page != 0 or order == orders[-1]:
                    raise
                log.warning("DataSF %s: ordering by %s refused (%s); trying %s", spec.key, order,
                            exc, orders[orders.index(order) + 1])
                continue
            return FetchResult(spec, got.url, got.rows, got.payload, got.pages, got.final_url)
        raise AssertionError("unreachable")  # pragma: no cover


__all__ = ["APP_TOKEN_ENV", "BASE_URL_ENV", "CASES", "DATASETS", "DATASETS_BY_ID", "DEATHS",
           "DEFAULT_BASE_URL", "REQUEST_THREAD_NAME", "SF_PLACES",
           "SF_POPULATION_2020_CENSUS", "TESTS", "ClientConfig", "DataSFClient", "DatasetSpec",
           "FetchResult", "FieldSpec", "HTTPStatusError", "NetworkError", "RedirectRefusedError",
           "UnreachableError", "check_gate", "describe_schema", "gate_rules",
           "parse_retry_after", "redirect_allowed",
           "token_allowed"]
