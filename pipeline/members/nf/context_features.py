"""The context flow's features: what the flow knows of a (place, week) besides its own recent
weeks, and the windows it trains on, cut from the vintages released by a date.

A window at origin week t of a place holds K rows (weeks t−K+1 … t), each of
:data:`N_CHANNELS` channels, in groups (:class:`ContextChannels` leaves a group out: its
channels are 0, the code of "not known", in training and in forecasting alike):

* **target** (always): the weekly flow's three channels (:func:`~pipeline.members.nf.weekly.
  context_rows`: the log of each week relative to the latest, the latest level, −k);
* **other signal**: the other hub target over the same weeks (the ED share for admissions,
  admissions for the ED share), as known at the cell's release date: its log relative to its
  latest known week, that latest level, and a 0/1 "known" flag (the ED share was released only
  from 2025-06-18: before then the admissions flow sees the flag at 0);
* **season**: sin and cos of the row's week of the year, and a "known" flag (0 in the
  synthetic prior, which has no calendar, so the flow learns the season from real windows only);
* **climatology**: the seasonal member's growth at this time of year
  (:func:`~pipeline.members.seasonal.seasonal_growth`): its median log growth at steps 1 … H
  and its mean interquartile width, from the climatology as known then, and a "known" flag (no
  earlier season yet, or none released);
* **scale**: log10 of the place's population minus 7 (a share is scaled by the place's people,
  not by its 100,000 visits).

The static groups (climatology, scale) repeat on every row, so an encoder that reads rows sees
them wherever it looks. Every channel but the target's is scaled by hand to about unit size and
is standardized as (x − 0) / 1 (:func:`fixed_channels`): the prior has them all at 0, and a
standardization fitted there would divide by nothing.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.members.nf.flow import HALF_CASE, LEVEL_SCALE, RealWindows
from pipeline.members.nf.weekly import context_rows, cut_windows
from pipeline.members.seasonal import SeasonalConfig, seasonal_growth, week_of_year
from pipeline.panels.history import WeeklyHistory
from pipeline.panels.panel import Panel, known_by, weeks_ending
from pipeline.panels.targets import DAYS_PER_WEEK, TargetError

TARGET_CHANNELS = 3
OTHER_CHANNELS = 3
SEASON_CHANNELS = 3
SCALE_CHANNELS = 1
CLIMATOLOGY_LEVELS = np.array([0.25, 0.5, 0.75])
SCALE_CENTRE = 7.0                      # log10 of 10 M people: the states' middle


def climatology_channels(horizon_weeks: int) -> int:
    """Median growth at each step, the mean interquartile width, the flag."""
    return horizon_weeks + 2


def n_channels(horizon_weeks: int) -> int:
    return (TARGET_CHANNELS + OTHER_CHANNELS + SEASON_CHANNELS
            + climatology_channels(horizon_weeks) + SCALE_CHANNELS)


@dataclass(frozen=True)
class ContextChannels:
    """Which groups of channels the flow reads (module docstring): COVID-19's flow leaves the
    season out (``HubMembersConfig.context_channels``), an ablation one more group."""

    other_signal: bool = True
    season: bool = True
    climatology: bool = True
    scale: bool = True

    def both(self, other: ContextChannels) -> ContextChannels:
        """The groups both read."""
        return ContextChannels(*(a and b for a, b in zip(dataclasses.astuple(self),
                                                         dataclasses.astuple(other))))


def _group_slices(horizon_weeks: int) -> dict[str, slice]:
    bounds = np.cumsum([0, TARGET_CHANNELS, OTHER_CHANNELS, SEASON_CHANNELS,
                        climatology_channels(horizon_weeks), SCALE_CHANNELS])
    names = ("target", "other_signal", "season", "climatology", "scale")
    return {n: slice(int(a), int(b)) for n, a, b in zip(names, bounds[:-1], bounds[1:])}


def fixed_channels(horizon_weeks: int) -> slice:
    """The channels standardized as (x − 0) / 1: every one after the target's."""
    return slice(TARGET_CHANNELS, n_channels(horizon_weeks))


@dataclass(frozen=True)
class WindowInputs:
    """What W windows are built from, aligned: ``series (W, K)`` the target's weeks ending at
    each origin (NaN before the series began), ``other (W, K)`` the other signal's (NaN where
    not known), ``ends (W,)`` the origins' dates, ``climatology (W, S, 3)`` the seasonal growth
    quartiles at steps 1 … S (NaN: none), ``people (W,)`` the places' populations."""

    series: NDArray[np.float64]
    other: NDArray[np.float64]
    ends: NDArray[np.datetime64]
    climatology: NDArray[np.float64]
    people: NDArray[np.float64]


def context_windows(inputs: WindowInputs, channels: ContextChannels
                    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """``(context (W, K, C), mask (W, K))`` (module docstring), vectorized over windows."""
    w, k = inputs.series.shape
    horizon = inputs.climatology.shape[1]
    target, mask = context_rows(inputs.series, k)
    out = np.zeros((w, k, n_channels(horizon)), dtype=np.float64)
    groups = _group_slices(horizon)
    out[..., groups["target"]] = target
    if channels.other_signal:
        out[..., groups["other_signal"]] = _other_rows(inputs.other)
    if channels.season:
        weeks = (inputs.ends.astype("datetime64[D]")[:, None]
                 - (DAYS_PER_WEEK * np.arange(k - 1, -1, -1)).astype("timedelta64[D]"))
        angle = 2 * np.pi * week_of_year(pd.DatetimeIndex(weeks.reshape(-1))).reshape(w, k) / 52
        out[..., groups["season"]] = np.stack([np.sin(angle), np.cos(angle), np.ones_like(angle)],
                                              axis=-1)
    if channels.climatology:
        out[..., groups["climatology"]] = _climatology_rows(inputs.climatology)[:, None, :]
    if channels.scale:
        out[..., groups["scale"]] = (np.log10(inputs.people) - SCALE_CENTRE)[:, None, None]
    out[~mask] = 0.0
    return out.astype(np.float32), mask


def _other_rows(other: NDArray[np.float64]) -> NDArray[np.float64]:
    """The other signal's rows: log relative to its latest known week, that level, known flag."""
    known = np.isfinite(other)
    logs = np.log(np.where(known, other, 0.0) + HALF_CASE)
    last = np.where(known.any(axis=1), known.shape[1] - 1 - np.argmax(known[:, ::-1], axis=1), 0)
    latest = np.take_along_axis(logs, last[:, None], axis=1)
    any_known = known.any(axis=1, keepdims=True)
    relative = np.where(known, logs - latest, 0.0)
    level = np.where(known & any_known, latest / LEVEL_SCALE, 0.0)
    return np.stack([relative, level, known.astype(np.float64)], axis=-1)


def _climatology_rows(quartiles: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(W, S + 2)``: median growth per step, mean interquartile width, known flag."""
    known: NDArray[np.bool_] = np.asarray(np.isfinite(quartiles).all(axis=(1, 2)))
    median = np.where(known[:, None], np.nan_to_num(quartiles[..., 1]), 0.0)
    width = np.where(known, np.nan_to_num(quartiles[..., 2] - quartiles[..., 0]).mean(axis=1),
                     0.0)
    return np.concatenate([median, width[:, None], known[:, None].astype(np.float64)], axis=1)


# ----------------------------------------------------------------------- the real-time sources


@dataclass(frozen=True, eq=False)
class ContextSources:
    """Every vintage the flow may read, by release date: the other signal's and the
    climatology's (each chosen by a panel's own release date: never a later one), the places'
    populations, and the seasonal member's settings."""

    other: Sequence[tuple[pd.Timestamp, Panel]] = ()
    climatology: Sequence[tuple[pd.Timestamp, Panel]] = ()
    populations: Mapping[str, int] | None = None
    seasonal: SeasonalConfig = SeasonalConfig()

    def released_by(self, as_of: pd.Timestamp | None) -> ContextSources:
        """These sources as a panel released ``as_of`` reads them: of each, only the newest
        vintage released by then (what a cell's forecast depends on, not the later ones)."""
        def newest(vintages: Sequence[tuple[pd.Timestamp, Panel]]
                   ) -> tuple[tuple[pd.Timestamp, Panel], ...]:
            released = [v for v in vintages if as_of is not None and v[0] <= as_of]
            return tuple(released[-1:])

        return dataclasses.replace(self, other=newest(self.other),
                                   climatology=newest(self.climatology))

    def people(self, place: str, history: WeeklyHistory) -> float:
        """The place's population (a share's history carries its 100,000 visits instead)."""
        if self.populations is not None and place in self.populations:
            return float(self.populations[place])
        return float(history.population)

    def climatology_at(self, as_of: pd.Timestamp | None, origins: Sequence[pd.Timestamp],
                       steps: int) -> NDArray[np.float64]:
        """``(O, S, 3)`` seasonal growth quartiles at each origin from the climatology
        released by ``as_of`` (NaN: none released, or no earlier season)."""
        out = np.full((len(origins), steps, len(CLIMATOLOGY_LEVELS)), np.nan)
        panel = known_by(self.climatology, as_of)
        if panel is None:
            return out
        for i, origin in enumerate(origins):
            out[i] = seasonal_growth(panel, origin, range(1, steps + 1), CLIMATOLOGY_LEVELS,
                                     self.seasonal)
        return out

    def other_weeks(self, as_of: pd.Timestamp | None, place: str, end: pd.Timestamp,
                    n_weeks: int) -> NDArray[np.float64]:
        """The other signal's ``n_weeks`` weeks ending ``end`` at ``place`` as released by
        ``as_of`` (NaN: not known)."""
        panel = known_by(self.other, as_of)
        if panel is None or place not in panel.histories:
            return np.full(n_weeks, np.nan)
        return weeks_ending(panel.histories[place], end, n_weeks)


def vintage_windows(panel: Panel, sources: ContextSources, cutoff: pd.Timestamp,
                    k_weeks: int, horizon_weeks: int, channels: ContextChannels,
                    place_offset: int = 0) -> RealWindows:
    """Every (place, week) window of one vintage whose target weeks end by ``cutoff``: context
    (module docstring, the other signal and climatology as released by the vintage's own date)
    and the weekly flow's targets (:func:`~pipeline.members.nf.weekly.weekly_targets`)."""
    calendar = panel.dates
    n_weeks = int(np.searchsorted(calendar.to_numpy(np.int64), pd.Timestamp(cutoff).value,
                                  side="right"))
    origins = np.arange(1, n_weeks - horizon_weeks)
    if origins.size == 0:
        return empty_windows(k_weeks, horizon_weeks)
    climate = sources.climatology_at(panel.as_of, list(calendar[origins]), horizon_weeks)
    parts: list[tuple[WindowInputs, NDArray[np.float32], NDArray[np.int64]]] = []
    for index, (place, history) in enumerate(panel.histories.items()):
        if not isinstance(history, WeeklyHistory) or len(history) != len(calendar):
            raise TargetError(f"{place}: the context flow reads weekly series on the panel's "
                              "calendar")
        series, target, ok = cut_windows(history, origins, k_weeks, horizon_weeks)
        other_all = np.concatenate([np.full(k_weeks - 1, np.nan), sources.other_weeks(
            panel.as_of, place, calendar[-1], len(calendar))])
        other = other_all[origins[:, None] + np.arange(k_weeks)[None, :]]
        inputs = WindowInputs(series[ok], other[ok], calendar[origins[ok]].to_numpy(),
                              climate[ok], np.full(int(ok.sum()), sources.people(place, history)))
        parts.append((inputs, target[ok], np.full(int(ok.sum()), place_offset + index)))
    inputs = WindowInputs(*(np.concatenate([getattr(p[0], f) for p in parts])
                            for f in ("series", "other", "ends", "climatology", "people")))
    context, mask = context_windows(inputs, channels)
    return RealWindows(context, mask, np.concatenate([p[1] for p in parts]),
                       np.concatenate([p[2] for p in parts]))


def empty_windows(k_weeks: int, horizon_weeks: int) -> RealWindows:
    return RealWindows(np.empty((0, k_weeks, n_channels(horizon_weeks)), np.float32),
                       np.empty((0, k_weeks), bool), np.empty((0, horizon_weeks), np.float32),
                       np.empty(0, np.int64))


def joined(windows: Sequence[RealWindows]) -> RealWindows:
    """Several pools of windows as one (their place ids kept apart by the callers' offsets)."""
    return RealWindows(*(np.concatenate([getattr(w, f) for w in windows])
                         for f in RealWindows._fields))
