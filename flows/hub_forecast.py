"""The Prefect flow of a CDC COVID-19 Forecast Hub round: ``hub_forecast``.

Tasks: ``forecast-rounds`` (the disease's admissions and ED share from data.cdc.gov, the
transport's retries and the cache as fallback; then every cached vintage's round, the newest
this week's: :func:`pipeline.hub_round.run.run_hub_round`; one task retry), then
``publish-round`` (the hub's
file validated against its ``tasks.json``, the report, the track record:
:func:`pipeline.hub_round.publish.publish_hub_round`). Deployed for the hub's deadline
(``flows/deploy.py``, ``prefect.yaml``: Wednesdays, after NHSN's Wednesday release).

    python -m flows.hub_forecast [--disease covid] [--data-source live|cache] [--preset tiny]
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
from typing import Literal

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from pipeline.hub_round.publish import publish_hub_round, require_hub_config
from pipeline.hub_round.run import HubRunConfig, hub_members_preset, run_hub_round
from pipeline.outputs.hub_conform import NoHubRoundError
from pipeline.progress import LogProgress

FLOW_NAME = "hub_forecast"


@flow(name=FLOW_NAME, log_prints=True)
def hub_forecast(disease: Literal["covid", "flu", "rsv"] = "covid",
                 data_source: Literal["live", "cache"] = "live",
                 output_dir: str = "reports", hub_config: str | None = None,
                 seed: int = 0, preset: Literal["default", "tiny"] = "default"
                 ) -> dict[str, object]:
    """This week's round of the hub for ``disease`` (module docstring) into
    ``<output_dir>/hub-<disease>/<reference date>/``.

    Args:
        disease: The hub's disease: covid (the CDC COVID-19 Forecast Hub); flu and rsv read
            NHSN's and NSSP's series of that disease.
        data_source: "live" fetches data.cdc.gov and falls back to the cache; "cache" reads
            only the cache (offline).
        output_dir: The reports folder on the worker's machine.
        hub_config: The hub's hub-config folder (its tasks.json validates the file). Empty:
            $FLOWCAST_HUB_CONFIG or the disease's beside the checkout (../shared/data/nhsn
            or ../shared/data/flusight hub-config; none for RSV: refused by name).
        seed: Seed of every random step.
        preset: default: the product's members; tiny: a small flow and few draws, a
            seconds-long smoke run.
    """
    logger = get_run_logger()
    config = HubRunConfig(disease=disease, data_source=data_source, output_dir=output_dir,
                          hub_config=hub_config, seed=seed,
                          members=hub_members_preset(preset))
    config = dataclasses.replace(config, rounds=dataclasses.replace(config.rounds, seed=seed))
    require_hub_config(config)        # no hub config (RSV): refused by name before any work
    run = task(name="forecast-rounds", cache_policy=NO_CACHE, persist_result=False,
               retries=1, retry_delay_seconds=30)(run_hub_round)(
        config, LogProgress(logger, "rounds", 2000))
    try:
        published = task(name="publish-round", cache_policy=NO_CACHE, persist_result=False)(
            publish_hub_round)(run)
    except NoHubRoundError as error:           # FluSight off season: no round, not a failure
        logger.info("%s", error)
        return {"reference_date": str(run.reference_date), "no_round": str(error),
                "output_dir": None, "model_output": None, "files": [],
                "data_stale": run.stale, "seconds": run.seconds}
    stale = "; ".join(f"{p.target}: {n}" for p in run.provenance.values() for n in p.notes)
    create_markdown_artifact(
        f"Hub round {published.reference_date} ({disease}): `{published.model_output}`"
        + (f"\n\nMade from cached data: {stale}" if run.stale else ""),
        key=f"hub-round-{disease}", description="the round's model-output file")
    logger.info("hub round %s → %s", published.reference_date, published.folder)
    return {"reference_date": published.reference_date, "output_dir": str(published.folder),
            "model_output": str(published.model_output), "files": list(published.files),
            "data_stale": run.stale, "seconds": run.seconds}


def main(argv: list[str] | None = None) -> int:
    from flows.weekly_forecast import local_api

    parser = argparse.ArgumentParser(prog="python -m flows.hub_forecast",
                                     description="Make this week's hub round once, locally.")
    parser.add_argument("--disease", default="covid", choices=["covid", "flu", "rsv"])
    parser.add_argument("--data-source", default="live", choices=["live", "cache"])
    parser.add_argument("--output-dir", default="reports")
    parser.add_argument("--hub-config", default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", default="default", choices=["default", "tiny"])
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    with local_api():
        result = hub_forecast(disease=args.disease, data_source=args.data_source,
                              output_dir=args.output_dir, hub_config=args.hub_config,
                              seed=args.seed)
    print(result["no_round"] if result.get("no_round") else
          f"hub round: {result['model_output']}")
    return 0


if __name__ == "__main__":
    from flows.server_guard import exit_now

    exit_now(main())
