"""A memo of member forecasts: a forecast already made is read back, never made twice.

The weekly run re-forecasts every Saturday origin of its track record with every member (about
a hundred origins × five forecasters, and each of the nowcast's completions at the latest
ones). Under real-time discipline a forecast from origin t depends only on what the member is
(its models, its reference places, its settings), the history up to t as it is known now, the
horizons, levels and seed — and on the code. The memo keys each forecast by a SHA-256 digest of
exactly those:

* the **member**: every dataclass field, array and tensor it holds, recursively
  (:mod:`pipeline.fingerprint`: model weights through ``state_dict``, a stored nf-real refit by
  its model-store key and version, whose name carries its files' hash; private fields, i.e.
  derived caches, are skipped);
* the **history** it was given: dates, daily cases, S, I, R and the population — a revised
  count, a new nowcast completion or a longer series is a different key;
* **horizons, levels and seed**;
* the **code**: every source file of the ``pipeline`` package, so a change to any forecasting
  code starts an empty memo.

A hit therefore returns what the member would compute, bit for bit (tests/test_memo.py checks
it on the weekly run). Next week's run re-uses the origins whose data did not change and
forecasts the new ones. The file keeps only the forecasts the last run used, so it does not
grow; it is a cache: an unreadable file is reported and replaced, never an error.
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

from pipeline.ensemble.members import Member
from pipeline.ensemble.targets import EpiHistory, QuantileForecast, TargetError
from pipeline.fingerprint import code_fingerprint, fingerprint
from pipeline.io import atomic_write_bytes

log = logging.getLogger(__name__)
FORMAT = "flowcast-forecast-memo-1"
_FIELDS = ("keys", "forecaster", "origin_ns", "horizons", "levels", "cases", "I")


def history_fingerprint(history: EpiHistory) -> str:
    """What a forecaster sees of a history: dates, cases, S, I, R, population."""
    return fingerprint(history.dates, history.cases, history.S, history.I, history.R,
                       history.population)


@dataclass(eq=False)
class ForecastMemo:
    """The member forecasts of one place's weekly runs, in ``path`` (an ``.npz`` file).

    ``load`` reads the last run's forecasts, ``wrap`` memoizes a member, ``save`` writes the
    forecasts this run used (hits and new ones) and drops the rest. ``hits``/``misses`` count
    this run's look-ups."""

    path: Path
    _stored: dict[str, QuantileForecast] = field(default_factory=dict)
    _used: dict[str, QuantileForecast] = field(default_factory=dict)
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

    def wrap(self, member: Member) -> MemoizedMember:
        return MemoizedMember(member, self, fingerprint(code_fingerprint(), member))

    def lookup(self, key: str) -> QuantileForecast | None:
        found = self._used.get(key) or self._stored.get(key)
        if found is not None:
            self.hits += 1
            self._used[key] = found
        else:
            self.misses += 1
        return found

    def record(self, key: str, forecast: QuantileForecast) -> None:
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
class MemoizedMember:
    """``member`` (:class:`~pipeline.ensemble.members.Member`) whose forecasts go through
    ``memo``; ``member_key`` fingerprints the member and the code."""

    member: Member
    memo: ForecastMemo
    member_key: str

    @property
    def name(self) -> str:
        return self.member.name

    def forecast(self, history: EpiHistory, horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int) -> QuantileForecast:
        key = fingerprint(self.member_key, history_fingerprint(history), tuple(horizons),
                          np.asarray(levels, dtype=np.float64), seed)
        found = self.memo.lookup(key)
        if found is not None:
            return found
        made = self.member.forecast(history, horizons, levels, seed)
        self.memo.record(key, made)
        return made


def _write(forecasts: Mapping[str, QuantileForecast]) -> bytes:
    """The forecasts as a few stacked arrays per shape (reading back 1,000 forecasts takes
    milliseconds, not the second of one array each)."""
    groups: dict[tuple[Any, ...], list[tuple[str, QuantileForecast]]] = {}
    for key, f in forecasts.items():
        paths_shape = None if f.paths is None else f.paths.shape[1:]
        groups.setdefault((len(f.horizons), len(f.levels), paths_shape), []).append((key, f))
    arrays: dict[str, NDArray[Any]] = {"format": np.array(FORMAT)}
    for g, entries in enumerate(groups.values()):
        fs = [f for _, f in entries]
        arrays.update({
            f"{g}/keys": np.array([k for k, _ in entries]),
            f"{g}/forecaster": np.array([f.forecaster for f in fs]),
            f"{g}/origin_ns": np.array([f.origin.value for f in fs], dtype=np.int64),
            f"{g}/horizons": np.array([f.horizons for f in fs], dtype=np.int64),
            f"{g}/levels": np.stack([np.asarray(f.levels, dtype=np.float64) for f in fs]),
            f"{g}/cases": np.stack([f.values["cases"] for f in fs]),
            f"{g}/I": np.stack([f.values["I"] for f in fs])})
        if fs[0].paths is not None:
            arrays[f"{g}/path_counts"] = np.array([len(f.paths) for f in fs
                                                   if f.paths is not None], dtype=np.int64)
            arrays[f"{g}/paths"] = np.concatenate([f.paths for f in fs if f.paths is not None])
    buffer = io.BytesIO()
    np.savez(buffer, allow_pickle=False, **arrays)
    return buffer.getvalue()


def _read(data: bytes) -> dict[str, QuantileForecast]:
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        if str(npz["format"]) != FORMAT:
            raise ValueError(f"format {str(npz['format'])!r}, expected {FORMAT!r}")
        arrays = {name: npz[name] for name in npz.files if name != "format"}
    groups: dict[str, dict[str, NDArray[Any]]] = {}
    for name, value in arrays.items():
        group, _, part = name.partition("/")
        groups.setdefault(group, {})[part] = value
    out: dict[str, QuantileForecast] = {}
    for group in groups.values():
        missing = [f for f in _FIELDS if f not in group]
        if missing:
            raise ValueError(f"a group of forecasts lacks {missing}")
        keys = group["keys"]
        paths: list[NDArray[np.float64] | None] = [None] * len(keys)
        if "paths" in group:
            ends = np.cumsum(group["path_counts"])
            if len(ends) != len(keys) or (len(ends) and ends[-1] != len(group["paths"])):
                raise ValueError("sample paths do not add up to their counts")
            paths = list(np.split(group["paths"], ends[:-1]))
        for i, key in enumerate(keys):
            out[str(key)] = QuantileForecast(
                forecaster=str(group["forecaster"][i]),
                origin=pd.Timestamp(int(group["origin_ns"][i])),
                horizons=tuple(int(h) for h in group["horizons"][i]),
                levels=group["levels"][i],
                values={"cases": group["cases"][i], "I": group["I"][i]}, paths=paths[i])
    return out
