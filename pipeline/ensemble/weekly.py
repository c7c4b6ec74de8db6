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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.ensemble.backtest import (PUBLISHED, BacktestConfig, BacktestResult,
                                           run_realtime_backtest, summarize)
from pipeline.ensemble.members import Member
from pipeline.ensemble.nf_member import GrowthModelConfig, NFGrowthMember, \
    train_or_reuse_growth_model
from pipeline.ensemble.nowcast_forecast import CompletionMixture, RunNowcast
from pipeline.ensemble.targets import EpiHistory, QuantileForecast
from pipeline.progress import ProgressReporter

SATURDAY = 5


@dataclass(frozen=True)
class WeeklyConfig:
    """The published forecast's settings; ``growth`` is the flow member's model."""

    growth: GrowthModelConfig = field(default_factory=GrowthModelConfig)
    include_nf: bool = True
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
        return summarize(self.backtest)


def build_weekly_members(config: WeeklyConfig, store_root: Path,
                         progress: ProgressReporter | None = None
                         ) -> tuple[list[Member], str | None, bool]:
    """(members, flow model key, reused): the one place the published ensemble's members are
    chosen. AutoETS and the flow member (from the model store); the hub baseline is a reference
    the backtest always scores, not a member — a flat forecast would only pull the average
    towards "no change" (measured on the SF backtest: with it the uncalibrated ensemble's WIS
    was 4 % higher on both targets)."""
    from pipeline.ensemble.autoets import AutoETSMember

    members: list[Member] = [AutoETSMember()]
    if not config.include_nf:
        return members, None, False
    stored = train_or_reuse_growth_model(config.growth, store_root, progress=progress)
    members.append(NFGrowthMember(stored.estimator, config.growth))
    return members, stored.key, stored.reused


def forecast_weekly(history: EpiHistory, config: WeeklyConfig, store_root: Path,
                    progress: ProgressReporter | None = None, *,
                    nowcast: RunNowcast | None = None,
                    mixture_from: pd.Timestamp | None = None,
                    mixed_completions: int = 32) -> WeeklyForecast:
    """Train or reuse the flow member, then forecast every Saturday origin in real time.

    With a ``nowcast`` (``history`` is then its per-day median), every member forecasts each
    of the first ``mixed_completions`` completions at the origins from ``mixture_from`` on and
    publishes their mixture
    (:class:`~pipeline.ensemble.nowcast_forecast.CompletionMixture`)."""
    members, key, reused = build_weekly_members(config, store_root, progress)
    if nowcast is not None:
        start = mixture_from or nowcast.completed.first_nowcast_day
        members = [CompletionMixture(m, nowcast.completed, start, mixed_completions)
                   for m in members]
    result = run_realtime_backtest(history, members, config.backtest_config(), progress)
    return WeeklyForecast(history, result, key, reused, nowcast)
