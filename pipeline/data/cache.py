"""On-disk cache of DataSF payloads: ``<data dir>/datasf/<dataset-id>/``.

Layout of one dataset's directory::

    manifest.json               what is cached: source, fetched-at, rows, dates, sha256, ...
    payload-<sha256[:16]>.json  raw API rows (JSON array)   or
    payload-<sha256[:16]>.csv   raw CSV export bytes (``flowcast data import``)

Consistency without locks: the payload is written first under a content-addressed name, then the
manifest is replaced atomically (``pipeline.io``) to point at it, then payloads no longer named by
the manifest are removed. A crash at any point leaves the previous manifest pointing at its own
complete payload. Callers validate a payload *before* :meth:`DatasetCache.store`, so a bad
payload never replaces a good cache. On read the payload's sha256 is checked against the manifest.

The data directory is ``$FLOWCAST_DATA_DIR`` or ``./data``.
"""
from __future__ import annotations

import contextlib
import json
import os
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

from pipeline.data.datasf import DatasetSpec
from pipeline.errors import DataSourceError
from pipeline.io import atomic_write_bytes, atomic_write_json, sha256_bytes

DATA_DIR_ENV = "FLOWCAST_DATA_DIR"
MANIFEST_NAME = "manifest.json"
MANIFEST_VERSION = 1

SourceKind = Literal["api", "csv-import"]


def data_dir(override: str | os.PathLike[str] | None = None) -> Path:
    """The data directory: ``override``, else ``$FLOWCAST_DATA_DIR``, else ``./data``."""
    if override is not None:
        return Path(override)
    return Path(os.environ.get(DATA_DIR_ENV) or "data")


def utc_now() -> datetime:
    return datetime.now(UTC)


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

    @property
    def fetched_at_dt(self) -> datetime:
        return datetime.fromisoformat(self.fetched_at)

    def age_days(self, now: datetime | None = None) -> float:
        return ((now or utc_now()) - self.fetched_at_dt).total_seconds() / 86400.0


@dataclass(frozen=True)
class CachedPayload:
    manifest: CacheManifest
    payload: bytes
    path: Path


@dataclass(frozen=True)
class DatasetCache:
    root: Path

    @classmethod
    def default(cls, override: str | os.PathLike[str] | None = None) -> DatasetCache:
        return cls(data_dir(override))

    def directory(self, spec: DatasetSpec) -> Path:
        return self.root / "datasf" / spec.dataset_id

    def manifest_path(self, spec: DatasetSpec) -> Path:
        return self.directory(spec) / MANIFEST_NAME

    def has(self, spec: DatasetSpec) -> bool:
        return self.manifest_path(spec).is_file()

    def read_manifest(self, spec: DatasetSpec) -> CacheManifest | None:
        path = self.manifest_path(spec)
        if not path.is_file():
            return None
        try:
            fields = json.loads(path.read_text(encoding="utf-8"))
            return CacheManifest(**fields)
        except (json.JSONDecodeError, TypeError, UnicodeDecodeError) as exc:
            raise DataSourceError(f"damaged cache manifest {path}: {exc}; re-run "
                                  f"`flowcast data fetch` or `flowcast data import`") from exc

    def load(self, spec: DatasetSpec) -> CachedPayload | None:
        """The cached payload, sha256-checked; ``None`` if nothing is cached."""
        manifest = self.read_manifest(spec)
        if manifest is None:
            return None
        path = self.directory(spec) / manifest.payload_file
        try:
            payload = path.read_bytes()
        except FileNotFoundError as exc:
            raise DataSourceError(f"cache manifest {self.manifest_path(spec)} names "
                                  f"{path.name}, which is missing") from exc
        if sha256_bytes(payload) != manifest.sha256:
            raise DataSourceError(f"cached payload {path} does not match its manifest sha256 "
                                  f"(damaged); re-run `flowcast data fetch` or `data import`")
        return CachedPayload(manifest, payload, path)

    def store(self, spec: DatasetSpec, payload: bytes, *, suffix: str, source_kind: SourceKind,
              source: str, row_count: int, first_date: str, last_date: str,
              data_as_of: str | None, final_cumulative: int | None,
              fetched_at: datetime | None = None) -> CacheManifest:
        """Write an already *validated* payload and point the manifest at it (see module doc)."""
        digest = sha256_bytes(payload)
        payload_name = f"payload-{digest[:16]}.{suffix}"
        directory = self.directory(spec)
        atomic_write_bytes(directory / payload_name, payload)
        manifest = CacheManifest(
            dataset_key=spec.key, dataset_id=spec.dataset_id, source_kind=source_kind,
            source=source, fetched_at=(fetched_at or utc_now()).isoformat(),
            row_count=row_count, first_date=first_date, last_date=last_date, sha256=digest,
            payload_file=payload_name, data_as_of=data_as_of, final_cumulative=final_cumulative)
        atomic_write_json(directory / MANIFEST_NAME, asdict(manifest))
        for old in directory.glob("payload-*"):
            if old.name != payload_name:
                with contextlib.suppress(FileNotFoundError):
                    old.unlink()
        return manifest
