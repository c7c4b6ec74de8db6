"""On-disk cache of source payloads: ``<data dir>/datasf/<dataset-id>/`` (DataSF) and
``<data dir>/chhs/<dataset-id>/`` (CDPH via the CHHS portal, :mod:`pipeline.data.california.cdph_source`).

Layout of one dataset's directory::

    manifest.json               what is cached: source, fetched-at, rows, dates, sha256, ...
    payload-<sha256[:16]>.json  raw API rows (JSON array)   or
    payload-<sha256[:16]>.csv   raw CSV export bytes (``flowcast data import``)

A tiny transactional store (issue 15: concurrent writers used to delete each other's payloads):

* payloads are content-addressed and immutable: the name is the hash, so two writers of the
  same bytes write the same file and writers of different bytes never touch each other's file;
* a commit (:meth:`DatasetCache.store`) runs under the dataset's file lock
  (``datasf/.locks/<id>.lock``, ``filelock``): it re-reads the live manifest, runs the
  caller's ``check`` against the live copy (shrinkage, backwards dates, revision policy: :mod:`pipeline.data.sf.revisions`), writes the
  payload (atomic temp file + ``os.replace``), swaps the manifest atomically, and only then
  deletes payloads that neither the new nor the previous manifest names. A writer therefore
  never deletes a payload the live manifest references, and a crash at any point leaves a
  manifest pointing at its own complete payload;
* readers take no lock: a reader whose payload was collected between reading the manifest and
  the payload reads the (newer) manifest again;
* on read the manifest's fields are checked (dates, hash, file name) and the payload's sha256 is
  compared with the manifest: any damage raises :class:`CacheDamagedError` naming the problem.

Callers validate a payload *before* :meth:`DatasetCache.store`, so a bad payload never replaces
a good cache. A payload refused by the revision policy is kept under ``held/`` for review.

The data directory is ``$FLOWCAST_DATA_DIR`` or ``./data``.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import re
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, fields
from datetime import UTC, date, datetime
from pathlib import Path
from typing import Literal, Protocol

from pipeline.errors import DataSourceError, ValidationError
from pipeline.io import (LOCK_TIMEOUT_S, atomic_write_bytes, atomic_write_json, file_lock,
                         sha256_bytes, sha256_file, sweep_stale)

log = logging.getLogger(__name__)

DATA_DIR_ENV = "FLOWCAST_DATA_DIR"
MANIFEST_NAME = "manifest.json"
MANIFEST_VERSION = 2          # 2 added final_url and previous_payload_file; 1 still reads
LOCKS_DIR = ".locks"
HELD_DIR = "held"
HELD_KEEP = 5                 # held-for-review payloads kept per dataset (newest)
_PAYLOAD_RE = re.compile(r"^payload-[0-9a-f]{16}\.(json|csv)$")
_SHA_RE = re.compile(r"^[0-9a-f]{64}$")
_READ_ATTEMPTS = 5

SourceKind = Literal["api", "csv-import"]
DEFAULT_CACHE_FOLDER = "datasf"


class CacheSpec(Protocol):
    """What the cache needs of a dataset: its key and id (a DataSF
    :class:`~pipeline.data.sf.datasf.DatasetSpec`, a CKAN resource spec, ...). A spec with a
    ``cache_folder`` attribute is kept under ``<data dir>/<cache_folder>/<id>/``; others under
    ``datasf/``."""

    @property
    def key(self) -> str: ...

    @property
    def dataset_id(self) -> str: ...


def cache_folder(spec: CacheSpec) -> str:
    return str(getattr(spec, "cache_folder", DEFAULT_CACHE_FOLDER))


def data_dir(override: str | os.PathLike[str] | None = None) -> Path:
    """The data directory: ``override``, else ``$FLOWCAST_DATA_DIR``, else ``./data``."""
    if override is not None:
        return Path(override)
    return Path(os.environ.get(DATA_DIR_ENV) or "data")


@contextlib.contextmanager
def data_folder(path: Path) -> Iterator[None]:
    """Run with ``path`` as the flowcast data folder (cache, model store, memo): a replay's
    week, a benchmark's scratch folder; the variable as it was afterwards."""
    before = os.environ.get(DATA_DIR_ENV)
    os.environ[DATA_DIR_ENV] = str(path)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(DATA_DIR_ENV, None)
        else:
            os.environ[DATA_DIR_ENV] = before


def utc_now() -> datetime:
    return datetime.now(UTC)


class CacheDamagedError(DataSourceError):
    """The cache manifest or payload is unreadable, inconsistent or missing."""


@dataclass(frozen=True)
class CacheManifest:
    dataset_key: str
    dataset_id: str
    source_kind: SourceKind
    source: str              # URL for API fetches, absolute file path for imports
    fetched_at: str          # ISO-8601 UTC, when flowcast read the source
    row_count: int
    first_date: str
    last_date: str
    sha256: str
    payload_file: str
    data_as_of: str | None = None     # DataSF's own vintage stamp, when the payload carries it
    final_cumulative: int | None = None
    version: int = MANIFEST_VERSION
    final_url: str | None = None      # where the answer came from after redirects (API only)
    previous_payload_file: str | None = None  # kept on disk for readers of the previous manifest

    @property
    def fetched_at_dt(self) -> datetime:
        return datetime.fromisoformat(self.fetched_at)

    def age_days(self, now: datetime | None = None) -> float:
        return ((now or utc_now()) - self.fetched_at_dt).total_seconds() / 86400.0


def manifest_problem(fields_: dict[str, object]) -> str | None:
    """What is wrong with a manifest's fields (None when nothing): one phrase naming the field."""
    def bad(name: str, why: str) -> str:
        return f"{name} {fields_.get(name)!r} {why}"

    try:
        stamp = datetime.fromisoformat(str(fields_["fetched_at"]))
    except (KeyError, ValueError):
        return bad("fetched_at", "is not an ISO-8601 timestamp")
    if stamp.tzinfo is None:
        return bad("fetched_at", "has no time zone")
    for name in ("first_date", "last_date"):
        try:
            date.fromisoformat(str(fields_[name])[:10])
        except (KeyError, ValueError):
            return bad(name, "is not a YYYY-MM-DD date")
    if str(fields_["first_date"])[:10] > str(fields_["last_date"])[:10]:
        return bad("first_date", f"is after last_date {fields_['last_date']!r}")
    row_count = fields_.get("row_count")
    if not isinstance(row_count, int) or row_count < 1:
        return bad("row_count", "is not a positive integer")
    if not _SHA_RE.match(str(fields_.get("sha256"))):
        return bad("sha256", "is not a sha256 hex digest")
    if not _PAYLOAD_RE.match(str(fields_.get("payload_file"))):
        return bad("payload_file", "is not a payload-<hash>.json|csv name")
    if data_as_of := fields_.get("data_as_of"):
        try:
            datetime.fromisoformat(str(data_as_of))
        except ValueError:
            return bad("data_as_of", "is not an ISO-8601 timestamp")
    return None


@dataclass(frozen=True)
class CachedPayload:
    manifest: CacheManifest
    payload: bytes
    path: Path


# A commit's check sees the live copy (None when there is none or it is damaged) and raises to
# refuse the new payload.
CommitCheck = Callable[[CachedPayload | None], None]


class RevisionRefusedError(ValidationError):
    """A valid payload that may not replace the cached copy (shrinks, goes back, rewrites):
    what a :data:`CommitCheck` raises; ``hold`` keeps it for review (:meth:`DatasetCache.hold`)."""

    def __init__(self, message: str, *, hold: bool = False) -> None:
        super().__init__(message)
        self.hold = hold  # True: breaks the revision policy -> keep it for review


@dataclass(frozen=True)
class DatasetCache:
    root: Path

    @classmethod
    def default(cls, override: str | os.PathLike[str] | None = None) -> DatasetCache:
        return cls(data_dir(override))

    def directory(self, spec: CacheSpec) -> Path:
        return self.root / cache_folder(spec) / spec.dataset_id

    def manifest_path(self, spec: CacheSpec) -> Path:
        return self.directory(spec) / MANIFEST_NAME

    def lock_path(self, spec: CacheSpec) -> Path:
        """Beside, not inside, the dataset directory: that holds only manifest and payloads."""
        return self.root / cache_folder(spec) / LOCKS_DIR / f"{spec.dataset_id}.lock"

    def has(self, spec: CacheSpec) -> bool:
        return self.manifest_path(spec).is_file()

    def read_manifest(self, spec: CacheSpec) -> CacheManifest | None:
        path = self.manifest_path(spec)
        if not path.is_file():
            return None
        fix = "re-run `flowcast data fetch` or `flowcast data import FILE`"
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(raw, dict):
                raise TypeError(f"expected a JSON object, got {type(raw).__name__}")
            known = {f.name for f in fields(CacheManifest)}
            manifest = CacheManifest(**{k: v for k, v in raw.items() if k in known})
        except (json.JSONDecodeError, TypeError, UnicodeDecodeError, OSError) as exc:
            raise CacheDamagedError(f"damaged cache manifest {path}: {exc}; {fix}") from exc
        problem = manifest_problem(asdict(manifest))
        if problem is not None:
            raise CacheDamagedError(f"damaged cache manifest {path}: {problem}; {fix}")
        return manifest

    def load(self, spec: CacheSpec) -> CachedPayload | None:
        """The cached payload, sha256-checked; ``None`` if nothing is cached.

        Without a lock: if a concurrent commit collected the payload between our reading the
        manifest and the payload, the manifest has changed, so read it again.
        """
        problem = ""
        for _ in range(_READ_ATTEMPTS):
            manifest = self.read_manifest(spec)
            if manifest is None:
                return None
            path = self.directory(spec) / manifest.payload_file
            try:
                payload = path.read_bytes()
            except FileNotFoundError:
                problem = (f"cache manifest {self.manifest_path(spec)} names {path.name}, which "
                           f"is missing")
            else:
                if sha256_bytes(payload) == manifest.sha256:
                    return CachedPayload(manifest, payload, path)
                problem = (f"cached payload {path} does not match its manifest sha256 "
                           f"(damaged); re-run `flowcast data fetch` or `data import`")
            if self.read_manifest(spec) == manifest:
                break  # not a race: the live manifest itself points at a bad payload
        raise CacheDamagedError(problem)

    def load_or_damage(self, spec: CacheSpec) -> tuple[CachedPayload | None, str | None]:
        """(payload, None), (None, None) when nothing is cached, (None, why) when damaged."""
        try:
            return self.load(spec), None
        except CacheDamagedError as exc:
            return None, str(exc)

    def store(self, spec: CacheSpec, payload: bytes, *, suffix: str, source_kind: SourceKind,
              source: str, row_count: int, first_date: str, last_date: str,
              data_as_of: str | None, final_cumulative: int | None,
              fetched_at: datetime | None = None, final_url: str | None = None,
              check: CommitCheck | None = None,
              lock_timeout_s: float = LOCK_TIMEOUT_S) -> CacheManifest:
        """Commit an already *validated* payload (see module doc); ``check`` may refuse it.

        After ``lock_timeout_s`` without the lock, :class:`pipeline.io.LockTimeoutError`; nothing
        is written, and readers (which take no lock) still see the committed copy."""
        digest = sha256_bytes(payload)
        payload_name = f"payload-{digest[:16]}.{suffix}"
        directory = self.directory(spec)
        directory.mkdir(parents=True, exist_ok=True)
        with file_lock(self.lock_path(spec), what=f"data cache {directory}",
                       timeout_s=lock_timeout_s):
            live, damage = self.load_or_damage(spec)
            if damage:
                log.warning("replacing damaged cache: %s", damage)
            if check is not None:
                check(live)
            target = directory / payload_name
            if not (target.is_file() and sha256_file(target) == digest):
                atomic_write_bytes(target, payload)
            previous = live.manifest.payload_file if live is not None else None
            manifest = CacheManifest(
                dataset_key=spec.key, dataset_id=spec.dataset_id, source_kind=source_kind,
                source=source, fetched_at=(fetched_at or utc_now()).isoformat(),
                row_count=row_count, first_date=first_date, last_date=last_date, sha256=digest,
                payload_file=payload_name, data_as_of=data_as_of,
                final_cumulative=final_cumulative, final_url=final_url,
                previous_payload_file=previous if previous != payload_name else None)
            atomic_write_json(directory / MANIFEST_NAME, asdict(manifest))
            self._collect(directory, keep={payload_name, previous})
        return manifest

    def _collect(self, directory: Path, keep: set[str | None]) -> None:
        """Delete payloads neither the live nor the previous manifest names (under the lock)."""
        for old in directory.glob("payload-*"):
            if old.name not in keep:
                with contextlib.suppress(FileNotFoundError):
                    old.unlink()
        sweep_stale(directory, (".*.tmp",))  # temp files of writers killed mid-write

    def hold(self, spec: CacheSpec, payload: bytes, *, suffix: str, reason: str) -> Path:
        """Keep a refused payload under ``held/`` for review (the newest ``HELD_KEEP``)."""
        held = self.directory(spec) / HELD_DIR
        path = held / f"payload-{sha256_bytes(payload)[:16]}.{suffix}"
        atomic_write_bytes(path, payload)
        atomic_write_json(path.with_name(path.name + ".reason.json"),
                          {"held_at": utc_now().isoformat(), "reason": reason})
        kept = sorted((p for p in held.glob("payload-*") if not p.name.endswith(".reason.json")),
                      key=lambda p: p.stat().st_mtime, reverse=True)
        for old in kept[HELD_KEEP:]:
            for stale in (old, old.with_name(old.name + ".reason.json")):
                with contextlib.suppress(FileNotFoundError):
                    stale.unlink()
        return path
