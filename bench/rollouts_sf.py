"""The weekly forecast's one model on the SF series → bench/results/rollouts_sf.json.

With the default forecast preset's joint flows (trained on the flow member's multi-wave prior;
reused from the model store, trained if absent) and its settings, on the shared DataSF data as
the run reads them (every day up to the data date, the days still being reported nowcast from the
CDPH vintages' delay model):

* rollouts: the rolling forward and backward rollouts re-anchored every 7 and 28 days (the
  report's), per view the share of days whose observed I lies in the 90 % band (5 %–95 % of the
  paths) and the largest ratio of the median I to the highest I observed;
* the same rollouts on synthetic paths of the prior (known truth);
* variants beside them, on both: the chained forward flow the report showed until 2026-11-27
  (``RolloutSettings.forward``) and other noise persistences of the chained paths
  (``RolloutSettings.noise_persistence``);
* β: on synthetic paths, the share of days whose true β lies in the forward flow's 90 %
  interval and the interval's median width relative to the prior's starting range;
* SMC: the NF-seeded filter over the last ``smc.days`` SF days (the report's), its minimum ESS
  as a share of the particles, for several seeds.

    python -m bench.rollouts_sf            # default preset
    python -m bench.rollouts_sf --quick    # tiny preset → bench/results/rollouts_sf-quick.json
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
SHARED_CDPH = Path(__file__).resolve().parents[2] / "shared" / "data" / "cdph"
SYNTHETIC_PATHS = 40
SMC_SEEDS = (0, 1, 2, 3, 4)


def _view_scores(samples: Any, observed: Any) -> dict[str, float]:
    import numpy as np

    infectious = samples[..., 1].numpy()
    predicted = ~np.isnan(infectious).any(axis=0)
    low, median, high = np.quantile(infectious[:, predicted], [0.05, 0.5, 0.95], axis=0)
    seen = observed[predicted]
    return {"days": int(predicted.sum()),
            "share_observed_I_in_90_band": float(np.mean((seen >= low) & (seen <= high))),
            "share_above_band": float(np.mean(seen > high)),
            "share_below_band": float(np.mean(seen < low)),
            "max_median_I_over_max_observed_I": float(median.max() / observed.max()),
            "max_median_I": float(median.max())}


def synthetic_coverage(models: Any, config: Any) -> dict[str, float]:
    """Mean 90 % band coverage of I over synthetic paths of the prior, per view, with
    ``config``'s rollouts (the report's views, drawn as the report draws them)."""
    import numpy as np
    import pandas as pd

    from pipeline.forecast.results import SIRArrays
    from pipeline.forecast.steps import rolling_view
    from pipeline.names import DIRECTIONS
    from pipeline.systems.waves import simulate_waves, sir_view

    view = sir_view(simulate_waves(config.resolved.prior, SYNTHETIC_PATHS, seed=12345), 999)
    keep = (view.sir[..., 1] > 0).all(axis=1)
    small = dataclasses.replace(config, rollouts=dataclasses.replace(config.rollouts, paths=64))
    out = {}
    for direction in DIRECTIONS:
        for every in config.rollouts.windows:
            covers = []
            for path in view.sir[keep]:
                series = SIRArrays(np.arange(len(path), dtype=np.float64), path,
                                   pd.date_range("2020-01-01", periods=len(path), freq="D"))
                result = rolling_view(models, series, small, direction, every)
                covers.append(_view_scores(result.samples, path[:, 1])
                              ["share_observed_I_in_90_band"])
            out[f"{direction}_{every}d"] = float(np.mean(covers))
    return out


def rollout_variants(config: Any) -> dict[str, Any]:
    """The report's rollouts and what they replaced: the chained forward flow (published until
    2026-11-27) and the chained paths' noise persistence."""
    def variant(**changes: Any) -> Any:
        return dataclasses.replace(config, rollouts=dataclasses.replace(config.rollouts,
                                                                        **changes))
    persistence = config.rollouts.noise_persistence
    return {"chained forward, noise persistence 0.5 (published until 2026-11-27)":
                variant(forward="chained-flow", noise_persistence=0.5),
            "chained forward, noise persistence 0 (fresh noise every day)":
                variant(forward="chained-flow", noise_persistence=0.0),
            **{f"{config.rollouts.forward} forward, backward noise persistence {p:g}":
                   variant(noise_persistence=p) for p in (0.5, 0.7, 0.9) if p != persistence}}


def beta_identification(models: Any, config: Any) -> dict[str, float]:
    """Forward β interval against the known β of synthetic paths (every 5th day)."""
    import numpy as np

    from pipeline.inference.estimate import (ObservationWindow, batch_window_context,
                                             sample_conditional)
    from pipeline.systems.waves import simulate_waves, sir_view

    prior, r = config.resolved.prior, config.resolved.window
    view = sir_view(simulate_waves(prior, SYNTHETIC_PATHS, seed=4321), 1234)
    windows, truth = [], []
    for m in range(view.sir.shape[0]):
        for t in range(r + 5, view.sir.shape[1], 5):
            if (view.sir[m, t - r:t, 1] > 0).all():
                windows.append(ObservationWindow(np.arange(t - r, t, dtype=np.float64),
                                                 view.sir[m, t - r:t], float(t)))
                truth.append(view.beta[m, t])
    context, mask = batch_window_context(windows, "forward", r)
    draws = sample_conditional(models.forward, context, mask, 400, 1).double().numpy()
    low, high = np.quantile(draws[..., 3], [0.05, 0.95], axis=1)
    beta = np.asarray(truth)
    return {"windows": len(truth),
            "share_true_beta_in_90_interval": float(np.mean((low <= beta) & (beta <= high))),
            "median_width_over_prior_range": float(np.median(high - low)
                                                   / (prior.beta_range[1] - prior.beta_range[0]))}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="tiny preset (smoke test)")
    parser.add_argument("--data", default=str(SHARED_DATASF))
    parser.add_argument("--cdph", default=str(SHARED_CDPH), help="CDPH county downloads (the "
                        "nowcast's delay model), imported when the cache has none")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    import numpy as np

    from pipeline import forecast as fc
    from pipeline.data.california.cdph import find_vintage_files
    from pipeline.data.california.cdph_source import import_cdph_exports
    from pipeline.forecast.joint_models import simulate_training_data, train_or_reuse_models
    from pipeline.forecast.nowcasting import nowcast_recent_days
    from pipeline.forecast.sources import import_exports, load_series, series_to_sir, sir_arrays
    from pipeline.forecast.steps import parameter_track, rollouts, seeded_smc
    from pipeline.io import atomic_write_json

    started = time.perf_counter()
    import_exports([args.data], if_empty=True)
    if Path(args.cdph).is_dir():      # the nowcast's delay model, as `make forecast` imports it
        import_cdph_exports(find_vintage_files(args.cdph), if_empty=True, accept_revisions=True)
    config = fc.resolve_config("tiny" if args.quick else "default",
                               data=fc.DataSourceConfig(kind="cache"))
    series = load_series(config.data)
    # the run's S/I/R frame: every day of the data, the days still being reported nowcast
    recent = nowcast_recent_days(series, series_to_sir(series), config.nowcast,
                                 config.step_seed("nowcast"))
    sir = sir_arrays(recent.sir_frame)
    models = train_or_reuse_models(config, simulate_training_data(config))
    t0 = time.perf_counter()
    rolled = rollouts(models, sir, config)
    rollout_seconds = time.perf_counter() - t0
    views = {f"{d}_{every}d": _view_scores(result.samples, sir.values[:, 1])
             for (d, every), result in rolled.items()}
    for name, v in views.items():
        print(f"SF {name}: observed I in 90% band {v['share_observed_I_in_90_band']:.3f}, "
              f"max median I / max observed {v['max_median_I_over_max_observed_I']:.2f}",
              flush=True)
    synthetic = synthetic_coverage(models, config)
    print("synthetic 90% band coverage:", synthetic, flush=True)
    variants = {}
    for name, variant in rollout_variants(config).items():
        variants[name] = {
            "rollouts_sf": {f"{d}_{every}d": _view_scores(result.samples, sir.values[:, 1])
                            for (d, every), result in rollouts(models, sir, variant).items()},
            "synthetic_rollout_coverage": synthetic_coverage(models, variant)}
        print(f"{name}: SF", {k: (round(v["share_observed_I_in_90_band"], 3),
                                  round(v["max_median_I_over_max_observed_I"], 2))
                              for k, v in variants[name]["rollouts_sf"].items()},
              "synthetic", {k: round(v, 3)
                            for k, v in variants[name]["synthetic_rollout_coverage"].items()},
              flush=True)
    beta = beta_identification(models, config)
    print("beta on synthetic paths:", beta, flush=True)
    params = parameter_track(models, sir, config)
    latest = params[(params["direction"] == "forward")].groupby("component").tail(1)
    smc = {}
    for seed in SMC_SEEDS:
        run = seeded_smc(models, recent.history, sir, dataclasses.replace(config, seed=seed))
        ess = run.result.ess[0].numpy() / config.smc.particles
        smc[str(seed)] = {"min_ess_share": float(ess.min()),
                          "min_ess_day": str(run.dates[int(np.argmin(ess))].date()),
                          "median_ess_share": float(np.median(ess))}
        print(f"SMC seed {seed}: min ESS {ess.min():.3f} of the particles", flush=True)
    out = {
        "preset": config.preset,
        "model": {"key": models.key, "reused": models.reused, "encoder": models.encoder,
                  "window_days": config.resolved.window, "gamma_fixed": config.resolved.gamma},
        "rollouts_sf": views,
        "rollout_settings": dataclasses.asdict(config.rollouts),
        "rollout_seconds": round(rollout_seconds, 2),
        "synthetic_rollout_coverage": synthetic,
        "variants": variants,
        "beta_synthetic": beta,
        "latest_forward_estimates": {row["component"]: {"q0.05": row["q0.05"], "q0.5": row["q0.5"],
                                                        "q0.95": row["q0.95"]}
                                     for _, row in latest.iterrows()},
        "smc": {"days": config.smc.days, "particles": config.smc.particles, "by_seed": smc,
                "min_ess_share_over_seeds": min(v["min_ess_share"] for v in smc.values())},
        "data": {"first_day": str(sir.dates[0].date()), "last_day": str(sir.dates[-1].date()),
                 "nowcast_from": (str(recent.nowcast.completed.first_nowcast_day.date())
                                  if recent.nowcast else None),
                 "max_observed_I": float(sir.values[:, 1].max())},
        "seconds": round(time.perf_counter() - started, 1),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}",
        "load_average_at_end": os.getloadavg(),
        "python": sys.version.split()[0],
        "command": "python -m bench.rollouts_sf " + " ".join(argv if argv is not None
                                                             else sys.argv[1:]),
    }
    path = Path(args.out) if args.out else RESULTS / ("rollouts_sf-quick.json" if args.quick
                                                      else "rollouts_sf.json")
    atomic_write_json(path, out)
    print(f"→ {path}")
    return out


if __name__ == "__main__":
    main()
