"""The weekly run's nowcast, and a member that forecasts each of its completions and publishes
their mixture.

At origins from ``active_from`` on (where the data are still being reported),
:class:`CompletionMixture` forecasts every completion of the nowcast
(:mod:`pipeline.nowcast.completions`) as a cell of its own — all completions of all cells in one
batch of the member — and publishes their equal mixture (the average of their CDFs,
:func:`~pipeline.combine.average.mix_quantiles`); earlier origins (final data) are forecast as
they are. At the round's own origin the current week is floored at the cases already reported
for its days (:func:`floor_current_week`).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.combine.average import mix_quantiles
from pipeline.members.base import MemberForecast, MemberWrapper
from pipeline.nowcast.completions import (CompletedHistories, Nowcast, complete_histories,
                                          day_index, week_sums)
from pipeline.nowcast.hub_weeks import HubWeeks
from pipeline.panels.history import EpiHistory
from pipeline.panels.panel import Cells
from pipeline.panels.targets import DAYS_PER_WEEK, SHARE


@dataclass(frozen=True, eq=False)
class RunNowcast:
    """The weekly run's nowcast: the completions, their per-day median (the history the
    backtest scores against), the round's weeks and where the delay model came from."""

    nowcast: Nowcast
    completed: CompletedHistories
    median_history: EpiHistory
    weeks: HubWeeks
    delay_model: str

    def week_samples(self, end: pd.Timestamp) -> NDArray[np.float64]:
        """``(K,)`` final cases of the 7-day week ending ``end`` in each completion."""
        return week_sums(self.completed, [pd.Timestamp(end)])[:, 0]

    def week_observed(self, end: pd.Timestamp) -> float:
        """The same week's cases as reported so far."""
        observed = self.completed.history(0).cases.astype(np.float64).copy()
        start = day_index(self.completed.dates, self.nowcast.dates[0])
        observed[start:] = self.nowcast.observed
        pos = day_index(self.completed.dates, end)
        return float(observed[pos - DAYS_PER_WEEK + 1:pos + 1].sum())

    def reported_share(self, end: pd.Timestamp) -> NDArray[np.float64]:
        """``(K,)`` share of the week's final cases reported so far."""
        return self.week_observed(end) / np.maximum(self.week_samples(end), 1.0)


def median_history(history: EpiHistory, nowcast: Nowcast) -> EpiHistory:
    """``history`` completed with the per-day median of the nowcast (never below reported)."""
    median = np.maximum(np.rint(np.median(nowcast.samples, axis=0)).astype(np.int64),
                        nowcast.observed)
    point = Nowcast(nowcast.dates, nowcast.observed, median[None, :],
                    nowcast.completeness.mean(axis=0, keepdims=True), nowcast.as_of)
    return complete_histories(history, point).history(0)


@dataclass(frozen=True, eq=False)
class CompletionMixture(MemberWrapper):
    """A weekly member that, at origins from ``active_from`` on (where the data are still being
    reported), forecasts every completion and publishes their mixture; earlier origins (final
    data) are forecast as they are. At the round's own origin the mixture's current week is
    floored at the cases already reported for its days in the data (:func:`floor_current_week`).
    Sample paths: an equal share of each completion's."""

    completed: CompletedHistories
    active_from: pd.Timestamp
    n_mixed: int = 32                  # the first completions are forecast

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Cells before ``active_from`` as the member forecasts them; each later cell as the
        mixture of its ``n_mixed`` completions, every completion of every such cell in one batch
        of the member (a completion keeps its cell's place, panel and seed)."""
        late = [b for b, o in enumerate(cells.origins) if o >= self.active_from]
        early = [b for b in range(len(cells)) if b not in set(late)]
        count = np.empty((len(cells), len(horizons), len(levels)))
        share: NDArray[np.float64] | None = None
        paths: list[NDArray[np.float64] | None] = [None] * len(cells)
        if early:
            made = self.member.forecast(cells.subset(early), horizons, levels)
            count[early] = made.count
            if SHARE in made.extra:
                share = np.full(count.shape, np.nan)
                share[early] = made.extra[SHARE]
            for i, b in enumerate(early):
                paths[b] = None if made.paths is None else made.paths[i]
        if late:
            completions = [self.completed.histories(up_to=cells.origins[b], count=self.n_mixed)
                           for b in late]
            index = [b for b, cs in zip(late, completions) for _ in cs]
            expanded = Cells(tuple(h for cs in completions for h in cs),
                             tuple(cells.places[b] for b in index),
                             tuple(cells.panels[b] for b in index),
                             tuple(cells.seeds[b] for b in index))
            made = self.member.forecast(expanded, horizons, levels)
            bounds = np.cumsum([0] + [len(cs) for cs in completions])
            for i, b in enumerate(late):
                part = slice(bounds[i], bounds[i + 1])
                count[b] = floor_current_week(mix_quantiles(made.count[part], levels),
                                              self.completed, cells.origins[b], horizons)
                if share is not None:       # a member's own I is not mixed: I = count / N
                    share[b] = count[b] / cells.histories[b].population
                paths[b] = (None if made.paths is None
                            else pooled_paths(list(made.paths[part])))
        return MemberForecast(count, {} if share is None else {SHARE: share},
                              np.stack([p for p in paths if p is not None])
                              if all(p is not None for p in paths) else None)


def floor_current_week(cases: NDArray[np.float64], completed: CompletedHistories,
                       origin: pd.Timestamp, horizons: Sequence[int]) -> NDArray[np.float64]:
    """Quantiles ``(..., H, Q)`` of weekly cases with the week after ``origin`` raised to at
    least the cases already reported for its days in the data.

    Only at the round's own origin — the last Saturday before the data date, whose week is
    partly in the data (1–6 days): a week cannot end below what has been reported in it (the
    hub baseline and the flows forecast from the origin and did not see those days). The floor
    is the reported count, not a completion's nowcast of it: flooring at each completion's own
    count was measured worse (``bench/nowcast.py``, hub horizon 0: 0.629 of drop-14 against
    0.568 unfloored), as the newest days' nowcast is the least certain. An earlier origin (a
    backtest cell) sees nothing after itself, so nothing changes there."""
    known = int((completed.dates[-1] - origin).days)
    if completed.reported is None or not 0 < known < DAYS_PER_WEEK or 1 not in horizons:
        return cases
    reported = float(completed.reported[-known:].sum())
    out = cases.copy()
    j = list(horizons).index(1)
    out[..., j, :] = np.maximum(out[..., j, :], reported)
    return out


def pooled_paths(paths: Sequence[NDArray[np.float64] | None]) -> NDArray[np.float64] | None:
    """An equal share of every completion's sample paths (None when any has none)."""
    if any(p is None for p in paths):
        return None
    arrays = [p for p in paths if p is not None]
    n = min(len(p) for p in arrays)
    per = int(np.ceil(n / len(arrays)))
    return np.concatenate([p[:per] for p in arrays])[:n]
