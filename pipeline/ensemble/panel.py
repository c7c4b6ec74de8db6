"""A panel: many places' histories on one calendar, their weekly origins, and forecast arrays.

The cross-county backtest forecasts every place (county) at every weekly origin. Instead of one
forecaster call per cell, forecasts and truths are arrays over the panel:

* ``truth[target]``: ``(C, O, H)`` — place × origin × horizon, NaN where not observed;
* a forecaster's quantiles ``(C, O, H, Q)`` of a target at the hub levels.

Members that can (the flow member) forecast all C × O cells in one batch; the others are called
cell by cell on ``history.up_to(origin)`` — the real-time discipline is the same either way: a
cell sees its own place's data up to its origin and nothing else.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.ensemble.backtest import origin_seed
from pipeline.ensemble.members import Member
from pipeline.ensemble.targets import (DAYS_PER_WEEK, TARGETS, EpiHistory, TargetError,
                                       observed_targets)
from pipeline.progress import ProgressReporter, SilentProgress

SATURDAY = 5


@runtime_checkable
class BatchMember(Protocol):
    """A member that forecasts many histories at once: weekly case quantiles ``(B, H, Q)``."""

    @property
    def name(self) -> str: ...

    def forecast_batch(self, histories: Sequence[EpiHistory], horizons: tuple[int, ...],
                       levels: NDArray[np.float64], seed: int) -> NDArray[np.float64]: ...


@runtime_checkable
class BatchTargetsMember(Protocol):
    """A member that forecasts each target on its own series, for many histories at once:
    ``{target: (B, H, Q)}``, history b with ``seeds[b]``."""

    @property
    def name(self) -> str: ...

    def forecast_targets_batch(self, histories: Sequence[EpiHistory], horizons: tuple[int, ...],
                               levels: NDArray[np.float64], seeds: Sequence[int]
                               ) -> dict[str, NDArray[np.float64]]: ...


@runtime_checkable
class PoolingMember(Protocol):
    """A member that learns across the places of a panel: from weekly counts ``(C, W)`` and the
    week index of each origin ``(O,)``, weekly case quantiles ``(C, O, H, Q)``; the forecast at
    origin week j may use any place's counts up to week j, nothing later."""

    @property
    def name(self) -> str: ...

    def forecast_panel(self, weekly_cases: NDArray[np.float64], origin_index: NDArray[np.intp],
                       horizons: tuple[int, ...], levels: NDArray[np.float64]
                       ) -> NDArray[np.float64]: ...


@dataclass(frozen=True, eq=False)
class Panel:
    """Places' daily histories on one calendar (same first and last date)."""

    histories: Mapping[str, EpiHistory]

    def __post_init__(self) -> None:
        if not self.histories:
            raise TargetError("a panel needs at least one place")
        spans = {(h.dates[0], h.dates[-1]) for h in self.histories.values()}
        if len(spans) != 1:
            raise TargetError(f"panel histories cover different days: {sorted(spans)[:3]}")

    @property
    def places(self) -> tuple[str, ...]:
        return tuple(self.histories)

    @property
    def dates(self) -> pd.DatetimeIndex:
        return next(iter(self.histories.values())).dates

    @property
    def populations(self) -> NDArray[np.float64]:
        return np.array([h.population for h in self.histories.values()], dtype=np.float64)

    def up_to(self, date: pd.Timestamp) -> Panel:
        return Panel({p: h.up_to(date) for p, h in self.histories.items()})


def weekly_origins(dates: pd.DatetimeIndex, *, min_history_weeks: int = 8,
                   horizon_weeks: int = 4, scored_only: bool = True,
                   weekday: int = SATURDAY) -> list[pd.Timestamp]:
    """Every ``weekday`` with ``min_history_weeks`` of data before it (and, ``scored_only``,
    ``horizon_weeks`` of truth after it), oldest first."""
    first = dates[0] + pd.Timedelta(days=DAYS_PER_WEEK * min_history_weeks - 1)
    last = dates[-1] - pd.Timedelta(days=DAYS_PER_WEEK * horizon_weeks if scored_only else 0)
    first = first + pd.Timedelta(days=(weekday - first.weekday()) % 7)
    origins = list(pd.date_range(first, last, freq="7D"))
    if not origins:
        raise TargetError(f"no weekly origins in {dates[0].date()} … {dates[-1].date()}")
    return origins


def truth_arrays(panel: Panel, origins: Sequence[pd.Timestamp],
                 horizons: tuple[int, ...]) -> dict[str, NDArray[np.float64]]:
    """``truth[target] (C, O, H)`` from the panel's full histories."""
    out = {t: np.full((len(panel.places), len(origins), len(horizons)), np.nan) for t in TARGETS}
    for c, history in enumerate(panel.histories.values()):
        for o, origin in enumerate(origins):
            observed = observed_targets(history, origin, horizons)
            for t in TARGETS:
                out[t][c, o] = observed[t]
    return out


def cell_histories(panel: Panel, origins: Sequence[pd.Timestamp]) -> list[EpiHistory]:
    """``history.up_to(origin)`` of every cell, place-major (index c·O + o)."""
    return [h.up_to(o) for h in panel.histories.values() for o in origins]


def member_forecast_arrays(member: Member | BatchMember | BatchTargetsMember | PoolingMember,
                           panel: Panel,
                           origins: Sequence[pd.Timestamp], horizons: tuple[int, ...],
                           levels: NDArray[np.float64], seed: int,
                           progress: ProgressReporter | None = None
                           ) -> dict[str, NDArray[np.float64]]:
    """A member's quantiles ``{target: (C, O, H, Q)}`` at every cell of the panel.

    Pooling and batch members forecast weekly cases (I = cases / N); batch-targets members (the
    hub baseline, which forecasts I on its own series) and the others, called per cell on
    ``history.up_to(origin)``, give both targets."""
    progress = progress or SilentProgress()
    n_c, n_o = len(panel.places), len(origins)
    population = panel.populations[:, None, None, None]
    if isinstance(member, PoolingMember):
        weekly, index = weekly_grid(panel, origins)
        cases = member.forecast_panel(weekly, index, horizons, levels)
        progress.advance(n_c * n_o, member=member.name)
        return {"cases": cases, "I": cases / population}
    values = forecast_cells(member, cell_histories(panel, origins), horizons, levels, seed,
                            progress)
    return {t: v.reshape(n_c, n_o, len(horizons), len(levels)) for t, v in values.items()}


def forecast_cells(member: Member | BatchMember | BatchTargetsMember,
                   cells: Sequence[EpiHistory], horizons: tuple[int, ...],
                   levels: NDArray[np.float64], seed: int,
                   progress: ProgressReporter | None = None) -> dict[str, NDArray[np.float64]]:
    """A member's quantiles ``{target: (B, H, Q)}`` of B histories, each seen alone: in batches
    when the member can, else one call per history (seeded by its origin)."""
    progress = progress or SilentProgress()
    if isinstance(member, BatchTargetsMember):
        seeds = [origin_seed(seed, h.origin) for h in cells]
        values = member.forecast_targets_batch(cells, horizons, levels, seeds)
        progress.advance(len(cells), member=member.name)
        return {t: values[t] for t in TARGETS}
    if isinstance(member, BatchMember):
        cases = member.forecast_batch(cells, horizons, levels, seed)
        progress.advance(len(cells), member=member.name)
        population = np.array([h.population for h in cells], dtype=np.float64)
        return {"cases": cases, "I": cases / population[:, None, None]}
    forecasts = []
    for history in cells:
        forecasts.append(member.forecast(history, horizons, levels,
                                         origin_seed(seed, history.origin)))
        progress.advance(1, member=member.name)
    return {t: np.stack([f.values[t] for f in forecasts]) for t in TARGETS}


def weekly_grid(panel: Panel, origins: Sequence[pd.Timestamp]
                ) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Weekly case counts ``(C, W)`` of the consecutive 7-day weeks ending on the origins'
    weekday, from the first whole week of the panel to the last one, and the week index of each
    origin ``(O,)``."""
    dates = panel.dates
    weekday = origins[0].weekday()
    last_end = dates[-1] - pd.Timedelta(days=(dates[-1].weekday() - weekday) % 7)
    first_end = dates[0] + pd.Timedelta(days=DAYS_PER_WEEK - 1)
    first_end = first_end + pd.Timedelta(days=(weekday - first_end.weekday()) % 7)
    n_weeks = (last_end - first_end).days // DAYS_PER_WEEK + 1
    ends = (first_end - dates[0]).days + DAYS_PER_WEEK * np.arange(n_weeks)    # day indices
    cases = np.stack([h.cases for h in panel.histories.values()]).astype(np.float64)
    cumulative = np.concatenate([np.zeros((cases.shape[0], 1)), np.cumsum(cases, axis=1)], axis=1)
    weekly = cumulative[:, ends + 1] - cumulative[:, ends + 1 - DAYS_PER_WEEK]
    index = np.array([(o - first_end).days // DAYS_PER_WEEK for o in origins], dtype=np.intp)
    if any(o.weekday() != weekday for o in origins) or (index < 0).any() or \
            (index >= n_weeks).any():
        raise TargetError("origins must share one weekday and lie within the panel's weeks")
    return weekly, index
