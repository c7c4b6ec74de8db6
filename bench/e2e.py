"""End-to-end wall-clock of one weekly run: from scratch (empty model store) and with a cached model.

    python -m bench.e2e            # default preset (targets: scratch <= 10 min, cached <= 30 s)
    python -m bench.e2e --quick    # tiny preset, seconds; writes bench/results/e2e-quick.json
    python -m bench.e2e --data-dir /tmp/e2e-data   # keep the data and the trained models there

What is measured, exactly (both in one fresh temporary FLOWCAST_DATA_DIR):

0. (untimed) the recorded DataSF exports and the six CDPH county vintages are imported into the
   data cache, as ``make forecast`` does, so both runs read the same data offline (the pooled
   members, the nowcast's delay model and the county skill included) and network time is never
   measured;
1. ``scratch_seconds``: one weekly run, ``python -m flows.weekly_forecast --data-source cache``,
   with an *empty model store* — it simulates the synthetic ensemble and trains both models;
2. ``cached_seconds``: the same command again — it finds the trained pair in the model store.

Each run is a fresh process, as a user or a served deployment runs it: the wall-clock includes
the Python/torch imports and the start of Prefect's ephemeral API, not only the flow body
(each run's ``results.json`` records the seconds of every step of ``run_forecast``, under
``seconds``). The runs must report
``model_reused`` False then True, else the benchmark fails.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
DATASF = ROOT.parent / "shared" / "data" / "datasf"
CDPH = ROOT.parent / "shared" / "data" / "cdph"
TARGETS = {"cached_seconds": 30, "scratch_seconds": 600}


def _env(data_dir: Path) -> dict[str, str]:
    env = dict(os.environ, FLOWCAST_DATA_DIR=str(data_dir),
               PREFECT_SERVER_ANALYTICS_ENABLED="false", DO_NOT_TRACK="1",
               OMP_WAIT_POLICY="PASSIVE")
    # Under load the ephemeral API can take longer than Prefect's default 20 s to come up.
    env.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
    return env


def _import_data(datasf: str, cdph: str, env: dict[str, str]) -> None:
    code = ("import sys; from pipeline.forecast.sources import import_exports; "
            "import_exports(sys.argv[1:])")
    subprocess.run([sys.executable, "-c", code, datasf], env=env, cwd=ROOT, check=True,
                   stdout=subprocess.DEVNULL)
    if Path(cdph).is_dir():     # as `make forecast` imports them (reviewed revisions accepted)
        code = ("import sys; from pipeline.data.california.cdph import find_vintage_files; "
                "from pipeline.data.california.cdph_source import import_cdph_exports; "
                "import_cdph_exports(find_vintage_files(sys.argv[1]), if_empty=True, "
                "accept_revisions=True)")
        subprocess.run([sys.executable, "-c", code, cdph], env=env, cwd=ROOT, check=True,
                       stdout=subprocess.DEVNULL)


def _live_attempt(env: dict[str, str]) -> dict[str, object]:
    """Seconds ``load_series`` spends on a live DataSF fetch in a fresh process, and whether it
    fell back to the cache (on a machine that cannot reach DataSF: how fast the run learns it)."""
    code = ("import json, time; from pipeline import forecast as fc; "
            "from pipeline.forecast.sources import load_series; t = time.perf_counter(); "
            "s = load_series(fc.DataSourceConfig(kind='live')); "
            "print(json.dumps({'seconds': round(time.perf_counter() - t, 3), "
            "'fell_back_to_cache': all(p.from_cache for p in s.provenance.datasets)}))")
    done = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, check=True,
                          capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _weekly_run(preset: str, out_dir: Path, env: dict[str, str], log: Path) -> tuple[float, dict]:
    """Wall-clock of one ``python -m flows.weekly_forecast`` process and its results.json."""
    cmd = [sys.executable, "-m", "flows.weekly_forecast", "--preset", preset,
           "--data-source", "cache", "--output-dir", str(out_dir)]
    start = time.perf_counter()
    with log.open("wb") as handle:
        proc = subprocess.run(cmd, env=env, cwd=ROOT, stdout=handle, stderr=subprocess.STDOUT)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"weekly run failed (exit {proc.returncode}); log:\n"
                         f"{log.read_text(errors='replace')[-4000:]}")
    index = json.loads((out_dir / "index.json").read_text())
    latest = out_dir / index["runs"][0]["reference_date"]
    results = json.loads((latest / "results.json").read_text())
    return seconds, results


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny preset (smoke test)")
    parser.add_argument("--preset", default=None, help="forecast preset (default: 'default', "
                                                       "'tiny' with --quick)")
    parser.add_argument("--datasf", default=str(DATASF), help="folder of DataSF CSV exports")
    parser.add_argument("--cdph", default=str(CDPH), help="folder of CDPH county downloads")
    parser.add_argument("--out", default=None, help="output JSON path")
    parser.add_argument("--data-dir", default=None,
                        help="keep the data cache and model store here (must hold no models "
                             "yet); default: a temporary directory, deleted afterwards")
    args = parser.parse_args(argv)
    preset = args.preset or ("tiny" if args.quick else "default")
    out = Path(args.out) if args.out else RESULTS / ("e2e-quick.json" if args.quick
                                                     else "e2e.json")
    with tempfile.TemporaryDirectory(prefix="flowcast-e2e-") as tmp:
        data_dir = Path(args.data_dir) if args.data_dir else Path(tmp) / "data"
        if (data_dir / "models").exists() and any((data_dir / "models").iterdir()):
            raise SystemExit(f"{data_dir}/models is not empty: the scratch run needs an empty "
                             "model store")
        env = _env(data_dir)
        _import_data(args.datasf, args.cdph, env)
        live = _live_attempt(env)
        print(f"live DataSF attempt: {live}", flush=True)
        timings: dict[str, float] = {}
        step_timings: dict[str, dict[str, float]] = {}
        for label, reused in (("scratch", False), ("cached", True)):
            reports = Path(tmp) / f"reports-{label}"
            log = Path(tmp) / f"{label}.log"
            seconds, results = _weekly_run(preset, reports, env, log)
            if results["model_reused"] is not reused:
                raise SystemExit(f"{label} run: model_reused={results['model_reused']}, "
                                 f"expected {reused}")
            timings[label], step_timings[label] = seconds, results["seconds"]
            steps = sum(step_timings[label].values())
            print(f"{label}: {seconds:.1f} s (steps {steps:.1f} s; model "
                  f"{'reused' if reused else 'trained'})", flush=True)
    payload = {"preset": preset,
               "cached_seconds": round(timings["cached"], 2),
               "scratch_seconds": round(timings["scratch"], 2),
               "step_seconds": step_timings,
               "datasf_live_attempt": live,
               "load_average_at_end": os.getloadavg(),
               "targets": TARGETS,
               "within_targets": {k: timings[k.split("_")[0]] <= v for k, v in TARGETS.items()},
               "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                           "python": platform.python_version()},
               "quick": args.quick,
               "note": "wall-clock of `python -m flows.weekly_forecast --data-source cache` as a "
                       "fresh process (imports + Prefect ephemeral API start-up included); data "
                       "imported beforehand from recorded DataSF exports and CDPH vintages (no "
                       "network); scratch = "
                       "empty model store, cached = the model it trained"}
    from pipeline.io import atomic_write_json

    atomic_write_json(out, payload)
    print(json.dumps(payload, indent=2))
    return payload


if __name__ == "__main__":
    main()
