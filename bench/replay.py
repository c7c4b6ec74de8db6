"""The hub round's operations replayed → bench/results/replay.json.

``full``: every Wednesday of ``../shared/data/nhsn`` in order, from an empty model store, each
through the hub_forecast flow as the Wednesday deployment runs it (:mod:`pipeline.hub_round.
replay`, the same code as ``flowcast replay``): ``rounds_due``, ``rounds_published``,
``rounds_failed``, ``degraded`` (each round with what was dropped and why), ``seconds``
(``first_round``, ``per_round_median``, ``per_round_max``, ``total``); the replay's
model-output folder read back with ``hubdata`` (``hubdata_rows``); and
``skill.pairwise_relative_wis``: the replayed admissions files scored beside every team of the
hub exactly as ``bench/nhsn.py`` scores them (its ``leaderboards``), beside ``nhsn.json``'s
published figure. The JSON is rewritten after every round (``"partial": true`` until the last).

``warm``: the same replay from a Wednesday mid-period (:data:`WARM_FROM`, ``--from``; both
targets released, the model store and the memo empty there: the releases before it are imported
at its start) to the last: the first round trains every refit up to it and forecasts every
past round; each later one, the store and the memo carried over, forecasts one round.
``seconds`` as ``full``'s, ``seconds_by_target`` (per target and member: the first round's, the
median and max of the later ones) and each round's ``target_seconds``.

``injected``: one-Wednesday replays (the tiny preset; the releases before it imported at its
start) with a failure injected: ``member_raises`` (nf-context raises: a published member of
both targets), ``member_nan`` (gbqr, admissions' other published member, and seasonal, the ED
share's, return a NaN median), ``refit_diverges`` (every nf-real fine-tune diverges),
``location_revised`` (the week's admissions release revises California's settled weeks
tenfold), ``target_stale`` (the ED share's last five releases withheld): each ``{"published", "valid", "dropped"}``, valid =
the round's file validated against the hub's tasks.json again and read back by hubdata.

``refits``: nf-real's fine-tuning at every refit date of the design rounds (both targets) × 3
seeds, with the settings before this change (no early stop, gradients clipped at 10) and after
(:class:`~pipeline.members.nf.real.FineTuneConfig`): how many diverged, and the learning
rates measured by their best validation NLL.

    python -m bench.replay                      # every part
    python -m bench.replay --part full          # the full replay only (long: run it nice'd)
    python -m bench.replay --part warm          # from WARM_FROM (--from) on
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "nhsn"
INJECTED_DUE = "2025-08-20"       # a Wednesday with both targets released (and five before it)
# the warm replay's first Wednesday: both targets released (the ED share since 2025-06-18),
# nine Wednesdays to the last release (2025-09-24), three refit dates among them
WARM_FROM = "2025-07-30"


def _parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--part", choices=("full", "warm", "injected", "refits", "all"),
                   default="all")
    p.add_argument("--hub", default=str(SHARED), help="the hub data (time series, forecasts)")
    p.add_argument("--disease", choices=("covid", "flu", "rsv"), default="covid",
                   help="the hub's disease (warm: flu writes warm_flu; FluSight: --hub "
                        "../shared/data/flusight)")
    p.add_argument("--work", default="data/replay-bench", help="the replays' folders")
    p.add_argument("--preset", choices=("default", "tiny"), default="default",
                   help="the full replay's members")
    p.add_argument("--from", dest="start", default=None,
                   help=f"the first Wednesday (warm: {WARM_FROM})")
    p.add_argument("--to", dest="end", default=None)
    p.add_argument("--case", action="append", default=None,
                   choices=("member_raises", "member_nan", "refit_diverges", "location_revised",
                            "target_stale"), help="the injected cases to run (default: all)")
    p.add_argument("--resume", action="store_true",
                   help="go on with the full replay's folder instead of starting it empty")
    p.add_argument("--out", default=str(RESULTS / "replay.json"))
    return p.parse_args(argv)


def _merge(path: Path, part: dict[str, Any]) -> None:
    """``part``'s keys into the JSON at ``path`` (the other parts' kept), atomically."""
    from pipeline.io import atomic_write_json, file_lock

    lock = Path(tempfile.gettempdir()) / f"flowcast-bench-{path.name}.lock"
    with file_lock(lock):                   # the parts may run side by side
        current = json.loads(path.read_text()) if path.is_file() else {}
        current.update(json.loads(json.dumps(part, default=str)))
        current["machine"] = f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}"
        current["python"] = sys.version.split()[0]
        atomic_write_json(path, current)


@contextmanager
def _prefect() -> Iterator[None]:
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    from flows.server_guard import start_temporary_server

    start_temporary_server()
    from flows.weekly_forecast import local_api

    with local_api():
        yield


def _replay(out: Path, releases: list[Any], preset: str, start: str | None, end: str | None,
            on_round: Callable[[dict[str, object]], None] | None = None,
            disease: str = "covid") -> dict[str, object]:
    import datetime as dt

    from flows.hub_forecast import flow_step
    from pipeline.hub_round import replay as rp
    from pipeline.hub_round.run import HubRunConfig

    run = HubRunConfig.of_preset(preset, disease=disease)
    config = rp.ReplayConfig(out, run, dt.date.fromisoformat(start) if start else None,
                             dt.date.fromisoformat(end) if end else None)
    rp.copy_hub_config(run.hub_config_dir(), out)
    return rp.replay(config, releases, flow_step(),
                     on_round)


def read_back(out: Path) -> int:
    """Rows of the replay's model-output folder as ``hubdata`` reads the hub at ``out``."""
    import hubdata

    return int(hubdata.connect_hub(out).get_dataset().to_table().num_rows)


def valid_files(out: Path, hub: Path) -> bool:
    """Every round file of the replay validated against the hub's tasks.json again."""
    from pipeline.outputs.hubverse_validation import load_tasks_config, validate_model_output

    tasks = load_tasks_config(hub / "hub-config" / "tasks.json")
    files = sorted((out / "model-output").rglob("*.csv"))
    for path in files:
        validate_model_output(path, tasks)
    return bool(files)


def skill(out: Path, hub: Path, model_id: str) -> dict[str, Any]:
    """The replayed files scored beside every team as bench/nhsn.py scores them."""
    from bench.nhsn import leaderboards, relative
    from pipeline.data.hub.team_forecasts import (quantile_table, read_excluded_locations,
                                                  read_hub_forecasts, read_model_output_dir,
                                                  read_target_data)
    from pipeline.evaluation.hub_leaderboard import score_quantile_forecasts
    from pipeline.panels.hub import HOSP_COVID

    exclusions = read_excluded_locations(hub / "excluded_locations.toml")
    truth = read_target_data(hub / "time-series.parquet", HOSP_COVID)
    teams = score_quantile_forecasts(quantile_table(read_hub_forecasts(
        hub / "hub-forecasts.parquet", targets=[HOSP_COVID])), truth.assign(target=HOSP_COVID))
    mine = read_model_output_dir(out, models=[model_id])
    ours = score_quantile_forecasts(quantile_table(mine[mine["target"] == HOSP_COVID]),
                                    truth.assign(target=HOSP_COVID))
    board = leaderboards(ours, teams, HOSP_COVID, exclusions)
    published = json.loads((RESULTS / "nhsn.json").read_text())["pairwise_relative_wis"]["all"]
    ranked = relative(board, model_id)
    return {"pairwise_relative_wis": ranked, "nhsn_json_published_all": published,
            "difference_all": None if ranked["all"] is None else ranked["all"] - published,
            "n_rounds_scored": int(ours["reference_date"].nunique()),
            "target": HOSP_COVID}


def run_full(args: argparse.Namespace, releases: list[Any], path: Path) -> None:
    import datetime as dt

    out = Path(args.work) / "full"
    if out.exists() and not args.resume:
        shutil.rmtree(out)
    started = time.perf_counter()
    from pipeline.hub_round.replay import wednesdays

    due = len(wednesdays(releases, *(dt.date.fromisoformat(d) if d else None
                                     for d in (args.start, args.end))))

    def partial(summary: dict[str, object]) -> None:
        _merge(path, {"full": {**_figures(summary), "partial": True,
                               "rounds_expected": due}})
        print(f"round {summary['rounds_due']}/{due} "
              f"({time.perf_counter() - started:.0f} s)", flush=True)

    with _prefect():
        summary = _replay(out, releases, args.preset, args.start, args.end, partial)
    from pipeline.outputs.hubverse_round import CDC_HUB_MODEL_ID

    figures = _figures(summary) | {
        "partial": False, "rounds_expected": due, "preset": args.preset,
        "hubdata_rows": read_back(out), "valid": valid_files(out, Path(args.hub)),
        "folder": str(out)}
    _merge(path, {"full": figures, **{k: figures[k] for k in (
        "rounds_due", "rounds_published", "rounds_failed", "degraded", "seconds")},
        "skill": skill(out, Path(args.hub), CDC_HUB_MODEL_ID)})


def run_warm(args: argparse.Namespace, releases: list[Any], path: Path) -> None:
    """The replay from a Wednesday mid-period, from an empty store and memo (module
    docstring)."""
    import datetime as dt

    from pipeline.hub_round.replay import wednesdays

    key = "warm" if args.disease == "covid" else f"warm_{args.disease}"
    out = Path(args.work) / key
    if out.exists():
        shutil.rmtree(out)
    start = args.start or WARM_FROM
    due = len(wednesdays(releases, dt.date.fromisoformat(start),
                         dt.date.fromisoformat(args.end) if args.end else None))
    started = time.perf_counter()

    def figures(summary: dict[str, object]) -> dict[str, object]:
        rounds = summary["rounds"]
        assert isinstance(rounds, list)
        return {**_figures(summary), "from": start, "preset": args.preset,
                "rounds_expected": due, "seconds_by_target": summary["seconds_by_target"],
                "rounds": [{k: r[k] for k in ("due", "state", "seconds", "target_seconds")}
                           for r in rounds]}

    def partial(summary: dict[str, object]) -> None:
        _merge(path, {key: {**figures(summary), "partial": True}})
        print(f"warm round {summary['rounds_due']}/{due} "
              f"({time.perf_counter() - started:.0f} s)", flush=True)

    with _prefect():
        summary = _replay(out, releases, args.preset, start, args.end, partial, args.disease)
    _merge(path, {key: {**figures(summary), "partial": False,
                           "valid": valid_files(out, Path(args.hub)), "folder": str(out)}})


def _figures(summary: dict[str, object]) -> dict[str, object]:
    return {k: summary[k] for k in ("rounds_due", "rounds_published", "rounds_failed",
                                    "degraded", "failed", "seconds")}


# ---------------------------------------------------------------------------- injected failures


def _raise(*args: object, **kwargs: object) -> Any:
    raise RuntimeError("injected failure")


def _nan_median(forecast: Callable[..., Any]) -> Callable[..., Any]:
    """A member's ``forecast`` with a NaN median: a numerical blow-up."""
    def broken(self: Any, cells: Any, horizons: tuple[int, ...], levels: Any) -> Any:
        import numpy as np

        from pipeline.members.base import MemberForecast

        count = forecast(self, cells, horizons, levels).count.copy()
        count[:, :, len(levels) // 2] = np.nan
        return MemberForecast(count)

    return broken


def _diverge(*args: object, **kwargs: object) -> Any:
    from pipeline.errors import TrainingDivergedError

    raise TrainingDivergedError("injected: validation NLL 30.64 is more than 10 nats above "
                                "the best")


def _revised(releases: list[Any], due: str) -> list[Any]:
    """The admissions release of ``due`` with California's settled weeks ×10."""
    import dataclasses
    import io

    import pandas as pd

    from pipeline.data.hub.nhsn_vintages import canonical_csv
    from pipeline.panels.hub import HOSP_COVID

    out = []
    for r in releases:
        if r.target == HOSP_COVID and str(r.as_of) == due:
            frame = pd.read_csv(io.BytesIO(r.payload), dtype={"location": str})
            weeks = pd.to_datetime(frame["target_end_date"])
            settled = (frame["location"] == "06") & (weeks < weeks.max() - pd.Timedelta(days=60))
            frame.loc[settled, "value"] = frame.loc[settled, "value"] * 10
            r = dataclasses.replace(r, payload=canonical_csv(frame))
        out.append(r)
    return out


def _stale(releases: list[Any], due: str) -> list[Any]:
    """The ED share's last five releases up to ``due`` withheld."""
    from pipeline.panels.hub import ED_COVID

    ed = sorted({r.as_of for r in releases if r.target == ED_COVID and str(r.as_of) <= due})
    gone = set(ed[-5:])
    return [r for r in releases if not (r.target == ED_COVID and r.as_of in gone)]


def run_injected(args: argparse.Namespace, releases: list[Any], path: Path) -> None:
    import pytest

    from pipeline.members.boosting import PooledBoostingMember
    from pipeline.members.nf import real
    from pipeline.members.nf.context import ContextFlowMember
    from pipeline.members.seasonal import SeasonalGrowthMember

    def nan_medians(mp: pytest.MonkeyPatch) -> None:
        for member in (PooledBoostingMember, SeasonalGrowthMember):
            mp.setattr(member, "forecast", _nan_median(member.forecast))

    cases: dict[str, tuple[Callable[[pytest.MonkeyPatch], None], list[Any]]] = {
        "member_raises": (lambda mp: mp.setattr(ContextFlowMember, "forecast", _raise),
                          releases),
        "member_nan": (nan_medians, releases),
        "refit_diverges": (lambda mp: mp.setattr(real, "stored_refit", _diverge), releases),
        "location_revised": (lambda mp: None, _revised(releases, INJECTED_DUE)),
        "target_stale": (lambda mp: None, _stale(releases, INJECTED_DUE)),
    }
    path_results = json.loads(path.read_text()).get("injected", {}) if path.is_file() else {}
    results: dict[str, Any] = dict(path_results)
    chosen = args.case or list(cases)
    with _prefect():
        for name, (inject, given) in ((n, cases[n]) for n in chosen):
            out = Path(args.work) / f"injected-{name}"
            if out.exists():
                shutil.rmtree(out)
            started = time.perf_counter()
            with pytest.MonkeyPatch.context() as mp:
                inject(mp)
                summary = _replay(out, given, "tiny", INJECTED_DUE, INJECTED_DUE)
            rounds = summary["rounds"]
            assert isinstance(rounds, list)
            last = rounds[-1]
            results[name] = {
                "published": last["state"] != "Failed", "state": last["state"],
                "valid": valid_files(out, Path(args.hub)) and read_back(out) > 0,
                "published_targets": list(last["published_targets"]),
                "dropped": list(last["dropped"]), "imported": [
                    line for line in last["imported"] if "held" in line or "refused" in line],
                "seconds": round(time.perf_counter() - started, 1)}
            print(f"injected {name}: {results[name]['state']}; dropped "
                  f"{[d['what'] + ' ' + d['name'] for d in results[name]['dropped']]}",
                  flush=True)
            _merge(path, {"injected": results})


def main(argv: list[str] | None = None) -> None:
    import pandas as pd

    from pipeline.hub_round.replay import releases_of_time_series

    args = _parse(argv)
    path = Path(args.out)
    releases = releases_of_time_series(pd.read_parquet(Path(args.hub) / "time-series.parquet"),
                                       args.disease)
    command = "python -m bench.replay " + " ".join(argv if argv is not None else sys.argv[1:])
    suffix = "" if args.disease == "covid" else f"_{args.disease}"
    _merge(path, {f"command_{args.part}{suffix}": command})
    if args.part in ("injected", "all"):
        run_injected(args, releases, path)
    if args.part in ("refits", "all"):
        from bench.refits import run_refits

        _merge(path, {"refits": run_refits()})
    if args.part in ("full", "all"):
        run_full(args, releases, path)
    if args.part in ("warm", "all"):
        run_warm(args, releases, path)
    print(f"→ {path}")


if __name__ == "__main__":
    main()
