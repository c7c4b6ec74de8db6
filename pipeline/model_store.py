"""Trained-model cache for the weekly forecast: reuse a model unless its config or data changed.

An entry is a directory ``<root>/<key>/`` whose ``key`` is the SHA-256 of the canonical JSON of
(training config, training-data hash, store schema version). Whatever the builder writes into
the entry (checkpoints, loss curves; sub-folders allowed) is listed with its SHA-256 in ``entry.json``; an entry whose
files no longer match is treated as absent (logged, then rebuilt), so a damaged cache costs a
retrain, never a wrong forecast.

Entries are built in a temporary sibling directory and renamed into place, so a crash while
training never leaves a half-written entry that a later run would trust. Two runs building the
same key at once both train; the second rename loses harmlessly (same content by construction).

Assumption: the training config fully determines the model given the training data and seed
(training is seeded); so "same key" means "same model" and reuse is safe.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from pipeline.errors import CheckpointError
from pipeline.io import atomic_write_json, sha256_bytes, sha256_file

log = logging.getLogger(__name__)

ENTRY_FILE = "entry.json"
# Bump when the layout or meaning of entries changes: old entries then simply stop matching.
STORE_SCHEMA = 1


def canonical_json(obj: Any) -> str:
    """Deterministic JSON (sorted keys, no whitespace, tuples as lists) for hashing configs."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_jsonable)


def _jsonable(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot hash config value of type {type(value).__name__}: {value!r}")


def model_key(config: Mapping[str, Any], data_sha256: str) -> str:
    """The cache key of a model trained with ``config`` on data whose hash is ``data_sha256``."""
    payload = {"schema": STORE_SCHEMA, "config": dict(config), "data_sha256": data_sha256}
    return sha256_bytes(canonical_json(payload).encode("utf-8"))


@dataclasses.dataclass(frozen=True)
class StoreEntry:
    key: str
    path: Path
    reused: bool
    created_at: str
    meta: dict[str, Any]


class ModelStore:
    """A directory of trained-model entries keyed by :func:`model_key`."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)

    def entry_dir(self, key: str) -> Path:
        return self.root / key

    def get(self, key: str) -> StoreEntry | None:
        """The valid entry for ``key``, or None (missing or damaged)."""
        path = self.entry_dir(key)
        record_path = path / ENTRY_FILE
        if not record_path.is_file():
            return None
        try:
            record = json.loads(record_path.read_text(encoding="utf-8"))
            files: dict[str, str] = record["files"]
            for name, digest in files.items():
                if sha256_file(path / name) != digest:
                    raise CheckpointError(f"{path / name} does not match its recorded sha256")
        except (OSError, json.JSONDecodeError, KeyError, TypeError, CheckpointError) as exc:
            log.warning("ignoring damaged model cache entry %s (%s); it will be rebuilt", path, exc)
            return None
        return StoreEntry(key=key, path=path, reused=True, created_at=record["created_at"],
                          meta=record.get("meta", {}))

    def put(self, key: str, build: Callable[[Path], Mapping[str, Any] | None],
            meta: Mapping[str, Any] | None = None) -> StoreEntry:
        """Run ``build(tmp_dir)`` (writes the model files, may return extra meta), then commit."""
        self.root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key[:12]}.", suffix=".building", dir=self.root))
        try:
            extra = build(tmp) or {}
            files = {p.relative_to(tmp).as_posix(): sha256_file(p) for p in sorted(tmp.rglob("*"))
                     if p.is_file() and p.name != ENTRY_FILE}
            if not files:
                raise CheckpointError(f"model builder wrote no files for cache entry {key}")
            created_at = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
            full_meta = {**dict(meta or {}), **dict(extra)}
            atomic_write_json(tmp / ENTRY_FILE, {"key": key, "created_at": created_at,
                                                 "files": files, "meta": full_meta})
            final = self.entry_dir(key)
            if final.exists():  # damaged, forced retrain, or a concurrent build won the race
                shutil.rmtree(final)
            os.replace(tmp, final)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return StoreEntry(key=key, path=final, reused=False, created_at=created_at, meta=full_meta)

    def get_or_build(self, config: Mapping[str, Any], data_sha256: str,
                     build: Callable[[Path], Mapping[str, Any] | None], *,
                     retrain: bool = False) -> StoreEntry:
        """Reuse the entry for (config, data) unless missing, damaged, or ``retrain`` is set."""
        key = model_key(config, data_sha256)
        if not retrain:
            hit = self.get(key)
            if hit is not None:
                log.info("reusing trained model %s (built %s)", key[:12], hit.created_at)
                return hit
            log.info("no trained model for key %s: training", key[:12])
        else:
            log.info("retrain requested: rebuilding model %s", key[:12])
        return self.put(key, build, meta={"config": dict(config), "data_sha256": data_sha256})
