"""Trained-model cache for the weekly forecast: reuse a model unless its config or data changed.

Entries are keyed by the SHA-256 of the canonical JSON of (training config, training-data hash,
store schema version). Layout of one key (a tiny transactional store, like the DataSF cache)::

    <root>/<key>/current.json          which version is live (swapped atomically)
    <root>/<key>/v-<content>-<nonce>/  one immutable version: the builder's files + entry.json
    <root>/.locks/<key>.lock           held while committing (``filelock``)
    <root>/.locks/<key>.build.lock     held while building (one builder per key)

Whatever the builder writes (checkpoints, loss curves; sub-folders allowed) is listed with its
SHA-256 in ``entry.json``; a version whose files no longer match is treated as absent (logged,
then rebuilt), so a damaged cache costs a retrain, never a wrong forecast.

A version is built in a temporary ``.building`` directory, then committed under the key's lock:
if the live version already holds the same content (a concurrent build of a seeded, deterministic
model) the new one is discarded; otherwise it is renamed to a fresh, never-existing version
directory, ``current.json`` is swapped to it, and versions that neither the new nor the previous
``current.json`` names and that are older than an hour are deleted. So a writer never deletes the
version the live pointer names, and concurrent writers never rename over each other (the old
delete-then-rename lost 18 of 80 concurrent writes, issue 15). Readers take no lock: a reader
that finds its version collected reads the (newer) pointer again. ``.building`` directories of
killed runs are swept after a day.

One builder per key: :meth:`ModelStore.get_or_build` builds under the key's build lock, so a
process that finds another building the same model (two runs at once, or a weekly run and its
background member training, :mod:`pipeline.forecast.member_training`) waits for it and reuses
its model instead of training it a second time. The lock is the kernel's: a builder that dies
releases it, and the waiter builds.

Entries of the first layout (files and ``entry.json`` directly in ``<root>/<key>/``) are still
read, so upgrading does not retrain.

Assumption: the training config fully determines the model given the training data and seed
(training is seeded); so "same key" means "same model" and reuse is safe.
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import json
import logging
import os
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from pipeline.errors import CheckpointError, ModelMissingError
from pipeline.io import atomic_write_json, file_lock, sha256_bytes, sha256_file, sweep_stale

log = logging.getLogger(__name__)

ENTRY_FILE = "entry.json"
CURRENT_FILE = "current.json"
LOCKS_DIR = ".locks"
# How long a process waits for another one building the same model (a training: minutes).
BUILD_LOCK_TIMEOUT_S = 3600.0
# Set by stored_models_only(): get_or_build raises instead of building.
_builds_forbidden = False
_VERSION_PREFIX = "v-"
_BUILDING_SUFFIX = ".building"
# A version no pointer names may still be in use by a reader that resolved it just before the
# swap (loading a checkpoint takes seconds); an hour is ample.
UNREFERENCED_GRACE_S = 3600.0
_READ_ATTEMPTS = 5
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
    """A directory of trained-model entries keyed by :func:`model_key` (see module doc)."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)

    def entry_dir(self, key: str) -> Path:
        """The key's directory (holds ``current.json`` and the versions)."""
        return self.root / key

    def lock_path(self, key: str) -> Path:
        return self.root / LOCKS_DIR / f"{key}.lock"

    def build_lock_path(self, key: str) -> Path:
        return self.root / LOCKS_DIR / f"{key}.build.lock"

    def _live_version(self, key: str) -> Path | None:
        """The directory the key's pointer names; a first-layout entry is its own version."""
        directory = self.entry_dir(key)
        pointer = directory / CURRENT_FILE
        try:
            version = json.loads(pointer.read_text(encoding="utf-8"))["version"]
        except FileNotFoundError:
            return directory if (directory / ENTRY_FILE).is_file() else None
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
            log.warning("ignoring damaged model cache pointer %s (%s)", pointer, exc)
            return None
        if not (isinstance(version, str) and version.startswith(_VERSION_PREFIX)
                and "/" not in version):
            log.warning("ignoring model cache pointer %s naming %r", pointer, version)
            return None
        return directory / version

    def get(self, key: str) -> StoreEntry | None:
        """The valid entry for ``key``, or None (missing or damaged)."""
        for _ in range(_READ_ATTEMPTS):
            path = self._live_version(key)
            if path is None:
                return None
            entry, problem = _verified(key, path)
            if entry is not None:
                return entry
            if self._live_version(key) == path:  # not a concurrent swap: really damaged
                log.warning("ignoring damaged model cache entry %s (%s); it will be rebuilt",
                            path, problem)
                return None
        return None

    def put(self, key: str, build: Callable[[Path], Mapping[str, Any] | None],
            meta: Mapping[str, Any] | None = None) -> StoreEntry:
        """Run ``build(tmp_dir)`` (writes the model files, may return extra meta), then commit."""
        self.root.mkdir(parents=True, exist_ok=True)
        sweep_stale(self.root, (f".*{_BUILDING_SUFFIX}",))
        tmp = Path(tempfile.mkdtemp(prefix=f".{key[:12]}.", suffix=_BUILDING_SUFFIX,
                                    dir=self.root))
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
            final = self._commit(key, tmp, files)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        entry, problem = _verified(key, final)
        if entry is None:
            raise CheckpointError(f"model cache entry {final} failed its check right after "
                                  f"commit: {problem}")
        return dataclasses.replace(entry, reused=False)

    def _commit(self, key: str, tmp: Path, files: dict[str, str]) -> Path:
        """Under the key's lock: reuse the live version if it holds the same files, else move
        ``tmp`` to a fresh version directory and swap the pointer to it."""
        content = sha256_bytes(canonical_json(files).encode("utf-8"))[:16]
        directory = self.entry_dir(key)
        with file_lock(self.lock_path(key), what=f"model cache entry {key[:12]}"):
            live = self._live_version(key)
            if live is not None and live.name.startswith(f"{_VERSION_PREFIX}{content}-"):
                same, _ = _verified(key, live)
                if same is not None:
                    shutil.rmtree(tmp, ignore_errors=True)
                    return live
            directory.mkdir(parents=True, exist_ok=True)
            version = directory / f"{_VERSION_PREFIX}{content}-{uuid.uuid4().hex[:8]}"
            os.rename(tmp, version)  # a fresh name: never over anyone's directory
            atomic_write_json(directory / CURRENT_FILE, {"version": version.name,
                                                         "previous": live.name if live else None})
            keep = {version.name, live.name if live is not None else ""}
            self._collect(directory, keep)
        return version

    @staticmethod
    def _collect(directory: Path, keep: set[str]) -> None:
        cutoff = time.time() - UNREFERENCED_GRACE_S
        for old in directory.glob(f"{_VERSION_PREFIX}*"):
            try:
                if old.name not in keep and old.stat().st_mtime < cutoff:
                    shutil.rmtree(old)
            except FileNotFoundError:
                continue

    def get_or_build(self, config: Mapping[str, Any], data_sha256: str,
                     build: Callable[[Path], Mapping[str, Any] | None], *,
                     retrain: bool = False) -> StoreEntry:
        """Reuse the entry for (config, data) unless missing, damaged, or ``retrain`` is set."""
        key = model_key(config, data_sha256)
        if not retrain and (hit := self._reused(key)) is not None:
            return hit
        if _builds_forbidden:
            raise ModelMissingError(f"model {key[:12]} is not in the store {self.root} "
                                    "(only stored models may be used here)")
        with file_lock(self.build_lock_path(key), timeout_s=BUILD_LOCK_TIMEOUT_S,
                       what=f"the build of model {key[:12]}"):
            # another process may have built it while this one waited for the lock
            if not retrain and (hit := self._reused(key)) is not None:
                return hit
            if retrain:
                log.info("retrain requested: rebuilding model %s", key[:12])
            else:
                log.info("no trained model for key %s: training", key[:12])
            return self.put(key, build, meta={"config": dict(config),
                                              "data_sha256": data_sha256})

    def _reused(self, key: str) -> StoreEntry | None:
        hit = self.get(key)
        if hit is not None:
            log.info("reusing trained model %s (built %s)", key[:12], hit.created_at)
        return hit


def _verified(key: str, path: Path) -> tuple[StoreEntry | None, str]:
    """The entry at ``path`` if ``entry.json`` is readable and every file matches its sha256."""
    try:
        record = json.loads((path / ENTRY_FILE).read_text(encoding="utf-8"))
        files: dict[str, str] = record["files"]
        for name, digest in files.items():
            if sha256_file(path / name) != digest:
                raise CheckpointError(f"{path / name} does not match its recorded sha256")
        return StoreEntry(key=key, path=path, reused=True, created_at=record["created_at"],
                          meta=record.get("meta", {})), ""
    except (OSError, json.JSONDecodeError, KeyError, TypeError, CheckpointError) as exc:
        return None, str(exc)


MODELS_FOLDER = "models"            # the model store's folder in the flowcast data folder


def default_store_root() -> Path:
    """The model store under the flowcast data folder ($FLOWCAST_DATA_DIR)."""
    from pipeline.data.core.cache import data_dir

    return data_dir() / MODELS_FOLDER


@contextlib.contextmanager
def stored_models_only() -> Iterator[None]:
    """Within the block, :meth:`ModelStore.get_or_build` reuses stored models and raises
    :class:`~pipeline.errors.ModelMissingError` where it would train one (a step computed in a
    forked child, whose models must be trained in the parent: on another number of torch
    threads a training would give other weights)."""
    global _builds_forbidden
    before, _builds_forbidden = _builds_forbidden, True
    try:
        yield
    finally:
        _builds_forbidden = before
