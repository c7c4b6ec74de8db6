"""Step 9 of the weekly forecast: the published forecast of weekly cases and I (the members'
ensemble, :mod:`pipeline.backtest.track_record`) at the latest Saturday, with the same method's
real-time backtest over every earlier Saturday; made in a forked child beside the epidemic
model's steps when every member's model is stored (:func:`start_weekly_forecast`).

The NF-seeded SMC member (:func:`smc_member`, on the run's forward joint flow) is scored beside
the members at every origin, not averaged into the published forecast.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import numpy as np

from pipeline.data.core.cache import data_dir
from pipeline.data.california.counties import county_slug
from pipeline.backtest.memo import ForecastMemo
from pipeline.backtest.track_record import TrackRecord, track_record
from pipeline.members.nf.flow import single_thread
from pipeline.members.smc import NFSeededSMCMember, PrecomputedMember, batched_smc_forecasts
from pipeline.panels.targets import HORIZONS_WEEKS, HUB_QUANTILE_LEVELS
from pipeline.forked import ChildBuild, start_in_child
from pipeline.errors import ModelMissingError
from pipeline.forecast.config import ForecastConfig
from pipeline.forecast.nowcasting import RecentDays, mixture_start
from pipeline.forecast.sources import reference_panel
from pipeline.forecast.results import TrainedModels
from pipeline.progress import ProgressReporter
from pipeline.training.model_store import stored_models_only

log = logging.getLogger(__name__)


def smc_member(models: TrainedModels, config: ForecastConfig) -> NFSeededSMCMember:
    """The NF-seeded SMC forecast member on the run's forward joint flow."""
    return NFSeededSMCMember(models.forward, config.resolved.window, config.resolved.prior,
                             n_particles=config.smc.member_particles,
                             filter_days=config.smc.days)


def weekly_forecast(recent: RecentDays, models: TrainedModels, config: ForecastConfig,
                    progress: ProgressReporter | None = None) -> TrackRecord:
    """The published forecast at the latest Saturday and the same method's real-time forecasts
    at every earlier Saturday (:mod:`pipeline.backtest.track_record`), with California's
    counties from the CDPH cache as the pooled members' reference places (the forecast's own
    place left out); the flows come from the model store. The days still being reported are
    nowcast and the forecast mixed over the nowcast's completions
    (:mod:`pipeline.forecast.nowcasting`). The NF-seeded SMC member is scored beside the members
    at every origin (one batch of filters) but not averaged into the published forecast
    (docs/forecasting.md)."""
    history, nowcast = recent.history, recent.nowcast
    record = config.track_record_config()
    place = config.data.place
    origins = record.origins(history)
    levels = np.asarray(HUB_QUANTILE_LEVELS)

    def smc_batch() -> PrecomputedMember:
        member = dataclasses.replace(smc_member(models, config), seed=config.step_seed("smc") + 1)
        with single_thread():
            return batched_smc_forecasts(member, history, place, origins, HORIZONS_WEEKS, levels)

    smc = start_in_child(smc_batch)     # filtered in a forked child while the members load

    def references() -> tuple[PrecomputedMember, ...]:
        scored = smc.result()
        return (scored,) if scored.forecasts else ()

    start = None if nowcast is None else mixture_start(nowcast, config.nowcast.mixture_weeks)
    memo = ForecastMemo.load(forecast_memo_path(place, config.data.folder))
    panel = reference_panel(place, history, config.data.folder)
    result = track_record(panel, place, record, config.store_root, progress,
                          references=references, nowcast=nowcast, mixture_from=start,
                          mixed_completions=config.nowcast.completions, memo=memo)
    try:
        memo.save()
    except OSError as error:    # a cache: the forecast stands, the next run re-forecasts
        log.warning("could not write the forecast memo %s: %s", memo.path, error)
    return result


# The weekly forecast under way in a forked child, with its seconds there.
WeeklyInChild = ChildBuild[tuple[TrackRecord, float]]


def start_weekly_forecast(recent: RecentDays, models: TrainedModels,
                          config: ForecastConfig) -> WeeklyInChild:
    """The weekly forecast started in a forked child (:mod:`pipeline.forked`), made while this
    process computes the epidemic model's estimates. Only when every member's model is stored:
    the child trains nothing (:func:`~pipeline.training.model_store.stored_models_only`; a
    missing model makes :func:`weekly_forecast_step` forecast here, training it). The members
    sample on one torch thread wherever they run, so the forecast is the same as here."""
    def build() -> tuple[TrackRecord, float]:
        started = time.perf_counter()
        with stored_models_only():
            weekly = weekly_forecast(recent, models, config)
        return weekly, time.perf_counter() - started

    return start_in_child(build)


def weekly_forecast_step(recent: RecentDays, models: TrainedModels, config: ForecastConfig,
                         progress: ProgressReporter | None = None,
                         ahead: WeeklyInChild | None = None) -> TrackRecord:
    """Step ``weekly-forecast``: the forecast ``ahead`` made in a child, else made here."""
    if ahead is not None:
        try:
            weekly, seconds = ahead.result()
            log.info("weekly forecast made in a child process beside the model's estimates "
                     "(%.1f s)", seconds)
            return weekly
        except ModelMissingError as missing:
            log.info("weekly forecast made here: %s", missing)
    return weekly_forecast(recent, models, config, progress)


def forecast_memo_path(place: str, folder: Path | None = None) -> Path:
    """The place's memo of member forecasts, under the data ``folder`` (None:
    $FLOWCAST_DATA_DIR or ./data)."""
    return data_dir(folder) / "forecast-memo" / f"{county_slug(place)}.npz"


def published_skill(weekly: TrackRecord) -> dict[str, dict[str, float | None]]:
    """Relative WIS vs the hub baseline (h1–h4, all) of the published forecast, per target."""
    summary = weekly.summary()["by_target"]
    return {target: dict(summary[target]["published"]["relative_wis_vs_baseline"])
            for target in summary}
