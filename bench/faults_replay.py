"""Faults of the replay's input (issue 49, item 6): ``flowcast replay`` (and ``forecast --hub``)
judge their input before any work, as ``flowcast data import`` does.

Each command case runs the real command (typer's runner, in process) with ``--out`` holding a
good earlier replay (its ``replay.json`` and a round file) and ``FLOWCAST_DATA_DIR`` a filled
cache; it must end in one named error line (no traceback) naming the problem, before anything is
written: ``--out``, the cache and the ``--out`` file keep every byte ("bytes lost" must be 0),
and no ``releases/`` folder appears. Cases: ``--source`` without ``observation`` or ``target``;
``--out`` naming a file; a parquet of 10 million rows (a few hundred KB: refused from its
metadata, unread); a source with no release of the disease's targets (an unknown target;
``--hub rsv`` on COVID-19 rows: the targets found and those expected named); ``--from
2025-13-45``; a deeply nested ``tasks.json`` and a 300 MB one (sparse: refused from its size,
unread), for the replay and for ``forecast --hub``.

The library case: two replays of different Wednesdays into one folder at once (one round
failing): ``replay.json`` must hold both rounds, one published and one failed.

``python -m bench.faults_replay`` runs these cases alone and merges them into
``bench/results/faults.json`` (source ``replay``), keeping every other case there.
"""
from __future__ import annotations

import multiprocessing
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from bench.faults import CaseResult, bytes_lost, cache_bytes, show
from bench.faults_nhsn import NHSN

if TYPE_CHECKING:
    from pipeline.hub_round.replay import RoundStep
    from pipeline.hub_round.run import HubRunConfig

ISSUE = 49
SOURCE = "replay"
TEN_MILLION = 10_000_000


@dataclass(frozen=True)
class ReplayFault:
    """A command (``args``: the scratch folder → its arguments after ``flowcast``) that must
    fail with ``expect`` in its one error line, writing nothing."""

    name: str
    args: Callable[[Path], list[str]]
    expect: tuple[str, ...]
    env: dict[str, str] = field(default_factory=dict)


def _series() -> pd.DataFrame:
    return pd.read_parquet(NHSN / "time-series.parquet")


def _parquet(tmp: Path, name: str, frame: pd.DataFrame) -> Path:
    path = tmp / name
    frame.to_parquet(path)
    return path


def _without(column: str) -> Callable[[Path], Path]:
    return lambda tmp: _parquet(tmp, f"no-{column}.parquet", _series().drop(columns=column))


def ten_million_rows(tmp: Path) -> Path:
    """A parquet of 10 million rows of one repeated COVID-19 row: a few hundred KB on disk
    (dictionary and run-length encoded), gigabytes once read whole."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    row = _series().iloc[-1]
    table = pa.table({
        "target_end_date": pa.repeat(pa.scalar(str(row["target_end_date"])), TEN_MILLION),
        "location": pa.repeat(pa.scalar(str(row["location"])), TEN_MILLION),
        "observation": pa.repeat(pa.scalar(float(row["observation"])), TEN_MILLION),
        "as_of": pa.repeat(pa.scalar(str(row["as_of"])), TEN_MILLION),
        "target": pa.repeat(pa.scalar(str(row["target"])), TEN_MILLION)})
    path = tmp / "ten-million.parquet"
    pq.write_table(table, path, compression="zstd")
    return path


def _unknown_target(tmp: Path) -> Path:
    return _parquet(tmp, "unknown-target.parquet", _series().assign(target="wk inc foo hosp"))


def _hub_config(tmp: Path, name: str, write: Callable[[Path], None]) -> Path:
    folder = tmp / name
    folder.mkdir(exist_ok=True)
    write(folder / "tasks.json")
    return folder


def deeply_nested(tmp: Path) -> Path:
    def write(path: Path) -> None:
        path.write_text('{"rounds": ' + "[" * 100_000 + "]" * 100_000 + "}")
    return _hub_config(tmp, "nested", write)


def three_hundred_mb(tmp: Path) -> Path:
    """A 300 MB tasks.json without writing 300 MB: a sparse file of that size."""
    def write(path: Path) -> None:
        with open(path, "wb") as handle:
            handle.write(b'{"rounds": [')
            handle.truncate(300 << 20)
    return _hub_config(tmp, "huge", write)


def _out_file(tmp: Path) -> Path:
    path = tmp / "replay-output.txt"
    path.write_text("a file, not the replay's folder\n")
    return path


def replay_faults() -> list[ReplayFault]:
    real = str(NHSN / "time-series.parquet")

    def replay(tmp: Path, *more: str) -> list[str]:
        return ["replay", "--out", str(tmp / "out"), "--preset", "tiny", *more]

    return [
        ReplayFault("replay-source-without-observation",
                    lambda t: replay(t, "--source", str(_without("observation")(t))),
                    ("missing column(s) ['observation']",)),
        ReplayFault("replay-source-without-target",
                    lambda t: replay(t, "--source", str(_without("target")(t))),
                    ("missing column(s) ['target']",)),
        ReplayFault("replay-out-names-a-file",
                    lambda t: ["replay", "--out", str(_out_file(t)), "--source", real],
                    ("is a file; --out names a directory",)),
        ReplayFault("replay-source-of-ten-million-rows",
                    lambda t: replay(t, "--source", str(ten_million_rows(t))),
                    ("10,000,000 rows", "refused unread")),
        ReplayFault("replay-source-of-an-unknown-target",
                    lambda t: replay(t, "--source", str(_unknown_target(t))),
                    ("targets found: wk inc foo hosp", "wk inc covid hosp")),
        ReplayFault("replay-rsv-on-covid-rows",
                    lambda t: replay(t, "--hub", "rsv", "--source", real),
                    ("wk inc rsv hosp", "targets found: wk inc covid hosp")),
        ReplayFault("replay-from-is-not-a-date",
                    lambda t: replay(t, "--from", "2025-13-45", "--source", real),
                    ("--from '2025-13-45': not a date",)),
        ReplayFault("replay-tasks-json-deeply-nested",
                    lambda t: replay(t, "--source", real, "--hub-config", str(deeply_nested(t))),
                    ("nested 100001 levels deep",)),
        ReplayFault("replay-tasks-json-of-300-mb",
                    lambda t: replay(t, "--source", real,
                                     "--hub-config", str(three_hundred_mb(t))),
                    ("more than 4,194,304 bytes", "refused unread")),
        ReplayFault("forecast-hub-tasks-json-deeply-nested",
                    lambda t: ["forecast", "--hub", "covid", "--data-source", "cache",
                               "--output-dir", str(t / "out"),
                               "--hub-config", str(deeply_nested(t))],
                    ("nested 100001 levels deep",)),
    ]


def _good_replay(out: Path) -> None:
    """An earlier replay's outputs in ``out``: what a faulted rerun must not touch."""
    (out / "model-output" / "flowcast-nfhub").mkdir(parents=True)
    (out / "model-output" / "flowcast-nfhub" / "2025-09-27-flowcast-nfhub.csv").write_text(
        "reference_date,target,horizon,location,target_end_date,output_type,output_type_id,"
        "value\n")
    (out / "replay.json").write_text('{"rounds_due": 1, "rounds_published": 1}\n')


def run_replay_fault(fault: ReplayFault, tmp: Path) -> CaseResult:
    """The command in process against a good earlier replay and a filled cache (module doc)."""
    from typer.testing import CliRunner

    import flows.cli  # noqa: F401 - registers `forecast` and `replay`
    from pipeline.cli import app, build_command

    build_command()
    tmp.mkdir(parents=True, exist_ok=True)
    data = tmp / "data"
    data.mkdir()
    (data / "nhsn").mkdir()
    (data / "nhsn" / "kept.csv").write_text("date,location,value\n2025-09-20,US,1\n")
    out = tmp / "out"
    _good_replay(out)
    args = fault.args(tmp)
    watched = {"out": cache_bytes(out), "data": cache_bytes(data)}
    files = {p: p.read_bytes() for p in tmp.iterdir() if p.is_file()
             and p.stat().st_size < 1 << 20}
    started = time.monotonic()
    result = CliRunner().invoke(app, args, prog_name="flowcast",
                                env={"FLOWCAST_DATA_DIR": str(data), "COLUMNS": "300",
                                     "NO_COLOR": "1", **fault.env})
    seconds = time.monotonic() - started
    lost = (bytes_lost(watched["out"], cache_bytes(out))
            + bytes_lost(watched["data"], cache_bytes(data))
            + sum(len(b) for p, b in files.items() if not p.is_file() or p.read_bytes() != b))
    output = " ".join(result.output.split())
    clean = result.exception is None or isinstance(result.exception, SystemExit)
    lines = [line for line in result.output.splitlines() if line.strip()]
    passed = (clean and result.exit_code == 1 and len(lines) == 1
              and lines[0].startswith("error: ") and "Traceback" not in result.output
              and all(e in output for e in fault.expect) and lost == 0
              and not (out / "releases").exists())
    note = output[-300:] if clean else f"raised {result.exception!r}"
    return CaseResult(fault.name, passed, seconds, lost, note, source=SOURCE, issue=ISSUE)


# ---------------------------------------------------------------- two replays into one folder


def _step_of(failing: str) -> RoundStep:
    """A round step that takes a second (so the two replays overlap) and fails on ``failing``."""
    from pipeline.hub_round.replay import RoundOutcome

    def step(config: HubRunConfig) -> RoundOutcome:
        due = str(config.due)
        time.sleep(1.0)
        if due == failing:
            raise RuntimeError(f"the round due {due} failed (injected)")
        return RoundOutcome(due, "Completed")
    return step


def _replay_one(out: str, due: str, failing: str) -> None:
    import datetime as dt

    from pipeline.hub_round.replay import ReplayConfig, releases_of_time_series, replay

    day = dt.date.fromisoformat(due)
    releases = [r for r in releases_of_time_series(_series(), "covid") if r.as_of <= day]
    replay(ReplayConfig(Path(out), start=day, end=day), releases, _step_of(failing))


def concurrent_replays(tmp: Path) -> CaseResult:
    """Two replays of different Wednesdays into one folder at once, one round failing."""
    import json

    from pipeline.hub_round.replay import releases_of_time_series, wednesdays

    days = [str(d) for d in wednesdays(releases_of_time_series(_series(), "covid"))[:2]]
    out = tmp / "out"
    started = time.monotonic()
    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_replay_one, args=(str(out), due, days[1]))
               for due in days]
    for w in workers:
        w.start()
    for w in workers:
        w.join(300)
    summary = json.loads((out / "replay.json").read_text())
    dues = sorted(r["due"] for r in summary["rounds"])
    passed = (dues == days and summary["rounds_published"] == 1
              and summary["rounds_failed"] == 1 and summary["failed"][0]["due"] == days[1])
    note = (f"replay.json: rounds {dues}, {summary['rounds_published']} published, "
            f"{summary['rounds_failed']} failed ({days[1]}: "
            f"{summary['failed'][0]['message'] if summary['failed'] else 'none'})")
    return CaseResult("replay-two-wednesdays-into-one-folder-at-once", passed,
                      time.monotonic() - started, 0, note, source=SOURCE, issue=ISSUE)


def run_all(scratch: Path) -> list[CaseResult]:
    results = [show(run_replay_fault(f, scratch / f"replay-{k}"))
               for k, f in enumerate(replay_faults())]
    (scratch / "concurrent").mkdir()
    return [*results, show(concurrent_replays(scratch / "concurrent"))]


def merge_into_catalogue(results: list[CaseResult], seconds: float) -> dict[str, object]:
    """``results`` in ``bench/results/faults.json`` in place of its earlier replay cases; the
    totals recomputed over every case, the other cases kept as they are."""
    import json
    from dataclasses import asdict

    from bench.faults import RESULT_PATH, _totals
    from pipeline.io import atomic_write_json

    summary = json.loads(RESULT_PATH.read_text())
    cases = [c for c in summary["cases"] if c.get("source") != SOURCE]
    cases += [asdict(r) for r in results]
    every = [CaseResult(**c) for c in cases]
    summary.update(_totals(every))
    summary["by_source"] = {s: _totals([r for r in every if r.source == s])
                            for s in sorted({r.source for r in every})}
    summary["by_issue"] = {str(i): _totals([r for r in every if r.issue == i])
                           for i in sorted({r.issue for r in every})}
    summary["cases"] = cases
    summary.setdefault("parts", {})[SOURCE] = {
        "command": "python -m bench.faults_replay", "date": time.strftime("%Y-%m-%d"),
        "seconds": round(seconds, 1), **_totals(results)}
    atomic_write_json(RESULT_PATH, summary)
    return summary


def main() -> int:
    import logging

    logging.basicConfig(level=logging.ERROR)
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="flowcast-faults-replay-") as tmp:
        results = run_all(Path(tmp))
    merge_into_catalogue(results, time.monotonic() - started)
    totals = {"passed": sum(r.passed for r in results), "lost": sum(r.bytes_lost for r in results)}
    print(f"replay cases {len(results)}, passed {totals['passed']}, bytes lost {totals['lost']}")
    return 0 if totals["passed"] == len(results) else 1


if __name__ == "__main__":
    sys.exit(main())
