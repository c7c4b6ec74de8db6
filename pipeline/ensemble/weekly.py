"""The published weekly forecast and its track record, as one step of the weekly run.

Every Saturday origin of the series is forecast in real time (each sees only its past, the
ensemble's weights and recalibration only past scores): the last origin is this week's published
forecast, the earlier ones are its backtest. Forecasting all of them costs seconds, so the report
always carries the skill of exactly the method it publishes, measured on exactly the data it
shows.

Origins are Saturdays so that forecast weeks are epiweeks (Sunday–Saturday), the weeks the
Forecast Hub and hubverse count in; data after the last Saturday wait for the next run.
"""
from __future__ import annotations

import datetime as dt
import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.ensemble.backtest import (PUBLISHED, BacktestConfig, BacktestResult,
                                        backtest_origins, run_realtime_backtest, summarize)
from pipeline.ensemble.autoets import AutoETSMember
from pipeline.ensemble.growth_regression import GrowthRegressionConfig, PooledGrowthMember
from pipeline.ensemble.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.ensemble.members import Member
from pipeline.ensemble.memo import ForecastMemo
from pipeline.ensemble.nf_finetune import (FineTuneConfig, fit_finetuned_member,
                                           latest_refit_date, refit_dates)
from pipeline.ensemble.nf_member import (GrowthModelConfig, NFGrowthMember, SyntheticWindows,
                                         train_or_reuse_growth_model)
from pipeline.ensemble.nowcast_forecast import CompletionMixture, RunNowcast
from pipeline.ensemble.published import BeyondReach, PublishedEnsemble
from pipeline.ensemble.targets import EpiHistory, QuantileForecast
from pipeline.training.digests import DataDigests
from pipeline.progress import ProgressReporter

SATURDAY = 5
# The hub baseline resamples its differences; 10,000 draws per forecast (reichlab: 100,000) keep
# the Monte Carlo error of its 1 % quantile under 0.1 percentage points of level, at a tenth of
# the cost over the thousands of cells of a panel and the nowcast's completions.
BASELINE_SAMPLES = 10_000


@dataclass(frozen=True)
class WeeklyConfig:
    """The published forecast's settings: the members' models (``growth``: the flow member's;
    ``regression``: growth-qr; ``finetune``: nf-real's refits) and which members run."""

    growth: GrowthModelConfig = field(default_factory=GrowthModelConfig)
    regression: GrowthRegressionConfig = field(default_factory=GrowthRegressionConfig)
    finetune: FineTuneConfig = field(default_factory=FineTuneConfig)
    include_nf: bool = True
    include_real: bool = True
    # draws per forecast of each flow member: 500 keep the Monte Carlo error of the 5 %/95 %
    # quantiles near 2 % of the spread, at half the cost of 1,000 over a panel's thousands of cells
    flow_samples: int = 500
    n_paths: int = 200
    min_history_weeks: int = 8
    seed: int = 0

    def backtest_config(self, *, scored_only: bool = False, first_origin: dt.date | None = None,
                        last_origin: dt.date | None = None) -> BacktestConfig:
        """Saturday origins; ``scored_only``: only those whose 4-week truth is observed (the
        weekly run also forecasts the latest ones: the last is the published forecast)."""
        return BacktestConfig(origin_weekday=SATURDAY, scored_only=scored_only,
                              first_origin=first_origin, last_origin=last_origin,
                              min_history_weeks=self.min_history_weeks, n_paths=self.n_paths,
                              seed=self.seed)


@dataclass(frozen=True, eq=False)
class WeeklyForecast:
    """``backtest``: every Saturday origin, the latest one unscored; ``latest``: the published
    forecast at the latest origin (quantiles of I and weekly cases, weekly S/I/R sample paths)."""

    history: EpiHistory
    backtest: BacktestResult
    model_key: str | None
    model_reused: bool
    nowcast: RunNowcast | None = None       # the days still being reported, when nowcast
    memo_reads: tuple[int, int] | None = None   # forecasts read back from the memo, of all asked

    @property
    def latest(self) -> QuantileForecast:
        return self.backtest.forecasts[self.backtest.origins[-1]][PUBLISHED]

    @property
    def origin(self) -> pd.Timestamp:
        return self.backtest.origins[-1]

    def member_forecasts(self) -> dict[str, QuantileForecast]:
        """Every forecaster's forecast at the latest origin (members, references, published)."""
        return dict(self.backtest.forecasts[self.origin])

    def summary(self) -> dict[str, Any]:
        """:func:`~pipeline.ensemble.backtest.summarize` of the track record (computed once:
        the report reads it a dozen times; treat it as read-only)."""
        return self._summary

    @functools.cached_property
    def _summary(self) -> dict[str, Any]:
        return summarize(self.backtest)


@dataclass(frozen=True, eq=False)
class WeeklyMembers:
    """The published ensemble's members; ``model_key``/``reused``: the flow member's store entry."""

    members: list[Member]
    model_key: str | None
    reused: bool


def build_weekly_members(config: WeeklyConfig, store_root: Path,
                         reference: Mapping[str, EpiHistory] | None = None,
                         history: EpiHistory | None = None, place: str | None = None,
                         progress: ProgressReporter | None = None, *,
                         newest_refits_first: bool = False) -> WeeklyMembers:
    """The one place the published ensemble's members are chosen, for one place's forecast.

    * ``hub-baseline`` — the flat Forecast Hub baseline: in the log-scale average it damps the
      trend members' growth at the longer horizons (cross-county backtest, variant without it:
      relative WIS at four weeks 0.84 against 0.79);
    * ``growth-qr`` — growth regression pooled over the forecast's own series and the
      ``reference`` places other than ``place`` (California's counties beside San Francisco);
    * ``nf-growth`` — the conditional flow trained on the multi-wave prior (model store);
    * ``nf-real`` — that flow fine-tuned on the calendar of
      :func:`~pipeline.ensemble.nf_finetune.refit_dates` on the real windows of the
      ``reference`` places known by then: the same models as the cross-county backtest's
      (shared through the model store). Without reference places there is no nf-real (one
      series alone is too few windows to fine-tune a flow on).

    AutoETS is scored beside them as a reference, not a member (cross-county relative WIS 1.17:
    worse than the baseline it would be averaged with). ``newest_refits_first``: see
    :func:`~pipeline.ensemble.nf_finetune.fit_finetuned_member`."""
    reference = dict(reference or {})
    others = tuple(h for name, h in reference.items() if name != place)
    members: list[Member] = [HubBaseline(HubBaselineConfig(n_samples=BASELINE_SAMPLES)),
                             PooledGrowthMember(others, config.regression)]
    origins = (backtest_origins(history, config.backtest_config())
               if history is not None else [])
    return _with_flows(members, config, store_root, list(reference.values()), origins, progress,
                       newest_refits_first)




def build_panel_members(places: Sequence[EpiHistory], origins: Sequence[pd.Timestamp],
                        config: WeeklyConfig, store_root: Path,
                        progress: ProgressReporter | None = None, *,
                        newest_refits_first: bool = False) -> WeeklyMembers:
    """The same members for a panel of places forecast together (the cross-county backtest):
    growth-qr pools the panel itself, nf-real is refitted on the panel's windows."""
    members: list[Member] = [
        HubBaseline(HubBaselineConfig(n_samples=BASELINE_SAMPLES)),
        PooledGrowthMember((), config.regression)]
    return _with_flows(members, config, store_root, list(places), list(origins), progress,
                       newest_refits_first)


def build_vintage_ensemble(config: WeeklyConfig, store_root: Path,
                           pool: Mapping[str, EpiHistory], origins: Sequence[pd.Timestamp],
                           progress: ProgressReporter | None = None,
                           beyond_reach: BeyondReach = "missing") -> PublishedEnsemble:
    """The same members for many histories known at one vintage, forecast at ``origins``
    (every county and nowcast completion of ``bench/nowcast.py``'s real-time evaluation):
    growth-qr pools ``pool`` (the vintage's places, each history's own left out), nf-real is
    fine-tuned on ``pool``'s windows at the latest refit date ≤ each origin — the only refits a
    forecast at those origins uses (:mod:`pipeline.ensemble.published`)."""
    dates = sorted({latest_refit_date(o, config.finetune.refit_every_weeks) for o in origins})
    chosen = _with_flows([HubBaseline(HubBaselineConfig(n_samples=BASELINE_SAMPLES))], config,
                         store_root, list(pool.values()), dates, progress)
    return PublishedEnsemble(tuple(chosen.members), dict(pool), config.regression, beyond_reach)


def _with_flows(members: list[Member], config: WeeklyConfig, store_root: Path,
                pool: list[EpiHistory], origins: list[pd.Timestamp],
                progress: ProgressReporter | None,
                newest_refits_first: bool = False) -> WeeklyMembers:
    """``members`` + nf-growth (trained or reused) + nf-real fine-tuned on ``pool`` at the refit
    dates among ``origins`` (when both are non-empty)."""
    if not config.include_nf:
        return WeeklyMembers(members, None, False)
    synthetic = SyntheticWindows(config.growth, DataDigests(store_root))
    stored = train_or_reuse_growth_model(config.growth, store_root, progress=progress,
                                         synthetic=synthetic)
    flow = NFGrowthMember(stored.estimator, config.growth, n_samples=config.flow_samples)
    members = [*members, flow]
    dates = refit_dates(origins, config.finetune.refit_every_weeks)
    if config.include_real and pool and dates:
        members.append(fit_finetuned_member(flow, synthetic, pool, dates, config.finetune,
                                            store_root, progress,
                                            newest_first=newest_refits_first))
    return WeeklyMembers(members, stored.key, stored.reused)


def forecast_weekly(history: EpiHistory, config: WeeklyConfig, store_root: Path,
                    reference: Mapping[str, EpiHistory] | None = None, place: str | None = None,
                    progress: ProgressReporter | None = None, *,
                    references: Sequence[Member] | Callable[[], Sequence[Member]] = (),
                    nowcast: RunNowcast | None = None,
                    mixture_from: pd.Timestamp | None = None,
                    mixed_completions: int = 32,
                    memo: ForecastMemo | None = None) -> WeeklyForecast:
    """Build the members (training or reusing their models), then forecast every Saturday origin
    in real time; ``references`` are scored beside the members, not averaged (or a function
    giving them, called once the members are built: the run filters the SMC member meanwhile).

    With a ``nowcast`` (``history`` is then its per-day median), every member forecasts each
    of the first ``mixed_completions`` completions at the origins from ``mixture_from`` on and
    publishes their mixture
    (:class:`~pipeline.ensemble.nowcast_forecast.CompletionMixture`). With a ``memo``, the
    members' and AutoETS's forecasts that an earlier run already made (same member, same
    history up to the origin) are read back (:mod:`pipeline.ensemble.memo`)."""
    chosen = build_weekly_members(config, store_root, reference, history, place, progress)
    members: list[Member] = list(chosen.members)
    scored = list(references() if callable(references) else references)
    if memo is not None:
        members = [memo.wrap(m) for m in members]
        scored = [memo.wrap(AutoETSMember()), *scored]
    if nowcast is not None:
        start = mixture_from or nowcast.completed.first_nowcast_day
        members = [CompletionMixture(m, nowcast.completed, start, mixed_completions)
                   for m in members]
    result = run_realtime_backtest(history, members, config.backtest_config(), progress,
                                   references=scored)
    reads = None if memo is None else (memo.hits, memo.hits + memo.misses)
    return WeeklyForecast(history, result, chosen.model_key, chosen.reused, nowcast, reads)
