"""A memo of member forecasts: a cell already forecast is read back, never forecast twice.

The weekly run re-forecasts every Saturday origin of its track record with every member (about
a hundred origins × five forecasters, and each of the nowcast's completions at the latest
ones). Under real-time discipline a cell's forecast depends only on what the member is (its
models, its settings), the history up to the cell's origin as it is known now, the pool it
learns from (for a pooling member: the cell's panel), the horizons, levels and seed — and on
the code. The memo keys each cell's forecast by a SHA-256 digest of exactly those:

* the **member**: every dataclass field, array and tensor it holds, recursively
  (:mod:`pipeline.fingerprint`: model weights through ``state_dict``, a stored nf-real refit by
  its model-store key and version, whose name carries its files' hash; private fields, i.e.
  derived caches, are skipped). A member refitted on a calendar or reading sources by release
  (:class:`~pipeline.members.base.KeyedByCell`: nf-real, nf-context, seasonal) is keyed cell by
  cell by what that cell's forecast reads — the refit current at its origin, the sources
  released by its vintage's date — not by every refit and release it holds: next week's refit
  or release leaves the past rounds' keys as they were, so a warm round forecasts one round;
* the **history** the cell sees (:meth:`~pipeline.panels.history.EpiHistory.fingerprint`) — a
  revised count, a new nowcast completion or a longer series is a different key;
* for a member that learns across places (``pools``), the cell's **panel** (all its places);
* **horizons, levels and seed**;
* the **code**: every source file of the ``pipeline`` package, so a change to any forecasting
  code starts an empty memo.

A hit therefore returns what the member would compute, bit for bit (tests/test_memo.py checks
it). The misses of one call are forecast in one batch. The file keeps only the forecasts the
last run used, so it does not grow; it is a cache: an unreadable file is reported and replaced,
never an error.
"""
from __future__ import annotations

import io
import logging
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.members.base import KeyedByCell, Member, MemberForecast, MemberWrapper
from pipeline.panels.panel import Cells, Panel
from pipeline.panels.targets import SHARE, TargetError
from pipeline.fingerprint import code_fingerprint, fingerprint
from pipeline.io import atomic_write_bytes

log = logging.getLogger(__name__)
FORMAT = "flowcast-forecast-memo-2"
_FIELDS = ("keys", "count")


@dataclass(frozen=True, eq=False)
class CellForecast:
    """One cell's forecast as the memo keeps it: ``count`` ``(H, Q)``, ``share`` (the I a
    member forecast itself) and ``paths`` ``(n, H, 3)``."""

    count: NDArray[np.float64]
    share: NDArray[np.float64] | None = None
    paths: NDArray[np.float64] | None = None


@dataclass(eq=False)
class ForecastMemo:
    """The member forecasts of one place's weekly runs, in ``path`` (an ``.npz`` file).

    ``load`` reads the last run's forecasts, ``wrap`` memoizes a member, ``save`` writes the
    forecasts this run used (hits and new ones) and drops the rest. ``hits``/``misses`` count
    this run's look-ups."""

    path: Path
    _stored: dict[str, CellForecast] = field(default_factory=dict)
    _used: dict[str, CellForecast] = field(default_factory=dict)
    hits: int = 0
    misses: int = 0

    @classmethod
    def load(cls, path: str | Path) -> ForecastMemo:
        memo = cls(Path(path))
        if memo.path.exists():
            try:
                memo._stored = _read(memo.path.read_bytes())
            except (OSError, ValueError, KeyError, TargetError, zipfile.BadZipFile,
                    EOFError) as error:
                log.warning("forecast memo %s is unreadable (%s): starting an empty one; "
                            "the run re-forecasts every origin and replaces it", memo.path,
                            error)
        return memo

    def wrap(self, member: Member, paths_kept: int | None = None) -> MemoizedMember:
        """``member`` through this memo; ``paths_kept``: how many of its sample paths the caller
        uses (the backtest's ``n_paths``), the only ones kept, hit or miss (a member's 1,000
        paths per cell would make the file hundreds of MB)."""
        # a member keyed by cell is fingerprinted per cell (MemoizedMember.keys), not whole
        whole = type(member).__qualname__ if isinstance(member, KeyedByCell) else member
        return MemoizedMember(member, self, fingerprint(code_fingerprint(), whole, paths_kept),
                              paths_kept)

    def lookup(self, key: str) -> CellForecast | None:
        found = self._used.get(key) or self._stored.get(key)
        if found is not None:
            self.hits += 1
            self._used[key] = found
        else:
            self.misses += 1
        return found

    def record(self, key: str, forecast: CellForecast) -> None:
        self._used[key] = forecast

    @property
    def changed(self) -> bool:
        """Whether the file would change: a new forecast, or one no longer used."""
        return self._used.keys() != self._stored.keys()

    def save(self) -> None:
        """Write the forecasts this run used, atomically (a failed write keeps the old file);
        nothing when they are the ones stored."""
        if self.changed or not self.path.exists():
            atomic_write_bytes(self.path, _write(self._used))

    def __len__(self) -> int:
        return len(self._used)


@dataclass(frozen=True, eq=False)
class MemoizedMember(MemberWrapper):
    """``member`` whose cells' forecasts go through ``memo``; ``member_key`` fingerprints the
    member and the code (a member keyed by cell: its type and the code, each cell's key adding
    the member's identity at that cell)."""

    memo: ForecastMemo
    member_key: str
    paths_kept: int | None = None

    def keys(self, cells: Cells, horizons: tuple[int, ...], levels: NDArray[np.float64]
             ) -> list[str]:
        pools = bool(getattr(self.member, "pools", False))
        panel_keys: dict[int, str] = {}
        # within this call the cells hold their panels, so a panel's id names it
        member_keys: dict[tuple[pd.Timestamp, int], str] = {}

        def panel_key(panel: Panel) -> str:
            if id(panel) not in panel_keys:
                panel_keys[id(panel)] = fingerprint(
                    sorted((p, h.fingerprint()) for p, h in
                           (*panel.histories.items(), *panel.references.items())))
            return panel_keys[id(panel)]

        def member_key(origin: pd.Timestamp, panel: Panel) -> str:
            if not isinstance(self.member, KeyedByCell):
                return self.member_key
            if (origin, id(panel)) not in member_keys:
                member_keys[(origin, id(panel))] = fingerprint(
                    self.member_key, self.member.cell_identity(origin, panel))
            return member_keys[(origin, id(panel))]

        steps = fingerprint(tuple(horizons), np.asarray(levels, dtype=np.float64))  # all cells'
        return [fingerprint(member_key(history.origin, panel), history.fingerprint(),
                            panel_key(panel) if pools else None, steps, seed)
                for history, panel, seed in zip(cells.histories, cells.panels, cells.seeds)]

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        keys = self.keys(cells, horizons, levels)
        found = {b: f for b, k in enumerate(keys) if (f := self.memo.lookup(k)) is not None}
        missing = [b for b in range(len(keys)) if b not in found]
        if missing:
            made = self.member.forecast(cells.subset(missing), horizons, levels)
            share = made.extra.get(SHARE)
            paths = None if made.paths is None else made.paths[:, :self.paths_kept]
            for i, b in enumerate(missing):
                found[b] = CellForecast(made.count[i], None if share is None else share[i],
                                        None if paths is None else np.array(paths[i]))
                self.memo.record(keys[b], found[b])
        ordered = [found[b] for b in range(len(keys))]
        shares = [f.share for f in ordered if f.share is not None]
        paths = [f.paths for f in ordered if f.paths is not None]
        return MemberForecast(np.stack([f.count for f in ordered]),
                              {SHARE: np.stack(shares)} if len(shares) == len(ordered) else {},
                              np.stack(paths) if len(paths) == len(ordered) else None)


def _write(forecasts: Mapping[str, CellForecast]) -> bytes:
    """The forecasts as a few stacked arrays per shape (reading back 1,000 forecasts takes
    milliseconds, not the second of one array each)."""
    groups: dict[tuple[Any, ...], list[tuple[str, CellForecast]]] = {}
    for key, f in forecasts.items():
        shape = (f.count.shape, f.share is not None,
                 None if f.paths is None else f.paths.shape)
        groups.setdefault(shape, []).append((key, f))
    arrays: dict[str, NDArray[Any]] = {"format": np.array(FORMAT)}
    for g, entries in enumerate(groups.values()):
        fs = [f for _, f in entries]
        arrays[f"{g}/keys"] = np.array([k for k, _ in entries])
        arrays[f"{g}/count"] = np.stack([f.count for f in fs])
        if fs[0].share is not None:
            arrays[f"{g}/share"] = np.stack([f.share for f in fs if f.share is not None])
        if fs[0].paths is not None:
            arrays[f"{g}/paths"] = np.stack([f.paths for f in fs if f.paths is not None])
    buffer = io.BytesIO()
    np.savez(buffer, allow_pickle=False, **arrays)
    return buffer.getvalue()


def _read(data: bytes) -> dict[str, CellForecast]:
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        if str(npz["format"]) != FORMAT:
            raise ValueError(f"format {str(npz['format'])!r}, expected {FORMAT!r}")
        arrays = {name: npz[name] for name in npz.files if name != "format"}
    groups: dict[str, dict[str, NDArray[Any]]] = {}
    for name, value in arrays.items():
        group, _, part = name.partition("/")
        groups.setdefault(group, {})[part] = value
    out: dict[str, CellForecast] = {}
    for group in groups.values():
        missing = [f for f in _FIELDS if f not in group]
        if missing:
            raise ValueError(f"a group of forecasts lacks {missing}")
        n = len(group["keys"])
        for part in ("count", "share", "paths"):
            if part in group and len(group[part]) != n:
                raise ValueError(f"{len(group[part])} {part} arrays for {n} keys")
        for i, key in enumerate(group["keys"]):
            out[str(key)] = CellForecast(group["count"][i],
                                         group["share"][i] if "share" in group else None,
                                         group["paths"][i] if "paths" in group else None)
    return out
