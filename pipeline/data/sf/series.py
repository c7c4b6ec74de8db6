"""The combined San Francisco daily series (cases, deaths, tests) with its provenance.

``load_sf_series`` is the entry point of the forecast flow:

* live (default): fetch each dataset from DataSF, validate, cache; if DataSF is unreachable or
  returns a bad payload, fall back to the cache and record why and how old the cache is;
* ``offline=True``: cache only; without a cache an :class:`OfflineError` names
  ``flowcast data import``.

Vintage. DataSF revises recent days (two vintages of the cases series differ on 215 of 744 days,
most at the trailing edge), so each dataset loses its last ``trailing_days`` days (default 14)
before the datasets are combined. :class:`DataVintage` records DataSF's "data as of" stamps, when
flowcast loaded the data, the last date kept and the number of days dropped; it travels with every
output (SIR frame, CSV, figures, reports).

Combination. The combined frame runs from the first cases date to the earliest trimmed last date
of the datasets, so every column is defined on every day. Before a dataset's first row its daily
counts are 0 (the deaths series begins with the first death; tests start before cases). The
cumulative columns are rebuilt from the daily counts (offset by DataSF's total on the first day
minus that day's count, 0 for the real exports), so they agree with the daily counts by
construction; DataSF's own cumulative columns were compared in validation.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from datetime import date, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import requests

from pipeline.data.core.cache import CacheManifest, CachedPayload, DatasetCache, SourceKind, utc_now
from pipeline.data.california.counties import SAN_FRANCISCO
from pipeline.data.sf.datasf import (DATASETS, CASES, SF_POPULATION_2020_CENSUS, ClientConfig,
                                     DataSFClient, DatasetSpec)
from pipeline.data.core.decoding import decode_boundary
from pipeline.data.core.fallback import DEFAULT_LOCK_TIMEOUT_S, live_or_cache, no_cache_error
from pipeline.data.sf.payloads import decode_cached as _decode_payload
from pipeline.data.sf.payloads import rows_frame
from pipeline.data.core.plausibility import DAILY, JumpRule
from pipeline.data.core.revision_policy import RevisionPolicy
from pipeline.data.sf.revisions import DEFAULT_POLICY, commit_validated
from pipeline.data.sf.validation import GapPolicy, ValidatedFrame, validate_frame
from pipeline.errors import ConfigError, OfflineError, ValidationError

log = logging.getLogger(__name__)

DEFAULT_TRAILING_DAYS = 14


@dataclass(frozen=True)
class SFDataConfig:
    """Where and how to load the SF series. ``datasets`` must include ``cases``."""

    datasets: tuple[str, ...] = ("cases", "deaths", "tests")
    trailing_days: int = DEFAULT_TRAILING_DAYS
    gap_policy: GapPolicy = GapPolicy.ZERO_FILL
    client: ClientConfig = field(default_factory=ClientConfig)
    data_dir: Path | None = None  # None -> $FLOWCAST_DATA_DIR or ./data
    accept_revisions: bool = False  # take a payload the revision policy would hold (reviewed)
    revision_policy: RevisionPolicy = DEFAULT_POLICY
    jump: JumpRule = DAILY   # the gate's history rule (pipeline.data.core.plausibility)
    lock_timeout_s: float = DEFAULT_LOCK_TIMEOUT_S

    def __post_init__(self) -> None:
        unknown = [d for d in self.datasets if d not in DATASETS]
        if unknown:
            raise ConfigError(f"unknown DataSF dataset(s) {unknown}; known: {sorted(DATASETS)}")
        if "cases" not in self.datasets:
            raise ConfigError("SFDataConfig.datasets must include 'cases'")
        if self.trailing_days < 0:
            raise ConfigError(f"trailing_days must be >= 0, got {self.trailing_days}")


@dataclass(frozen=True)
class DatasetProvenance:
    dataset_key: str
    dataset_id: str
    source_kind: SourceKind
    source: str
    fetched_at: str
    sha256: str
    row_count: int
    first_date: str
    last_date: str          # last date in the payload, before trimming
    data_as_of: str | None
    from_cache: bool
    stale_days: float       # age of the cached copy when it was used; 0 for a live fetch
    notes: tuple[str, ...] = ()
    final_url: str | None = None  # where DataSF answered from after redirects (API only)
    skipped: Mapping[str, str] = field(default_factory=dict)  # place -> why the gate dropped it


@dataclass(frozen=True)
class DataVintage:
    """What data a result rests on: the publisher's vintage, when loaded, what was kept."""

    data_as_of: str | None    # earliest DataSF "data as of" stamp (CDPH: the vintage's last day)
    loaded_at: str            # when flowcast loaded (fetched or read from cache) the data
    first_date: str
    last_date_kept: str
    trimmed_days: int
    publisher: str = "DataSF"

    def describe(self) -> str:
        kept = (f"last {self.trimmed_days} days of each dataset dropped as still under revision"
                if self.trimmed_days else "every day loaded: the forecast nowcasts the days still "
                "being reported, or drops them without a delay model")
        return (f"{self.publisher} data as of {self.data_as_of or 'unknown'}; days "
                f"{self.first_date}…{self.last_date_kept} ({kept}); loaded {self.loaded_at}")


@dataclass(frozen=True)
class SeriesProvenance:
    vintage: DataVintage
    datasets: tuple[DatasetProvenance, ...]

    @property
    def max_stale_days(self) -> float:
        return max((d.stale_days for d in self.datasets), default=0.0)

    def to_dict(self) -> dict[str, Any]:
        return {"vintage": asdict(self.vintage),
                "datasets": [asdict(d) for d in self.datasets],
                "max_stale_days": self.max_stale_days}


@dataclass(frozen=True)
class SFSeries:
    """Daily frame ``date, new_cases, cumulative_cases, new_deaths, cumulative_deaths, tests,
    positives, negatives, indeterminate`` (those of the loaded datasets) + provenance, of
    ``place`` and its ``population``: San Francisco from DataSF, or a California county from
    CDPH (cases and deaths only; ``pipeline.forecast.sources.load_county_series``)."""

    frame: pd.DataFrame
    provenance: SeriesProvenance
    place: str = SAN_FRANCISCO
    population: int = SF_POPULATION_2020_CENSUS

    @property
    def vintage(self) -> DataVintage:
        return self.provenance.vintage


def decode_cached(cached: CachedPayload, spec: DatasetSpec) -> pd.DataFrame:
    """Kept for callers of the old name; see :func:`pipeline.data.sf.payloads.decode_cached`."""
    return _decode_payload(cached)


def _fetch_live(spec: DatasetSpec, client: DataSFClient, cache: DatasetCache,
                config: SFDataConfig, now: datetime) -> tuple[ValidatedFrame, DatasetProvenance]:
    result = client.fetch(spec)
    # The rows were decoded at the client's boundary; reading them as a frame is decoding too.
    with decode_boundary("payload", result.url, len(result.payload)):
        validated = validate_frame(rows_frame(result.rows, source=result.url), spec,
                                   source=result.url, gap_policy=config.gap_policy,
                                   today=pd.Timestamp(now.date()))
    manifest = commit_validated(cache, validated, result.payload, suffix="json",
                                source_kind="api", source=result.url,
                                final_url=result.final_url, gap_policy=config.gap_policy,
                                accept_revisions=config.accept_revisions,
                                policy=config.revision_policy, jump=config.jump,
                                lock_timeout_s=config.lock_timeout_s)
    return validated, _provenance(manifest, from_cache=False, stale_days=0.0,
                                  notes=validated.report.warnings)


def _no_cache(spec: DatasetSpec, cache: DatasetCache, why: str | None) -> OfflineError:
    return no_cache_error(f"DataSF {spec.key} data ({spec.dataset_id})", cache.directory(spec),
                          why, fetch="flowcast data fetch",
                          otherwise=f"import a DataSF CSV export ({spec.export_url()}) with "
                                    f"`flowcast data import FILE`")


def require_sf_cached(config: SFDataConfig | None = None) -> None:
    """The error an offline read would end in, now and without reading anything: the first
    dataset the series reads that the cache does not hold (a run checks before any work)."""
    config = config if config is not None else SFDataConfig()
    cache = DatasetCache.default(config.data_dir)
    missing = [DATASETS[key] for key in config.datasets if not cache.has(DATASETS[key])]
    if missing:
        raise _no_cache(missing[0], cache, None)


def _from_cache(spec: DatasetSpec, cache: DatasetCache, gap_policy: GapPolicy,
                now: datetime, why: str | None) -> tuple[ValidatedFrame, DatasetProvenance]:
    cached = cache.load(spec)
    if cached is None:
        raise _no_cache(spec, cache, why)
    validated = validate_frame(_decode_payload(cached), spec, source=str(cached.path),
                               gap_policy=gap_policy)
    stale = cached.manifest.age_days(now)
    # The cache's age alone hides an archived export: also say how old the data themselves are.
    data_age = (now.date() - date.fromisoformat(str(cached.manifest.last_date)[:10])).days
    notes = ((why,) if why else ()) + (
        f"using cache, fetched {stale:.0f} days ago (its last day, {cached.manifest.last_date}, "
        f"is {data_age} days before today)",)
    log.warning("DataSF %s: %s", spec.key, "; ".join(notes))
    return validated, _provenance(cached.manifest, from_cache=True, stale_days=stale,
                                  notes=notes + validated.report.warnings)


def _provenance(manifest: CacheManifest, *, from_cache: bool, stale_days: float,
                notes: tuple[str, ...]) -> DatasetProvenance:
    return DatasetProvenance(
        dataset_key=manifest.dataset_key, dataset_id=manifest.dataset_id,
        source_kind=manifest.source_kind, source=manifest.source,
        fetched_at=manifest.fetched_at, sha256=manifest.sha256, row_count=manifest.row_count,
        first_date=manifest.first_date, last_date=manifest.last_date,
        data_as_of=manifest.data_as_of, from_cache=from_cache, stale_days=stale_days,
        notes=notes, final_url=manifest.final_url)


def load_dataset(spec: DatasetSpec, config: SFDataConfig, *, offline: bool = False,
                 session: requests.Session | None = None, now: datetime | None = None
                 ) -> tuple[ValidatedFrame, DatasetProvenance]:
    """One dataset, live with cache fallback (or cache only when ``offline``)."""
    validated, provenance, _ = _load_one(spec, config, offline=offline, session=session,
                                         now=now or utc_now(), unreachable=None)
    return validated, provenance


def _load_one(spec: DatasetSpec, config: SFDataConfig, *, offline: bool,
              session: requests.Session | None, now: datetime, unreachable: str | None
              ) -> tuple[ValidatedFrame, DatasetProvenance, str | None]:
    """:func:`load_dataset`, plus why DataSF is unreachable (None when it answered). With
    ``unreachable`` already known, the cache is read without trying the network again."""
    cache = DatasetCache.default(config.data_dir)
    if offline:
        return (*_from_cache(spec, cache, config.gap_policy, now, why=None), None)
    if unreachable is not None:
        # Name this dataset's own resource: the first failure's text cites the first dataset's URL
        # (the deaths and tests notes used to carry the cases URL, gyr2-k29z).
        why = (f"DataSF unreachable (an earlier dataset's fetch failed), so "
               f"{spec.resource_url(config.client.base_url)} was not retried for {spec.key}")
        return (*_from_cache(spec, cache, config.gap_policy, now, why=why), unreachable)
    client = DataSFClient(config.client, session=session)
    live = live_or_cache(lambda: _fetch_live(spec, client, cache, config, now), source="DataSF",
                         has_cache=lambda: cache.has(spec))
    if live.value is not None:
        return (*live.value, None)
    return (*_from_cache(spec, cache, config.gap_policy, now, why=live.why),
            live.why if live.unreachable else None)


def trim_trailing_days(frame: pd.DataFrame, days: int) -> pd.DataFrame:
    """Drop the last ``days`` calendar days (the frame is daily and gap-free)."""
    if days == 0:
        return frame
    cutoff = frame["date"].iloc[-1] - pd.Timedelta(days=days)
    return frame.loc[frame["date"] <= cutoff].reset_index(drop=True)


def _daily_on(validated: ValidatedFrame, dates: pd.DatetimeIndex) -> pd.DataFrame:
    """The dataset's daily counts on ``dates`` (0 outside its own range) + rebuilt cumulative."""
    spec, frame = validated.spec, validated.frame
    daily = frame.set_index("date")[list(spec.count_columns)].reindex(dates, fill_value=0)
    if spec.cumulative is not None and spec.cumulative_of is not None:
        first = frame.iloc[0]
        offset = int(first[spec.cumulative.canonical]) - int(first[spec.cumulative_of])
        before = frame.loc[frame["date"] < dates[0], spec.cumulative_of].sum()
        daily[spec.cumulative.canonical] = (offset + int(before)
                                            + daily[spec.cumulative_of].cumsum())
    return daily.astype(np.int64)


def combine(frames: dict[str, ValidatedFrame], trailing_days: int) -> pd.DataFrame:
    trimmed = {k: ValidatedFrame(v.spec, trim_trailing_days(v.frame, trailing_days), v.report)
               for k, v in frames.items()}
    empty = [k for k, v in trimmed.items() if len(v.frame) == 0]
    if empty:
        raise ValidationError(f"no days left in {empty} after dropping the last "
                              f"{trailing_days} days")
    start = trimmed[CASES.key].frame["date"].iloc[0]
    end = min(v.frame["date"].iloc[-1] for v in trimmed.values())
    dates = pd.DatetimeIndex(pd.date_range(start, end, freq="D", name="date")
                             .astype("datetime64[us]"))
    parts = [_daily_on(trimmed[k], dates) for k in trimmed]
    return pd.concat(parts, axis=1).rename_axis("date").reset_index()


def load_sf_series(config: SFDataConfig | None = None, *, offline: bool = False,
                   session: requests.Session | None = None,
                   now: datetime | None = None) -> SFSeries:
    """Cases (+ deaths, tests) as one validated, vintage-trimmed daily frame with provenance.

    ``config`` defaults to ``SFDataConfig()``, built here and not at import: it reads
    ``$FLOWCAST_DATASF_BASE_URL``, and a bad value must fail the fetch, not every import."""
    config = config if config is not None else SFDataConfig()
    now = now or utc_now()
    frames: dict[str, ValidatedFrame] = {}
    provenance: list[DatasetProvenance] = []
    # One host serves every dataset: once it failed every retry, the others go straight to the
    # cache instead of repeating the whole backoff schedule (offline runs would wait 3x as long).
    unreachable: str | None = None
    for key in config.datasets:
        validated, prov, unreachable = _load_one(DATASETS[key], config, offline=offline,
                                                 session=session, now=now,
                                                 unreachable=unreachable)
        frames[key] = validated
        provenance.append(prov)
    frame = combine(frames, config.trailing_days)
    stamps = [p.data_as_of for p in provenance if p.data_as_of]
    vintage = DataVintage(
        data_as_of=min(stamps) if stamps else None,
        loaded_at=now.isoformat(timespec="seconds"),
        first_date=str(frame["date"].iloc[0].date()),
        last_date_kept=str(frame["date"].iloc[-1].date()),
        trimmed_days=config.trailing_days)
    return SFSeries(frame, SeriesProvenance(vintage, tuple(provenance)))
