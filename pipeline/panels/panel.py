"""A panel: the places forecast together, the places pooled beside them, and their origins.

The panel is the engine's one unit of data. San Francisco is a panel of one place (its DataSF
series) with California's other counties as **references** (places the pooled member learns
from, never forecast); California's counties are a panel of every county of 100,000 people or
more; the CDC hub's 53 locations are a panel of weekly NHSN counts. One place is a panel of one.

* :class:`Panel` — the places' histories (daily or weekly, :mod:`pipeline.panels.history`) as
  known at one vintage, the references, and the places the data gate skipped (named, with why);
* :class:`Cells` — what a member forecasts in one call: B (place, origin) cells, each with its
  own history cut at the origin, the panel it came from (a pooled member's pool) and its seed;
* :func:`weekly_origins` — every Saturday with enough history (and truth) before/after it.

Real-time discipline: a cell sees its own place's data up to its origin; a pooled member sees
every place of the cell's panel up to the same origin (:meth:`Panel.pool`), nothing later.
"""
from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.panels.history import EpiHistory, History, WeeklyHistory
from pipeline.panels.quantiles import Observed
from pipeline.panels.targets import DAYS_PER_WEEK, SATURDAY, TargetError

NS_PER_DAY = 86_400 * 10**9


def weeks_ending(history: History, end: pd.Timestamp, n_weeks: int) -> NDArray[np.float64]:
    """Counts of the ``n_weeks`` weeks ending ``end``, ``end`` − 7, … (oldest first) of any
    history; NaN for weeks not wholly inside it (or after its last day)."""
    if isinstance(history, WeeklyHistory):
        # whole days from the first week in integers, no Timestamp boxed: the nowcast and the
        # report read one week of every place of every earlier vintage, 300,000 calls a round
        offset = (pd.Timestamp(end).value
                  - int(history.dates.values[:1].view(np.int64)[0])) // NS_PER_DAY
        if n_weeks == 1:
            week = offset // DAYS_PER_WEEK
            inside = offset % DAYS_PER_WEEK == 0 and 0 <= week < len(history)
            return np.array([history.cases[week] if inside else np.nan], dtype=np.float64)
        index = offset // DAYS_PER_WEEK - np.arange(n_weeks)[::-1]
        inside = (offset % DAYS_PER_WEEK == 0) & (index >= 0) & (index < len(history))
        return np.where(inside, history.cases[np.clip(index, 0, len(history) - 1)], np.nan)
    assert isinstance(history, EpiHistory)
    cumulative = np.concatenate([[0.0], np.cumsum(np.asarray(history.cases, dtype=np.float64))])
    return cumulative_weeks_ending(cumulative, history.dates[0], end, n_weeks)


def cumulative_weeks_ending(cumulative: NDArray[np.float64], first: pd.Timestamp,
                            end: pd.Timestamp, n_weeks: int) -> NDArray[np.float64]:
    """Weekly sums from a daily series' cumulative counts (a leading 0, then one per day from
    ``first``) for the weeks ending ``end``, ``end`` − 7, …; NaN outside the series."""
    n_days = len(cumulative) - 1
    week_ends = (pd.Timestamp(end) - first).days - DAYS_PER_WEEK * np.arange(n_weeks)[::-1]
    inside = (week_ends - DAYS_PER_WEEK + 1 >= 0) & (week_ends < n_days)
    safe = np.clip(week_ends, DAYS_PER_WEEK - 1, n_days - 1)
    sums = cumulative[safe + 1] - cumulative[safe + 1 - DAYS_PER_WEEK]
    return np.where(inside, sums, np.nan)


@dataclass(frozen=True, eq=False)
class Panel:
    """``histories``: the places forecast, by name (one vintage of their data); ``references``:
    places only pooled (a place's own reference series is never in its pool); ``skipped``:
    places the data gate left out, with why (the run names them); ``name``: what the panel is
    (``san-francisco``, ``california-counties``, ``nhsn-covid-hosp``); ``as_of``: the
    vintage's release date, where the source has vintages; ``signal``: another signal of the
    same places from the same download (the counties' test positivity beside their cases),
    which a pooling member may read up to each cell's origin."""

    histories: Mapping[str, History]
    references: Mapping[str, History] = field(default_factory=dict)
    skipped: Mapping[str, str] = field(default_factory=dict)
    name: str = "panel"
    as_of: pd.Timestamp | None = None       # when this vintage of the data was released
    signal: Panel | None = None

    def __post_init__(self) -> None:
        if not self.histories:
            raise TargetError(f"panel {self.name!r} needs at least one place")
        targets = {h.targets for h in (*self.histories.values(), *self.references.values())}
        if len(targets) != 1:
            raise TargetError(f"panel {self.name!r} mixes targets {sorted(targets)}")

    @property
    def places(self) -> tuple[str, ...]:
        return tuple(self.histories)

    @property
    def targets(self) -> tuple[str, ...]:
        return next(iter(self.histories.values())).targets

    @property
    def count_target(self) -> str:
        return next(iter(self.histories.values())).count_target

    @property
    def populations(self) -> NDArray[np.float64]:
        return np.array([h.population for h in self.histories.values()], dtype=np.float64)

    @property
    def dates(self) -> pd.DatetimeIndex:
        """The calendar of its first place (the places of one source share it)."""
        return next(iter(self.histories.values())).dates

    @functools.cached_property
    def last_date(self) -> pd.Timestamp:
        """The newest day any place reports; kept once read (a round's origin: the report
        reads it per place and round, 50,000 times a round over a season's rounds)."""
        return max(h.origin for h in self.histories.values())

    @property
    def first_date(self) -> pd.Timestamp:
        return min(h.dates[0] for h in self.histories.values())

    def up_to(self, date: pd.Timestamp) -> Panel:
        """Every place as known up to ``date`` (places that began later are left out)."""
        def cut(histories: Mapping[str, History]) -> dict[str, History]:
            return {p: h.up_to(date) for p, h in histories.items() if h.dates[0] <= date}

        signal = (None if self.signal is None or self.signal.first_date > date
                  else self.signal.up_to(date))
        return Panel(cut(self.histories), cut(self.references), self.skipped, self.name,
                     self.as_of, signal)

    def only(self, places: Sequence[str]) -> Panel:
        """The same panel forecasting only ``places`` (the others become references)."""
        unknown = [p for p in places if p not in self.histories]
        if unknown:
            raise TargetError(f"places {unknown} are not in panel {self.name!r}")
        return Panel({p: self.histories[p] for p in places},
                     {**self.references, **{p: h for p, h in self.histories.items()
                                            if p not in places}}, self.skipped, self.name,
                     self.as_of, self.signal)

    def _pool_rows(self, place: str) -> list[tuple[str, History]]:
        """:meth:`pool`'s rows: the references other than ``place``, then every place of the
        panel (a reference may share a name with a place: SF's CDPH series beside DataSF's)."""
        return ([(p, h) for p, h in self.references.items() if p != place]
                + list(self.histories.items()))

    def pool_places(self, place: str) -> list[str]:
        """The places of :meth:`pool`'s rows, in its order."""
        return [p for p, _ in self._pool_rows(place)]

    def pool(self, place: str, origin: pd.Timestamp, n_weeks: int) -> NDArray[np.float64]:
        """``(P, n_weeks)`` weekly counts a pooled member learns from for a cell of ``place``:
        the references other than ``place``, then every place of the panel, each over the weeks
        ending ``origin`` (NaN where not observed). The cell's own series is its panel row."""
        return np.stack([weeks_ending(h, origin, n_weeks) for _, h in self._pool_rows(place)])

    def pool_populations(self, place: str) -> NDArray[np.float64]:
        """``(P,)`` the populations of :meth:`pool`'s rows, in its order."""
        return np.array([h.population for _, h in self._pool_rows(place)], dtype=np.float64)

    def own_row(self, place: str) -> int:
        """The row of ``place`` in :meth:`pool`'s matrix."""
        return sum(1 for p in self.references if p != place) + self.places.index(place)


def known_by(vintages: Sequence[tuple[pd.Timestamp, Panel]], as_of: pd.Timestamp | None
             ) -> Panel | None:
    """The newest of ``vintages`` (by release date, oldest first) released by ``as_of`` (None:
    none was; or ``as_of`` unknown): a source as a panel released then reads it."""
    if as_of is None:
        return None
    released = [panel for released_on, panel in vintages if released_on <= as_of]
    return released[-1] if released else None


class PoolKey(NamedTuple):
    """What a pooled member's pool depends on (:meth:`Cells.pool_groups`)."""

    panel: int
    origin: pd.Timestamp
    n_weeks: int
    own_reference: str | None


@dataclass(frozen=True, eq=False)
class Cells:
    """B forecast cells: history b is ``places[b]``'s data up to its origin, from ``panels[b]``
    (as known at that origin: what a pooled member may learn from), drawn with ``seeds[b]``."""

    histories: tuple[History, ...]
    places: tuple[str, ...]
    panels: tuple[Panel, ...]
    seeds: tuple[int, ...]

    def __post_init__(self) -> None:
        n = len(self.histories)
        if not (len(self.places) == len(self.panels) == len(self.seeds) == n):
            raise TargetError(f"cells: {n} histories, {len(self.places)} places, "
                              f"{len(self.panels)} panels, {len(self.seeds)} seeds")

    def __len__(self) -> int:
        return len(self.histories)

    @property
    def origins(self) -> tuple[pd.Timestamp, ...]:
        return tuple(h.origin for h in self.histories)

    @property
    def populations(self) -> NDArray[np.float64]:
        return np.array([h.population for h in self.histories], dtype=np.float64)

    def pool_groups(self) -> dict[PoolKey, list[int]]:
        """The cells that share a pool (:meth:`Panel.pool`), by (panel, origin, weeks, place):
        the same panel, origin and number of weeks, and the same place where the place is also
        one of the panel's references (its pool leaves its own reference series out; a
        reference of another name changes no place's pool)."""
        groups: dict[PoolKey, list[int]] = {}
        for b, (panel, place, history) in enumerate(zip(self.panels, self.places,
                                                        self.histories)):
            key = PoolKey(id(panel), history.origin, len(history.weekly_cases()),
                          place if place in panel.references else None)
            groups.setdefault(key, []).append(b)
        return groups

    def subset(self, index: Sequence[int]) -> Cells:
        return Cells(tuple(self.histories[i] for i in index), tuple(self.places[i] for i in index),
                     tuple(self.panels[i] for i in index), tuple(self.seeds[i] for i in index))

    @classmethod
    def of(cls, histories: Sequence[History], seeds: Sequence[int],
           places: Sequence[str] | None = None, panels: Sequence[Panel] | None = None) -> Cells:
        """Cells of histories seen alone (each its own one-place panel unless given)."""
        names = list(places) if places is not None else ["place"] * len(histories)
        own = (list(panels) if panels is not None
               else [Panel({n: h}, name=n) for n, h in zip(names, histories)])
        return cls(tuple(histories), tuple(names), tuple(own), tuple(int(s) for s in seeds))


def origin_seed(seed: int, origin: pd.Timestamp) -> int:
    """A cell's seed at ``origin``: depends on the date, not on which cells are forecast with
    it (every place shares its origin's seed, as the hub baseline always drew)."""
    return int(np.random.SeedSequence([seed, origin.toordinal()]).generate_state(1)[0])


def panel_cells(panel: Panel, origins: Sequence[pd.Timestamp], seed: int,
                places: Sequence[str] | None = None) -> Cells:
    """Every (place, origin) cell of one vintage, place-major (index c·O + o)."""
    chosen = list(places) if places is not None else list(panel.places)
    return Cells(tuple(panel.histories[p].up_to(o) for p in chosen for o in origins),
                 tuple(p for p in chosen for _ in origins), tuple(panel for _ in chosen
                                                                  for _ in origins),
                 tuple(origin_seed(seed, o) for _ in chosen for o in origins))


def weekly_origins(dates: pd.DatetimeIndex, *, min_history_weeks: int = 8,
                   horizon_weeks: int = 4, scored_only: bool = True,
                   weekday: int = SATURDAY, first: pd.Timestamp | None = None,
                   last: pd.Timestamp | None = None) -> list[pd.Timestamp]:
    """Every ``weekday`` with ``min_history_weeks`` of data before it (and, ``scored_only``,
    ``horizon_weeks`` of truth after it), between ``first`` and ``last`` when given, oldest
    first."""
    earliest = dates[0] + pd.Timedelta(days=DAYS_PER_WEEK * min_history_weeks - 1)
    latest = dates[-1] - pd.Timedelta(days=DAYS_PER_WEEK * horizon_weeks if scored_only else 0)
    earliest = earliest + pd.Timedelta(days=(weekday - earliest.weekday()) % 7)
    if first is not None:
        earliest = max(earliest, pd.Timestamp(first)
                       + pd.Timedelta(days=(weekday - pd.Timestamp(first).weekday()) % 7))
    if last is not None:
        latest = min(latest, pd.Timestamp(last))
    origins = list(pd.date_range(earliest, latest, freq="7D"))
    if not origins:
        raise TargetError(f"no weekly origins between {earliest.date()} and {latest.date()} in "
                          f"data of {dates[0].date()} … {dates[-1].date()} (at least "
                          f"{min_history_weeks} weeks of data"
                          + (f" and {horizon_weeks} weeks of truth" if scored_only else "")
                          + " needed)")
    return origins


def observed_truth(panel: Panel, origins: Sequence[pd.Timestamp], horizons: tuple[int, ...]
                   ) -> dict[str, Observed]:
    """``truth[target]``: each place's latest data at each origin's horizons (NaN where not
    observed; an origin that is not one of a place's dates has no truth)."""
    out = {t: np.full((len(panel.places), len(origins), len(horizons)), np.nan)
           for t in panel.targets}
    for c, history in enumerate(panel.histories.values()):
        for t, values in history.observed_at(origins, horizons).items():
            out[t][c] = values
    return {t: Observed(v, panel.places, tuple(origins), horizons) for t, v in out.items()}
