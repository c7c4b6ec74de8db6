"""The one interface every forecaster implements, batched over places × origins.

A member receives :class:`~pipeline.panels.panel.Cells` — B (place, origin) cells, each with its
history cut at its origin, the panel it belongs to and its seed — and returns quantiles of the
panel's count target at the requested weekly horizons and levels for every cell at once
(:class:`MemberForecast`). A member that forecasts another target on its own series (the hub
baseline's I from the daily I series) adds it; the others' I is the count over N
(:func:`with_share`). Members that simulate weekly S/I/R paths return them (the published
forecast's sample paths follow their ranks).

``max_horizon``: the flows forecast a fixed number of weeks; beyond it a member has no forecast
(:func:`reach`). Everything a member may use of the world is in the cells: a cell's forecast
depends only on its own history, its panel as known at its origin and its own seed.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.panels.history import History, WeeklyHistory
from pipeline.panels.panel import Cells, Panel
from pipeline.panels.targets import SHARE, TargetError


@dataclass(frozen=True, eq=False)
class MemberForecast:
    """``count`` ``(B, H, Q)``: quantiles of the cells' weekly count; ``extra``: other targets
    forecast on their own series; ``paths`` ``(B, n, H, 3)``: weekly S, I, R sample paths."""

    count: NDArray[np.float64]
    extra: Mapping[str, NDArray[np.float64]] = field(default_factory=dict)
    paths: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        if self.count.ndim != 3:
            raise TargetError(f"member quantiles must be (cells, horizons, levels), got "
                              f"{self.count.shape}")

    def values(self, histories: tuple[History, ...]) -> dict[str, NDArray[np.float64]]:
        """Every target of the cells' panel: the count, and I where the panel has it."""
        return with_share(self.count, histories, self.extra)


def with_share(count: NDArray[np.float64], histories: tuple[History, ...],
               extra: Mapping[str, NDArray[np.float64]] | None = None
               ) -> dict[str, NDArray[np.float64]]:
    """``{target: (B, H, Q)}`` of the cells' targets: the count, and I = count / N where the
    cells are daily (their targets include I) and the member did not forecast I itself."""
    targets = histories[0].targets if histories else ()
    out = {histories[0].count_target: count} if histories else {}
    if SHARE in targets:
        population = np.array([h.population for h in histories], dtype=np.float64)
        out[SHARE] = (extra or {}).get(SHARE, count / population[:, None, None])
    return {t: out[t] for t in targets if t in out}


@runtime_checkable
class Member(Protocol):
    """A forecaster of cells (module docstring)."""

    @property
    def name(self) -> str: ...

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast: ...


@runtime_checkable
class KeyedByCell(Protocol):
    """A member whose parts differ by a cell's origin or release: a model refitted on a
    calendar, sources as released by the cell's own vintage. ``cell_identity`` is what its
    forecast of a cell at ``origin`` from ``panel`` depends on beyond the cell's own history,
    seed, horizons and levels (its settings, the refit of that origin, the sources released
    by the panel's date). The forecast memo keys such a cell by that rather than by the whole
    member: a refit or release that came later would otherwise re-key every past cell, and a
    warm round would forecast every past round again."""

    def cell_identity(self, origin: pd.Timestamp, panel: Panel) -> object: ...


@runtime_checkable
class LimitedReach(Protocol):
    """A member that forecasts at most ``max_horizon`` weeks ahead (the flows; a wrapper of
    another member says None when the member it wraps has no limit)."""

    @property
    def max_horizon(self) -> int | None: ...


@dataclass(frozen=True, eq=False)
class MemberWrapper:
    """A member wrapped by another (the memo, the completion mixture): the wrapper keeps its
    name and reach."""

    member: Member

    @property
    def name(self) -> str:
        return self.member.name

    @property
    def max_horizon(self) -> int | None:
        return getattr(self.member, "max_horizon", None)


def reach(member: object, horizons: tuple[int, ...]) -> tuple[int, ...]:
    """The horizons ``member`` can forecast."""
    limit = member.max_horizon if isinstance(member, LimitedReach) else None
    return horizons if limit is None else tuple(h for h in horizons if h <= limit)


def forecast_within_reach(member: Member, cells: Cells, horizons: tuple[int, ...],
                          levels: NDArray[np.float64]) -> MemberForecast:
    """``member``'s forecast at ``horizons``, NaN beyond its reach."""
    steps = reach(member, horizons)
    if steps == horizons:
        return member.forecast(cells, horizons, levels)
    count = np.full((len(cells), len(horizons), len(levels)), np.nan)
    if steps:
        made = member.forecast(cells, steps, levels)
        count[:, [horizons.index(h) for h in steps]] = made.count
    return MemberForecast(count)


def weekly_series(cells: Cells, member: str) -> list[NDArray[np.float64]]:
    """Each cell's weekly counts, for a member that needs two complete weeks of every cell."""
    own = [h.weekly_cases() for h in cells.histories]
    short = [h for h, w in zip(cells.histories, own) if w.size < 2]
    if short:
        unit = "weeks" if isinstance(short[0], WeeklyHistory) else "days"
        raise TargetError(f"{member} at {short[0].origin.date()}: needs two complete weeks, got "
                          f"{len(short[0])} {unit}")
    return own


@dataclass(frozen=True, eq=False)
class PoolGroup:
    """Cells that learn from one pool (:meth:`~pipeline.panels.panel.Cells.pool_groups`): their
    panel, origin and weeks known, and per cell its place, position among the cells, own weekly
    counts and population."""

    panel: Panel
    origin: pd.Timestamp
    n_weeks: int
    places: list[str]
    index: list[int]
    own: list[NDArray[np.float64]]
    populations: NDArray[np.float64]

    @property
    def pool(self) -> NDArray[np.float64]:
        """The weekly counts the group learns from (:meth:`~pipeline.panels.panel.Panel.pool`:
        the same for every cell of the group)."""
        return self.panel.pool(self.places[0], self.origin, self.n_weeks)


def forecast_by_pool(cells: Cells, horizons: tuple[int, ...], levels: NDArray[np.float64],
                     member: str, group_forecast: Callable[[PoolGroup], NDArray[np.float64]]
                     ) -> MemberForecast:
    """A pooled member's forecast of every cell: one ``group_forecast`` ``(B_g, H, Q)`` per
    group of cells sharing a pool, each cell needing two complete weeks
    (:func:`weekly_series`)."""
    own = weekly_series(cells, member)
    out = np.empty((len(cells), len(horizons), len(levels)))
    for (_, origin, n, _), index in cells.pool_groups().items():
        out[index] = group_forecast(PoolGroup(
            cells.panels[index[0]], origin, n, [cells.places[b] for b in index], index,
            [own[b] for b in index], cells.populations[index]))
    return MemberForecast(out)


class ForecastsByPool:
    """A pooled member's :meth:`forecast`: every group of cells sharing a pool forecast at once
    by the member's :meth:`group_forecast` (:func:`forecast_by_pool`)."""

    name: str

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        levels = np.asarray(levels, dtype=np.float64)
        return forecast_by_pool(cells, horizons, levels, self.name,
                                lambda group: self.group_forecast(group, horizons, levels))

    def group_forecast(self, group: PoolGroup, horizons: tuple[int, ...],
                       levels: NDArray[np.float64]) -> NDArray[np.float64]:
        """``(B, H, Q)`` counts of the group's cells."""
        raise NotImplementedError


def quantiles_of_samples(samples: NDArray[np.float64], levels: NDArray[np.float64]
                         ) -> NDArray[np.float64]:
    """``(B, H, Q)`` quantiles of ``samples (B, n, H)`` along the draws."""
    return np.moveaxis(np.quantile(samples, levels, axis=1), 0, -1)
