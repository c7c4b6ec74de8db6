"""Every vintage a source ever published, kept by its own date (CDPH's county file, NHSN's weekly
releases): the live copy of :mod:`pipeline.data.core.cache` plus an immutable archive beside it.

Layout, in the dataset's cache directory::

    manifest.json, payload-<sha[:16]>.<ext>    the live vintage (the transactional store)
    vintages/<as-of>-<sha[:16]>.<ext>          every vintage ever accepted, content-addressed
    held/payload-<sha[:16]>.<ext>              payloads the revision policy refused, for review

:meth:`VintageArchive.commit` decides **under the dataset's lock** what a new vintage becomes:
the live copy (if it is not older than the live one and the caller's check, the revision policy,
allows it), an archived older vintage (imports: archived downloads arrive in any order), or a
refusal. Deciding under the lock is what makes two concurrent imports safe: the probe of issue 32
imported an older and a newer vintage at once, and the older one, checked against the live copy
*before* the lock, failed with "last date moves backwards" in 3 of 3 trials instead of being
archived. Archive files are written without the lock: a writer of the same bytes writes the same
file, and different bytes never share a name.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from datetime import date
from pathlib import Path
from typing import Any, Literal

from pipeline.data.core.cache import (CacheDamagedError, CachedPayload, CacheManifest, CacheSpec,
                                      CommitCheck, DatasetCache, RevisionRefusedError, utc_now)
from pipeline.io import atomic_write_bytes, sha256_bytes

log = logging.getLogger(__name__)

VINTAGES_DIR = "vintages"
_VINTAGE_RE = re.compile(r"^(\d{4}-\d{2}-\d{2})-([0-9a-f]{16})\.(csv|json)$")
Older = Literal["archive", "refuse"]


def manifest_as_of(manifest: CacheManifest) -> date:
    """The live vintage's date: the manifest's ``data_as_of`` (NHSN's release date), else its
    last date (a CDPH vintage is dated by its last day)."""
    return date.fromisoformat((manifest.data_as_of or manifest.last_date)[:10])


class _OlderThanLive(Exception):
    """Raised under the lock: the new vintage is older than the live one (archive it)."""

    def __init__(self, live: date) -> None:
        super().__init__(str(live))
        self.live = live


@dataclass(frozen=True)
class Committed:
    """What a vintage became: ``live`` (``manifest`` is the new live one) or ``archived`` (older
    than the live vintage of ``live_as_of``; the live copy is unchanged)."""

    action: Literal["live", "archived"]
    path: Path
    manifest: CacheManifest | None = None
    live_as_of: date | None = None


@dataclass(frozen=True)
class VintageArchive:
    """The vintages of one dataset ``spec`` in ``cache``."""

    cache: DatasetCache
    spec: CacheSpec

    @property
    def folder(self) -> Path:
        return self.cache.directory(self.spec) / VINTAGES_DIR

    def archive(self, as_of: date, payload: bytes, suffix: str) -> Path:
        """Keep ``payload`` as ``vintages/<as-of>-<sha16>.<suffix>`` (immutable, no lock)."""
        digest = sha256_bytes(payload)
        path = self.folder / f"{as_of}-{digest[:16]}.{suffix}"
        if not (path.is_file() and sha256_bytes(path.read_bytes()) == digest):
            atomic_write_bytes(path, payload)
        return path

    def listing(self) -> list[tuple[date, Path]]:
        """Every archived vintage, oldest first, one per date (the last written)."""
        if not self.folder.is_dir():
            return []
        chosen: dict[date, Path] = {}
        for path in sorted(self.folder.iterdir(), key=lambda p: (p.name[:10], p.stat().st_mtime)):
            match = _VINTAGE_RE.match(path.name)
            if match:
                chosen[date.fromisoformat(match.group(1))] = path
        return sorted(chosen.items())

    def read(self, path: Path) -> bytes:
        """An archived vintage's bytes, checked against the hash in its name."""
        data = path.read_bytes()
        match = _VINTAGE_RE.match(path.name)
        if match is None or not sha256_bytes(data).startswith(match.group(2)):
            raise CacheDamagedError(f"cached vintage {path} does not match the hash in its name "
                                    f"(damaged); delete it or import that vintage again")
        return data

    def commit(self, payload: bytes, *, as_of: date, suffix: str, older: Older,
               check: CommitCheck | None, accept_hint: str, **manifest: Any) -> Committed:
        """Store a validated vintage (module doc). ``older="archive"``: a vintage older than the
        live one is archived, the live copy untouched; ``"refuse"``: ``check`` decides (a live
        source going backwards is refused there). A revision the policy holds is kept under
        ``held/`` and re-raised naming the file and ``accept_hint``. ``manifest`` holds the
        fields of :meth:`DatasetCache.store`."""
        def guarded(live: CachedPayload | None) -> None:
            if live is not None and older == "archive":
                live_date = manifest_as_of(live.manifest)
                # a live vintage dated after today (stored by an older flowcast, issue 39) is
                # no reason to archive a real one: every later release would be archived
                if as_of < live_date <= utc_now().date():
                    raise _OlderThanLive(live_date)
            if check is not None:
                check(live)

        try:
            stored = self.cache.store(self.spec, payload, suffix=suffix, check=guarded,
                                      **manifest)
        except _OlderThanLive as older_than:
            return Committed("archived", self.archive(as_of, payload, suffix),
                             live_as_of=older_than.live)
        except RevisionRefusedError as exc:
            if not exc.hold:
                raise
            held = self.cache.hold(self.spec, payload, suffix=suffix, reason=str(exc))
            raise RevisionRefusedError(f"{exc} (payload held in {held}; after review accept it "
                                       f"with {accept_hint})", hold=True) from exc
        return Committed("live", self.archive(as_of, payload, suffix), manifest=stored)
