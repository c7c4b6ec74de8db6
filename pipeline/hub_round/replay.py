"""The hub round's operations replayed: every Wednesday with a release, in order, from an empty
model store, each through the same run as the Wednesday deployment's.

For each Wednesday W (a day some release of the disease's targets is dated):

1. the releases dated W are imported into the replay's own data folder ``DIR/data`` through the
   same gate and revision review a live fetch passes (:func:`pipeline.data.hub.target_import.
   import_target_csv` → ``commit_weekly``: live, archived, or held for review); later releases
   are not there yet, so they are invisible;
2. the week's round is made by ``step`` — the deployment's run (the Prefect flow
   ``hub_forecast`` from ``flowcast replay``; :func:`library_step`, the same library calls the
   flow's tasks make, where Prefect is not wanted) — offline, due W, into ``DIR/rounds``: run
   state, report, summary;
3. the round's file is copied to ``DIR/model-output/<model>/``, a hubverse model-output folder;
4. the model store, the forecast memo and the held revisions stay in ``DIR/data`` for the next
   Wednesday; ``DIR/replay.json`` (written after every round, atomically) says what each round
   did: rounds due, published, degraded (what was dropped, and why), failed, their seconds.

A rerun with the same ``DIR`` replays only the Wednesdays not yet in ``replay.json``: imported
with a later release, the same command replays the later weeks.
"""
from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import json
import logging
import os
import shutil
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pandas as pd

from pipeline.data.hub.nhsn_vintages import (canonical_csv, cached_weekly_vintages,
                                             disease_targets, target_spec)
from pipeline.data.hub.target_import import VintageImport, import_target_csv
from pipeline.errors import ConfigError, FlowcastError
from pipeline.hub_round.publish import publish_hub_round
from pipeline.hub_round.run import Disease, HubRunConfig, run_hub_round
from pipeline.io import atomic_write_bytes, atomic_write_json, file_lock
from pipeline.outputs.hub_calendar import HubCalendar
from pipeline.outputs.hub_conform import NoHubRoundError
from pipeline.outputs.hubverse_round import CDC_HUB_MODEL_ID

log = logging.getLogger(__name__)
SUMMARY_NAME = "replay.json"
RoundState = Literal["Completed", "Completed (degraded)", "Failed", "No round"]


@dataclass(frozen=True)
class Release:
    """One release of one target: its date and its rows as the canonical target CSV."""

    target: str
    as_of: dt.date
    payload: bytes


@dataclass(frozen=True)
class RoundOutcome:
    """What one Wednesday's run did: its state (``Completed``, ``Completed (degraded)`` or
    ``Failed``) and message, the round's file, the targets it holds, what it dropped."""

    due: str
    state: RoundState
    message: str = ""
    reference_date: str | None = None
    model_output: str | None = None
    published_targets: tuple[str, ...] = ()
    dropped: tuple[dict[str, str], ...] = ()
    seconds: float = 0.0
    imported: tuple[str, ...] = ()
    # the Wednesday whose file of the same round this one replaces (a second release in the
    # round's window), said in the log and the summary
    replaces: str | None = None
    # per target: its seconds in all and each member's (pipeline.hub_round.run.target_seconds)
    target_seconds: dict[str, dict[str, float]] = field(default_factory=dict)


RoundStep = Callable[[HubRunConfig], RoundOutcome]


@dataclass(frozen=True)
class ReplayConfig:
    """Where the replay writes (``out``), which Wednesdays (``start`` … ``end``, inclusive;
    None: every one), and the round's settings (``run``: members, seed, model id; its
    ``output_dir``, ``data_source`` and ``due`` are the replay's)."""

    out: Path
    run: HubRunConfig = field(default_factory=HubRunConfig)
    start: dt.date | None = None
    end: dt.date | None = None

    def __post_init__(self) -> None:
        if self.start is not None and self.end is not None and self.start > self.end:
            raise ConfigError(f"replay from {self.start} to {self.end}: the start is after the "
                              "end")


def cached_releases(disease: Disease, data_dir: str | os.PathLike[str] | None = None
                    ) -> list[Release]:
    """Every release of the disease's targets the cache holds (live and archived; not those
    held for review), oldest first: the replay's input."""
    out = []
    for target in disease_targets(disease):
        for vintage in cached_weekly_vintages(target, data_dir):
            path = Path(vintage.source)
            payload = (path.read_bytes() if path.suffix == ".csv"
                       else canonical_csv(vintage.frame))
            out.append(Release(target, vintage.as_of.date(), payload))
    return sorted(out, key=lambda r: (r.as_of, r.target))


def releases_of_time_series(frame: pd.DataFrame, disease: Disease) -> list[Release]:
    """The releases of a hub ``time-series.parquet``'s rows (``target_end_date, location,
    observation, as_of, target``) for the disease's targets, oldest first."""
    targets = disease_targets(disease)
    rows = frame[frame["target"].isin(targets)]
    out = []
    for (target, as_of), part in rows.groupby(["target", "as_of"], sort=True):
        body = part.rename(columns={"observation": "value"})
        out.append(Release(str(target), pd.Timestamp(str(as_of)).date(), canonical_csv(body)))
    return sorted(out, key=lambda r: (r.as_of, r.target))


def wednesdays(releases: Sequence[Release], start: dt.date | None = None,
               end: dt.date | None = None) -> list[dt.date]:
    """The days with a release (the hub's Wednesdays), within ``start`` … ``end``."""
    days = sorted({r.as_of for r in releases})
    return [d for d in days if (start is None or d >= start) and (end is None or d <= end)]


def import_releases(releases: Sequence[Release], data_dir: Path, folder: Path
                    ) -> list[VintageImport]:
    """The releases into the cache at ``data_dir`` through the gate and the revision review
    (kept under ``folder`` as the files imported); a refused or held release is said, not
    raised: the round goes on with what the cache holds."""
    done: list[VintageImport] = []
    for release in releases:
        path = folder / _release_name(release)
        incoming = path.with_name(f"incoming-{path.name}")   # named as imported once done
        atomic_write_bytes(incoming, release.payload)
        try:
            summary = import_target_csv(incoming, target=release.target, as_of=release.as_of,
                                        data_dir=data_dir)
            done += summary.vintages
        except FlowcastError as error:        # refused whole (no location passes the gate)
            log.warning("release %s of %s refused: %s", release.as_of, release.target, error)
            done.append(VintageImport(release.target, str(release.as_of), "refused", 0, "", "",
                                      str(error)))
        os.replace(incoming, path)
    return done


def _release_name(release: Release) -> str:
    return f"{release.as_of}-{target_spec(release.target).dataset_id}.csv"


def _release_file(out: Path, release: Release) -> Path:
    """Where the replay keeps a release it imported (its presence: imported)."""
    return out / "releases" / _release_name(release)


def _folder_lock(out: Path) -> contextlib.AbstractContextManager[None]:
    """The replay folder's lock: two replays into one folder (issue 49) import each release
    once and merge their summaries."""
    # long: the other replay may be importing a season of releases at its first Wednesday
    return file_lock(out / ".replay.lock", timeout_s=600.0, what=f"the replay folder {out}")


def _import_due(releases: Sequence[Release], due: dt.date, out: Path, data_dir: Path
                ) -> list[VintageImport]:
    """The releases dated by ``due`` that the folder has not imported yet, under its lock."""
    with _folder_lock(out):
        return import_releases([r for r in releases if r.as_of <= due
                                and not _release_file(out, r).is_file()], data_dir,
                               out / "releases")


def library_step(config: HubRunConfig) -> RoundOutcome:
    """One Wednesday through the library calls the deployment's tasks make (run, publish)."""
    assert config.due is not None
    try:
        run = run_hub_round(config)
    except NoHubRoundError as error:      # off season: the hub takes no round that day
        return RoundOutcome(str(config.due), "No round", str(error))
    published = publish_hub_round(run)
    return RoundOutcome(
        str(config.due), "Completed (degraded)" if run.degraded else "Completed",
        run.degraded_message(), published.reference_date, str(published.model_output),
        run.published_targets, tuple({"what": d.what, "target": d.target, "name": d.name,
                                      "why": d.why} for d in run.dropped),
        target_seconds=run.target_seconds)


def replay(config: ReplayConfig, releases: Sequence[Release],
           step: RoundStep = library_step,
           on_round: Callable[[dict[str, object]], None] | None = None) -> dict[str, object]:
    """Every Wednesday of ``releases`` (module docstring); the summary, also in
    ``DIR/replay.json`` (and to ``on_round`` after each round). A round that fails is recorded
    and the next Wednesday goes on. Each Wednesday imports every release dated by then not yet
    imported (from ``start`` on, the earlier ones come in at the first)."""
    out = config.out
    data_dir = out / "data"
    model_dir = out / "model-output" / config.run.model_id
    previous = _read_summary(out)
    done = {r["due"]: r for r in previous.get("rounds", [])}
    rounds = [dict(r) for r in previous.get("rounds", [])]
    for due in wednesdays(releases, config.start, config.end):
        if str(due) in done:
            continue
        started = time.perf_counter()
        imported = _import_due(releases, due, out, data_dir)
        run_config = dataclasses.replace(config.run, data_source="cache", due=due,
                                         output_dir=str(out / "rounds"),
                                         data_dir=str(data_dir))
        try:
            outcome = step(run_config)
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as error:  # noqa: BLE001 - a failed round is recorded, not fatal
            log.error("the round due %s failed: %s", due, error, exc_info=True)
            outcome = RoundOutcome(str(due), "Failed", f"{type(error).__name__}: {error}")
        if outcome.model_output is not None:
            model_dir.mkdir(parents=True, exist_ok=True)
            copied = model_dir / Path(outcome.model_output).name
            atomic_write_bytes(copied, Path(outcome.model_output).read_bytes())
        outcome = dataclasses.replace(
            outcome, replaces=_replaced(rounds, outcome),
            seconds=round(time.perf_counter() - started, 1),
            imported=tuple(f"{v.target} {v.as_of}: {v.action}" + (f" ({v.note})" if v.note
                                                                   else "")
                           for v in imported))
        log.info("replay %s: %s %s (%.1f s)", due, outcome.state, outcome.message,
                 outcome.seconds)
        rounds.append(json.loads(json.dumps(dataclasses.asdict(outcome))))  # as in the file
        rounds = write_summary(out, rounds, config)
        if on_round is not None:
            on_round(summarize(rounds, config))
    return summarize(write_summary(out, rounds, config), config)


def write_summary(out: Path, rounds: Sequence[dict[str, object]], config: ReplayConfig
                  ) -> list[dict[str, object]]:
    """``rounds`` merged with those another replay into ``out`` wrote meanwhile (ours win on a
    shared Wednesday), written under the folder's lock; the merged rounds, by due date. Two
    replays of different Wednesdays into one folder once left the last one's file alone,
    without the other's (failed) round (issue 49)."""
    with _folder_lock(out):
        merged = {str(r["due"]): r for r in _read_summary(out).get("rounds", [])}
        merged.update({str(r["due"]): r for r in rounds})
        ordered = [merged[due] for due in sorted(merged)]
        atomic_write_json(out / SUMMARY_NAME, summarize(ordered, config))
    return ordered


def _replaced(rounds: Sequence[dict[str, object]], outcome: RoundOutcome) -> str | None:
    """The earlier Wednesday whose file of the same round ``outcome`` replaces, if any."""
    if outcome.model_output is None:
        return None
    earlier = [r["due"] for r in rounds if r["reference_date"] == outcome.reference_date
               and r["model_output"] is not None]
    if earlier:
        log.warning("the round of %s made on %s replaces the file made on %s (a second release "
                    "in its window)", outcome.reference_date, outcome.due, earlier[-1])
    return str(earlier[-1]) if earlier else None


def calendar_check(rounds: Sequence[dict[str, object]], calendar: HubCalendar
                   ) -> dict[str, object]:
    """The hub's rounds over the replayed span (their deadlines from the first replayed day to
    the last) against the files made: ``rounds_missed`` (a release came in the round's window,
    and no file was made of it), ``rounds_duplicated`` (one round made from releases of more
    than one window: the wrong round published), and the rounds with no release in their
    window at all (no file can be made of them; the data's gaps, not the calendar's)."""
    days = sorted(dt.date.fromisoformat(str(r["due"])) for r in rounds)
    if not days:
        return {"hub_rounds": 0, "rounds_missed": [], "rounds_duplicated": [],
                "rounds_without_release": []}
    made: dict[str, list[str]] = {}
    for r in rounds:
        if r["model_output"] is not None:
            made.setdefault(str(r["reference_date"]), []).append(str(r["due"]))
    served = {d: calendar.round_for(d) for d in days}
    hub = calendar.rounds_between(days[0], days[-1])
    with_release = [ref for ref in hub if ref in served.values()]
    wrong_window = {ref: dues for ref, dues in made.items()
                    if any(served.get(dt.date.fromisoformat(d)) != dt.date.fromisoformat(ref)
                           for d in dues) and dt.date.fromisoformat(ref) in hub}
    return {"hub_rounds": len(hub), "rounds_with_release": len(with_release),
            "rounds_missed": [str(ref) for ref in with_release if str(ref) not in made],
            "rounds_duplicated": sorted(wrong_window),
            "rounds_without_release": [str(ref) for ref in hub if ref not in with_release]}


def _read_summary(out: Path) -> dict[str, list[dict[str, object]]]:
    path = out / SUMMARY_NAME
    if not path.is_file():
        return {}
    data = json.loads(path.read_text(encoding="utf-8"))
    return {"rounds": list(data.get("rounds", []))}


def summarize(rounds: Sequence[dict[str, object]], config: ReplayConfig) -> dict[str, object]:
    """The replay's figures: rounds due, published, degraded (what, why), failed; seconds."""
    published = [r for r in rounds if r["state"] in ("Completed", "Completed (degraded)")]
    due = [r for r in rounds if r["state"] != "No round"]
    # the rounds' seconds (a day with no round open costs only its import: not a round)
    seconds = [float(str(r["seconds"])) for r in due]
    calendar = config.run.calendar()
    return {
        "model_id": config.run.model_id, "disease": config.run.disease,
        "rounds_due": len(due), "rounds_published": len(published),
        "rounds_failed": len(due) - len(published),
        "no_round": [{"due": r["due"], "message": r["message"]}
                     for r in rounds if r["state"] == "No round"],
        "replaced": [{"due": r["due"], "reference_date": r["reference_date"],
                      "replaces": r.get("replaces")} for r in rounds if r.get("replaces")],
        "calendar": calendar_check(rounds, calendar) if calendar is not None else None,
        "degraded": [{"due": r["due"], "reference_date": r["reference_date"],
                      "message": r["message"], "dropped": r["dropped"]}
                     for r in rounds if r["state"] == "Completed (degraded)"],
        "failed": [{"due": r["due"], "message": r["message"]}
                   for r in rounds if r["state"] == "Failed"],
        "seconds": ({"first_round": seconds[0], "per_round_median": statistics.median(seconds),
                     "per_round_max": max(seconds), "total": round(sum(seconds), 1)}
                    if seconds else {}),
        "seconds_by_target": seconds_by_target(rounds),
        "rounds": list(rounds)}


def seconds_by_target(rounds: Sequence[dict[str, object]]) -> dict[str, dict[str, object]]:
    """Per target and member (and the target ``total``): the seconds of the first round and
    the median and max of the later ones (a warm round's, the memo and the store carried
    over)."""
    figures: dict[str, dict[str, list[float]]] = {}
    for r in rounds:
        by_target = r.get("target_seconds") or {}
        assert isinstance(by_target, dict)
        for target, parts in by_target.items():
            for name, value in parts.items():
                figures.setdefault(target, {}).setdefault(name, []).append(float(value))
    return {target: {name: {"first_round": values[0],
                            "later_median": statistics.median(values[1:]) if values[1:] else None,
                            "later_max": max(values[1:]) if values[1:] else None}
                     for name, values in parts.items()}
            for target, parts in figures.items()}


def copy_hub_config(hub_config: Path | None, out: Path) -> None:
    """The hub's ``hub-config`` beside the replay's model-output folder, so that hub tools
    (``hubdata``) read ``DIR`` as a hub."""
    if hub_config is None:
        return
    target = out / "hub-config"
    target.mkdir(parents=True, exist_ok=True)
    for name in ("tasks.json", "admin.json"):
        if (hub_config / name).is_file():
            shutil.copyfile(hub_config / name, target / name)


__all__ = ["CDC_HUB_MODEL_ID", "Release", "ReplayConfig", "RoundOutcome", "cached_releases",
           "copy_hub_config", "library_step", "releases_of_time_series", "replay", "wednesdays"]
