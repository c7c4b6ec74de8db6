"""The CDPH county source: live from the CHHS portal, cached, revision-checked, with fallback.

Flow of one vintage (a download of ``covid19cases_test.csv``, live or imported)::

    bytes -> parse_cdph_csv (pipeline.data.california.cdph: the file must be CDPH's; every county through
             the validation gate, pipeline.data.core.gate: a county that fails is skipped, named)
          -> VintageArchive.commit (pipeline.data.core.vintages) under the dataset's lock: an older
             vintage is archived (imports) or refused (live); else the revision policy against
             the live copy -> manifest swapped; the bytes also kept in vintages/

Cache layout (``<data dir>/chhs/covid-19-time-series-metrics-by-county-and-state/``; the
transactional store of :mod:`pipeline.data.core.cache`)::

    manifest.json                   the live vintage: source, fetched-at, dates, sha256, ...
    payload-<sha256[:16]>.csv       the live (and the previous) payload, content-addressed
    vintages/<as-of>-<sha[:16]>.csv every vintage ever accepted, immutable (nowcasting needs them)
    held/payload-<sha[:16]>.csv     payloads the revision policy refused, with .reason.json

Revision policy (a :class:`~pipeline.data.core.revision_policy.RevisionPolicy`, judged county by
county: :mod:`pipeline.data.california.county_revisions`): a new vintage against the live one may
not end earlier, start later nor drop a county; a county whose settled days change beyond
max(100, 50 %) is held alone (named in every vintage read from then on, its accepted series
kept; :func:`accept_county_revisions` after review), the vintage live for the others; more than
a quarter of the counties, or the other counties' statewide total falling by more than 2 %,
holds the payload for review (``held/``; ``--accept-revisions`` takes it). On the six real
vintages the four-month step 2021-04-28 → 2021-09-06 holds Los Angeles alone.

The validation gate runs before any commit and on every read of a cached vintage: a county that
fails it is skipped and named (``CDPHVintage.skipped``, and a note on the provenance), the other
counties are used. A held cache lock (another run stuck mid-commit) falls back to the cache like
an unreachable portal (:mod:`pipeline.data.core.fallback`).
"""
from __future__ import annotations

import contextlib
import csv
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import date, datetime
from pathlib import Path

import pandas as pd
import requests

from pipeline.data.core.cache import (CachedPayload, CacheManifest, DatasetCache, SourceKind,
                                      utc_now)
from pipeline.data.core.revision_policy import RevisionPolicy
from pipeline.data.california.cdph import CDPHFormatError, CDPHVintage, parse_cdph_csv
from pipeline.data.california.chhs import (BASE_URL_ENV, CDPH_COUNTIES, CHHSClient,
                                           CHHSClientConfig, CKANResourceSpec)
from pipeline.data.core.fallback import DEFAULT_LOCK_TIMEOUT_S, live_or_cache, no_cache_error
from pipeline.data.core.vintages import Committed, VintageArchive
from pipeline.data.california.county_revisions import (DEFAULT_POLICY, check_cdph_successor,
                                                     with_county_holds)
from pipeline.data.hub.held_locations import (Hold, Holds, read_holds, record_release,
                                               write_holds)
from pipeline.errors import ConfigError, DataSourceError, OfflineError, ValidationError

log = logging.getLogger(__name__)

PARSED_DIR = "parsed"         # in vintages/: each parsed vintage, by its bytes' hash
SPEC: CKANResourceSpec = CDPH_COUNTIES
_IMPORT_HINT = (f"import a downloaded covid19cases_test.csv ({SPEC.download_url()}) with "
                f"`flowcast data import FILE`")




@dataclass(frozen=True)
class CDPHConfig:
    """Where and how to load the CDPH county vintage."""

    client: CHHSClientConfig = field(default_factory=CHHSClientConfig)
    data_dir: Path | None = None          # None -> $FLOWCAST_DATA_DIR or ./data
    accept_revisions: bool = False        # take a payload the revision policy would hold
    policy: RevisionPolicy = DEFAULT_POLICY
    lock_timeout_s: float = DEFAULT_LOCK_TIMEOUT_S  # then the fetched payload is dropped


@dataclass(frozen=True)
class CDPHProvenance:
    """Where a loaded vintage came from; the fields of the DataSF loader's
    :class:`pipeline.data.sf.series.DatasetProvenance` (without its DataSF-only stamp)."""

    dataset_key: str
    dataset_id: str
    source_kind: SourceKind
    source: str             # package_show URL (live) or the imported file
    fetched_at: str
    sha256: str
    row_count: int
    first_date: str
    last_date: str          # the vintage's last day (its as-of date)
    from_cache: bool
    stale_days: float       # age of the cached copy when it was used; 0 for a live fetch
    final_url: str | None = None
    notes: tuple[str, ...] = ()
    skipped: Mapping[str, str] = field(default_factory=dict)  # county -> why the gate dropped it


@dataclass(frozen=True)
class CDPHLoad:
    """A loaded vintage and where it came from (live or cache, how old, why)."""

    vintage: CDPHVintage
    provenance: CDPHProvenance


# ---------------------------------------------------------------------------- validation


def is_cdph_export(columns: Sequence[str]) -> bool:
    """Does a CSV header look like CDPH's county file? ``area`` and ``area_type`` (no DataSF
    export has them) are enough, so a CDPH file missing another column is read as CDPH and its
    error names that column."""
    names = {str(c).strip().lower() for c in columns}
    return {"area", "area_type"} <= names


def validate_cdph_payload(data: bytes, source: str) -> CDPHVintage:
    """Parse (the file must be CDPH's) and gate every county (:mod:`pipeline.data.california.cdph`); a
    county that fails the gate is skipped, named; a file that is not CDPH's, or that no county
    passes, raises a named :class:`ValidationError`."""
    return parse_cdph_csv(data, source)


# ---------------------------------------------------------------------------- held counties


def counties_waiting(data_dir: str | os.PathLike[str] | None = None) -> dict[str, Hold]:
    """The counties whose revision waits for review, each with its hold."""
    return read_holds(DatasetCache.default(data_dir).directory(SPEC)).waiting()


def accept_county_revisions(counties: Sequence[str],
                            data_dir: str | os.PathLike[str] | None = None) -> dict[str, Hold]:
    """The operator accepts the waiting revision of each of ``counties`` alone: from the live
    vintage on, they read as released. Returns the holds ended."""
    cache = DatasetCache.default(data_dir)
    manifest = cache.read_manifest(SPEC)
    if manifest is None:
        raise ConfigError("no cached CDPH county vintage: nothing to accept")
    folder = cache.directory(SPEC)
    holds = read_holds(folder)
    write_holds(folder, holds.accepted(tuple(counties), live=manifest.last_date[:10]))
    return {c: holds.waiting()[c] for c in counties}


def _cached_vintage(live: CachedPayload, cache: DatasetCache) -> CDPHVintage | None:
    try:
        return parse_cached(cache, live.payload, str(live.path))
    except DataSourceError as exc:
        log.warning("cached CDPH vintage no longer parses (%s); replacing it", exc)
        return None


def commit_vintage(cache: DatasetCache, vintage: CDPHVintage, payload: bytes, *,
                   source_kind: SourceKind, source: str, final_url: str | None = None,
                   accept_revisions: bool = False, older: str = "refuse",
                   policy: RevisionPolicy = DEFAULT_POLICY,
                   lock_timeout_s: float = DEFAULT_LOCK_TIMEOUT_S) -> Committed:
    """Store an already validated vintage (:meth:`VintageArchive.commit`, under the cache lock):
    live if the revision policy allows it against the live copy; older than the live one,
    archived (``older="archive"``, imports) or refused (``"refuse"``, a live portal going
    back). A county revised beyond the policy is held alone (:mod:`pipeline.data.hub.
    held_locations`: its accepted series kept, named), the vintage live for the others; a
    vintage the policy refuses whole is held for review (the error names where) and the cache
    is unchanged."""
    folder = cache.directory(SPEC)
    holds = read_holds(folder)
    found: dict[str, str] = {}
    reference: list[str] = []

    def check(live: CachedPayload | None) -> None:
        if live is None or accept_revisions:
            return
        cached = _cached_vintage(live, cache)
        if cached is not None:
            found.update(check_cdph_successor(vintage, cached, policy,
                                              references=_references(cache, holds)))
            reference.append(str(cached.as_of.date()))

    frame = vintage.frame
    committed = archive(cache).commit(
        payload, as_of=vintage.as_of.date(), suffix="csv",
        older="archive" if older == "archive" and not accept_revisions else "refuse",
        check=check, accept_hint="`flowcast data fetch --source chhs --accept-revisions` (or "
                                 "`flowcast data import --accept-revisions FILE`)",
        source_kind=source_kind, source=source, row_count=len(frame),
        first_date=str(frame["date"].min().date()), last_date=str(vintage.as_of.date()),
        data_as_of=None, final_cumulative=None, final_url=final_url,
        lock_timeout_s=lock_timeout_s)
    if committed.action == "live":
        record_release(folder, holds, as_of=str(vintage.as_of.date()), accepted=accept_revisions,
                       found=found, reference=reference[0] if reference else None)
    return committed


def _references(cache: DatasetCache, holds: Holds) -> dict[str, CDPHVintage]:
    """Each waiting county's reference vintage (its last accepted series), from the archive."""
    waiting = holds.waiting()
    if not waiting:
        return {}
    kept = archive(cache)
    by_date = {str(as_of): path for as_of, path in kept.listing()}
    return {county: parse_cached(cache, kept.read(by_date[h.reference]), str(by_date[h.reference]))
            for county, h in waiting.items() if h.reference in by_date}


def archive(cache: DatasetCache) -> VintageArchive:
    return VintageArchive(cache, SPEC)


def vintages_dir(cache: DatasetCache) -> Path:
    return archive(cache).folder


def parse_cached(cache: DatasetCache, data: bytes, source: str) -> CDPHVintage:
    """A cached payload's vintage, its parse kept beside the vintages (``parsed/``)."""
    return parse_cdph_csv(data, source, parsed_dir=vintages_dir(cache) / PARSED_DIR)


def skipped_note(vintage: CDPHVintage) -> tuple[str, ...]:
    """The provenance note naming the counties left out, each with why: the validation gate
    skipped it, or its revision is held for review (none: no note)."""
    if not vintage.skipped:
        return ()
    return (f"{len(vintage.skipped)} county(ies) left out of the vintage of "
            f"{vintage.as_of.date()}: " + "; ".join(vintage.skipped.values()),)


# ---------------------------------------------------------------------------- loading


def _provenance(manifest: CacheManifest, vintage: CDPHVintage, *, from_cache: bool,
                stale_days: float, notes: tuple[str, ...]) -> CDPHProvenance:
    return CDPHProvenance(
        dataset_key=manifest.dataset_key, dataset_id=manifest.dataset_id,
        source_kind=manifest.source_kind, source=manifest.source,
        fetched_at=manifest.fetched_at, sha256=manifest.sha256, row_count=manifest.row_count,
        first_date=manifest.first_date, last_date=manifest.last_date, from_cache=from_cache,
        stale_days=stale_days, final_url=manifest.final_url,
        notes=notes + skipped_note(vintage), skipped=dict(vintage.skipped))


def _no_cache(cache: DatasetCache, why: str | None) -> OfflineError:
    return no_cache_error("CDPH county data", cache.directory(SPEC), why,
                          fetch="flowcast data fetch --source chhs", otherwise=_IMPORT_HINT)


def require_cdph_cached(config: CDPHConfig | None = None) -> None:
    """The error an offline read would end in, now and without reading anything (a run checks
    before any work)."""
    cache = DatasetCache.default((config or CDPHConfig()).data_dir)
    if not cache.has(SPEC):
        raise _no_cache(cache, None)


def _from_cache(cache: DatasetCache, now: datetime, why: str | None) -> CDPHLoad:
    cached = cache.load(SPEC)
    if cached is None:
        raise _no_cache(cache, why)
    vintage = with_county_holds(parse_cached(cache, cached.payload, str(cached.path)),
                                read_holds(cache.directory(SPEC)))
    stale = cached.manifest.age_days(now)
    data_age = (now.date() - date.fromisoformat(cached.manifest.last_date[:10])).days
    notes = ((why,) if why else ()) + (
        f"using cache, fetched {stale:.0f} days ago (its last day, {cached.manifest.last_date}, "
        f"is {data_age} days before today)",)
    log.warning("CDPH counties: %s", "; ".join(notes))
    return CDPHLoad(vintage, _provenance(cached.manifest, vintage, from_cache=True,
                                         stale_days=stale, notes=notes))


def _fetch_live(cache: DatasetCache, config: CDPHConfig, session: requests.Session | None,
                now: datetime) -> CDPHLoad:
    fetched = CHHSClient(config.client, session=session).fetch(SPEC)
    source = fetched.package_url
    vintage = validate_cdph_payload(fetched.payload, fetched.final_url)
    if vintage.as_of > pd.Timestamp(now.date()) + pd.Timedelta(days=1):
        raise ValidationError(f"{fetched.final_url}: last date {vintage.as_of.date()} is after "
                              f"today ({now.date()}); refused")
    committed = commit_vintage(cache, vintage, fetched.payload, source_kind="api",
                               source=source, final_url=fetched.final_url,
                               accept_revisions=config.accept_revisions, policy=config.policy,
                               lock_timeout_s=config.lock_timeout_s)
    assert committed.manifest is not None  # older="refuse": live or refused, never archived
    vintage = with_county_holds(vintage, read_holds(cache.directory(SPEC)))
    notes = (f"CKAN resource {fetched.resource.id or fetched.resource.name}, last modified "
             f"{fetched.resource.last_modified or 'unknown'}",)
    return CDPHLoad(vintage, _provenance(committed.manifest, vintage, from_cache=False,
                                         stale_days=0.0, notes=notes))


def load_cdph(config: CDPHConfig | None = None, *, offline: bool = False,
              session: requests.Session | None = None, now: datetime | None = None) -> CDPHLoad:
    """The county vintage, live with cache fallback (cache only when ``offline``).

    Any network fault (after the retries) or payload fault (not the CSV, a dropped county, an
    implausible count, a revision beyond policy, ...) falls back to the cached copy, with a note
    saying why and how old it is. Without a cache: offline an :class:`OfflineError` naming
    ``flowcast data import``; online the fault itself. A configuration error (a base URL
    without a scheme) is raised, never hidden by the cache."""
    config = config or CDPHConfig()
    now = now or utc_now()
    cache = DatasetCache.default(config.data_dir)
    if offline:
        return _from_cache(cache, now, why=None)
    live = live_or_cache(lambda: _fetch_live(cache, config, session, now), source="CHHS portal",
                         has_cache=lambda: cache.has(SPEC))
    if live.value is not None:
        return live.value
    return _from_cache(cache, now, why=live.why)


def load_cdph_vintage(config: CDPHConfig | None = None, *, offline: bool = False,
                      session: requests.Session | None = None,
                      now: datetime | None = None) -> CDPHVintage:
    """:func:`load_cdph` without the provenance (the notes are logged)."""
    return load_cdph(config, offline=offline, session=session, now=now).vintage


def cached_vintages(data_dir: str | os.PathLike[str] | None = None) -> list[CDPHVintage]:
    """Every vintage the cache holds, oldest first (one per as-of date: the last written), each
    through the validation gate (its skipped counties named on it).

    Each file's sha256 must match the prefix in its name (a damaged file is a
    :class:`~pipeline.data.core.cache.CacheDamagedError`). A cache filled before ``vintages/``
    existed still yields its live copy."""
    cache = DatasetCache.default(data_dir)
    kept, holds = archive(cache), read_holds(cache.directory(SPEC))
    vintages: list[CDPHVintage] = []
    for as_of, path in kept.listing():
        vintage = with_county_holds(parse_cached(cache, kept.read(path), str(path)), holds)
        if vintage.as_of.date() != as_of:
            raise CDPHFormatError(f"cached CDPH vintage {path} ends {vintage.as_of.date()}, not "
                                  f"on the date in its name")
        vintages.append(vintage)
    if not vintages:
        live = cache.load(SPEC)
        if live is not None:
            vintages.append(parse_cached(cache, live.payload, str(live.path)))
    return vintages


# ---------------------------------------------------------------------------- import


@dataclass(frozen=True)
class CDPHImportSummary:
    path: Path
    as_of: str
    first_date: str
    counties: int
    row_count: int
    action: str              # "imported" | "archived" | "skipped"
    note: str = ""


def peek_columns(path: str | os.PathLike[str]) -> list[str]:
    """The header of a CSV file (its first row), for telling CDPH from DataSF exports; [] when
    the file cannot be read as text."""
    with contextlib.suppress(OSError, UnicodeDecodeError, StopIteration, csv.Error):
        with open(path, encoding="utf-8-sig", newline="") as handle:
            return [c.strip() for c in next(csv.reader(handle))]
    return []


@dataclass(frozen=True)
class CheckedExport:
    """A CDPH file read and validated, not yet stored."""

    path: Path
    vintage: CDPHVintage
    payload: bytes


def validate_cdph_exports(paths: Sequence[str | os.PathLike[str]]) -> list[CheckedExport]:
    """Read and validate every file (the first problem raises; nothing is stored)."""
    checked = []
    for p in paths:
        path = Path(p)
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise CDPHFormatError(f"cannot read CDPH export {path}: {exc.strerror or exc}") \
                from exc
        checked.append(CheckedExport(path, validate_cdph_payload(data, str(path)), data))
    return checked


def import_cdph_exports(paths: Sequence[str | os.PathLike[str]],
                        data_dir: str | os.PathLike[str] | None = None, *,
                        if_empty: bool = False, accept_revisions: bool = False,
                        policy: RevisionPolicy = DEFAULT_POLICY) -> list[CDPHImportSummary]:
    """Validate every file first (nothing is stored if one fails), then store them oldest
    first (:func:`store_cdph_exports`)."""
    return store_cdph_exports(validate_cdph_exports(paths), data_dir, if_empty=if_empty,
                              accept_revisions=accept_revisions, policy=policy)


def store_cdph_exports(checked: Sequence[CheckedExport],
                       data_dir: str | os.PathLike[str] | None = None, *,
                       if_empty: bool = False, accept_revisions: bool = False,
                       policy: RevisionPolicy = DEFAULT_POLICY) -> list[CDPHImportSummary]:
    """Store validated files oldest first: each becomes the live copy if the revision policy
    allows (a refusal stops here: the files before it are stored, the rest are not); one older
    than the live copy is kept in ``vintages/`` only (archived downloads come in any order)."""
    cache = DatasetCache.default(data_dir)
    summaries = []
    # --if-empty is decided once, before the first file: an archive of several vintages goes in
    # whole, or not at all
    held_before = cache.load_or_damage(SPEC)[0]
    skip_all = (if_empty and held_before is not None
                and _cached_vintage(held_before, cache) is not None)
    for path, vintage, data in ((c.path, c.vintage, c.payload)
                                for c in sorted(checked, key=lambda c: c.vintage.as_of)):
        note, action = "", "imported"
        if skip_all:
            action, note = "skipped", "cache already holds CDPH county data (--if-empty)"
        else:
            damage = cache.load_or_damage(SPEC)[1]
            # older than the live vintage -> archived, decided under the lock (concurrent
            # importers of older and newer vintages both end where they belong)
            committed = commit_vintage(cache, vintage, data, source_kind="csv-import",
                                       source=str(path.resolve()), older="archive",
                                       accept_revisions=accept_revisions, policy=policy)
            if committed.action == "archived":
                action = "archived"
                note = (f"older than the live vintage of {committed.live_as_of}: kept in "
                        f"{vintages_dir(cache)}, live copy unchanged")
            elif damage:
                note = f"repaired a damaged cache: {damage}"
        if vintage.skipped:
            note = "; ".join(filter(None, (note, *skipped_note(vintage))))
        frame = vintage.frame
        summaries.append(CDPHImportSummary(
            path=path, as_of=str(vintage.as_of.date()), first_date=str(frame["date"].min().date()),
            counties=len(vintage.counties), row_count=len(frame), action=action, note=note))
    return summaries


__all__ = ["BASE_URL_ENV", "CDPHConfig", "CDPHImportSummary", "CDPHLoad", "CDPHProvenance",
           "CheckedExport", "accept_county_revisions", "cached_vintages", "check_cdph_successor",
           "counties_waiting", "with_county_holds",
           "commit_vintage", "import_cdph_exports", "is_cdph_export",
           "load_cdph", "load_cdph_vintage", "store_cdph_exports", "validate_cdph_exports",
           "validate_cdph_payload"]
