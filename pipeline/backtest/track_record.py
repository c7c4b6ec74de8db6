"""A place's published forecast and its track record, made in one real-time backtest.

Every Saturday origin of the place's series is forecast in real time (each sees only its past,
the combiner only past scores): the last origin is this week's published forecast, the earlier
ones are its track record. Forecasting all of them costs seconds (the memo reads back what the
last run made), so the report always carries the skill of exactly the method it publishes,
measured on exactly the data it shows.

Origins are Saturdays so that forecast weeks are epiweeks (Sunday–Saturday), the weeks the
Forecast Hub and hubverse count in; data after the last Saturday wait for the next run.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.backtest.config import BacktestConfig, Variant

from pipeline.backtest.backtest import OneVintage, run_backtest
from pipeline.backtest.memo import ForecastMemo
from pipeline.backtest.result import BacktestResult, QuantileForecast
from pipeline.combine.combiner import PUBLISHED, CombineConfig
from pipeline.errors import ConfigError
from pipeline.members.autoets import AutoETSMember
from pipeline.members.base import Member
from pipeline.members.isolation import Dropped
from pipeline.members.published import MembersConfig, build_members
from pipeline.nowcast.mixture import CompletionMixture, RunNowcast
from pipeline.panels.history import History
from pipeline.panels.panel import Panel, weekly_origins
from pipeline.panels.targets import HORIZONS_WEEKS
from pipeline.progress import ProgressReporter, start_phase


@dataclass(frozen=True)
class TrackRecordConfig:
    """The published forecast's members and combiner, and the track record's origins: every
    Saturday with ``min_history_weeks`` of data (only the latest ``recent_origins`` of them when
    given), from ``first`` to ``last`` when given (``scored_only``: those with four weeks of
    truth); ``n_paths`` published sample paths per origin."""

    members: MembersConfig = field(default_factory=MembersConfig)
    combine: CombineConfig = field(default_factory=CombineConfig)
    min_history_weeks: int = 8
    n_paths: int = 200
    seed: int = 0
    variants: tuple[Variant, ...] = ()      # other combiners scored beside it (benchmarks)
    # a smoke run's short track record (the tiny preset): the forecasts of the latest origins
    # only; None: every origin since ``min_history_weeks``
    recent_origins: int | None = None

    def __post_init__(self) -> None:
        if self.recent_origins is not None and self.recent_origins < 1:
            raise ConfigError(f"TrackRecordConfig.recent_origins={self.recent_origins} must be "
                              ">= 1 (or None: every origin)")

    def origins(self, history: History, *, scored_only: bool = False,
                first: dt.date | None = None, last: dt.date | None = None
                ) -> list[pd.Timestamp]:
        start = None if first is None else pd.Timestamp(first)
        if self.recent_origins is not None:
            # the same first origin whether scored only or not: the reported origins are
            # always among the forecast ones
            every = weekly_origins(history.dates, min_history_weeks=self.min_history_weeks,
                                   scored_only=False)
            recent = every[-min(self.recent_origins, len(every))]
            start = recent if start is None else max(start, recent)
        return weekly_origins(history.dates, min_history_weeks=self.min_history_weeks,
                              horizon_weeks=max(HORIZONS_WEEKS), scored_only=scored_only,
                              first=start, last=None if last is None else pd.Timestamp(last))

    def backtest_config(self) -> BacktestConfig:
        return BacktestConfig(seed=self.seed, combine=self.combine, variants=self.variants,
                              n_paths=self.n_paths)


@dataclass(frozen=True, eq=False)
class TrackRecord:
    """``result``: every Saturday origin of ``place``, the latest one unscored; ``latest``: the
    published forecast at the latest origin (quantiles of I and weekly cases, weekly S/I/R
    sample paths)."""

    place: str
    result: BacktestResult
    model_key: str | None
    model_reused: bool
    nowcast: RunNowcast | None = None       # the days still being reported, when nowcast
    memo_reads: tuple[int, int] | None = None   # forecasts read back from the memo, of all asked
    built_without: tuple[Dropped, ...] = ()     # members not built, refits replaced (and why)

    @property
    def history(self) -> History:
        return self.result.panel.histories[self.place]

    @property
    def origin(self) -> pd.Timestamp:
        return self.result.origins[-1]

    @property
    def origins(self) -> tuple[pd.Timestamp, ...]:
        return self.result.origins

    @property
    def latest(self) -> QuantileForecast:
        return self.result.forecast_at(self.place, self.origin, PUBLISHED)

    def forecast_at(self, origin: pd.Timestamp, forecaster: str = PUBLISHED
                    ) -> QuantileForecast:
        return self.result.forecast_at(self.place, origin, forecaster)

    def member_forecasts(self) -> dict[str, QuantileForecast]:
        """Every forecaster's forecast at the latest origin (members, references, published)."""
        return self.result.forecasters_at(self.place, self.origin)

    def dropped(self) -> tuple[Dropped, ...]:
        """What the published forecast at the latest origin went without, and why (the same
        rule as a hub round's, :mod:`pipeline.members.isolation`): a member that could not be
        built, a refit replaced by an earlier one, a member the guard left out there."""
        target = self.result.panel.count_target
        return self.built_without + tuple(
            Dropped("member", target, name, why)
            for name, why in self.result.dropped_members(-1).items()
            if name in self.result.members)

    def summary(self) -> dict[str, Any]:
        """The backtest's summary (computed once: the report reads it a dozen times)."""
        return self.result.summary()

    @property
    def scores(self) -> pd.DataFrame:
        return self.result.scores()


def track_record(panel: Panel, place: str, config: TrackRecordConfig, store_root: Path,
                 progress: ProgressReporter | None = None, *,
                 references: Sequence[Member] | Callable[[], Sequence[Member]] = (),
                 nowcast: RunNowcast | None = None,
                 mixture_from: pd.Timestamp | None = None, mixed_completions: int = 32,
                 memo: ForecastMemo | None = None, first: dt.date | None = None,
                 last: dt.date | None = None, scored_only: bool = False) -> TrackRecord:
    """Build the members (training or reusing their models), then forecast every Saturday
    origin of ``place`` (the others of ``panel`` are pooled) in real time; ``references`` are
    scored beside the members, not averaged (AutoETS always).

    With a ``nowcast`` (the place's history is then its per-day median), every member forecasts
    each of the first ``mixed_completions`` completions at the origins from ``mixture_from`` on
    and publishes their mixture (:class:`~pipeline.nowcast.mixture.CompletionMixture`). With a
    ``memo``, the forecasts an earlier run already made (same member, same data up to the
    origin) are read back (:mod:`pipeline.backtest.memo`). ``first``/``last``/``scored_only``
    choose the origins reported; the earlier ones still teach the combiner. ``references`` may
    be a function giving them, called once the members are built (the run filters the SMC
    member in a child meanwhile)."""
    panel = panel.only([place])
    history = panel.histories[place]
    every = config.origins(history)
    if progress is not None:
        start_phase(progress, "members' models", None)
    chosen = build_members(config.members, store_root, panel, every, progress)
    members: list[Member] = list(chosen.members)
    scored: list[Member] = [AutoETSMember(),
                            *(references() if callable(references) else references)]
    if memo is not None:
        members = [memo.wrap(m, config.n_paths) for m in members]
        scored = [memo.wrap(scored[0], config.n_paths), *scored[1:]]
    if nowcast is not None:
        start = mixture_from or nowcast.completed.first_nowcast_day
        members = [CompletionMixture(m, nowcast.completed, start, mixed_completions)
                   for m in members]
    reported = config.origins(history, scored_only=scored_only, first=first, last=last)
    result = run_backtest(OneVintage(panel), members, every, config.backtest_config(),
                          references=scored, reported=reported, progress=progress)
    reads = None if memo is None else (memo.hits, memo.hits + memo.misses)
    return TrackRecord(place, result, chosen.model_key, chosen.reused, nowcast, reads,
                       chosen.dropped)
