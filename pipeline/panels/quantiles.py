"""Quantile forecasts that carry their labels: ``values[place, origin, horizon, level]`` beside
the places, origins (a hub's rounds: their reference dates), horizons and levels they are of, so
that a forecast is selected by what it is, not by its position (statsforecast's long frame, the
hubverse's long format).

:class:`Quantiles` is what a backtest, a hub round and a report exchange: :meth:`Quantiles.at`
one place, origin, horizon or level; :meth:`Quantiles.select` a sub-panel that keeps its labels;
:meth:`Quantiles.median`; :meth:`Quantiles.frame` the long rows; :meth:`Quantiles.score` its
scores against :class:`Observed`, the truth of the same cells (labels checked, not assumed).
:func:`long_frame` is the one place an array becomes rows (hub files, score tables, derived
targets): one column per axis, in the array's order.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from pipeline.evaluation.quantile_function import level_index, median_index
from pipeline.evaluation.summary import CellScores, score_cells
from pipeline.panels.targets import TargetError

AXES = ("place", "origin", "horizon", "level")


def long_frame(values: ArrayLike, axes: Mapping[str, Sequence[Any] | ArrayLike],
               value: str = "value") -> pd.DataFrame:
    """One row per element of ``values`` (C order): a column per axis of ``axes`` (name →
    labels, one per position along that axis, in the array's axis order) and ``value``."""
    arr = np.asarray(values)
    labels = [np.asarray(v) for v in axes.values()]
    if arr.shape != tuple(len(v) for v in labels):
        raise TargetError(f"values of shape {arr.shape} do not fit the axes "
                          f"{ {k: len(v) for k, v in zip(axes, labels)} }")
    grids = np.meshgrid(*(np.arange(len(v)) for v in labels), indexing="ij")
    return pd.DataFrame({**{name: v[g.reshape(-1)] for name, v, g in zip(axes, labels, grids)},
                         value: arr.reshape(-1)})


def positions(labels: Sequence[Any], wanted: Sequence[Any], axis: str) -> list[int]:
    """Where each wanted label is along an axis of a labelled array; a label missing, or there
    twice (two rounds of one origin), is a :class:`TargetError`: a cell is found by what it is
    or not at all."""
    found = [[i for i, label in enumerate(labels) if label == w] for w in wanted]
    missing = [w for w, at in zip(wanted, found) if not at]
    if missing:
        raise TargetError(f"{axis} {missing} not in the forecast's {axis}s "
                          f"({len(labels)}: {list(labels)[:5]} …)")
    twice = [w for w, at in zip(wanted, found) if len(at) > 1]
    if twice:
        raise TargetError(f"{axis} {twice} appears more than once along the {axis}s")
    return [at[0] for at in found]


@dataclass(frozen=True, eq=False)
class Quantiles:
    """Quantiles ``values (C, O, H, Q)`` of ``places`` × ``origins`` × ``horizons`` ×
    ``levels`` (ascending); NaN where no forecast was made."""

    values: NDArray[np.float64]
    places: tuple[str, ...]
    origins: tuple[pd.Timestamp, ...]
    horizons: tuple[int, ...]
    levels: NDArray[np.float64]

    def __post_init__(self) -> None:
        shape = (len(self.places), len(self.origins), len(self.horizons), len(self.levels))
        if self.values.shape != shape:
            raise TargetError(f"quantiles of shape {self.values.shape} do not fit {shape[0]} "
                              f"places × {shape[1]} origins × {shape[2]} horizons × "
                              f"{shape[3]} levels")
        if np.any(np.diff(self.levels) <= 0):
            raise TargetError(f"levels {np.asarray(self.levels).tolist()} are not increasing")

    def _index(self, place: str | None, origin: pd.Timestamp | str | None,
               horizon: int | None, level: float | None) -> tuple[Any, ...]:
        return (slice(None) if place is None else positions(self.places, [place], "place")[0],
                slice(None) if origin is None else
                positions(self.origins, [pd.Timestamp(origin)], "origin")[0],
                slice(None) if horizon is None else
                positions(self.horizons, [horizon], "horizon")[0],
                slice(None) if level is None else level_index(self.levels, level))

    def at(self, *, place: str | None = None, origin: pd.Timestamp | str | None = None,
           horizon: int | None = None, level: float | None = None) -> NDArray[np.float64]:
        """The values at the labels given, those axes dropped (``at(place="US", horizon=1)``:
        ``(O, Q)``)."""
        return self.values[self._index(place, origin, horizon, level)]

    def select(self, *, places: Sequence[str] | None = None,
               origins: Sequence[pd.Timestamp] | NDArray[np.bool_] | None = None,
               horizons: Sequence[int] | None = None) -> Quantiles:
        """The forecast of some places, origins (labels, or a mask over them) and horizons,
        with their labels."""
        c, o, h = _cell_positions(self.places, self.origins, self.horizons, places, origins,
                                  horizons)
        return Quantiles(self.values[np.ix_(c, o, h, list(range(len(self.levels))))],
                         tuple(self.places[i] for i in c), tuple(self.origins[i] for i in o),
                         tuple(self.horizons[i] for i in h), self.levels)

    def with_values(self, values: NDArray[np.float64]) -> Quantiles:
        """Other quantiles of the same cells (rescaled, reconciled, held within bounds)."""
        return Quantiles(values, self.places, self.origins, self.horizons, self.levels)

    def score(self, truth: Observed, unit: NDArray[np.float64] | float = 1.0) -> CellScores:
        """The scores ``(C, O, H)`` of every cell against ``truth`` of the same places,
        origins and horizons (:func:`~pipeline.evaluation.summary.score_cells`; ``unit``
        turns the target into counts for the PIT)."""
        mine = (self.places, self.origins, self.horizons)
        theirs = (truth.places, truth.origins, truth.horizons)
        for axis, a, b in zip(AXES, mine, theirs):
            if tuple(a) != tuple(b):
                raise TargetError(f"the forecast's {axis}s {list(a)[:5]} … are not the "
                                  f"truth's {list(b)[:5]} …")
        return score_cells(self.values, truth.values, self.levels, unit)

    def median(self) -> NDArray[np.float64]:
        """``(C, O, H)`` the medians."""
        return self.values[..., median_index(self.levels)]

    def frame(self) -> pd.DataFrame:
        """The long rows (place, origin, horizon, level, value) of every forecast made."""
        out = long_frame(self.values, dict(zip(AXES, (self.places, self.origins,
                                                     self.horizons, self.levels))))
        return out[np.isfinite(out["value"].to_numpy(dtype=np.float64))].reset_index(drop=True)


@dataclass(frozen=True, eq=False)
class Observed:
    """What was observed ``values (C, O, H)`` at ``places`` × ``origins`` × ``horizons`` (the
    week ending 7h days after the origin); NaN where not observed (yet)."""

    values: NDArray[np.float64]
    places: tuple[str, ...]
    origins: tuple[pd.Timestamp, ...]
    horizons: tuple[int, ...]

    def __post_init__(self) -> None:
        shape = (len(self.places), len(self.origins), len(self.horizons))
        if self.values.shape != shape:
            raise TargetError(f"observations of shape {self.values.shape} do not fit "
                              f"{shape[0]} places × {shape[1]} origins × {shape[2]} horizons")

    def select(self, *, places: Sequence[str] | None = None,
               origins: Sequence[pd.Timestamp] | NDArray[np.bool_] | None = None,
               horizons: Sequence[int] | None = None) -> Observed:
        """The observations of some places, origins (labels, or a mask) and horizons."""
        c, o, h = _cell_positions(self.places, self.origins, self.horizons, places, origins,
                                  horizons)
        return Observed(self.values[np.ix_(c, o, h)], tuple(self.places[i] for i in c),
                        tuple(self.origins[i] for i in o), tuple(self.horizons[i] for i in h))

    def with_values(self, values: NDArray[np.float64]) -> Observed:
        """Other observations of the same cells (rescaled, some masked)."""
        return Observed(values, self.places, self.origins, self.horizons)


def _cell_positions(all_places: Sequence[str], all_origins: Sequence[pd.Timestamp],
                    all_horizons: Sequence[int], places: Sequence[str] | None,
                    origins: Sequence[pd.Timestamp] | NDArray[np.bool_] | None,
                    horizons: Sequence[int] | None) -> tuple[list[int], list[int], list[int]]:
    """The positions of the places, origins (labels, or a mask) and horizons asked for; all of
    an axis where none is asked."""
    c = (list(range(len(all_places))) if places is None
         else positions(all_places, list(places), "place"))
    if origins is None:
        o = list(range(len(all_origins)))
    elif isinstance(origins, np.ndarray) and origins.dtype == bool:
        o = [int(i) for i in np.flatnonzero(origins)]
    else:
        o = positions(all_origins, [pd.Timestamp(x) for x in origins], "origin")
    h = (list(range(len(all_horizons))) if horizons is None
         else positions(all_horizons, list(horizons), "horizon"))
    return c, o, h
