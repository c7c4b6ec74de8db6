"""Nowcast, then forecast, from the data date: a hub round's weeks from a nowcast's completions
(the weeks in the data) and a forecaster's forecast mixed over them (the later weeks).

**Weeks**: :mod:`pipeline.nowcast.hub_weeks`.

**The days after the origin.** When D is not a Saturday, the current week (hub horizon 0) has
its first days in the data. By default the week is the forecast's week from the origin (which
the weekly run publishes too), raised to at least the cases already reported for those days
(:func:`floor_current_week`: a week cannot end below what has been reported in it; before, the
weekly run's 5 % quantile of the current week, 93 cases, lay below the 321 already reported for
its first four days). ``partial_week=True`` makes it the nowcast of
those days plus the forecast's week scaled by the share of a week's cases its other days carry
(weekday shares of the completed history's last eight weeks; a monotone map of the forecast, so
quantiles map exactly). Measured on the CDPH vintages (``bench/nowcast.py``) it did worse: those
days are the least complete, and their nowcast the least certain.

**Mixing.** Each completion k of the nowcast is forecast as a history of its own (one batch);
the published distribution is their equal mixture: each completion's continuous quantile
function (:func:`pipeline.evaluation.quantile_function.quantiles_at`) is read at the same stratified
levels, the draws are pooled and the hub quantiles taken from the pool — the average of the
CDFs, not of the quantiles.

The forecaster is any member (AutoETS in the benchmark) or an
:class:`~pipeline.combine.combiner.Ensemble`, whose members are each mixed over the completions
and then combined (the weekly run's order).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.combine.average import mix_quantiles
from pipeline.combine.combiner import Ensemble
from pipeline.members.base import Member, forecast_within_reach
from pipeline.nowcast.completions import CompletedHistories, day_index, week_sums
from pipeline.nowcast.hub_weeks import HUB_HORIZONS, HubWeeks, hub_weeks, last_saturday
from pipeline.nowcast.mixture import floor_current_week
from pipeline.panels.history import EpiHistory
from pipeline.panels.panel import Cells, Panel, origin_seed
from pipeline.panels.targets import DAYS_PER_WEEK, TargetError

WEEKDAY_SHARE_WEEKS = 8
Place = TypeVar("Place", str, None)          # a place's name (None: one unnamed place)
Forecaster = Member | Ensemble


def weekday_shares(histories: CompletedHistories, until: pd.Timestamp,
                   weeks: int = WEEKDAY_SHARE_WEEKS) -> NDArray[np.float64]:
    """``(K, 7)`` share of a week's cases on each weekday (Monday = 0) over the ``weeks`` weeks
    ending on ``until``."""
    end = day_index(histories.dates, until) + 1
    start = max(end - weeks * DAYS_PER_WEEK, 0)
    cases = histories.cases[:, start:end].astype(np.float64) + 0.5
    weekday = histories.dates[start:end].weekday.to_numpy()
    totals = np.stack([cases[:, weekday == w].sum(axis=1) for w in range(DAYS_PER_WEEK)], axis=1)
    return totals / totals.sum(axis=1, keepdims=True)


# ------------------------------------------------------------------------------ the forecast


@dataclass(frozen=True, eq=False)
class NowcastForecast:
    """Quantiles ``(H, Q)`` of weekly cases at the hub weeks ``weeks`` (nowcast or forecast),
    per completion ``(K, H, Q)`` too (hub files' sample paths and diagnostics)."""

    weeks: HubWeeks
    levels: NDArray[np.float64]
    quantiles: NDArray[np.float64]
    per_completion: NDArray[np.float64]
    forecaster: str


def forecast_cells(forecaster: Forecaster, histories: Sequence[EpiHistory],
                   places: Sequence[Place], horizons: tuple[int, ...],
                   levels: NDArray[np.float64], seed: int, panel: Panel | None = None
                   ) -> NDArray[np.float64]:
    """Count quantiles ``(M, B, H, Q)`` of B histories at their own origins: every member of
    an :class:`~pipeline.combine.combiner.Ensemble` (M of them), or the one forecaster's
    (M = 1). ``panel``: what pooled members learn from (each history's place is its row);
    without it each history is a panel of its own."""
    names = [p if p is not None else "place" for p in places]
    panels = [panel if panel is not None else Panel({n: h}) for n, h in zip(names, histories)]
    cells = Cells.of(histories, [origin_seed(seed, h.origin) for h in histories], names, panels)
    if isinstance(forecaster, Ensemble):
        return forecaster.member_quantiles(cells, horizons, levels)
    return forecast_within_reach(forecaster, cells, horizons, levels).count[None]


def nowcast_then_forecast(histories: CompletedHistories, data_date: pd.Timestamp,
                          forecaster: Forecaster, levels: NDArray[np.float64], seed: int, *,
                          horizons: tuple[int, ...] = HUB_HORIZONS,
                          partial_week: bool = False) -> NowcastForecast:
    """Every completion forecast from the last Saturday ≤ ``data_date`` (one batch), nowcast
    weeks from the completions' own counts, mixed (module docstring)."""
    return nowcast_then_forecast_places({None: histories}, data_date, forecaster, levels, seed,
                                        horizons=horizons, partial_week=partial_week)[None]


def nowcast_then_forecast_places(completed: Mapping[Place, CompletedHistories],
                                 data_date: pd.Timestamp, forecaster: Forecaster,
                                 levels: NDArray[np.float64], seed: int, *,
                                 horizons: tuple[int, ...] = HUB_HORIZONS,
                                 partial_week: bool = False, panel: Panel | None = None
                                 ) -> dict[Place, NowcastForecast]:
    """:func:`nowcast_then_forecast` of every place's completions, all in one forecaster call.
    An ensemble's members are each mixed over the completions, then combined (the weekly run's
    order); any other forecaster is mixed as it comes. ``panel``: the places pooled members
    learn from (:func:`forecast_cells`)."""
    weeks = hub_weeks(data_date, horizons)
    for place, histories in completed.items():
        if histories.dates[-1] != weeks.data_date:
            raise TargetError(f"{place or 'the'} completed histories end "
                              f"{histories.dates[-1].date()}, the data date is "
                              f"{weeks.data_date.date()}")
    steps = weeks.forecast_steps
    forecast_at = [weeks.weeks.index(w) for w in weeks.weeks if w.kind == "forecast"]
    places = [p for p, h in completed.items() for _ in range(len(h))]
    cells = [h for c in completed.values() for h in c.histories(up_to=weeks.origin)]
    bounds = np.cumsum([0] + [len(c) for c in completed.values()])
    members = np.empty((1, len(cells), 0, len(levels)))                              # (M, B, H, Q)
    if steps:
        members = forecast_cells(forecaster, cells, places, steps, levels, seed, panel)
    out: dict[Place, NowcastForecast] = {}
    for i, (place, histories) in enumerate(completed.items()):
        per = _nowcast_weeks(histories, weeks, len(levels))                          # (K, W, Q)
        mixed: NDArray[np.float64] | None = None
        if steps:
            own = np.stack([_with_known_days(m[bounds[i]:bounds[i + 1]], histories, weeks,
                                             partial_week) for m in members])   # (M, K, H, Q)
            if isinstance(forecaster, Ensemble):
                per[:, forecast_at] = forecaster.combine(own)
                mixed = forecaster.combine(np.stack([mix_quantiles(m, levels) for m in own]))
            else:
                per[:, forecast_at] = own[0]
        quantiles = mix_quantiles(per, levels)
        if mixed is not None:
            quantiles[forecast_at] = mixed
        out[place] = NowcastForecast(weeks, np.asarray(levels, dtype=np.float64), quantiles,
                                     per, forecaster.name)
    return out


def _nowcast_weeks(histories: CompletedHistories, weeks: HubWeeks, n_levels: int
                   ) -> NDArray[np.float64]:
    """``(K, W, Q)``: each completion's count of every nowcast week (a point per completion),
    NaN at the forecast weeks."""
    per = np.full((len(histories), len(weeks.weeks), n_levels), np.nan)
    nowcast_weeks = [w for w in weeks.weeks if w.kind == "nowcast"]
    if nowcast_weeks:
        sums = week_sums(histories, [w.end for w in nowcast_weeks])                # (K, W)
        for j, w in enumerate(nowcast_weeks):
            per[:, weeks.weeks.index(w)] = sums[:, j, None]
    return per


def _with_known_days(forecast: NDArray[np.float64], histories: CompletedHistories,
                     weeks: HubWeeks, partial_week: bool) -> NDArray[np.float64]:
    """The current week (step 1) as its known days' nowcast plus the forecast of the rest
    (``partial_week``), else the forecast's week floored at its known days."""
    known = weeks.known_days_after_origin
    if not partial_week or known == 0 or 1 not in weeks.forecast_steps:
        return floor_current_week(forecast, histories, weeks.origin, weeks.forecast_steps)
    shares = weekday_shares(histories, weeks.origin)                            # (K, 7)
    days = (weeks.origin + pd.Timedelta(days=d) for d in range(1, known + 1))
    weekday = np.array([d.weekday() for d in days])
    rest = 1.0 - shares[:, weekday].sum(axis=1)                                  # (K,)
    tail = histories.cases[:, -known:].sum(axis=1).astype(np.float64)
    out = forecast.copy()
    j = weeks.forecast_steps.index(1)
    out[:, j] = tail[:, None] + rest[:, None] * forecast[:, j]
    return out


def truncated_forecast(history: EpiHistory, data_date: pd.Timestamp,
                       forecaster: Forecaster, levels: NDArray[np.float64],
                       seed: int, *, drop_days: int,
                       horizons: tuple[int, ...] = HUB_HORIZONS) -> NDArray[np.float64]:
    """Quantiles ``(H, Q)`` at the hub weeks of ``data_date`` without a nowcast: the data
    after ``data_date − drop_days`` are dropped (today's run drops 14), the origin is the last
    Saturday ≤ the last day kept and the forecast runs as many weeks as the hub weeks need; a
    week ending on or before that origin is its count as reported (the truncated data as is)."""
    return truncated_forecasts({None: history}, data_date, forecaster, levels, seed,
                               drop_days=drop_days, horizons=horizons)[None]


def truncated_forecasts(histories: Mapping[Place, EpiHistory], data_date: pd.Timestamp,
                        forecaster: Forecaster, levels: NDArray[np.float64],
                        seed: int, *, drop_days: int, horizons: tuple[int, ...] = HUB_HORIZONS,
                        panel: Panel | None = None) -> dict[Place, NDArray[np.float64]]:
    """:func:`truncated_forecast` of every place, one forecaster call per origin (places whose
    data end on the same day share it); ``panel``: as :func:`forecast_cells`."""
    weeks = hub_weeks(data_date, horizons)
    seen = {p: h.up_to(weeks.data_date - pd.Timedelta(days=drop_days))
            for p, h in histories.items()}
    origins = {p: last_saturday(h.origin) for p, h in seen.items()}
    out = {p: np.empty((len(weeks.weeks), len(levels))) for p in histories}
    for origin in dict.fromkeys(origins.values()):
        group = [p for p in histories if origins[p] == origin]
        steps = [int((w.end - origin).days // DAYS_PER_WEEK) for w in weeks.weeks]
        ahead = tuple(s for s in steps if s > 0)
        if ahead:
            members = forecast_cells(forecaster, [seen[p].up_to(origin) for p in group], group,
                                     ahead, levels, seed, panel)
            forecast = (forecaster.combine(members) if isinstance(forecaster, Ensemble)
                        else members[0])
            for b, p in enumerate(group):
                for j, s in enumerate(ahead):
                    out[p][steps.index(s)] = forecast[b, j]
        for p in group:
            for i, s in enumerate(steps):
                if s <= 0:
                    pos = day_index(histories[p].dates, weeks.weeks[i].end)
                    out[p][i] = float(histories[p].cases[pos - DAYS_PER_WEEK + 1:pos + 1].sum())
    return out


