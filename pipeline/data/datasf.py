"""DataSF (data.sfgov.org, a Socrata portal) dataset specs and the SODA 2.x JSON client.

Three San Francisco COVID-19 datasets feed the forecast (paper, section "COVID-19 Dataset"):
cases over time ``gyr2-k29z``, deaths over time ``g2di-xufg`` and tests over time ``nfpa-mg4g``.
Each is described by a :class:`DatasetSpec` that knows its field names in both forms DataSF
publishes: the JSON API (snake_case, every value a string) and the full CSV export (display names
such as "Specimen Collection Date", US dates, unsorted rows).

The client pages with ``$limit``/``$offset`` under a fixed ``$order`` (Socrata gives no stable
order without one, so pages could overlap or skip rows), sends the optional app token
(``FLOWCAST_DATASF_APP_TOKEN`` -> header ``X-App-Token``), and retries with exponential backoff on
connection errors, timeouts, HTTP 429 and 5xx. A 4xx other than 429 is not retried: it means the
request itself is wrong (bad dataset id, bad query), so the error names status, URL and body.
"""
from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import requests

from pipeline.errors import DataSourceError

log = logging.getLogger(__name__)

APP_TOKEN_ENV = "FLOWCAST_DATASF_APP_TOKEN"
DEFAULT_BASE_URL = "https://data.sfgov.org"

# Date formats seen in DataSF payloads: API floating timestamps, CSV-export US timestamps,
# and the slash-ISO form of the tests export.
API_DATE_FORMATS = ("%Y-%m-%dT%H:%M:%S.%f", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d")
CSV_DATE_FORMATS = ("%m/%d/%Y %I:%M:%S %p", "%Y/%m/%d", "%m/%d/%Y", "%Y-%m-%d")


@dataclass(frozen=True)
class FieldSpec:
    """One column: canonical name used inside flowcast, its API name and its CSV display name."""

    canonical: str
    api: str
    display: str

    def names(self) -> tuple[str, ...]:
        return (self.canonical, self.api, self.display)


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
# and is recomputed by flowcast, so it is not required.
TESTS = DatasetSpec(
    key="tests", dataset_id="nfpa-mg4g", title="COVID-19 Testing Over Time",
    date=FieldSpec("date", "specimen_collection_date", "Specimen Collection Date"),
    counts=(FieldSpec("tests", "tests", "Tests"),
            FieldSpec("positives", "pos", "Pos"),
            FieldSpec("negatives", "neg", "Neg"),
            FieldSpec("indeterminate", "indeterminate", "Indeterminate")),
    as_of=(FieldSpec("data_as_of", "last_updated_at", "Last Updated At"), _LOADED))

DATASETS: dict[str, DatasetSpec] = {s.key: s for s in (CASES, DEATHS, TESTS)}
DATASETS_BY_ID: dict[str, DatasetSpec] = {s.dataset_id: s for s in DATASETS.values()}


@dataclass(frozen=True)
class ClientConfig:
    """How to talk to DataSF. Tests set ``backoff_base_s`` ~0 so retries cost no time."""

    base_url: str = DEFAULT_BASE_URL
    page_size: int = 1000
    timeout_s: float = 30.0
    max_retries: int = 4
    backoff_base_s: float = 1.0
    backoff_max_s: float = 30.0
    app_token_env: str = APP_TOKEN_ENV
    max_pages: int = 1000  # a daily series has < 2,000 rows; this only stops a runaway loop


@dataclass(frozen=True)
class FetchResult:
    """All rows of one dataset (as returned, strings) plus the exact bytes to cache."""

    spec: DatasetSpec
    url: str
    rows: list[dict[str, object]]
    payload: bytes
    pages: int


def _retryable_status(status: int) -> bool:
    return status == 429 or 500 <= status < 600


def _body_excerpt(response: requests.Response, limit: int = 300) -> str:
    text = response.text or ""
    return text[:limit] + ("…" if len(text) > limit else "")


@dataclass
class DataSFClient:
    """Paginated, retrying reader of DataSF JSON resources.

    ``sleep`` is injectable so tests can check the backoff schedule without waiting.
    """

    config: ClientConfig = field(default_factory=ClientConfig)
    session: requests.Session | None = None
    sleep: Callable[[float], None] = time.sleep

    def __post_init__(self) -> None:
        if self.session is None:
            self.session = requests.Session()
        token = os.environ.get(self.config.app_token_env, "").strip()
        if token:
            self.session.headers["X-App-Token"] = token

    def backoff_delay(self, attempt: int) -> float:
        """Delay before retry ``attempt`` (1-based): base * 2**(attempt-1), capped."""
        return min(self.config.backoff_max_s, self.config.backoff_base_s * 2 ** (attempt - 1))

    def fetch(self, spec: DatasetSpec) -> FetchResult:
        """Every row of ``spec``'s dataset, ordered by date, in pages of ``page_size``."""
        url = spec.resource_url(self.config.base_url)
        rows: list[dict[str, object]] = []
        for page in range(self.config.max_pages):
            params = {"$limit": str(self.config.page_size),
                      "$offset": str(page * self.config.page_size),
                      "$order": f"{spec.date.api} ASC"}
            batch = self._get_page(url, params)
            rows.extend(batch)
            if len(batch) < self.config.page_size:
                payload = json.dumps(rows, separators=(",", ":")).encode("utf-8")
                return FetchResult(spec, url, rows, payload, page + 1)
        raise DataSourceError(f"{url}: more than {self.config.max_pages} pages; stopping")

    def _get_page(self, url: str, params: dict[str, str]) -> list[dict[str, object]]:
        assert self.session is not None
        attempts = self.config.max_retries + 1
        last_problem = ""
        for attempt in range(1, attempts + 1):
            try:
                response = self.session.get(url, params=params, timeout=self.config.timeout_s)
            except (requests.ConnectionError, requests.Timeout) as exc:
                last_problem = f"{type(exc).__name__}: {exc}"
            else:
                if response.status_code == 200:
                    return _parse_page(response)
                if not _retryable_status(response.status_code):
                    raise DataSourceError(
                        f"HTTP {response.status_code} from {response.url}: "
                        f"{_body_excerpt(response)!r}")
                last_problem = f"HTTP {response.status_code}: {_body_excerpt(response)!r}"
            if attempt < attempts:
                delay = self.backoff_delay(attempt)
                log.warning("DataSF %s (offset %s): %s; retry %d/%d in %.1f s", url,
                            params["$offset"], last_problem, attempt, attempts - 1, delay)
                self.sleep(delay)
        raise NetworkError(f"{url} failed after {attempts} attempts; last: {last_problem}")


class NetworkError(DataSourceError):
    """DataSF could not be reached (connection, timeout, 429/5xx after every retry)."""


def _parse_page(response: requests.Response) -> list[dict[str, object]]:
    try:
        data = json.loads(response.content)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataSourceError(
            f"invalid JSON from {response.url} ({len(response.content)} bytes, truncated or "
            f"damaged): {exc}") from exc
    if not isinstance(data, list) or not all(isinstance(r, dict) for r in data):
        raise DataSourceError(f"{response.url}: expected a JSON array of objects, got "
                              f"{type(data).__name__}")
    return data
