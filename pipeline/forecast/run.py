"""``run_forecast(config) -> ForecastResults``: the weekly forecast's one composition of its steps.

The Prefect flow (``flows/weekly_forecast.py``) and the tests run this function; the flow only
passes a :class:`StepRunner` that turns each step into a Prefect task, so it cannot drift from
what the tests check. A step's name is its task's name, and every step's seconds are recorded
(``ForecastResults.timings``, ``results.json``'s ``seconds``: what ``bench/e2e.py`` reports).
``bench/backtest.py`` calls the steps it needs (the data source and the ensemble) directly.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Literal, ParamSpec, TypeVar

import pandas as pd
import requests

from pipeline.forecast.config import ForecastConfig
from pipeline.forecast.county_skill import county_skill
from pipeline.forecast.nowcasting import nowcast_recent_days
from pipeline.forecast.joint_models import (cached_variant_models, models_stored,
                                            simulate_training_data, train_or_reuse_models)
from pipeline.forecast.member_training import member_training, wait_for_members
from pipeline.forecast.results import ForecastResults, SIRArrays, TrainedModels, TrainingData
from pipeline.forecast.sources import (data_is_stale, load_series, series_to_sir, sir_arrays,
                                       staleness_notes)
from pipeline.forecast.published_forecast import (published_skill, start_weekly_forecast,
                                                  weekly_forecast_step)
from pipeline.forecast.steps import (future_paths, latest_estimates, nll_table_variants,
                                     rollouts, seeded_smc, start_parameter_track)
from pipeline.progress import ProgressReporter, SilentProgress

Step = Literal["fetch-datasf", "fetch-cdph", "convert-to-sir", "nowcast-recent-days", "simulate-training-data",
               "train-or-reuse-models", "latest-estimates", "rollouts", "future-paths",
               "beta-gamma-estimates", "nll-table", "nf-seeded-smc", "weekly-forecast",
               "county-skill", "train-forecast-members"]
# The fetch step is named after the publisher (the Prefect flow retries either).
FETCH_STEPS: tuple[Step, ...] = ("fetch-datasf", "fetch-cdph")
P = ParamSpec("P")
R = TypeVar("R")
# A step's progress reporter, by step (training and the weekly forecast report progress).
ProgressFactory = Callable[[Step], ProgressReporter]

log = logging.getLogger(__name__)


class StepRunner:
    """Runs one step and records its wall time; subclasses change how a step is invoked."""

    def __init__(self, logger: logging.Logger | logging.LoggerAdapter[logging.Logger] = log
                 ) -> None:
        self.logger = logger
        self.timings: dict[str, float] = {}

    def __call__(self, step: Step, fn: Callable[P, R], *args: P.args, **kwargs: P.kwargs) -> R:
        started = time.monotonic()
        result = self.invoke(step, fn, *args, **kwargs)
        self.timings[step] = time.monotonic() - started
        self.logger.info("%s (%.1f s)", step, self.timings[step])
        return result

    def invoke(self, step: Step, fn: Callable[P, R], *args: P.args, **kwargs: P.kwargs) -> R:
        return fn(*args, **kwargs)


def _silent(step: Step) -> ProgressReporter:
    return SilentProgress()


def run_forecast(config: ForecastConfig, progress: ProgressFactory = _silent, *,
                 retrain: bool = False, runner: StepRunner | None = None,
                 session: requests.Session | None = None) -> ForecastResults:
    """Fetch DataSF (or a county's CDPH series) → S/I/R → nowcast of the days still being
    reported → synthetic ensemble → (cached) joint estimators → estimates, rollouts, β/γ, NLL,
    NF-seeded SMC, and the published forecast (mixed over the nowcast's completions) with its
    backtest."""
    run = runner or StepRunner()
    source = config.data
    fetch: Step = "fetch-datasf" if source.county is None else "fetch-cdph"
    series = run(fetch, load_series, source, session=session)
    stale = data_is_stale(series, source.kind)
    notes = staleness_notes(series)
    run.logger.info("%s series: %s", source.provider if source.county is None
                    else f"{source.provider} {source.county}", series.vintage.describe())
    for note in notes:
        (run.logger.warning if stale else run.logger.info)("%s", note)
    sir = run("convert-to-sir", series_to_sir, series)
    recent = run("nowcast-recent-days", nowcast_recent_days, series, sir, config.nowcast,
                 config.step_seed("nowcast"), source.county, source.folder)
    run.logger.info("%s", recent.nowcast.delay_model if recent.nowcast else
                    f"no nowcast: last {config.nowcast.fallback_trailing_days} days dropped")
    arrays = sir_arrays(recent.sir_frame)
    data = run("simulate-training-data", simulate_training_data, config)
    # From scratch, the forecast's members train in a background process beside the joint pair,
    # sharing the work through the model store (pipeline.forecast.member_training).
    needed = config.training.background_members and (retrain or not models_stored(config, data))
    with member_training(config, recent.history, config.store_root, needed,
                         run.logger) as background:
        models = run("train-or-reuse-models", train_or_reuse_models, config, data,
                     retrain=retrain, progress=progress("train-or-reuse-models"))
        _log_models(run, models)
        # Every model stored: the weekly forecast is made in a forked child meanwhile; the β
        # track is drawn in another while this process draws the rollouts.
        ahead = (start_weekly_forecast(recent, models, config)
                 if models.reused and not background.running else None)
        track = start_parameter_track(models, arrays, config)
        latest = run("latest-estimates", latest_estimates, models, arrays, config)
        rolled = run("rollouts", rollouts, models, arrays, config)
        future = run("future-paths", future_paths, models, arrays, config)
        parameters = run("beta-gamma-estimates", track.result)
        nll = run("nll-table", nll_with_cached_variants, models, data, arrays, config)
        smc = run("nf-seeded-smc", seeded_smc, models, recent.history, arrays, config)
        run.logger.info("NF-seeded SMC over %d days, min ESS %.0f of %d particles",
                        len(smc.dates), float(smc.result.ess.min()), config.smc.particles)
        weekly = run("weekly-forecast", weekly_forecast_step, recent, models, config,
                     progress("weekly-forecast"), ahead)
        run.logger.info("published forecast from %s; relative WIS vs hub baseline %s",
                        weekly.origin.date(), published_skill(weekly))
        if weekly.memo_reads is not None:
            run.logger.info("forecast memo: %d of %d member forecasts of the track record "
                            "read back, the rest forecast", *weekly.memo_reads)
        counties = run("county-skill", county_skill, config, progress=progress("county-skill"))
        if background.running:
            run("train-forecast-members", wait_for_members, background)
    return ForecastResults(
        config=config, sir_frame=recent.sir_frame, vintage=series.vintage.describe(), stale=stale,
        stale_notes=tuple(notes) if stale else (), models=models, latest=latest,
        rollouts=rolled, future=future, parameters=parameters, nll=nll, smc=smc, weekly=weekly,
        data_as_of=series.vintage.data_as_of, timings=dict(run.timings), county_skill=counties)


def nll_with_cached_variants(models: TrainedModels, data: TrainingData, sir: SIRArrays,
                             config: ForecastConfig) -> pd.DataFrame:
    """NLL of this run's models plus any other encoder variant already in the model store (e.g.
    trained by ``flows.scale_out``), so the report's Table 5 fills up without retraining."""
    return nll_table_variants(models, cached_variant_models(config, data), sir, config)


def _log_models(run: StepRunner, models: TrainedModels) -> None:
    run.logger.info("%s forward/backward models %s… (%s encoder; best val NLL fw %.3f, bw %.3f)",
                    "reused" if models.reused else "trained", models.key[:12], models.encoder,
                    models.best_val_nll["forward"], models.best_val_nll["backward"])
