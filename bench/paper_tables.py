"""Reproduce the paper's Tables 1–4 (mean KL divergences) beside the paper's numbers.

    .venv/bin/python -m bench.paper_tables --quick      # tiny sizes, a minute or two
    .venv/bin/python -m bench.paper_tables              # full run (trains 19 models; serial)
    .venv/bin/python -m bench.paper_tables --jobs 2 --vehicle-train-budget-s 600
                                                        # train missing models 2 at a time first

Writes ``bench/results/paper_tables.json`` (``cells``: every cell of Tables 1–4 as
{"table", "row", "col", "paper", "ours", "floor", "ess_median"}, plus ``protocol`` and ``kl_floor``),
``bench/results/paper_tables.md`` (the same, rendered), and confidence-region figures under
``bench/results/figures/``. Trained checkpoints are cached under ``bench/work/`` (git-ignored),
keyed by model and training budget: a re-run with the same budgets loads them instead of
training. ``flowcast reproduce tables`` runs the same code (:mod:`pipeline.paper`, whose
``config.PROTOCOL`` states the protocol; docs/estimation.md, "Reference posteriors").
"""
from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

from pipeline.paper import BenchConfig, Locations, pretrain, run
from pipeline.paper.config import MIN_REFERENCE_ESS

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes (pipeline check)")
    parser.add_argument("--train-budget-s", type=float, default=None,
                        help="wall-clock cap per trained SIR model (default 200 s; quick 10 s)")
    parser.add_argument("--vehicle-train-budget-s", type=float, default=None,
                        help="cap for the vehicle models (Tables 1-2; default 360 s)")
    parser.add_argument("--jobs", type=int, default=2,
                        help="train missing models this many at a time first (default 2)")
    parser.add_argument("--threads-per-job", type=int, default=1,
                        help="torch threads of each --jobs process")
    parser.add_argument("--pretrain-only", choices=("vehicle", "sir", "all"), default=None,
                        help="only train the missing models of these tables, then stop")
    args = parser.parse_args()
    cfg = BenchConfig.quick_config() if args.quick else BenchConfig()
    if args.train_budget_s is not None:
        cfg = dataclasses.replace(cfg, train_budget_s=args.train_budget_s)
    if args.vehicle_train_budget_s is not None:
        cfg = dataclasses.replace(cfg, vehicle_train_budget_s=args.vehicle_train_budget_s)
    locations = Locations.under(ROOT)
    if args.pretrain_only is not None:
        systems = ("vehicle", "sir") if args.pretrain_only == "all" else (args.pretrain_only,)
        pretrain(cfg, locations, max(1, args.jobs), args.threads_per_job, systems)
        return
    if args.jobs > 1:
        pretrain(cfg, locations, args.jobs, args.threads_per_job)
    result = run(cfg, locations)
    print(f"{len(result['cells'])} cells, {result['cells_at_or_below_paper']} at or below the "
          f"paper; {result['seconds']:.0f} s", flush=True)
    missing = [f"{c['table']} / {c['row']} / {c['col']}" for c in result["cells"]
               if not math.isfinite(c["ours"])]
    if missing:
        raise SystemExit(f"no usable windows (reference ESS < {MIN_REFERENCE_ESS}) for {missing}")


if __name__ == "__main__":
    main()
