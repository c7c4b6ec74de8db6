"""The three CDC hubs' Wednesdays on their real releases → ``bench/results/replay.json``
(``held``, ``calendar``, ``rsv``) and ``bench/results/rsv.json``.

``held``: for FluSight, the COVID-19 hub (NHSN) and the RSV hub, every release of
``../shared/data/<hub>/time-series.parquet`` imported in order, as the replay imports them
(through the gate and the per-location revision review), and at each day the hub's calendar
has a round for, the newest vintage of each target read as the round reads it: the locations
of the hub's ``locations.csv`` missing from it (no forecast: ``rounds_missing`` per location,
``max_rounds_missing``; a location no release of the target ever held is ``never_released``,
not counted) and those forecast from a held series (``rounds_held``). ``before_issue_49``:
the same figures on the code before (commit 90868f4, a scratch run of the same data path),
where a held location was left out until the operator accepted its revision. This is the
replay's data path without the forecast (seconds, not hours); the files themselves are made
by the ``rsv`` part and ``bench.replay --part warm``.

``calendar``: over the same releases, the round each release day serves by the hub's calendar
(:mod:`pipeline.outputs.hub_calendar`) against the hub's rounds due in the span
(:func:`pipeline.hub_round.replay.calendar_check`): ``rounds_missed`` (a release in the
round's window and no round made), ``rounds_duplicated`` (a round made from another window's
release), and the rounds with no release in their window (the data's gaps); beside them what
the weekly rule (a release serves the first Saturday at least two days on) would have done.

``rsv``: the design replay of ``../shared/data/rsv`` (every release day from an empty store,
the deployment's flow, default members): rounds due, published, failed, valid files, seconds;
and the published forecast's relative WIS against the product's hub baseline (the RSV hub has
no team forecasts before its first round, 2025-09-20: the baseline is the only reference), per
target and horizon, scored on the newest release, from the last round's track record, with its
50 % / 95 % coverage (bootstrap intervals over rounds) and the online calibration's cost over
every round and in the worst window of 15 (``calibration_cost_by_window``).

    python -m bench.replay_hubs --part held
    python -m bench.replay_hubs --part calendar
    python -m bench.replay_hubs --part rsv [--preset tiny] [--from 2025-09-03]
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import pandas as pd

from bench.replay import RESULTS, _merge, _prefect, read_back

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
HUBS = {"flusight": "flu", "nhsn": "covid", "rsv": "rsv"}


def _parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--part", choices=("held", "calendar", "rsv", "all"), default="all")
    p.add_argument("--work", default="data/replay-bench")
    p.add_argument("--preset", choices=("default", "tiny"), default="default")
    p.add_argument("--from", dest="start", default=None)
    p.add_argument("--out", default=str(RESULTS / "replay.json"))
    return p.parse_args(argv)


def _releases(hub: str) -> list[Any]:
    from pipeline.hub_round.replay import releases_of_time_series

    return releases_of_time_series(pd.read_parquet(SHARED / hub / "time-series.parquet"),
                                   HUBS[hub])  # type: ignore[arg-type]


def _calendar(hub: str) -> Any:
    from pipeline.outputs.hub_calendar import HubCalendar
    from pipeline.outputs.hubverse_validation import load_tasks_config

    return HubCalendar.of_tasks(load_tasks_config(SHARED / hub / "hub-config" / "tasks.json"),
                                HUBS[hub], hub)


def data_path(hub: str) -> dict[str, Any]:
    """Each release day of ``hub`` through the replay's import, and what its round reads."""
    from pipeline.data.hub.nhsn_vintages import cached_weekly_vintages, disease_targets
    from pipeline.hub_round.replay import _release_file, import_releases, wednesdays

    releases, calendar = _releases(hub), _calendar(hub)
    hub_locations = set(pd.read_csv(SHARED / hub / "locations.csv",
                                    dtype={"location": str})["location"])
    targets = disease_targets(HUBS[hub])
    started = time.perf_counter()
    days: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        for day in wednesdays(releases):
            import_releases([r for r in releases if r.as_of <= day
                             and not _release_file(out, r).is_file()], out / "data",
                            out / "releases")
            reference = calendar.round_for(day)
            row: dict[str, Any] = {"due": str(day), "reference_date":
                                   None if reference is None else str(reference)}
            for target in targets:
                vintages = cached_weekly_vintages(target, out / "data")
                if not vintages:
                    continue
                newest = vintages[-1]
                row[target] = {"as_of": str(newest.as_of.date()),
                               "missing": sorted(hub_locations - set(newest.locations)),
                               "held": sorted(newest.held)}
            days.append(row)
    return {"days": days, "seconds": round(time.perf_counter() - started, 1)}


def held_figures(hub: str, days: list[dict[str, Any]]) -> dict[str, Any]:
    """Per target: the rounds (days the hub's calendar has a round) each location was missing
    from or forecast from a held series."""
    from pipeline.data.hub.nhsn_vintages import disease_targets

    out: dict[str, Any] = {}
    rounds = [d for d in days if d["reference_date"] is not None]
    for target in disease_targets(HUBS[hub]):
        present = [d for d in rounds if target in d]
        missing: dict[str, int] = {}
        held: dict[str, int] = {}
        # a hub location no release of the target ever held (NSSP has no ED data of Missouri
        # nor Puerto Rico) cannot be forecast by anyone: named apart, not counted as missing
        never = set.intersection(*(set(d[target]["missing"]) for d in days if target in d)) \
            if any(target in d for d in days) else set()
        for d in present:
            for loc in set(d[target]["missing"]) - never:
                missing[loc] = missing.get(loc, 0) + 1
            for loc in d[target]["held"]:
                held[loc] = held.get(loc, 0) + 1
        out[target] = {"rounds": len(present),
                       "never_released": sorted(never),
                       "max_rounds_missing": max(missing.values(), default=0),
                       "rounds_missing": dict(sorted(missing.items())),
                       "rounds_held": dict(sorted(held.items())),
                       "rounds_forecast_from_held_series": sum(held.values())}
    return out


def calendar_figures(hub: str, days: list[dict[str, Any]]) -> dict[str, Any]:
    """The calendar's check of the rounds the release days serve, and the weekly rule's."""
    from pipeline.hub_round.replay import calendar_check
    from pipeline.panels.hub import reference_date_for

    calendar = _calendar(hub)

    def made(rule: str) -> list[dict[str, object]]:
        rows = []
        for d in days:
            day = dt.date.fromisoformat(d["due"])
            ref = (d["reference_date"] if rule == "calendar" else
                   str(reference_date_for(pd.Timestamp(day)).date()))
            rows.append({"due": d["due"], "reference_date": ref,
                         "model_output": None if ref is None else f"{ref}.csv"})
        return rows

    now, before = calendar_check(made("calendar"), calendar), calendar_check(made("weekly"),
                                                                              calendar)
    return {**now, "release_days": len(days),
            "days_without_round": [d["due"] for d in days if d["reference_date"] is None],
            "weekly_rule": {k: before[k] for k in ("rounds_missed", "rounds_duplicated")}}


def run_data_parts(args: argparse.Namespace, path: Path) -> None:
    held: dict[str, Any] = {}
    calendar: dict[str, Any] = {}
    for hub in HUBS:
        result = data_path(hub)
        figures = held_figures(hub, result["days"])
        held[hub] = {**figures, "seconds": result["seconds"],
                     "max_rounds_missing": max(f["max_rounds_missing"] for f in figures.values())}
        calendar[hub] = calendar_figures(hub, result["days"])
        print(f"{hub}: held {json.dumps({t: v['max_rounds_missing'] for t, v in held[hub].items() if isinstance(v, dict)})}; "
              f"calendar missed {calendar[hub]['rounds_missed']} duplicated "
              f"{calendar[hub]['rounds_duplicated']}", flush=True)
    _merge(path, {"held": held, "calendar": {
        **calendar, "rounds_missed": sum(len(c["rounds_missed"]) for c in calendar.values()),
        "rounds_duplicated": sum(len(c["rounds_duplicated"]) for c in calendar.values())},
        "command_held": "python -m bench.replay_hubs --part held"})


# ---------------------------------------------------------------------------- the RSV replay


def rsv_skill(out: Path) -> dict[str, Any]:
    """The published forecast's WIS relative to the product's hub baseline, per target and
    horizon, from the last round's track record (every round's forecasts from its own vintage,
    scored on the newest release)."""
    folders = sorted((out / "rounds" / "hub-rsv").glob("*/track_record_scores.csv"))
    if not folders:
        return {}
    scores = pd.read_csv(folders[-1])
    relative = _relative(scores)
    for target, part in scores[scores["horizon"] >= 0].groupby("target"):
        relative[str(target)] |= _coverage_and_cost(part)
    return {"source": str(folders[-1].relative_to(out)), "columns": list(scores.columns),
            **relative}


def _cube(scores: pd.DataFrame, model: str, column: str, places: pd.Index,
          columns: pd.MultiIndex) -> Any:
    """``column`` of ``model``'s scores as a (location, reference date, horizon) array, NaN
    where it has no score."""
    frame = scores[scores["model_id"] == model]
    wide = frame.pivot_table(index="location", columns=["reference_date", "horizon"],
                             values=column).reindex(index=places, columns=columns)
    return wide.to_numpy(dtype=float).reshape(len(places), *columns.levshape)


def _coverage_and_cost(scores: pd.DataFrame) -> dict[str, Any]:
    """The published forecast's 50 % / 95 % coverage over a target's horizons 0-3 with their
    moving-block bootstrap intervals over rounds, and the online calibration's cost (its WIS ÷
    the same average uncalibrated) over every round and in the worst window of 15."""
    import numpy as np

    from pipeline.evaluation.bootstrap import coverage_interval
    from pipeline.evaluation.summary import calibration_cost

    places = pd.Index(sorted(scores["location"].unique()))
    dates = sorted(scores["reference_date"].unique())
    columns = pd.MultiIndex.from_product([dates, sorted(scores["horizon"].unique())])
    out: dict[str, Any] = {}
    for level in ("50", "95"):
        covered = _cube(scores, "published", f"coverage_{level}", places, columns)
        interval = coverage_interval(covered, np.ones(covered.shape, dtype=bool))
        out[f"coverage{level}"] = round(float(np.nanmean(covered)), 4)
        out[f"coverage{level}_interval"] = (None if interval is None
                                            else [round(float(x), 4) for x in interval])
    if "ensemble-uncalibrated" in set(scores["model_id"]):
        cost = calibration_cost(_cube(scores, "published", "wis", places, columns),
                                _cube(scores, "ensemble-uncalibrated", "wis", places, columns),
                                dates)
        out["calibration_cost_by_window"] = {
            k: (round(v, 4) if isinstance(v, float) else v) for k, v in cost.items()}
    return out


def _relative(scores: pd.DataFrame) -> dict[str, Any]:
    """Mean WIS of ``published`` (and of each member) ÷ that of the hub baseline over the
    cells both scored, per target, over horizons 0-3 (the hubs' leaderboards) and by horizon."""
    wide = scores.pivot_table(index=["target", "reference_date", "location", "horizon"],
                              columns="model_id", values="wis")
    base = "hub-baseline"
    out: dict[str, Any] = {"baseline": base}
    for target, part in wide.groupby(level="target"):
        ahead = part[part.index.get_level_values("horizon") >= 0]

        def ratio(frame: pd.DataFrame, member: str) -> float | None:
            both = frame[[member, base]].dropna()
            return (round(float(both[member].mean() / both[base].mean()), 4) if len(both)
                    else None)

        out[str(target)] = {
            "relative_wis": ratio(ahead, "published"),
            "by_horizon": {str(h): ratio(p, "published")
                           for h, p in part.groupby(level="horizon")},
            "cells": int(ahead["published"].notna().sum()),
            "rounds": int(part.index.get_level_values("reference_date").nunique()),
            "members": {str(m): ratio(ahead, str(m)) for m in part.columns if m != base}}
    return out


def run_rsv(args: argparse.Namespace, path: Path) -> None:
    from flows.hub_forecast import flow_step
    from pipeline.hub_round import replay as rp
    from pipeline.hub_round.run import HubRunConfig
    from bench.replay import valid_files

    out = Path(args.work) / "rsv"
    if out.exists():
        shutil.rmtree(out)
    releases = _releases("rsv")
    run = HubRunConfig.of_preset(args.preset, disease="rsv")
    config = rp.ReplayConfig(out, run, dt.date.fromisoformat(args.start) if args.start else None)
    rp.copy_hub_config(run.hub_config_dir(), out)
    started = time.perf_counter()
    expected = len(rp.wednesdays(releases, config.start))

    def partial(summary: dict[str, object]) -> None:
        print(f"rsv round {summary['rounds_due']}/{expected} "
              f"({time.perf_counter() - started:.0f} s)", flush=True)

    with _prefect():
        summary = rp.replay(config, releases,
                            flow_step(), partial)
    figures = {k: summary[k] for k in ("rounds_due", "rounds_published", "rounds_failed",
                                       "degraded", "failed", "no_round", "replaced",
                                       "calendar", "seconds")}
    figures |= {"preset": args.preset, "start": args.start, "valid": valid_files(out, SHARED /
                                                                                 "rsv"),
                "hubdata_rows": read_back(out), "skill": rsv_skill(out),
                "team_forecasts": "none: the RSV hub's first round is 2025-09-20, after every "
                                  "design release; relative WIS is against the product's hub "
                                  "baseline"}
    command = "python -m bench.replay_hubs --part rsv" + (
        f" --preset {args.preset}" if args.preset != "default" else "") + (
        f" --from {args.start}" if args.start else "")
    _merge(path, {"rsv": figures, "command_rsv": command})
    _merge(RESULTS / "rsv.json", {"replay": figures, "command": command})


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    path = Path(args.out)
    if args.part in ("held", "calendar", "all"):
        run_data_parts(args, path)
    if args.part in ("rsv", "all"):
        run_rsv(args, path)
    print(f"→ {path}")


if __name__ == "__main__":
    main(sys.argv[1:])
