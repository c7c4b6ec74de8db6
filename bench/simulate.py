"""Benchmark: generate the paper-scale simulated data and report time and peak memory.

    python -m bench.simulate            # full scale -> bench/results/simulate.json
    python -m bench.simulate --quick    # tiny sizes -> bench/results/simulate-quick.json

Stages (each timed with ``time.perf_counter``, run once, in this order in one process):

1. SIR ``sir-multi``: 500 trajectories x 1001 days x 3 = 1,501,500 observed values (RK4, float64),
   then its forward windowed dataset (R = 5, target = state).
2. Vehicle ``vehicle-dropout``: 100,000 trajectories x 151 states, each kept with p = 0.1
   (~1.51 million kept points), then its forward windowed dataset.

``sir_multi_seconds`` / ``vehicle_dropout_seconds`` are simulation + windowing (the time to
produce the training set); the parts are reported beside them. ``peak_rss_mb`` is the process's
peak resident set size (``getrusage`` ``ru_maxrss``), which includes the interpreter and torch.
"""
from __future__ import annotations

import argparse
import gc
import os
import platform
import resource
import sys
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, TypeVar

import psutil
import torch

import pipeline
from pipeline.training.datasets import windows_from_sir, windows_from_vehicle
from pipeline.io import atomic_write_json
from pipeline.systems.sir import simulate_ensemble
from pipeline.systems.vehicle import simulate_vehicle

RESULTS = Path(__file__).resolve().parent / "results"
QUICK_SIR_TRAJECTORIES = 10
QUICK_VEHICLE_TRAJECTORIES = 1_000
T = TypeVar("T")


def timed(work: Callable[[], T]) -> tuple[T, float]:
    started = time.perf_counter()
    result = work()
    return result, time.perf_counter() - started


def peak_rss_mb() -> float:
    # Linux reports ru_maxrss in KiB (macOS in bytes).
    scale = 1.0 / 1024 if sys.platform != "darwin" else 1.0 / (1024 * 1024)
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def current_rss_mb() -> float:
    return psutil.Process().memory_info().rss / (1024 * 1024)


def machine_info() -> dict[str, Any]:
    cpu_model = platform.processor()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            cpu_model = next((line.split(":", 1)[1].strip() for line in handle
                              if line.startswith("model name")), cpu_model)
    except OSError:
        pass
    return {"platform": platform.platform(), "python": platform.python_version(),
            "torch": torch.__version__, "flowcast": pipeline.__version__,
            "cpu_model": cpu_model, "cpu_count": os.cpu_count(),
            "memory_gb": round(psutil.virtual_memory().total / 1024**3, 1),
            "torch_threads": torch.get_num_threads()}


def run(quick: bool, seed: int) -> dict[str, Any]:
    results: dict[str, Any] = {"rss_after_imports_mb": round(current_rss_mb(), 1)}
    sir_n = QUICK_SIR_TRAJECTORIES if quick else None
    ensemble, sir_sim = timed(lambda: simulate_ensemble("sir-multi", n_trajectories=sir_n,
                                                        seed=seed))
    sir_ds, sir_win = timed(lambda: windows_from_sir(ensemble, "forward", "state"))
    results.update(sir_multi_points=ensemble.n_observed_values,
                   sir_multi_trajectories=ensemble.n_trajectories,
                   sir_multi_windows=len(sir_ds),
                   sir_multi_simulate_seconds=round(sir_sim, 4),
                   sir_multi_windows_seconds=round(sir_win, 4),
                   sir_multi_seconds=round(sir_sim + sir_win, 4))
    del ensemble, sir_ds
    gc.collect()

    vehicle_n = QUICK_VEHICLE_TRAJECTORIES if quick else None
    vehicles, veh_sim = timed(lambda: simulate_vehicle("vehicle-dropout", n=vehicle_n, seed=seed))
    veh_ds, veh_win = timed(lambda: windows_from_vehicle(vehicles, "forward", "state"))
    results.update(vehicle_dropout_points=vehicles.n_points,
                   vehicle_dropout_trajectories=vehicles.n_trajectories,
                   vehicle_dropout_windows=len(veh_ds),
                   vehicle_dropout_simulate_seconds=round(veh_sim, 4),
                   vehicle_dropout_windows_seconds=round(veh_win, 4),
                   vehicle_dropout_seconds=round(veh_sim + veh_win, 4))
    results["peak_rss_mb"] = round(peak_rss_mb(), 1)
    return results


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes (a smoke check)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads (default: torch's default for this machine)")
    parser.add_argument("--out", type=Path, default=None,
                        help="result file (default: bench/results/simulate.json, "
                             "or simulate-quick.json with --quick)")
    args = parser.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    out = args.out or RESULTS / ("simulate-quick.json" if args.quick else "simulate.json")
    record = {"benchmark": "simulate", "quick": args.quick, "seed": args.seed,
              "command": " ".join([Path(sys.executable).name, "-m", "bench.simulate",
                                   *(argv if argv is not None else sys.argv[1:])]),
              "started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "machine": machine_info()}
    record.update(run(args.quick, args.seed))
    atomic_write_json(out, record)
    for key in ("sir_multi_points", "sir_multi_seconds", "vehicle_dropout_points",
                "vehicle_dropout_seconds", "peak_rss_mb"):
        print(f"{key:>24}: {record[key]}")
    print(f"{'written':>24}: {out}")
    return record


if __name__ == "__main__":
    main()
