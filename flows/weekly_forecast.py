"""The ``weekly_forecast`` Prefect flow: thin tasks over :mod:`pipeline.forecast.steps`.

Run once, locally (Prefect's ephemeral API; no server needed)::

    python -m flows.weekly_forecast                      # default preset, live data
    python -m flows.weekly_forecast --preset tiny --data-source import \
        --import-from ../shared/data/datasf
    python -m flows.weekly_forecast --county "Los Angeles" --data-source cache   # CDPH data

The flow adds orchestration only: each step of ``run_forecast`` runs as a task of the same name
(:class:`PrefectSteps`), with retries and a time limit on the DataSF (or CDPH) fetch; then the outputs are
published, artifacts posted, and a stale-data run marked. Tasks hand large objects (tensors,
models) to each other in memory, so every task has ``cache_policy=NO_CACHE`` and does not persist
results: the expensive step (training) is cached by :mod:`pipeline.training.model_store` instead.
Outputs are staged and promoted only after every step succeeded
(:func:`pipeline.forecast.publish.publish`), so a failed run never replaces the last good report.
"""
# No `from __future__ import annotations`: Prefect builds the parameter model from the live
# annotations (Literal[...]) when a served deployment loads this module; strings fail there.

if __name__ == "__main__":
    # Run as a script: Prefect's temporary API server comes up while the imports below load
    # (flows/server_guard.py).
    from flows.server_guard import start_temporary_server

    start_temporary_server()

import argparse
import contextlib
import dataclasses
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Literal, ParamSpec, TypeVar

import pandas as pd
from prefect import flow, get_run_logger, task
from prefect.artifacts import (create_link_artifact, create_markdown_artifact,
                               create_table_artifact)
from prefect.cache_policies import NO_CACHE
from prefect.logging.loggers import LoggingAdapter
from prefect.client.schemas.objects import State
from prefect.states import Completed

from pipeline import forecast as fc
from pipeline.data.california.counties import california_county, county_slug
from pipeline.data.core.cache import data_dir
from pipeline.errors import ConfigError
from pipeline.forecast.config import DataSourceKind
from pipeline.forecast.nowcasting import archive_from_environment
from pipeline.forecast.publish import PublishedRun, publish
from pipeline.forecast.run import FETCH_STEPS, Step, StepRunner
from pipeline.forecast.steps import REPORT_LEVELS
from pipeline.progress import LogProgress
from pipeline.report.render import preload_pdf_renderer
from pipeline.forecast.report.headline import compute_headline, markdown
from pipeline.forecast.report.weekly import data_banner

FORECAST_PRESETS_CHOICES = tuple(fc.FORECAST_PRESETS)
P = ParamSpec("P")
R = TypeVar("R")
# Artifact keys are stable so the UI shows each one's history across weekly runs (a county's
# runs: the same keys with the county's slug for "sf", :func:`artifact_key`).
ARTIFACT_NLL = "sf-weekly-nll"
ARTIFACT_PARAMS = "sf-weekly-beta-gamma"
ARTIFACT_REPORT = "sf-weekly-report"
ARTIFACT_SUMMARY = "sf-weekly-summary"
# Base http(s) address where the reports folder is served; the report artifact links there.
REPORTS_URL_ENV = "FLOWCAST_REPORTS_URL"
# A run made from cached data because DataSF could not be reached finishes COMPLETED under this
# state name, carries this tag and emits this event (automations can match any of the three).
STALE_STATE_NAME = "Completed (stale data)"
# A run whose published forecast went without a member (it failed: pipeline.members.isolation).
DEGRADED_STATE_NAME = "Completed (degraded)"
STALE_TAG = "stale-data"
STALE_EVENT = "flowcast.forecast.stale-data"


def artifact_key(key: str, county: str | None) -> str:
    """``key`` for San Francisco's runs; for a county's, its slug in place of ``sf``."""
    return key if county is None else f"{county_slug(county)}{key[len('sf'):]}"


class PrefectSteps(StepRunner):
    """Runs each step of ``run_forecast`` as a Prefect task named after it. The fetch (DataSF's,
    or CDPH's for a county) gets
    retries with exponential delays (live data only) and a time limit: the client's own
    deadlines bound each dataset, this limit is the backstop (Prefect interrupts a sync task
    in the flow's main thread with SIGALRM)."""

    def __init__(self, logger: logging.Logger | LoggingAdapter, config: fc.ForecastConfig) -> None:
        super().__init__(logger)
        source = config.data
        retries = source.task_retries if source.kind == "live" else 0  # cache: nothing to wait for
        self.fetch_retry_delays = [source.task_retry_delay_s * 2 ** k for k in range(retries)]
        self.fetch_timeout_s = source.task_timeout_s

    def invoke(self, step: Step, fn: Callable[P, R], *args: P.args, **kwargs: P.kwargs) -> R:
        if step in FETCH_STEPS:
            fetch = task(name=step, cache_policy=NO_CACHE, persist_result=False,
                         retries=len(self.fetch_retry_delays),
                         retry_delay_seconds=self.fetch_retry_delays or 0,
                         retry_jitter_factor=0.5, timeout_seconds=self.fetch_timeout_s)(fn)
            return fetch(*args, **kwargs)
        return task(name=step, cache_policy=NO_CACHE, persist_result=False)(fn)(*args, **kwargs)


def _publish_artifacts(results: fc.ForecastResults, published: PublishedRun) -> None:
    county, place = results.config.data.county, results.config.data.place
    create_table_artifact(_records(results.nll.round(4)), key=artifact_key(ARTIFACT_NLL, county),
                          description=f"Mean NLL of the observed S/I/R at random "
                                      f"{'SF' if county is None else place} days "
                                      "(forward/backward × model variant; paper Table 5 layout)")
    params = results.parameters[results.parameters["component"].isin(["beta", "gamma", "Rt"])]
    columns = ["direction", "date", "component", *(f"q{level:g}" for level in REPORT_LEVELS)]
    latest = params.groupby(["direction", "component"]).tail(8)[columns]
    create_table_artifact(_records(latest.round(6)), key=artifact_key(ARTIFACT_PARAMS, county),
                          description="β, γ and R_t estimates (median, 50% and 90% intervals), "
                                      "latest days")
    _publish_report_link(published, results.config)
    # The report's page-1 headline, with its one data banner (stale or old data, once; the
    # transport's long error text stays in the run log).
    banner = data_banner(results)
    if results.stale:
        banner = f"{banner} (Run tagged `{STALE_TAG}`, state `{STALE_STATE_NAME}`.)"
    create_markdown_artifact(markdown(compute_headline(results), banner,
                                      report_path=str(published.folder / published.report)),
                             key=artifact_key(ARTIFACT_SUMMARY, county),
                             description=f"Headline of the weekly {_short(place)} forecast "
                                         "(report page 1)")


def _records(frame: pd.DataFrame) -> list[dict[str, object]]:
    return [{str(k): v for k, v in row.items()} for row in frame.to_dict(orient="records")]


def _short(place: str) -> str:
    return "SF" if place == "San Francisco" else place


def _publish_report_link(published: PublishedRun, config: fc.ForecastConfig) -> None:
    """A link the Prefect UI can open when the reports folder is served over http(s)
    ($FLOWCAST_REPORTS_URL, its base address); browsers refuse file:// links from the UI, so
    without it the artifact names the file on the worker's machine and says how to serve it."""
    final_dir, report = published.folder, published.report
    served = Path(config.outputs.output_dir)   # a county's runs lie in its subfolder
    relative = final_dir.relative_to(served).as_posix()
    key = artifact_key(ARTIFACT_REPORT, config.data.county)
    description = f"Weekly {_short(config.data.place)} forecast report"
    base = os.environ.get(REPORTS_URL_ENV, "").rstrip("/")
    if base.startswith(("http://", "https://")):
        create_link_artifact(f"{base}/{relative}/{report}",
                             link_text=f"report {relative}", key=key, description=description)
        return
    create_markdown_artifact(
        f"Report {relative}: `{final_dir / report}` on the worker's machine. To link it "
        f"here, serve the reports folder (e.g. `python -m http.server -d {served} "
        f"8080`) and set `{REPORTS_URL_ENV}=http://<host>:8080` for the worker.",
        key=key, description=description)


@flow(name="weekly_forecast", log_prints=True)
def weekly_forecast(preset: Literal["default", "tiny"] = "default",
                    encoder: Literal["mlp", "transformer", "transformer-ke", "mamba"] | None = None,
                    data_source: Literal["live", "cache", "import"] = "live",
                    import_from: list[str] | None = None,
                    output_dir: str = "reports",
                    seed: int = 0,
                    retrain: bool = False,
                    datasf_base_url: str | None = None,
                    county: str | None = None) -> dict[str, object] | State:
    """:func:`pipeline.forecast.run_forecast` step by step as tasks (fetch DataSF, or a
    county's CDPH series → S/I/R → synthetic ensemble → (cached) joint estimators → estimates,
    rollouts, β/γ, NLL, NF-seeded SMC, the published forecast and its backtest) → report in
    ``<output_dir>/<reference-date>/`` (a county's: ``<output_dir>/<county-slug>/<reference-date>/``).

    A run that had to fall back to cached data finishes in the state "Completed (stale data)",
    is tagged ``stale-data`` and emits the event ``flowcast.forecast.stale-data``. A run whose
    published forecast went without a member that failed (an exception, non-finite or crossing
    quantiles, its time limit: :mod:`pipeline.members.isolation`) finishes "Completed
    (degraded)", its message naming the member and why (the same rule as a hub round).

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
        county: A California county (e.g. "Los Angeles") to forecast from CDPH's county data
            (the CHHS portal, $FLOWCAST_CHHS_BASE_URL, with the cache as fallback; "import"
            takes CDPH covid19cases_test.csv files) on the county's own population. Empty: San
            Francisco from DataSF.
    """
    logger = get_run_logger()
    started = time.monotonic()
    _preload_done()
    config = flow_config(preset, encoder=encoder, data_source=data_source,
                         import_from=import_from, output_dir=output_dir, seed=seed,
                         datasf_base_url=datasf_base_url, county=county)
    logger.info("weekly forecast%s: preset=%s encoder=%s data=%s seed=%d retrain=%s",
                "" if config.data.county is None else f" for {config.data.county}", preset,
                config.training.encoder, data_source, seed, retrain)
    results = fc.run_forecast(config, lambda step: LogProgress(logger, step, 500),
                              retrain=retrain, runner=PrefectSteps(logger, config))
    published = task(name="render-report", cache_policy=NO_CACHE, persist_result=False)(
        publish)(results)
    logger.info("wrote %d files to %s", len(published.files), published.folder)
    _publish_artifacts(results, published)
    elapsed = time.monotonic() - started
    logger.info("weekly forecast %s done in %.1f s → %s", results.reference_date, elapsed,
                published.folder)
    dropped = results.weekly.dropped()       # members the guard left out (a hub round's rule)
    outcome: dict[str, object] = {
        "reference_date": results.reference_date, "place": config.data.place,
        "output_dir": str(published.folder),
        "files": list(published.files), "data_stale": results.stale,
        "model_key": results.models.key, "model_reused": results.models.reused,
        "seconds": elapsed, "step_seconds": dict(results.timings),
        "degraded": bool(dropped), "dropped": [dataclasses.asdict(d) for d in dropped]}
    left_out = "; ".join(d.line() for d in dropped)
    if dropped:
        logger.warning("forecast %s degraded: %s", results.reference_date, left_out)
    if not results.stale:
        return (Completed(name=DEGRADED_STATE_NAME, data=outcome,
                          message=f"forecast {results.reference_date} degraded: {left_out}")
                if dropped else outcome)
    logger.warning("forecast made from STALE cached data: %s", "; ".join(results.stale_notes))
    _mark_stale(results.reference_date, results.stale_notes, config.data.place)
    return Completed(name=STALE_STATE_NAME, data=outcome,
                     message=f"forecast {results.reference_date} made from cached data "
                             f"({config.data.provider} unreachable)"
                             + (f"; degraded: {left_out}" if dropped else ""))


def flow_config(preset: str, *, encoder: str | None, data_source: DataSourceKind,
                import_from: list[str] | None, output_dir: str, seed: int,
                datasf_base_url: str | None, county: str | None = None) -> fc.ForecastConfig:
    """The flow's parameters as a :class:`~pipeline.forecast.ForecastConfig` (``county`` as
    CDPH spells it, whatever its case; an unknown name fails here, before any work); the data
    folder and the CDPH archive read from the environment here, once ($FLOWCAST_DATA_DIR or
    ./data; $FLOWCAST_CDPH_ARCHIVE where the preset names no archive)."""
    base = fc.resolve_config(preset)
    data = dataclasses.replace(base.data, kind=data_source, import_paths=tuple(import_from or ()),
                               base_url=datasf_base_url or None,
                               county=california_county(county) if county else None,
                               data_dir=str(data_dir()))
    config = fc.resolve_config(preset, encoder=encoder, seed=seed, data=data,
                               output_dir=output_dir)
    if config.nowcast.archive:
        return config
    return dataclasses.replace(config, nowcast=dataclasses.replace(
        config.nowcast, archive=archive_from_environment()))


def _mark_stale(reference_date: str, notes: tuple[str, ...], place: str) -> None:
    """Tag the running flow run ``stale-data`` and emit ``flowcast.forecast.stale-data`` (its
    payload names the place forecast: San Francisco or the county)."""
    from prefect.client.orchestration import get_client
    from prefect.context import FlowRunContext
    from prefect.events import emit_event

    context = FlowRunContext.get()
    run = context.flow_run if context is not None else None
    if run is None:
        return
    with get_client(sync_client=True) as client:
        tags = client.read_flow_run(run.id).tags
        if STALE_TAG not in tags:
            client.update_flow_run(run.id, tags=[*tags, STALE_TAG])
    emit_event(event=STALE_EVENT, resource={"prefect.resource.id": f"prefect.flow-run.{run.id}",
                                            "prefect.resource.name": run.name},
               payload={"reference_date": reference_date, "place": place,
                        "notes": list(notes)})


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m flows.weekly_forecast",
                                     description="Run the weekly SF (or a California county's) "
                                                 "forecast once, locally.")
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
    parser.add_argument("--county", default=None,
                        help="a California county, from CDPH data (default: San Francisco, "
                             "DataSF)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.county is not None:  # a misspelt county fails here, before Prefect starts
        try:
            args.county = california_county(args.county)
        except ConfigError as error:
            parser.error(str(error))
    logging.basicConfig(level=logging.INFO)
    with local_api():
        result = weekly_forecast(preset=args.preset, encoder=args.encoder,
                                 data_source=args.data_source, import_from=args.import_from,
                                 output_dir=args.output_dir, seed=args.seed,
                                 retrain=args.retrain, datasf_base_url=args.datasf_base_url,
                                 county=args.county)
    # Called directly, a flow that returned a State gives back that state's data: the outcome.
    assert isinstance(result, dict)
    print(f"report: {result['output_dir']}")
    return 0


@contextlib.contextmanager
def local_api() -> Iterator[int | None]:
    """Prefect's temporary API for a run from the command line, up and guarded (a killed run
    does not orphan it: :func:`flows.server_guard.ephemeral_api`); yields its pid, or None with
    a configured API."""
    # torch imports its symbolic shapes (sympy: 480 modules, 0.5 s) at the flows' first
    # sample: imported here, they load while the server comes up
    import torch.fx.experimental.symbolic_shapes  # noqa: F401

    from flows.server_guard import ephemeral_api

    # WeasyPrint (1.1 s of imports, needed only for the report's PDF at the end) loads on the
    # core the run leaves idle while it waits for the server and for its flow run to be created
    global _PRELOAD
    _PRELOAD = threading.Thread(target=preload_pdf_renderer, name="preload-weasyprint",
                                daemon=True)
    _PRELOAD.start()
    with ephemeral_api() as pid:
        yield pid


_PRELOAD: threading.Thread | None = None


def _preload_done() -> None:
    """Wait for the WeasyPrint import of :func:`local_api`: the run forks children, and a child
    forked while another thread imports a module could deadlock importing it."""
    if _PRELOAD is not None:
        _PRELOAD.join()


if __name__ == "__main__":
    from flows.server_guard import exit_now

    exit_now(main())
