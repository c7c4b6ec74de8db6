"""A hub round's files, written into a staging folder and promoted to
``<output_dir>/hub-<disease>/<reference date>/`` only when all were written (a failed run never
replaces the last good round):

* ``model-output/<model>/<reference date>-<model>.csv`` and ``model-metadata/<model>.yml``: the
  round as the hub's ``tasks.json`` asks for it (:mod:`pipeline.outputs.hub_conform`: its
  sample count, integer values, bounds; no round where the hub has none, e.g. FluSight off
  season), every location × target × horizon −1 … 3, 23 quantiles and the sample
  trajectories per location × target, and the targets FluSight derives from the admissions'
  joint paths (rate change, peak); validated against the hub's ``tasks.json``;
* ``track_record_scores.csv``: every forecaster's scores over the earlier rounds;
  ``summary.json``: the round's facts and the track record per target × horizon;
* ``report.html`` and ``report.pdf`` (:mod:`pipeline.report.hub`).
"""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.backtest.hub_result import HubRoundsResult
from pipeline.combine.combiner import PUBLISHED
from pipeline.data.core.cache import utc_now
from pipeline.data.hub.locations import POPULATION
from pipeline.data.hub.nhsn_vintages import HOSP_FLU
from pipeline.errors import ConfigError, FlowcastError
from pipeline.hub_round.run import HubRun, HubRunConfig
from pipeline.io import atomic_write_json, atomic_write_text
from pipeline.outputs.derived_round import (PEAK_WEEK, RATE_CHANGE, derive_targets,
                                            derived_round_frame)
from pipeline.outputs.hub_conform import require_round
from pipeline.outputs.hub_tasks import target_model_task, task_values
from pipeline.outputs.hubverse_round import (MODEL_METADATA_DIR, compound_sample_ids,
                                             load_model_metadata,
                                             write_hub_round)
from pipeline.outputs.hubverse_validation import load_tasks_config
from pipeline.outputs.run_folders import RunOutputs, RunRecord, new_run_id
from pipeline.report.content import Notice, NoticeKind
from pipeline.report.hub import hub_report_content, track_record_table
from pipeline.report.render import write_report



@dataclass(frozen=True)
class PublishedRound:
    reference_date: str
    folder: Path
    files: tuple[str, ...]
    model_output: Path


def round_frame(run: HubRun, tasks: Mapping[str, Any] | None = None) -> pd.DataFrame:
    """The newest round of every target in the hubverse format, sample ids unique per
    location × target (one id a trajectory across the horizons), of the targets with a release
    for this round; with the hub's ``tasks``, the targets it derives from the weekly admissions'
    joint paths (FluSight's rate change and peak: :func:`derived_frame`)."""
    current = run.published_targets
    if not current:
        raise NoCurrentReleaseError(
            f"no target has a release for the round of {run.reference_date}: "
            + "; ".join(d.why for d in run.dropped if d.what == "target"))
    frames = [run.results[t].round_frame(len(run.results[t].rounds) - 1) for t in current]
    if tasks is not None:
        frames += [derived_frame(run.results[t], tasks) for t in current
                   if _asks_derived(tasks, run.results[t])]
    return compound_sample_ids(pd.concat(frames, ignore_index=True))


def dropped_and_held_notices(run: HubRun) -> tuple[Notice, ...]:
    """Page 1's notices beyond the locations left out: what the round dropped from its
    submission (a target, a published member) or replaced (a published member's refit), and
    the locations whose revised history waits for review (forecast from their accepted
    series, or left out when the release has no row of them, until the next release repeats
    the revision, the source takes it back or the operator accepts it)."""
    kinds = {"target": NoticeKind.LEFT_OUT, "member": NoticeKind.LEFT_OUT,
             "refit": NoticeKind.NOTE}
    dropped = [Notice(kinds[d.what], f"Not in this submission as planned: {d.line()}")
               for d in run.dropped if d.what in kinds and run.in_submission(d)]
    held = [Notice(NoticeKind.HELD, f"{p.target}: {location} held: a revision waiting for "
                                    f"review ({why}); accepted when the next release repeats "
                                    "it, ended when one takes it back")
            for p in run.provenance.values() for location, why in p.held.items()]
    return tuple(dropped + held)


class NoCurrentReleaseError(FlowcastError):
    """No target of the disease has a release serving this round: nothing to publish."""


def _asks_derived(tasks: Mapping[str, Any], result: HubRoundsResult) -> bool:
    """Does the hub's round ask for targets derived from this result's paths (the rate change
    of FluSight's weekly admissions)?"""
    day = result.rounds[-1].reference.date()
    return (result.target == HOSP_FLU and result.samples is not None
            and target_model_task(tasks, day, RATE_CHANGE) is not None)


def derived_frame(result: HubRoundsResult, tasks: Mapping[str, Any]) -> pd.DataFrame:
    """The newest round's derived targets (:mod:`pipeline.outputs.derived_round`): the rate
    change, and the peak when the hub's peak-week categories are the round's season weeks."""
    last = len(result.rounds) - 1
    targets = derive_targets(result, result.rounds[-1].panel, POPULATION)
    peak = target_model_task(tasks, result.rounds[-1].reference.date(), PEAK_WEEK)
    weeks = None if peak is None else [
        str(v) for v in task_values(peak["output_type"]["pmf"]["output_type_id"])]
    return derived_round_frame(targets, last, weeks)


def require_hub_config(config: HubRunConfig) -> Path:
    """The hub's config folder, or a :class:`ConfigError` naming what is missing: a round is
    never written unvalidated."""
    hub_config = config.hub_config_dir()
    if hub_config is None:
        where = {"covid": "the CDC hub's, github.com/CDCgov/covid19-forecast-hub",
                 "flu": "FluSight's, github.com/cdcepi/FluSight-forecast-hub",
                 "rsv": "the RSV hub's, github.com/CDCgov/rsv-forecast-hub"}
        raise ConfigError(f"the {config.disease} hub's tasks.json is needed to validate the "
                          "round file: pass --hub-config DIR or set FLOWCAST_HUB_CONFIG to the "
                          f"hub's hub-config folder ({where[config.disease]})")
    return hub_config


def summary(run: HubRun) -> dict[str, Any]:
    """The round's facts and each target's track record (JSON)."""
    out: dict[str, Any] = {"reference_date": str(run.reference_date),
                           "model_id": run.config.model_id, "model_key": run.model_key,
                           "model_reused": run.model_reused, "stale": run.stale,
                           "skipped": run.skipped(), "held": run.held(),
                           "degraded": run.degraded,
                           "dropped": [dataclasses.asdict(d) for d in run.dropped],
                           "seconds": {k: round(v, 1) for k, v in run.seconds.items()}}
    for target in {d.target for d in run.dropped if d.what == "target"} - set(run.results):
        out[target] = {"published": False, "dropped": _dropped_of(run, target)}
    for target, result in run.results.items():
        table = track_record_table(result)
        out[target] = {"published": target in run.published_targets,
                       "dropped": _dropped_of(run, target),
                       "rounds": {"first": str(result.rounds[0].reference.date()),
                                  "last": str(result.rounds[-1].reference.date()),
                                  "n": len(result.rounds)},
                       "n_locations": len(result.places),
                       "track_record": json.loads(table.to_json(orient="index"))}
    return out


def _dropped_of(run: HubRun, target: str) -> list[dict[str, str]]:
    return [{"what": d.what, "name": d.name, "why": d.why}
            for d in run.dropped if d.target == target]


def publish_hub_round(run: HubRun) -> PublishedRound:
    """Write the round's files and report (module docstring) and promote them."""
    config = run.config
    tasks = load_tasks_config(require_hub_config(config) / "tasks.json")
    # off season FluSight has no round: nothing is written, said by name (NoHubRoundError)
    require_round(tasks, pd.Timestamp(run.reference_date), f"the {config.disease} hub")
    metadata = load_model_metadata(MODEL_METADATA_DIR / f"{config.model_id}.yml")
    reference = str(run.reference_date)
    outputs = RunOutputs(Path(config.output_dir) / f"hub-{config.disease}",
                         place=f"CDC hub ({config.disease})")
    with outputs.staged(reference) as staging:
        written = write_hub_round(round_frame(run, tasks), hub_dir=staging,
                                  model_id=config.model_id, tasks=tasks, metadata=metadata)
        scores = pd.concat([r.scores() for r in run.results.values()], ignore_index=True)
        atomic_write_text(staging / "track_record_scores.csv",
                          scores.to_csv(index=False, float_format="%.6g"))
        atomic_write_json(staging / "summary.json", summary(run))
        notes = [f"{p.target}: {n}" for p in run.provenance.values() for n in p.notes] + \
            list(written.notes)
        vintage = "; ".join(f"{p.target}: as of {p.as_of} ({p.source_kind}"
                            f"{', cache' if p.from_cache else ''})"
                            for p in run.provenance.values())
        content = hub_report_content(run.results, reference_date=run.reference_date,
                                     model_id=config.model_id, data_vintage=vintage,
                                     warnings=notes, skipped=run.skipped(),
                                     config=dataclasses.asdict(config),
                                     notices=dropped_and_held_notices(run))
        write_report(content, staging)
        files = tuple(sorted(p.relative_to(staging).as_posix()
                             for p in staging.rglob("*") if p.is_file()))
        record = RunRecord(reference_date=reference, run_id=new_run_id(),
                           finished_at=utc_now().isoformat(timespec="seconds"),
                           data_stale=run.stale, data_vintage=vintage, model_key=run.model_key,
                           seed=config.seed, preset=f"hub-{config.disease}", files=files,
                           summary={"forecast": PUBLISHED, "notes": notes,
                                    "degraded": run.degraded_message()})
        folder = outputs.promote(staging, record)
    return PublishedRound(reference, folder, files,
                          folder / written.path.relative_to(staging))
