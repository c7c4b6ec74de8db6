"""The Prefect flow of a CDC COVID-19 Forecast Hub round: ``hub_forecast``.

Tasks: ``forecast-rounds`` (the disease's admissions and ED share from data.cdc.gov, the
transport's retries and the cache as fallback; then every cached vintage's round, the newest
this week's: :func:`pipeline.hub_round.run.run_hub_round`; no task retry: what is left to fail
there is deterministic — the same seed on the same data fails the same way — and a member,
refit or target that fails is left out of the round, not retried), then
``publish-round`` (the hub's
file validated against its ``tasks.json``, the report, the track record:
:func:`pipeline.hub_round.publish.publish_hub_round`). A round that left a target or a member
out ends ``Completed (degraded)``, its message naming what and why (a target: its age), the
artifact too. Deployed for the hub's deadline
(``flows/deploy.py``, ``prefect.yaml``: Wednesdays, after NHSN's Wednesday release).

    python -m flows.hub_forecast [--disease covid] [--data-source live|cache] [--preset tiny]
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
from typing import Literal

import datetime as dt
import time
from zoneinfo import ZoneInfo

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact
from prefect.cache_policies import NO_CACHE
from prefect.client.schemas.objects import State
from prefect.states import Completed

from pipeline.data.core.cache import data_dir
from pipeline.hub_round.publish import PublishedRound, publish_hub_round, require_hub_config
from pipeline.hub_round.replay import RoundOutcome, RoundStep
from pipeline.hub_round.run import HubRun, HubRunConfig, run_hub_round
from pipeline.outputs.hub_conform import NoHubRoundError
from pipeline.progress import LogProgress

FLOW_NAME = "hub_forecast"
DEGRADED_STATE_NAME = "Completed (degraded)"
HUB_TIMEZONE = "America/New_York"     # the hubs' deadlines are 23:59 US Eastern


@flow(name=FLOW_NAME, log_prints=True)
def hub_forecast(disease: Literal["covid", "flu", "rsv"] = "covid",
                 data_source: Literal["live", "cache"] = "live",
                 output_dir: str = "reports", hub_config: str | None = None,
                 seed: int = 0, preset: Literal["default", "tiny"] = "default",
                 due: dt.date | None = None, deadline_only: bool = False,
                 config: HubRunConfig | None = None) -> dict[str, object] | State:
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
        due: The Wednesday the round is due (a replay's week,
            :mod:`pipeline.hub_round.replay`); a target without a release for its round is
            left out. Empty: the newest round the data serve.
        deadline_only: Make a round only on the day one is due by the hub's calendar (its
            tasks.json, deadlines moved for holidays included): the deployments run on every
            day a deadline can fall on (Monday to Thursday) and all but that one end at once
            with "no round due today".
        config: The round's whole configuration (a replay's week: its members, rounds,
            model id and data folder), taken as it is; the arguments above then give only
            ``deadline_only``.
    """
    logger = get_run_logger()
    config = config or run_config(disease, data_source, output_dir, hub_config, seed, preset,
                                  due)
    require_hub_config(config)        # no hub config: refused by name before any work
    try:                              # off season, or not the deadline: known before any work
        if deadline_only:
            config = dataclasses.replace(config, due=due_today(config))
        config.due_round(config.calendar())
    except NoHubRoundError as error:
        logger.info("%s", error)
        return no_round_outcome(str(error), config)
    try:       # FluSight off season: the data's newest round is none of the hub's (no failure)
        run = task(name="forecast-rounds", cache_policy=NO_CACHE, persist_result=False)(
            run_hub_round)(config, LogProgress(logger, "rounds", 2000))
        published = task(name="publish-round", cache_policy=NO_CACHE, persist_result=False)(
            publish_hub_round)(run)
    except NoHubRoundError as error:
        logger.info("%s", error)
        return no_round_outcome(str(error), config, error.reference)
    stale = "; ".join(f"{p.target}: {n}" for p in run.provenance.values() for n in p.notes)
    create_markdown_artifact(
        f"Hub round {published.reference_date} ({disease}): `{published.model_output}`"
        + (f"\n\nMade from cached data: {stale}" if run.stale else "")
        + (f"\n\n**Degraded**: {run.degraded_message()}" if run.degraded else "")
        + "".join(f"\n\n**Held** ({target}): {location}: {why}"
                  for target, held in run.held().items() for location, why in held.items()),
        key=f"hub-round-{disease}", description="the round's model-output file")
    logger.info("hub round %s → %s", published.reference_date, published.folder)
    outcome = round_outcome(run, published)
    if not run.degraded:
        return outcome
    logger.warning("hub round %s degraded: %s", published.reference_date,
                   run.degraded_message())
    return Completed(name=DEGRADED_STATE_NAME, data=outcome,
                     message=f"round {published.reference_date} degraded: "
                             f"{run.degraded_message()}")


def run_config(disease: Literal["covid", "flu", "rsv"], data_source: Literal["live", "cache"],
               output_dir: str, hub_config: str | None, seed: int,
               preset: Literal["default", "tiny"], due: dt.date | None) -> HubRunConfig:
    """The round's configuration from the deployment's parameters; the data folder read from
    the environment here, once ($FLOWCAST_DATA_DIR or ./data)."""
    config = HubRunConfig.of_preset(preset, disease=disease, data_source=data_source,
                                    output_dir=output_dir, hub_config=hub_config, seed=seed,
                                    due=due, data_dir=str(data_dir()))
    return dataclasses.replace(config, rounds=dataclasses.replace(config.rounds, seed=seed))


def due_today(config: HubRunConfig, now: dt.datetime | None = None) -> dt.date:
    """Today (``now``, else the clock) in the hub's timezone (US Eastern), when a round is due
    only on its deadline: a day the calendar has no deadline on is :class:`NoHubRoundError`
    ("no round due today")."""
    today = (now or dt.datetime.now(ZoneInfo(HUB_TIMEZONE))).astimezone(
        ZoneInfo(HUB_TIMEZONE)).date()
    calendar = config.calendar()
    if calendar is None or calendar.due_on(today) is None:
        upcoming = calendar.round_for(today) if calendar is not None else None
        raise NoHubRoundError(
            f"no {config.disease} hub round is due today ({today})"
            + (f"; the round of {upcoming} is due {calendar.deadline(upcoming)}"
               if calendar is not None and upcoming is not None else ""))
    return today


def no_round_outcome(why: str, config: HubRunConfig, reference: dt.date | None = None
                     ) -> dict[str, object]:
    """The flow's outcome when there is no round to make: rc 0, nothing written;
    ``reference``: the round the data would have served, where known."""
    return {"reference_date": str(reference) if reference else None, "no_round": why, "output_dir": None, "model_output": None,
            "files": [], "data_stale": False, "seconds": {}, "published_targets": [],
            "degraded": False, "dropped": [], "due": str(config.due) if config.due else None}


def round_outcome(run: HubRun, published: PublishedRound) -> dict[str, object]:
    """What the flow returns: where the round went, and what it left out."""
    return {"reference_date": published.reference_date, "output_dir": str(published.folder),
            "model_output": str(published.model_output), "files": list(published.files),
            "data_stale": run.stale, "seconds": run.seconds,
            "target_seconds": run.target_seconds,
            "published_targets": list(run.published_targets), "degraded": run.degraded,
            "held": run.held(),
            "dropped": [dataclasses.asdict(d) for d in run.dropped]}


def flow_step() -> RoundStep:
    """One Wednesday of a replay (:mod:`pipeline.hub_round.replay`) as the deployment runs it:
    this flow on the week's whole configuration (members, rounds, model id, data folder), its
    state kept (Completed, Completed (degraded) or Failed)."""
    def step(config: HubRunConfig) -> RoundOutcome:
        started = time.perf_counter()
        state = hub_forecast(config=config, return_state=True)
        due = str(config.due)
        if not state.is_completed():
            try:
                state.result()
                why = state.message or "failed"
            except Exception as error:  # noqa: BLE001 - the failed round's error, in words
                why = f"{type(error).__name__}: {error}"
            return RoundOutcome(due, "Failed", why, seconds=time.perf_counter() - started)
        outcome = state.result()
        assert isinstance(outcome, dict)
        if outcome.get("no_round"):
            return RoundOutcome(due, "No round", str(outcome["no_round"]),
                                seconds=time.perf_counter() - started)
        degraded, targets, dropped = (outcome["degraded"], outcome["published_targets"],
                                      outcome["dropped"])
        assert isinstance(targets, list) and isinstance(dropped, list)
        return RoundOutcome(
            due, "Completed (degraded)" if degraded else "Completed",
            (state.message or "") if degraded else "", str(outcome["reference_date"]),
            str(outcome["model_output"]), tuple(str(t) for t in targets),
            tuple({str(k): str(v) for k, v in d.items()} for d in dropped),
            time.perf_counter() - started, target_seconds=_target_seconds(outcome))

    return step


def _target_seconds(outcome: dict[str, object]) -> dict[str, dict[str, float]]:
    """The flow's per-target seconds (target, member), typed again."""
    given = outcome.get("target_seconds") or {}
    assert isinstance(given, dict)
    return {str(t): {str(n): float(v) for n, v in parts.items()} for t, parts in given.items()}


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
                              seed=args.seed, preset=args.preset)
    # Called directly, a flow that returned a State gives back that state's data: the outcome.
    assert isinstance(result, dict)
    print(result["no_round"] if result.get("no_round") else
          f"hub round: {result['model_output']}")
    return 0


if __name__ == "__main__":
    from flows.server_guard import exit_now

    exit_now(main())
