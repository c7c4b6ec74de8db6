"""The hub's rounds, forecast in real time: every round from the vintage released by its due
date, nowcast, forecast, combined, reconciled, and laid out as the hub's horizons.

For each round (:class:`~pipeline.panels.hub.HubRound`) the newest weeks of its vintage are
nowcast from the revision pattern of the vintages released before it
(:mod:`pipeline.nowcast.revisions`); the members forecast every location from the nowcast's
median history, steps 1 … S after the vintage's last week, all rounds and locations as the one
backtest's cells (:func:`~pipeline.backtest.backtest.run_backtest`, a vintage per origin); the
combiner's average (its weights and online calibration learnt at each round from the outcomes
its vintage held, the newest weeks at their nowcast's median — a later revision does not move a
past round —, the calibration burnt in on the year before the first round,
:func:`burn_in_origins`) is reconciled top-down (:mod:`pipeline.combine.reconcile`: the states'
medians sum to the national one) at each round and step where that scored better on the
outcomes then known. Each round's hub horizons −1 … 3 are then the steps
``h + lag`` (the vintage is ``lag`` weeks behind the reference date): a step ≤ 0 is a week in
the data, whose forecast is its nowcast.

The result holds every forecaster's quantiles (locations × rounds × hub horizons × levels,
labelled by the rounds' reference dates) in the hub's units (counts, or the ED share as a
proportion), the truth of the latest vintage, the published sample trajectories, and each
round's hub file (:meth:`~pipeline.backtest.hub_result.HubRoundsResult.round_frame`).
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.backtest.config import BacktestConfig, Variant

from pipeline.backtest.backtest import Vintages, run_backtest
from pipeline.backtest.hub_result import RECONCILED, UNRECONCILED, HubRoundsResult
from pipeline.backtest.result import BacktestResult
from pipeline.combine.average import EnsembleError
from pipeline.combine.combiner import PUBLISHED, UNCALIBRATED, CombineConfig, KnownTruth
from pipeline.combine.plausibility import bounded
from pipeline.combine.reconcile import (median_gap, reconcilable, reconciled_where_better,
                                        top_down)
from pipeline.evaluation.quantile_function import quantiles_at
from pipeline.members.base import Member
from pipeline.members.hub_baseline import HUB_BASELINE
from pipeline.nowcast.revisions import RevisionNowcastConfig, WeekNowcast, nowcast_weeks
from pipeline.data.hub.locations import POPULATION
from pipeline.panels.hub import HUB_HORIZONS, US, HubRound, is_share, target_scale
from pipeline.panels.panel import Panel, weeks_ending
from pipeline.panels.quantiles import Observed, Quantiles
from pipeline.panels.targets import HUB_QUANTILE_LEVELS
from pipeline.progress import ProgressReporter

# when the states are scaled to the national median: at every round; at the rounds and steps
# where that scored better on the outcomes known then (:func:`~pipeline.combine.reconcile.
# reconciled_where_better`); never
ReconcileRule = Literal["always", "where-better", "never"]
# the history a place needs at a burn-in origin (the hub baseline and the flows read 8 weeks)
BURN_IN_MIN_HISTORY_WEEKS = 8


@dataclass(frozen=True)
class HubBacktestConfig:
    """The hub's horizons and levels, the members' seed, the published combiner (a member
    without a forecast — the seasonal one before its data existed — is left out of a cell's
    average), the variants, the nowcast, when to reconcile top-down (counts with a national total),
    the sample trajectories per location and target, and the weeks of the online calibration's
    burn-in before the first round (:func:`burn_in_origins`)."""

    horizons: tuple[int, ...] = HUB_HORIZONS
    levels: tuple[float, ...] = HUB_QUANTILE_LEVELS
    seed: int = 0
    combine: CombineConfig = field(default_factory=lambda: CombineConfig(
        beyond_reach="reachable-members", outer_interval=0.95))
    variants: tuple[Variant, ...] = ()
    nowcast: RevisionNowcastConfig = field(default_factory=RevisionNowcastConfig)
    reconcile: ReconcileRule = "where-better"
    n_samples: int = 200
    member_time_limit_s: float | None = 1800.0
    # the online calibration's burn-in: weeks before the first round (:func:`burn_in_origins`)
    burn_in_weeks: int = 52

    def __post_init__(self) -> None:
        if self.burn_in_weeks < 0:
            raise EnsembleError(f"burn_in_weeks={self.burn_in_weeks} must be >= 0")
        if self.reconcile not in get_args(ReconcileRule):
            raise EnsembleError(f"reconcile={self.reconcile!r} is not one of "
                                f"{get_args(ReconcileRule)}")


def forecast_places(rounds: Sequence[HubRound]) -> tuple[str, ...]:
    """The locations every round's vintage holds (the others are named as skipped there)."""
    common = set(rounds[0].panel.places)
    for rnd in rounds[1:]:
        common &= set(rnd.panel.places)
    order = [p for p in rounds[-1].panel.places if p in common]
    return tuple(order)


def run_hub_rounds(rounds: Sequence[HubRound], latest: Panel, members: Sequence[Member],
                   config: HubBacktestConfig = HubBacktestConfig(), *,
                   references: Sequence[Member] = (),
                   progress: ProgressReporter | None = None) -> HubRoundsResult:
    """Every round in real time (module docstring), scored against ``latest``."""
    if not rounds:
        raise EnsembleError("no hub round to forecast")
    started = time.perf_counter()
    levels = np.asarray(config.levels, dtype=np.float64)
    target = latest.count_target
    places = forecast_places(rounds)
    nowcasts = tuple(nowcast_weeks(r.panel, [e.panel for e in rounds[:i]], levels,
                                   config.nowcast) for i, r in enumerate(rounds))
    known = [n.panel.only(places) for n in nowcasts]
    truth_panel = Panel({p: latest.histories[p] for p in places if p in latest.histories},
                        name=latest.name, as_of=latest.as_of)
    steps = tuple(range(1, max(config.horizons) + max(r.lag_weeks for r in rounds) + 1))
    burn_in = burn_in_origins(known[0], config.burn_in_weeks)
    data = Vintages(_aligned(truth_panel, places, known),
                    [*(known[0].up_to(o) for o in burn_in), *known])
    origins = [*burn_in, *(r.origin for r in rounds)]
    truth_at = data.truth_known(origins, steps)
    result = run_backtest(
        data, members, origins,
        BacktestConfig(horizons=steps, levels=config.levels, seed=config.seed,
                       combine=config.combine, variants=config.variants,
                       n_paths=config.n_samples,
                       member_time_limit_s=config.member_time_limit_s),
        references=references, reported=[r.origin for r in rounds],
        truth_at=truth_at, progress=progress)
    seconds = {"nowcast_and_backtest": time.perf_counter() - started}
    count = result.forecasts[target]
    gap, reconciled = None, None
    if (config.reconcile != "never" and not is_share(target)
            and reconcilable(places, US, POPULATION)):
        gap = median_gap(count[PUBLISHED].values, places, US, levels)
        reconciled = _reconcile(count, result.bounds, config, places, steps,
                                lambda r: truth_at(len(burn_in) + r)[:, len(burn_in):],
                                [r.origin for r in rounds])
    scale = target_scale(target)
    reference_dates = tuple(r.reference for r in rounds)
    by_hub = {name: Quantiles(_hub_horizons(q.values, rounds, nowcasts, places,
                                            config.horizons, steps, levels) / scale,
                              places, reference_dates, tuple(config.horizons), levels)
              for name, q in count.items()}
    samples = (_hub_samples(result, by_hub[PUBLISHED].values * scale, rounds, config.horizons,
                            steps, levels) / scale if result.paths is not None else None)
    truth = Observed(_truth(latest, places, rounds, config.horizons) / scale, places,
                     reference_dates, tuple(config.horizons))
    seconds["total"] = time.perf_counter() - started
    return HubRoundsResult(target=target, rounds=tuple(rounds), places=places,
                           horizons=tuple(config.horizons), levels=levels, forecasts=by_hub,
                           truth=truth, samples=samples, backtest=result, nowcasts=nowcasts,
                           gap=gap, reconciled=reconciled, seconds=seconds)


def _reconcile(count: dict[str, Quantiles], bounds: NDArray[np.float64] | None,
               config: HubBacktestConfig, places: Sequence[str], steps: tuple[int, ...],
               truth_at: KnownTruth, origins: Sequence[pd.Timestamp]) -> NDArray[np.bool_]:
    """The published forecast, its average uncalibrated and the variants reconciled top-down
    in place, each where ``config.reconcile`` says (``where-better``: by its own record on the
    outcomes known at each round), with the two ways beside them (:data:`UNRECONCILED`,
    :data:`RECONCILED`); returns ``(R, S)`` where the published one was reconciled."""
    levels = np.asarray(config.levels, dtype=np.float64)
    baseline = count[HUB_BASELINE].values
    count[UNRECONCILED] = count[PUBLISHED]
    chosen = np.ones(count[PUBLISHED].values.shape[1:3], dtype=bool)
    for name in (PUBLISHED, UNCALIBRATED, *(v.name for v in config.variants)):
        plain = count[name].values
        whole = top_down(plain, places, US, levels)
        if name == PUBLISHED:
            count[RECONCILED] = count[name].with_values(whole)
        if config.reconcile == "where-better":
            whole, where = reconciled_where_better(plain, whole, baseline, truth_at, origins,
                                                   steps, levels)
            chosen = where if name == PUBLISHED else chosen
        count[name] = count[name].with_values(whole)
    if bounds is not None:
        # a state's quantiles move with the nation's: held within its bound again (1.3 % of
        # COVID-19 admissions' published quantiles fell below it: bench.nhsn at f3da0a0)
        for name in (PUBLISHED, RECONCILED):
            count[name] = count[name].with_values(bounded(count[name].values, bounds))
    return chosen


def burn_in_origins(first: Panel, weeks: int,
                    min_history_weeks: int = BURN_IN_MIN_HISTORY_WEEKS) -> list[pd.Timestamp]:
    """The burn-in's origins, oldest first: the ``weeks`` weeks before the first round's
    origin at which every place of its vintage has ``min_history_weeks`` weeks of data.

    The online calibration (:mod:`pipeline.combine.recalibration`) starts at the average's own
    intervals and needs most of a season of outcomes to reach the stretch the members need:
    with one tracker at η = 0.15 and no burn-in, FluSight's first season was covered 38.7 % /
    87.5 %, the next 50.0 % / 92.4 %. So before the first round its vintage is cut at each of
    these origins and forecast by the same members (a flow not yet refitted is its pre-trained
    prior; a member whose data were not released yet is left out), and the outcomes teach the
    tracker as their weeks end; they are not reported. A year, so that every phase of a season
    is seen. Everything they use is in the first round's vintage: no round sees anything it
    did not know. A place with no such history (COVID-19 admissions' first release holds two
    weeks) has no burn-in. An origin whose week some place did not report is skipped: the
    members forecast from a reported week (a round's newest weeks are nowcast; these are not),
    and one such week in FluSight's release of 2025-01 had the flows left out of every round.
    With the burn-in that tracker covered 43.4 % / 92.6 % and 53.1 % / 94.4 %, relative WIS
    0.772 / 0.593 against 0.789 / 0.596 (FluSight's 59 rounds; ``docs/forecasting.md``)."""
    histories = list(first.histories.values())
    earliest = max(h.dates[0] for h in histories) + pd.Timedelta(weeks=min_history_weeks)
    candidates = (first.last_date - pd.Timedelta(weeks=k) for k in range(weeks, 0, -1))
    return [o for o in candidates if o >= earliest
            and all(np.isfinite(weeks_ending(h, o, 1)[0]) for h in histories)]


def _aligned(latest: Panel, places: Sequence[str], known: Sequence[Panel]) -> Panel:
    """The latest panel with the forecast places in the rounds' order."""
    missing = [p for p in places if p not in latest.histories]
    if missing:
        raise EnsembleError(f"the latest vintage has no data for {missing}")
    return Panel({p: latest.histories[p] for p in places}, name=latest.name, as_of=latest.as_of)


def _hub_horizons(values: NDArray[np.float64], rounds: Sequence[HubRound],
                  nowcasts: Sequence[WeekNowcast], places: Sequence[str],
                  horizons: Sequence[int], steps: Sequence[int], levels: NDArray[np.float64]
                  ) -> NDArray[np.float64]:
    """``(C, R, H, Q)`` at the hub horizons from the steps' ``(C, R, S, Q)``; a week in the
    data (step ≤ 0) is its nowcast."""
    out = np.full((len(places), len(rounds), len(horizons), len(levels)), np.nan)
    for r, (rnd, nowcast) in enumerate(zip(rounds, nowcasts)):
        for k, h in enumerate(horizons):
            step = h + rnd.lag_weeks
            if step >= 1:
                out[:, r, k] = values[:, r, list(steps).index(step)]
            elif -step < len(nowcast.ends):
                out[:, r, k] = np.stack([nowcast.quantiles[p][-step] for p in places])
    return out


def _hub_samples(result: BacktestResult, published: NDArray[np.float64],
                 rounds: Sequence[HubRound], horizons: Sequence[int], steps: Sequence[int],
                 levels: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(C, R, n, H)`` trajectories: the published paths' weekly counts at the forecast weeks
    (their ranks from the flow's paths), and at a week in the data draws of its nowcast ranked
    like the first forecast week (a larger nowcast goes with a larger forecast)."""
    assert result.paths is not None
    counts = result.paths[..., 1] * result.populations[:, None, None, None]  # (C, R, n, S)
    n_c, n_r, n = counts.shape[:3]
    out = np.full((n_c, n_r, n, len(horizons)), np.nan)
    for r, rnd in enumerate(rounds):
        first = counts[:, r, :, 0]
        ranks = np.argsort(np.argsort(first, axis=1, kind="stable"), axis=1, kind="stable")
        u = (ranks + 0.5) / n
        for k, h in enumerate(horizons):
            step = h + rnd.lag_weeks
            if step >= 1:
                out[:, r, :, k] = counts[:, r, :, list(steps).index(step)]
            elif np.isfinite(published[:, r, k]).all():
                out[:, r, :, k] = quantiles_at(levels, published[:, r, k], u)
    return np.maximum(out, 0.0)


def _truth(latest: Panel, places: Sequence[str], rounds: Sequence[HubRound],
           horizons: Sequence[int]) -> NDArray[np.float64]:
    """``(C, R, H)`` the latest vintage's value of each round's hub weeks (NaN: not held)."""
    out = np.full((len(places), len(rounds), len(horizons)), np.nan)
    for c, place in enumerate(places):
        history = latest.histories.get(place)
        if history is None:
            continue
        for r, rnd in enumerate(rounds):
            ends = [rnd.target_end(h) for h in horizons]
            out[c, r] = [weeks_ending(history, end, 1)[0] for end in ends]
    return out
