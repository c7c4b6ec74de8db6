"""Rolling-origin backtest over the San Francisco S/I/R series → bench/results/backtest.json.

NF rollout (the weekly flow's forward model) against the persistence baseline and the plain
bootstrap particle filter, scored by WIS at 1–4 weeks on the 23 hub quantiles; relative WIS
= Σ WIS(NF) / Σ WIS(baseline) over the same forecasts (< 1: the NF is better). The forecast
step itself is :func:`pipeline.forecast.backtest` — the same code the weekly report uses — here
over every weekly origin (``--max-origins`` to cap it) instead of the flow's latest few.

The model is the weekly flow's: it is looked up in the flow's model store
(``$FLOWCAST_DATA_DIR/models``, key = training config + training-data hash), so after a weekly run
on the same preset and seed the bench does not retrain. Only when no such model exists is it
trained (and stored, so the next weekly run reuses it). ``model_reused`` in the JSON says which.

    python -m bench.backtest            # default forecast preset, all weekly origins
    python -m bench.backtest --quick    # tiny model, last 3 origins, few samples (seconds)

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
    p.add_argument("--max-origins", type=int, default=None,
                   help="keep the latest N weekly origins (default: all; 3 with --quick)")
    p.add_argument("--samples", type=int, default=None, help="sample paths per forecast")
    p.add_argument("--smc-particles", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="output JSON path")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = _parse(argv)
    import torch

    torch.set_num_threads(min(2, os.cpu_count() or 1))
    from pipeline import forecast as fc
    from pipeline.backtest import summarize, summary_by_horizon
    from pipeline.io import atomic_write_json

    preset = args.preset or ("tiny" if args.quick else "default")
    samples = args.samples or (40 if args.quick else 200)
    particles = args.smc_particles or (300 if args.quick else 2000)
    max_origins = args.max_origins if args.max_origins is not None else (3 if args.quick else
                                                                         10_000)
    base = fc.resolve_config(preset)
    # cache first (the weekly flow's data); import the exports only into an empty cache
    config = fc.resolve_config(preset, seed=args.seed, backtest_origins=max_origins,
                               backtest_paths=samples, backtest_smc_particles=particles,
                               data=dataclasses.replace(base.data, kind="cache"))

    t0 = time.perf_counter()
    fc.import_exports([args.data], if_empty=True)
    series = fc.load_series(config)
    sir = fc.series_to_sir(series).frame
    data = fc.simulate_training_data(config)
    models = fc.train_or_reuse_models(config, data)   # the weekly flow's model store
    t_model = time.perf_counter() - t0
    print(f"model {models.key[:12]}… {'reused from the model store' if models.reused else 'trained'}"
          f" ({t_model:.1f} s)", flush=True)

    t1 = time.perf_counter()
    result = fc.backtest(models, sir, config)
    t_backtest = time.perf_counter() - t1

    summary = fc.backtest_summary(result)
    out = {
        **summary,
        "by_horizon": summary_by_horizon(result).to_dict(orient="records"),
        "summary": summarize(result).reset_index().to_dict(orient="records"),
        "smc_particles": particles, "preset": preset, "seed": args.seed,
        "model_key": models.key, "model_reused": models.reused, "encoder": models.encoder,
        "seconds": {"model": round(t_model, 2), "backtest": round(t_backtest, 2)},
        "quick": args.quick, "machine": f"{platform.machine()}, {os.cpu_count()} CPUs",
        "python": sys.version.split()[0],
        "data_dir": os.environ.get("FLOWCAST_DATA_DIR", "(default)"),
    }
    path = Path(args.out) if args.out else RESULTS / ("backtest-quick.json" if args.quick
                                                      else "backtest.json")
    atomic_write_json(path, out)
    print(f"relative WIS (NF vs baseline): {out['relative_wis']}  coverage: {out['coverage']}")
    print(f"{out['n_origins']} origins, backtest {t_backtest:.1f} s → {path}")
    return out


if __name__ == "__main__":
    main()
