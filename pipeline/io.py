"""Atomic file writing and hashing shared by caches, datasets, checkpoints and reports.

A failed run must never leave a half-written file or replace the last good one, so every
writer goes through a temporary file in the same directory followed by ``os.replace``.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from pipeline.errors import FlowcastError


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str], mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary sibling of ``path``; on clean exit fsync and rename it over ``path``."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        # mkstemp creates 0600 files; give the final file the mode a plain open() would.
        os.fchmod(fd, 0o666 & ~_current_umask())
        with os.fdopen(fd, mode) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    with atomic_open(path, "wb") as handle:
        handle.write(data)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


class JSONBoundError(FlowcastError):
    """A JSON file larger or more deeply nested than its reader allows: refused unparsed."""


def json_depth(text: bytes) -> int:
    """The deepest nesting of ``[``/``{`` in the JSON ``text``, brackets inside strings not
    counted; vectorized, so a file is judged without the recursive parse a deep one would
    crash (``RecursionError``)."""
    # escaped backslashes and quotes never open or close a string: drop them first
    plain = np.frombuffer(text.replace(b"\\\\", b"").replace(b'\\"', b""), dtype=np.uint8)
    in_string = np.cumsum(plain == ord('"')) % 2 == 1
    step = (np.isin(plain, (ord("["), ord("{"))).astype(np.int64)
            - np.isin(plain, (ord("]"), ord("}"))).astype(np.int64))
    return int(np.cumsum(np.where(in_string, 0, step)).max(initial=0))


def read_bounded_json(path: str | os.PathLike[str], *, max_bytes: int, max_depth: int,
                      what: str = "") -> Any:
    """The JSON file ``path`` parsed, once its size (at most ``max_bytes``, read no further)
    and nesting (at most ``max_depth``) are known to be within bounds; else one
    :class:`JSONBoundError` naming the file and the bound."""
    name = what or str(path)
    with open(path, "rb") as handle:
        text = handle.read(max_bytes + 1)        # a huge file is never read whole
    if len(text) > max_bytes:
        raise JSONBoundError(f"{name}: more than {max_bytes:,} bytes; refused unread (a "
                             f"config of this kind is far smaller)")
    depth = json_depth(text)
    if depth > max_depth:
        raise JSONBoundError(f"{name}: nested {depth} levels deep, more than the {max_depth} "
                             f"allowed; refused unparsed")
    return json.loads(text)


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike[str], chunk_size: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(chunk_size), b""):
            digest.update(chunk)
    return digest.hexdigest()


# -- locks and leftovers ----------------------------------------------------------------------
# Caches, the model store and the run outputs are shared by concurrent runs (a served deployment,
# a manual `make forecast`, `flows.scale_out` workers). Each guards its read-modify-write steps
# with an OS file lock (``filelock``: flock on POSIX, released by the kernel if the holder dies,
# so a killed run never leaves a lock behind).

LOCK_TIMEOUT_S = 120.0
STALE_AFTER_S = 86_400.0  # leftovers older than a day are from dead runs, never live ones


class LockTimeoutError(FlowcastError):
    """A file lock was not acquired in time (its holder is named in the message)."""


@contextlib.contextmanager
def file_lock(path: str | os.PathLike[str], *, timeout_s: float = LOCK_TIMEOUT_S,
              what: str = "") -> Iterator[None]:
    """Hold the exclusive lock file ``path`` for the block; error naming it after ``timeout_s``.

    The lock is the kernel's; the error names the pid holding it as the kernel reports it
    (:func:`lock_holder`), or no pid when that cannot be verified.
    """
    import filelock  # local: only writers need it

    lock_path = Path(path)
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    lock = filelock.FileLock(str(lock_path), timeout=timeout_s)
    try:
        lock.acquire()
    except filelock.Timeout as exc:
        owner = lock_holder(lock_path)
        holder = f"pid {owner}" if owner is not None else "a process that cannot be named here"
        raise LockTimeoutError(f"{what or lock_path}: still locked after {timeout_s:.0f} s by "
                               f"{holder} ({lock_path})") from exc
    try:
        yield
    finally:
        lock.release()


def lock_holder(lock_path: Path) -> int | None:
    """The pid the kernel says holds ``lock_path``'s lock (``/proc/locks``, by the file's
    device and inode), or None when it cannot be verified (issue 39: the message used to name
    the pid written at the last import, not the process holding the lock)."""
    try:
        stat = lock_path.stat()
        table = Path("/proc/locks").read_text(encoding="utf-8")
    except OSError:
        return None
    inode = f"{os.major(stat.st_dev):02x}:{os.minor(stat.st_dev):02x}:{stat.st_ino}"
    for line in table.splitlines():
        fields = line.split()
        # "1: FLOCK  ADVISORY  WRITE 4242 08:01:1234 0 EOF" (a "->" marks a waiter)
        if len(fields) >= 6 and "->" not in fields[1] and fields[5] == inode:
            return int(fields[4]) if fields[4].isdigit() else None
    return None


def sweep_stale(directory: str | os.PathLike[str], patterns: tuple[str, ...], *,
                older_than_s: float = STALE_AFTER_S, now: float | None = None) -> list[Path]:
    """Delete entries of ``directory`` matching ``patterns`` last modified ``older_than_s`` ago.

    For leftovers of killed runs (staging folders, ``.building`` folders, temp files): a live
    run touches its own within minutes, so a day-old one belongs to nobody.
    """
    import shutil
    import time

    root = Path(directory)
    if not root.is_dir():
        return []
    cutoff = (time.time() if now is None else now) - older_than_s
    removed = []
    for pattern in patterns:
        for path in root.glob(pattern):
            try:
                if path.lstat().st_mtime >= cutoff:
                    continue
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                else:
                    path.unlink()
            except FileNotFoundError:
                continue  # another sweeper got there first
            removed.append(path)
    return removed
