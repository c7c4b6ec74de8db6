"""The ``weekly_forecast`` Prefect flow: thin tasks over :mod:`pipeline.forecast.steps`.

Run once, locally (Prefect's ephemeral API; no server needed)::

    python -m flows.weekly_forecast                      # default preset, live data
    python -m flows.weekly_forecast --preset tiny --data-source import \
        --import-from ../shared/data/datasf

Tasks hand large objects (tensors, models) to each other in memory, so every task has
``cache_policy=NO_CACHE`` and does not persist results: the expensive step (training) is cached
by :mod:`pipeline.training.model_store` instead, keyed by what determines the model. Outputs are staged in
``<output_dir>/.staging-<date>-<run>/`` and promoted to ``<output_dir>/<reference-date>/`` only
after every step succeeded (:mod:`pipeline.outputs.run_folders`), so a failed run never replaces the last
good report.
"""
# No `from __future__ import annotations`: Prefect builds the parameter model from the live
# annotations (Literal[...]) when a served deployment loads this module; strings fail there.

import argparse
import dataclasses
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any, Literal

from prefect import flow, get_run_logger, task
from prefect.artifacts import (create_link_artifact, create_markdown_artifact,
                               create_table_artifact)
from prefect.cache_policies import NO_CACHE
from prefect.states import Completed
from prefect.tasks import exponential_backoff

from pipeline import forecast as fc
from pipeline.outputs.run_folders import RunOutputs, RunRecord, new_run_id

FORECAST_PRESETS_CHOICES = tuple(fc.FORECAST_PRESETS)
# Artifact keys are stable so the UI shows each one's history across weekly runs.
ARTIFACT_NLL = "sf-weekly-nll"
ARTIFACT_PARAMS = "sf-weekly-beta-gamma"
ARTIFACT_REPORT = "sf-weekly-report"
ARTIFACT_SUMMARY = "sf-weekly-summary"
# Base http(s) address where the reports folder is served; the report artifact links there.
REPORTS_URL_ENV = "FLOWCAST_REPORTS_URL"
# A run made from cached data because DataSF could not be reached finishes COMPLETED under this
# state name, carries this tag and emits this event (automations can match any of the three).
STALE_STATE_NAME = "Completed (stale data)"
STALE_TAG = "stale-data"
STALE_EVENT = "flowcast.forecast.stale-data"

_task = dict(cache_policy=NO_CACHE, persist_result=False)


class _LoggerProgress:
    """ProgressReporter that logs every ``every`` steps (flows have no terminal bar)."""

    def __init__(self, logger: Any, label: str, every: int) -> None:
        self.logger, self.label, self.every, self.done = logger, label, max(1, every), 0

    def advance(self, steps: int = 1, **fields: float | str) -> None:
        before, self.done = self.done, self.done + steps
        if before // self.every != self.done // self.every:
            status = " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                              for k, v in fields.items())
            self.logger.info("%s: %d steps %s", self.label, self.done, status)


@task(name="fetch-datasf", retries=2, retry_delay_seconds=exponential_backoff(backoff_factor=10),
      retry_jitter_factor=0.5, **_task)
def fetch_datasf(config: fc.ForecastConfig) -> Any:
    """DataSF series. HTTP errors are retried with backoff inside the client; if the series still
    cannot be had (no network and no cache) the task itself is retried (the flow sets the
    retries and exponential delays from ``DataSourceConfig.task_retries/task_retry_delay_s``)."""
    logger = get_run_logger()
    series = fc.load_series(config)
    stale = fc.data_is_stale(series, config.data.kind)
    logger.info("DataSF series: %s", series.vintage.describe())
    for note in fc.staleness_notes(series):
        (logger.warning if stale else logger.info)("%s", note)
    return series


@task(name="convert-to-sir", **_task)
def convert_to_sir(series: Any) -> Any:
    sir = fc.series_to_sir(series)
    frame = sir.frame
    get_run_logger().info("S/I/R series: %d days %s … %s; last S=%.4f I=%.5f R=%.4f", len(frame),
                          frame["date"].iloc[0].date(), frame["date"].iloc[-1].date(),
                          *frame[["S", "I", "R"]].iloc[-1])
    return sir


@task(name="simulate-training-data", **_task)
def simulate_training_data(config: fc.ForecastConfig) -> fc.TrainingData:
    data = fc.simulate_training_data(config)
    get_run_logger().info("synthetic %s ensemble: %d trajectories, data sha256 %s…",
                          config.prior.name, data.n_trajectories, data.data_sha256[:12])
    return data


@task(name="train-or-reuse-models", **_task)
def train_models(config: fc.ForecastConfig, data: fc.TrainingData, retrain: bool) -> Any:
    logger = get_run_logger()
    models = fc.train_or_reuse_models(config, data, retrain=retrain,
                                      progress=_LoggerProgress(logger, "training", 500))
    logger.info("%s forward/backward models %s… (%s encoder; best val NLL fw %.3f, bw %.3f)",
                "reused" if models.reused else "trained", models.key[:12], models.encoder,
                models.best_val_nll["forward"], models.best_val_nll["backward"])
    return models


@task(name="latest-estimates", **_task)
def latest_estimates(models: Any, sir: Any, config: fc.ForecastConfig) -> Any:
    latest = fc.latest_estimates(models, sir.frame, config)
    fw = latest.table[latest.table["direction"] == "forward"].set_index("component")
    get_run_logger().info("forward estimate for %s: I=%.5f (95%% %.5f–%.5f)",
                          latest.dates["forward"], fw.loc["I", "mean"], fw.loc["I", "q0.025"],
                          fw.loc["I", "q0.975"])
    return latest


@task(name="rollouts", **_task)
def rollouts(models: Any, sir: Any, config: fc.ForecastConfig) -> Any:
    out = fc.rollouts(models, sir.frame, config)
    get_run_logger().info("rollouts: %s", ", ".join(f"{d} {w}-day" for d, w in out))
    return out


@task(name="future-paths", **_task)
def future_paths(models: Any, sir: Any, config: fc.ForecastConfig) -> Any:
    return fc.future_paths(models, sir.frame, config)


@task(name="beta-gamma-estimates", **_task)
def parameter_track(models: Any, sir: Any, config: fc.ForecastConfig) -> Any:
    return fc.parameter_track(models, sir.frame, config)


@task(name="nll-table", **_task)
def nll_table(models: Any, sir: Any, config: fc.ForecastConfig, data: fc.TrainingData) -> Any:
    """NLL of this run's models plus any other encoder variant already in the model store (e.g.
    trained by ``flows.scale_out``), so the report's Table 5 fills up without retraining."""
    variants = fc.cached_variant_models(config, data)
    get_run_logger().info("NLL table: %s%s", config.encoder,
                          f" + cached variants {sorted(variants)}" if variants else "")
    return fc.nll_table_variants(models, variants, sir.frame, config)


@task(name="nf-seeded-smc", **_task)
def seeded_smc(models: Any, sir: Any, config: fc.ForecastConfig) -> Any:
    run = fc.seeded_smc(models, sir.frame, config)
    get_run_logger().info("NF-seeded SMC over %d days, min ESS %.0f of %d particles",
                          len(run.dates), float(run.result.ess.min()), config.smc_particles)
    return run


@task(name="weekly-forecast", **_task)
def published_forecast(series: Any, sir: Any, config: fc.ForecastConfig) -> Any:
    """The published forecast at the latest Saturday and its real-time backtest."""
    logger = get_run_logger()
    weekly = fc.weekly_forecast(series, sir, config,
                                progress=_LoggerProgress(logger, "weekly forecast", 500))
    summary = weekly.summary()
    for target in ("cases", "I"):
        skill = summary["by_target"][target]["published"]
        rel = skill["relative_wis_vs_baseline"]
        logger.info("published %s: relative WIS vs hub baseline %s (all %.3f); coverage 50%% "
                    "%.2f, 90%% %.2f over %d origins", target,
                    " ".join(f"{k} {v:.3f}" for k, v in rel.items() if k != "all" and v),
                    rel["all"] or float("nan"), skill["coverage50"], skill["coverage90"],
                    summary["n_origins"])
    logger.info("published forecast from %s; flow member %s… %s", weekly.origin.date(),
                (weekly.model_key or "-")[:12], "reused" if weekly.model_reused else "trained")
    return weekly


@task(name="render-report", **_task)
def render_outputs(results: fc.ForecastResults, staging: Path) -> list[str]:
    files = fc.write_tables(results, staging) + fc.write_report(results, staging)
    get_run_logger().info("wrote %d files to %s", len(files), staging)
    return files


def _publish_artifacts(results: fc.ForecastResults, final_dir: Path, files: list[str]) -> None:
    create_table_artifact(results.nll.round(4).to_dict(orient="records"), key=ARTIFACT_NLL,
                          description="Mean NLL of the observed S/I/R at random SF days "
                                      "(forward/backward × model variant; paper Table 5 layout)")
    params = results.parameters[results.parameters["component"].isin(["beta", "gamma", "Rt"])]
    columns = ["direction", "date", "component", *(f"q{level:g}" for level in fc.REPORT_LEVELS)]
    latest = params.groupby(["direction", "component"]).tail(8)[columns]
    create_table_artifact(latest.round(6).to_dict(orient="records"), key=ARTIFACT_PARAMS,
                          description="β, γ and R_t estimates (median, 50% and 90% intervals), "
                                      "latest days")
    report = next((f for f in files if f.endswith(".html")), files[0])
    _publish_report_link(final_dir, report)
    # The report's page-1 headline, with its one data banner (stale or old data, once; the
    # transport's long error text stays in the run log).
    from pipeline.report.headline import compute_headline, markdown
    from pipeline.report.weekly import data_banner

    banner = data_banner(results)
    if results.stale:
        banner = f"{banner} (Run tagged `{STALE_TAG}`, state `{STALE_STATE_NAME}`.)"
    create_markdown_artifact(markdown(compute_headline(results), banner,
                                      report_path=str(final_dir / report)),
                             key=ARTIFACT_SUMMARY,
                             description="Headline of the weekly SF forecast (report page 1)")


def _publish_report_link(final_dir: Path, report: str) -> None:
    """A link the Prefect UI can open when the reports folder is served over http(s)
    ($FLOWCAST_REPORTS_URL, its base address); browsers refuse file:// links from the UI, so
    without it the artifact names the file on the worker's machine and says how to serve it."""
    base = os.environ.get(REPORTS_URL_ENV, "").rstrip("/")
    if base.startswith(("http://", "https://")):
        create_link_artifact(f"{base}/{final_dir.name}/{report}",
                             link_text=f"report {final_dir.name}", key=ARTIFACT_REPORT,
                             description="Weekly SF forecast report")
        return
    create_markdown_artifact(
        f"Report {final_dir.name}: `{final_dir / report}` on the worker's machine. To link it "
        f"here, serve the reports folder (e.g. `python -m http.server -d {final_dir.parent} "
        f"8080`) and set `{REPORTS_URL_ENV}=http://<host>:8080` for the worker.",
        key=ARTIFACT_REPORT, description="Weekly SF forecast report")


@flow(name="weekly_forecast", log_prints=True)
def weekly_forecast(preset: Literal["default", "tiny"] = "default",
                    encoder: Literal["mlp", "transformer", "transformer-ke", "mamba"] | None = None,
                    data_source: Literal["live", "cache", "import"] = "live",
                    import_from: list[str] | None = None,
                    output_dir: str = "reports",
                    seed: int = 0,
                    retrain: bool = False,
                    datasf_base_url: str | None = None) -> dict[str, Any]:
    """Fetch DataSF → S/I/R → synthetic ensemble → (cached) joint estimators → estimates,
    rollouts, β/γ, NLL, NF-seeded SMC, backtest → report in ``<output_dir>/<reference-date>/``.

    A run that had to fall back to cached data finishes in the state "Completed (stale data)",
    is tagged ``stale-data`` and emits the event ``flowcast.forecast.stale-data``.

    Args:
        preset: Forecast size. "default" is the product (about 15 min from scratch, about a minute
            with a cached model); "tiny" is a seconds-long smoke run with toy-sized models.
        encoder: Context encoder of the flow models (mlp, transformer, transformer-ke, mamba).
            Empty: the preset's own (transformer for "default").
        data_source: Where the SF series comes from. "live" fetches DataSF and falls back to the
            local cache (the run is then marked stale); "cache" reads only the cache (offline);
            "import" imports the DataSF CSV exports given in import_from first.
        import_from: DataSF CSV exports (files or folders) on the worker's machine, for
            data_source "import".
        output_dir: Folder on the worker's machine for the reports; each run writes
            <output_dir>/<reference-date>/ and updates <output_dir>/index.html.
        seed: Seed of every random step; the same seed, data and model give the same numbers.
        retrain: Train new models even when the model cache holds a matching pair.
        datasf_base_url: A DataSF mirror or proxy (https://host). Empty: $FLOWCAST_DATASF_BASE_URL
            or https://data.sfgov.org. The app token comes from $FLOWCAST_DATASF_APP_TOKEN only
            (flow parameters are stored in plain text).
    """
    logger = get_run_logger()
    started = time.monotonic()
    base = fc.resolve_config(preset)
    config = fc.resolve_config(preset, encoder=encoder, seed=seed, data=dataclasses.replace(
        base.data, kind=data_source, import_paths=tuple(import_from or ()),
        base_url=datasf_base_url or None))
    logger.info("weekly forecast: preset=%s encoder=%s data=%s seed=%d retrain=%s", preset,
                config.encoder or "(preset)", data_source, seed, retrain)
    retries = config.data.task_retries if data_source == "live" else 0  # cache: nothing to wait for
    # The client's own deadlines bound each dataset; this time limit is the backstop (Prefect
    # interrupts a sync task run in the flow's main thread with SIGALRM).
    fetch = fetch_datasf.with_options(
        timeout_seconds=config.data.task_timeout_s,
        retries=retries, retry_delay_seconds=[config.data.task_retry_delay_s * 2 ** k
                                              for k in range(retries)] or 0)
    series = fetch(config)
    sir = convert_to_sir(series)
    data = simulate_training_data(config)
    models = train_models(config, data, retrain)
    latest = latest_estimates(models, sir, config)
    rolled = rollouts(models, sir, config)
    future = future_paths(models, sir, config)
    params = parameter_track(models, sir, config)
    nll = nll_table(models, sir, config, data)
    smc = seeded_smc(models, sir, config)
    weekly = published_forecast(series, sir, config)
    results = fc.ForecastResults(
        config=config, sir_frame=sir.frame, vintage=series.vintage.describe(),
        stale=fc.data_is_stale(series, data_source),
        stale_notes=tuple(fc.staleness_notes(series)) if fc.data_is_stale(series, data_source)
        else (), models=models, latest=latest, rollouts=rolled, future=future,
        parameters=params, nll=nll, smc=smc, weekly=weekly)

    outputs = RunOutputs(output_dir)
    reference_date = str(future.reference_date)
    run_id = new_run_id()
    with outputs.staged(reference_date, run_id) as staging:
        files = render_outputs(results, staging)
        record = RunRecord(
            reference_date=reference_date, run_id=run_id,
            finished_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            data_stale=results.stale, data_vintage=series.vintage.data_as_of or "unknown",
            model_key=models.key, seed=seed, preset=preset, files=tuple(files),
            summary={"model_reused": models.reused,
                     "nll": results.nll.to_dict(orient="records"),
                     "backtest": fc.published_skill(weekly),
                     # reports/index.html shows it (pipeline.outputs.run_folders.render_index_html)
                     "headline": fc.headline_record(results)})
        final_dir = outputs.promote(staging, record)
    _publish_artifacts(results, final_dir, files)
    elapsed = time.monotonic() - started
    logger.info("weekly forecast %s done in %.1f s → %s", reference_date, elapsed, final_dir)
    outcome = {"reference_date": reference_date, "output_dir": str(final_dir), "files": files,
               "data_stale": results.stale, "model_key": models.key,
               "model_reused": models.reused, "seconds": elapsed}
    if not results.stale:
        return outcome
    logger.warning("forecast made from STALE cached data: %s", "; ".join(results.stale_notes))
    _mark_stale(reference_date, results.stale_notes)
    return Completed(name=STALE_STATE_NAME, data=outcome,
                     message=f"forecast {reference_date} made from cached data (DataSF "
                             "unreachable)")


def _mark_stale(reference_date: str, notes: tuple[str, ...]) -> None:
    """Tag the running flow run ``stale-data`` and emit ``flowcast.forecast.stale-data``."""
    from prefect.client.orchestration import get_client
    from prefect.context import get_run_context
    from prefect.events import emit_event

    run = get_run_context().flow_run  # type: ignore[union-attr]
    if run is None:
        return
    with get_client(sync_client=True) as client:
        tags = client.read_flow_run(run.id).tags
        if STALE_TAG not in tags:
            client.update_flow_run(run.id, tags=[*tags, STALE_TAG])
    emit_event(event=STALE_EVENT, resource={"prefect.resource.id": f"prefect.flow-run.{run.id}",
                                            "prefect.resource.name": run.name},
               payload={"reference_date": reference_date, "notes": list(notes)})


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m flows.weekly_forecast",
                                     description="Run the weekly SF forecast once, locally.")
    parser.add_argument("--preset", default="default", choices=FORECAST_PRESETS_CHOICES)
    parser.add_argument("--encoder", default=None,
                        choices=["mlp", "transformer", "transformer-ke", "mamba"])
    parser.add_argument("--data-source", default="live", choices=["live", "cache", "import"])
    parser.add_argument("--import-from", nargs="*", default=None,
                        help="DataSF CSV exports (files or folders) for --data-source import")
    parser.add_argument("--output-dir", default="reports")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--retrain", action="store_true", help="ignore the cached model")
    parser.add_argument("--datasf-base-url", default=None,
                        help="DataSF mirror or proxy (default: $FLOWCAST_DATASF_BASE_URL or "
                             "https://data.sfgov.org)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    from flows.server_guard import guard_ephemeral_server
    guard_ephemeral_server()  # a killed run no longer orphans Prefect's temporary server
    result = weekly_forecast(preset=args.preset, encoder=args.encoder,
                             data_source=args.data_source, import_from=args.import_from,
                             output_dir=args.output_dir, seed=args.seed, retrain=args.retrain,
                             datasf_base_url=args.datasf_base_url)
    print(f"report: {result['output_dir']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
