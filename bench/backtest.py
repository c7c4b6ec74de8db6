"""Rolling-origin backtest over the San Francisco S/I/R series → bench/results/backtest.json.

NF rollout (the weekly flow's forward model) against the persistence baseline and the plain
bootstrap particle filter, scored by WIS at 1–4 weeks on the 23 hub quantiles; relative WIS
= Σ WIS(NF) / Σ WIS(baseline) over the same forecasts (< 1: the NF is better).

    python -m bench.backtest            # default forecast preset, all weekly origins
    python -m bench.backtest --quick    # tiny model, last 4 origins, few samples (seconds)

``--quick`` writes bench/results/backtest-quick.json so it never overwrites the full result.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
SHARED_DATASF = Path(__file__).resolve().parents[2] / "shared" / "data" / "datasf"


def _parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run in seconds")
    p.add_argument("--preset", default=None, help="forecast preset (default: 'default', "
                                                  "'tiny' with --quick)")
    p.add_argument("--data", default=str(SHARED_DATASF), help="DataSF CSV exports directory")
    p.add_argument("--max-origins", type=int, default=None, help="keep the latest N origins")
    p.add_argument("--samples", type=int, default=None, help="sample paths per forecast")
    p.add_argument("--smc-particles", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="output JSON path")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = _parse(argv)
    os.environ.setdefault("FLOWCAST_DATA_DIR", str(RESULTS.parent / "work" / "backtest-data"))
    import torch

    torch.set_num_threads(min(2, os.cpu_count() or 1))
    from pipeline import forecast as fc
    from pipeline.backtest import (BacktestConfig, PersistenceForecaster, relative_wis,
                                   run_backtest, summarize, summary_by_horizon)
    from pipeline.forecasters import NFRolloutForecaster, SMCForecaster
    from pipeline.io import atomic_write_json

    preset = args.preset or ("tiny" if args.quick else "default")
    base = fc.resolve_config(preset)
    config = fc.resolve_config(preset, seed=args.seed, data=dataclasses.replace(
        base.data, kind="import", import_paths=(args.data,)))
    samples = args.samples or (50 if args.quick else 200)
    particles = args.smc_particles or (300 if args.quick else 2000)
    max_origins = args.max_origins if args.max_origins is not None else (4 if args.quick else None)

    t0 = time.perf_counter()
    series = fc.load_series(config)
    sir = fc.series_to_sir(series).frame
    data = fc.simulate_training_data(config)
    models = fc.train_or_reuse_models(config, data,
                                      store_root=RESULTS.parent / "work" / "backtest-models")
    t_model = time.perf_counter() - t0

    forecasters = [PersistenceForecaster(), SMCForecaster(n_particles=particles),
                   NFRolloutForecaster(estimator=models.forward)]
    bt_config = BacktestConfig(n_samples=samples, max_origins=max_origins, seed=args.seed)
    t1 = time.perf_counter()
    result = run_backtest(sir, forecasters, bt_config)
    t_backtest = time.perf_counter() - t1

    s = result.scores
    nf = "nf-rollout"
    summary = summarize(result)
    by_h = summary_by_horizon(result)
    per_compartment = {c: {"persistence": relative_wis(s[s["compartment"] == c], nf,
                                                       "persistence"),
                           "smc": relative_wis(s[s["compartment"] == c], nf, "smc")}
                       for c in ("S", "I", "R")}
    out = {
        "relative_wis": {"persistence": relative_wis(s, nf, "persistence"),
                         "smc": relative_wis(s, nf, "smc")},
        "relative_wis_by_compartment": per_compartment,
        "coverage": {name: {"50": float(row["coverage_50"]), "90": float(row["coverage_90"])}
                     for name, row in summary.iterrows()},
        "mean_wis": {name: float(row["mean_wis"]) for name, row in summary.iterrows()},
        "by_horizon": by_h.to_dict(orient="records"),
        "n_origins": int(s["origin"].nunique()),
        "origins": [str(s["origin"].min().date()), str(s["origin"].max().date())],
        "n_samples": samples, "smc_particles": particles, "preset": preset,
        "model_key": models.key, "model_reused": models.reused, "encoder": models.encoder,
        "seconds": {"model": round(t_model, 2), "backtest": round(t_backtest, 2)},
        "quick": args.quick, "machine": f"{platform.machine()}, {os.cpu_count()} CPUs",
        "python": sys.version.split()[0],
    }
    path = Path(args.out) if args.out else RESULTS / ("backtest-quick.json" if args.quick
                                                      else "backtest.json")
    atomic_write_json(path, out)
    print(f"relative WIS (NF vs baseline): {out['relative_wis']}  coverage: {out['coverage']}")
    print(f"{out['n_origins']} origins, backtest {t_backtest:.1f} s → {path}")
    return out


if __name__ == "__main__":
    main()
