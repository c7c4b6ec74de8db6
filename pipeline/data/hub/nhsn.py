"""NHSN hospital admissions and NSSP ED-visit shares for the hub's 53 locations: live from
data.cdc.gov with cache fallback, or imported from a hub's target data; every vintage kept.

What the CDC COVID-19 Forecast Hub forecasts (FluSight and the RSV hub likewise): weekly
confirmed admissions from NHSN's Hospital Respiratory Data (HRD) and the share of emergency
department visits due to the disease (NSSP), for the US, the 50 states, DC and Puerto Rico, by
weeks ending on Saturday. Every release revises recent weeks, so every release is a **vintage**,
dated by the day it was known (``as_of``: the hub's release Wednesday for imports, the fetch day
for live reads). The disease is a choice: ``covid``, ``flu``, ``rsv``.

Live (data.cdc.gov, Socrata SODA, through the shared pager and bounded transport,
:mod:`pipeline.data.core.soda`):

* admissions: HRD official ``ua7e-t2fy`` (or preliminary ``mpgq-jmmr``), ``$select`` =
  ``weekendingdate, jurisdiction, totalconf{c19,flu,rsv}newadm``, ``$order`` = week then
  jurisdiction (a total order, so pages neither overlap nor skip), weeks from ``first_week``
  (2024-11-09, the first week of the hub's target data; reporting is mandatory again from
  2024-11-01); ``jurisdiction`` ``USA`` → ``US``, postal abbreviations → FIPS;
* ED shares: NSSP ``rdmq-nq56``, rows with ``county`` = "All" (a state's or the nation's own
  row; the others are sub-state areas), ``geography`` (a state's name, "United States") and
  ``percent_visits_{covid,influenza,rsv}`` / 100. The column names are those the delphi ``nssp``
  indicator reads (cmu-delphi/covidcast-indicators); not checked against the live portal here.

Each payload passes the validation gate and the revision policy
(:mod:`pipeline.data.hub.nhsn_vintages`) and is committed under the cache lock; any fault falls
back to the cached vintage with a note (:mod:`pipeline.data.core.fallback`). Imports:
:mod:`pipeline.data.hub.target_import`. The interface the engine calls is re-exported here.
"""
from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import date, datetime
from pathlib import Path
from typing import Literal
from urllib.parse import urlsplit

import requests

from pipeline.data.core.cache import CacheManifest, DatasetCache, SourceKind, utc_now
from pipeline.data.core.fallback import DEFAULT_LOCK_TIMEOUT_S, live_or_cache, no_cache_error
from pipeline.data.hub.target_import import (HubImportSummary, VintageImport,
                                             import_hub_time_series, import_target_csv)
from pipeline.data.hub.nhsn_vintages import (ED_COVID, ED_FLU, ED_RSV, FIRST_WEEK, HOSP_COVID,
                                             HOSP_FLU, HOSP_RSV, HRD_OFFICIAL, HRD_PRELIMINARY,
                                             NSSP, TARGETS, TargetSpec, WeeklyVintage,
                                             cached_weekly_vintages, commit_weekly, disease_targets,
                                             parse_vintage, skipped_note, target_spec,
                                             read_with_holds, vintage_as_of)
from pipeline.data.hub.held_locations import read_holds
from pipeline.data.core.soda import SodaClient, SodaConfig
from pipeline.errors import ConfigError

log = logging.getLogger(__name__)

BASE_URL_ENV = "FLOWCAST_NHSN_BASE_URL"
APP_TOKEN_ENV = "FLOWCAST_NHSN_APP_TOKEN"
DEFAULT_BASE_URL = "https://data.cdc.gov"
IMPORT_HINT = ("import a hub's target data with `flowcast data import <hub folder or "
               "time-series.parquet>` (e.g. ../shared/data/nhsn)")


@dataclass(frozen=True)
class NHSNClientConfig(SodaConfig):
    """data.cdc.gov through the shared transport. Size caps from the genuine payloads: a page
    of 1,000 HRD rows with the three selected fields is 98 KB, of NSSP rows 116 KB (built from
    the hub's real vintages as the portal writes them); a page may have 1 MB, one target's
    pages together 16 MB."""

    base_url: str | None = None          # None: $FLOWCAST_NHSN_BASE_URL or data.cdc.gov
    app_token_env: str = APP_TOKEN_ENV
    max_body_bytes: int = 1 << 20
    max_fetch_bytes: int = 16 << 20


def resolve_base_url(explicit: str | None = None) -> str:
    """``explicit``, else ``$FLOWCAST_NHSN_BASE_URL``, else data.cdc.gov; checked at use, so a
    bad value fails the fetch (never an import, never hidden by the cache)."""
    value = (explicit if explicit is not None else os.environ.get(BASE_URL_ENV, "")).strip()
    value = value or DEFAULT_BASE_URL
    parts = urlsplit(value)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ConfigError(f"NHSN base URL must be http(s)://host[/path], got {value!r} "
                          f"(--nhsn-base-url / ${BASE_URL_ENV})")
    return value


@dataclass(frozen=True)
class NHSNConfig:
    """What to load: ``disease``'s admissions and ED share (or ``targets``), how and where."""

    disease: Literal["covid", "flu", "rsv"] = "covid"
    targets: tuple[str, ...] | None = None        # None: the disease's two targets
    release: Literal["official", "preliminary"] = "official"
    client: NHSNClientConfig = field(default_factory=NHSNClientConfig)
    data_dir: Path | None = None
    accept_revisions: bool = False
    lock_timeout_s: float = DEFAULT_LOCK_TIMEOUT_S
    first_week: date = FIRST_WEEK

    def __post_init__(self) -> None:
        for target in self.chosen_targets():
            target_spec(target)
        if self.release not in ("official", "preliminary"):
            raise ConfigError(f"release must be official or preliminary, got {self.release!r}")

    def chosen_targets(self) -> tuple[str, ...]:
        return self.targets if self.targets is not None else disease_targets(self.disease)


@dataclass(frozen=True)
class NHSNProvenance:
    """Where a loaded vintage came from, how old it is, why the cache was used, what the gate
    skipped."""

    target: str
    dataset_id: str
    source_kind: SourceKind
    source: str
    fetched_at: str
    sha256: str
    as_of: str
    first_week: str
    last_week: str
    from_cache: bool
    stale_days: float
    final_url: str | None = None
    notes: tuple[str, ...] = ()
    skipped: Mapping[str, str] = field(default_factory=dict)
    held: Mapping[str, str] = field(default_factory=dict)   # revisions waiting, per location


@dataclass(frozen=True)
class NHSNLoad:
    """The latest vintage of each target and its provenance."""

    vintages: Mapping[str, WeeklyVintage]
    provenance: Mapping[str, NHSNProvenance]

    def __getitem__(self, target: str) -> WeeklyVintage:
        return self.vintages[target]

    @property
    def stale(self) -> bool:
        return any(p.from_cache for p in self.provenance.values())


def _provenance(manifest: CacheManifest, vintage: WeeklyVintage, *, from_cache: bool,
                stale_days: float, notes: tuple[str, ...], cache: DatasetCache) -> NHSNProvenance:
    waiting = read_holds(cache.directory(target_spec(vintage.target))).waiting()
    return NHSNProvenance(
        target=vintage.target, dataset_id=manifest.dataset_id,
        source_kind=manifest.source_kind, source=manifest.source,
        fetched_at=manifest.fetched_at, sha256=manifest.sha256,
        as_of=str(vintage.as_of.date()), first_week=manifest.first_date,
        last_week=manifest.last_date, from_cache=from_cache, stale_days=stale_days,
        final_url=manifest.final_url, notes=notes + skipped_note(vintage),
        skipped=dict(vintage.skipped),
        held={loc: f"since the release of {h.since}: {h.reason}; "
                   + ("forecast from its accepted series" if loc in vintage.held
                      else "left out") for loc, h in waiting.items()})


def _from_cache(cache: DatasetCache, spec: TargetSpec, now: datetime,
                why: str | None) -> tuple[WeeklyVintage, NHSNProvenance]:
    cached = cache.load(spec)
    if cached is None:
        raise no_cache_error(f"NHSN data for {spec.target!r}", cache.directory(spec), why,
                             fetch="flowcast data fetch --source nhsn", otherwise=IMPORT_HINT)
    as_of = date.fromisoformat(str(cached.manifest.data_as_of)[:10])
    vintage = read_with_holds(cache, spec, parse_vintage(
        spec, cached.payload, suffix=cached.path.suffix.lstrip("."), as_of=as_of,
        source=str(cached.path)))
    stale = cached.manifest.age_days(now)
    notes = ((why,) if why else ()) + (
        f"using cache: the vintage of {as_of}, fetched {stale:.0f} days ago (its last week "
        f"ends {cached.manifest.last_date})",)
    log.warning("NHSN %s: %s", spec.target, "; ".join(notes))
    return vintage, _provenance(cached.manifest, vintage, from_cache=True, stale_days=stale,
                                notes=notes, cache=cache)


def _query(spec: TargetSpec, config: NHSNConfig) -> tuple[str, tuple[str, ...], tuple[str, ...],
                                                          str]:
    """(resource, order, select, where) of the live read of ``spec``."""
    since = config.first_week.isoformat()
    if spec.kind == "admissions":
        resource = HRD_OFFICIAL if config.release == "official" else HRD_PRELIMINARY
        return (resource, ("weekendingdate", "jurisdiction"),
                ("weekendingdate", "jurisdiction", spec.live_column),
                f"weekendingdate >= '{since}'")
    return (NSSP, ("week_end", "geography"),
            ("week_end", "geography", "county", spec.live_column), "county = 'All'")


def _fetch_live(cache: DatasetCache, spec: TargetSpec, config: NHSNConfig,
                session: requests.Session | None, now: datetime
                ) -> tuple[WeeklyVintage, NHSNProvenance]:
    base = resolve_base_url(config.client.base_url)
    resource, order, select, where = _query(spec, config)
    got = SodaClient(config.client, base, source="NHSN", session=session).fetch(
        resource, order=order, select=select, where=where)
    vintage = parse_vintage(spec, got.payload, suffix="json", as_of=now.date(),
                            source=got.final_url)
    committed = commit_weekly(cache, vintage, got.payload, suffix="json", source_kind="api",
                              source=got.url, older="refuse", final_url=got.final_url,
                              accept_revisions=config.accept_revisions,
                              lock_timeout_s=config.lock_timeout_s, today=now.date())
    assert committed.manifest is not None  # older="refuse": live or refused, never archived
    vintage = read_with_holds(cache, spec, vintage)
    notes = (f"{resource}: {len(got.rows):,} rows in {got.pages} page(s)",)
    return vintage, _provenance(committed.manifest, vintage, from_cache=False, stale_days=0.0,
                                notes=notes, cache=cache)


def load_nhsn(config: NHSNConfig | None = None, *, offline: bool = False,
              session: requests.Session | None = None, now: datetime | None = None) -> NHSNLoad:
    """The latest vintage of each of ``config``'s targets, live with cache fallback (cache only
    when ``offline``). A fault falls back to the cached vintage with a note saying why and how
    old it is (``provenance[target].from_cache``, ``stale_days``); once data.cdc.gov is
    unreachable, the other target is read from the cache without trying again. Without a
    cache: :class:`OfflineError` naming the import command (a rejected payload: its own
    error)."""
    config = config or NHSNConfig()
    now = now or utc_now()
    cache = DatasetCache.default(config.data_dir)
    vintages: dict[str, WeeklyVintage] = {}
    provenance: dict[str, NHSNProvenance] = {}
    unreachable: str | None = None
    for target in config.chosen_targets():
        spec = target_spec(target)
        if offline or unreachable is not None:
            why = None if offline else (f"data.cdc.gov unreachable (an earlier target's fetch "
                                        f"failed), so {target} was not retried")
            vintages[target], provenance[target] = _from_cache(cache, spec, now, why)
            continue
        live = live_or_cache(lambda: _fetch_live(cache, spec, config, session, now),
                             source="NHSN", has_cache=lambda: cache.has(spec))
        if live.value is None:
            unreachable = live.why if live.unreachable else None
            live_value = _from_cache(cache, spec, now, live.why)
        else:
            live_value = live.value
        vintages[target], provenance[target] = live_value
    return NHSNLoad(vintages, provenance)


__all__ = ["BASE_URL_ENV", "ED_COVID", "ED_FLU", "ED_RSV", "HOSP_COVID", "HOSP_FLU", "HOSP_RSV",
           "TARGETS", "HubImportSummary", "NHSNClientConfig", "NHSNConfig", "NHSNLoad",
           "NHSNProvenance", "VintageImport", "WeeklyVintage", "cached_weekly_vintages",
           "import_hub_time_series", "import_target_csv", "load_nhsn", "resolve_base_url",
           "vintage_as_of"]
