"""Real-time backtest of the published weekly forecast → bench/results/backtest.json.

Every Saturday origin of the shared DataSF data with 4 weeks of truth (from 8 weeks into the
data), with the weekly forecast's own settings (``pipeline.forecast.steps`` preset ``default``: the same
members, flow model, ensemble and recalibration the weekly run publishes). At each origin every member sees the
data up to that day only; the published forecast is their quantile average with weights and a
recalibration fitted to past origins' scores only (:mod:`pipeline.ensemble.backtest`).
Targets I and weekly reported cases, 1–4 weeks, 23 hub quantiles; WIS relative to the COVID-19
Forecast Hub baseline per target × horizon (never pooled across targets), 50 %/90 % coverage,
PIT histograms, and the count of invalid values in the published sample paths. The NF-seeded SMC
forecaster (``nf-smc``: the weekly run's joint flow seeding a filter on the multi-wave model,
:mod:`pipeline.ensemble.smc_member`) is scored beside the members, as in the weekly run, and not
averaged (``--no-smc`` leaves it out).

    python -m bench.backtest              # the published forecast (hub baseline, growth-qr,
                                          # nf-growth, nf-real; California's counties pooled)
    python -m bench.backtest --no-nf      # without the flow members
    python -m bench.backtest --quick      # last 6 origins → bench/results/backtest-quick.json
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
SHARED_DATASF = Path(__file__).resolve().parents[2] / "shared" / "data" / "datasf"
SHARED_CDPH = Path(__file__).resolve().parents[2] / "shared" / "data" / "cdph"


def _parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="the last 6 origins only (seconds)")
    p.add_argument("--no-nf", action="store_true", help="members without the NF member")
    p.add_argument("--no-smc", action="store_true", help="without the NF-seeded SMC forecaster")
    p.add_argument("--data", default=str(SHARED_DATASF), help="DataSF CSV exports directory "
                   "(imported only into an empty cache)")
    p.add_argument("--cdph", default=str(SHARED_CDPH), help="CDPH county downloads (the "
                   "pooled members' reference places; imported only into an empty cache)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="output JSON path")
    return p.parse_args(argv)


def design_variants(history: Any, members: list[Any], config: Any) -> dict[str, Any]:
    """The published forecast's design choices against their alternatives, same origins: per
    target, relative WIS (h1–h4, all) and coverage of the published forecast under each."""
    import dataclasses

    from pipeline.ensemble.backtest import run_realtime_backtest, summarize
    from pipeline.ensemble.calibration import CalibrationConfig
    from pipeline.ensemble.combine import EnsembleConfig

    def without(name: str) -> list[Any]:
        return [m for m in members if m.name != name]

    published = config.ensemble
    choices = {
        "linear average": (members, dataclasses.replace(published, scale="linear"),
                           config.calibration),
        "skill weights (inverse WIS, last 12 origins)": (
            members, dataclasses.replace(published, weighting="skill"), config.calibration),
        "widen-only recalibration (the SF-only design)": (
            members, published, CalibrationConfig()),
        "recalibration that may narrow (probit-normal with bias)": (
            members, published, CalibrationConfig(widen_only=False)),
        "the SF-only design: AutoETS + nf-growth, skill weights, linear, widen-only": (
            [m for m in members if m.name == "nf-growth"] + [_autoets()],
            EnsembleConfig(weighting="skill", scale="linear"), CalibrationConfig()),
        **{f"without {m.name}": (without(m.name), published, config.calibration)
           for m in members},
    }
    out: dict[str, Any] = {}
    for name, (chosen, ensemble, calibration) in choices.items():
        result = run_realtime_backtest(history, chosen, dataclasses.replace(
            config, ensemble=ensemble, calibration=calibration))
        out[name] = {target: {"relative_wis_vs_baseline": s["published"]["relative_wis_vs_baseline"],
                              "coverage50": s["published"]["coverage50"],
                              "coverage90": s["published"]["coverage90"]}
                     for target, s in summarize(result)["by_target"].items()}
        print(f"variant {name!r}: I all {out[name]['I']['relative_wis_vs_baseline']['all']:.3f}"
              f", cases all {out[name]['cases']['relative_wis_vs_baseline']['all']:.3f}")
    return out


def _autoets() -> Any:
    from pipeline.ensemble.autoets import AutoETSMember

    return AutoETSMember()


def smc_reference(history: Any, config: Any, seed: int) -> tuple[list[Any], float]:
    """The NF-seeded SMC forecaster at every origin the backtest runs (warm-up included), one
    batch of filters, with the default forecast's joint flow (trained if absent); seconds."""
    import dataclasses

    import numpy as np

    from pipeline import forecast as fc
    from pipeline.ensemble.backtest import backtest_origins
    from pipeline.ensemble.smc_member import batched_smc_forecasts
    from pipeline.forecast.joint_models import simulate_training_data, train_or_reuse_models
    from pipeline.forecast.steps import smc_member

    t0 = time.perf_counter()
    forecast_config = fc.resolve_config("default", seed=seed)
    models = train_or_reuse_models(forecast_config, simulate_training_data(forecast_config))
    origins = backtest_origins(history, dataclasses.replace(config, first_origin=None))
    scored = batched_smc_forecasts(smc_member(models, forecast_config), history, origins,
                                   config.horizons, np.asarray(config.levels),
                                   forecast_config.step_seed("smc") + 1)
    return [scored], time.perf_counter() - t0


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = _parse(argv)
    import dataclasses

    from pipeline import forecast as fc
    from pipeline.forecast.sources import (SF_COUNTY, import_exports,
                                           load_reference_histories, load_sf_history)
    from pipeline.data.cdph import find_vintage_files
    from pipeline.data.cdph_source import import_cdph_exports
    from pipeline.training.model_store import default_store_root
    from pipeline.ensemble.backtest import (backtest_origins,
                                               run_realtime_backtest, summarize)
    from pipeline.ensemble.weekly import build_weekly_members
    from pipeline.io import atomic_write_json

    import_exports([args.data], if_empty=True)
    if Path(args.cdph).is_dir():
        import_cdph_exports(find_vintage_files(args.cdph), if_empty=True, accept_revisions=True)
    source = fc.DataSourceConfig(kind="cache")
    history = load_sf_history(source)
    reference = load_reference_histories()
    weekly = dataclasses.replace(fc.resolve_config("default", seed=args.seed).weekly_config(),
                                 include_nf=not args.no_nf)
    config = weekly.backtest_config(scored_only=True)
    if args.quick:
        origins = backtest_origins(history, config)
        config = dataclasses.replace(config, first_origin=origins[-6].date())
    t0 = time.perf_counter()
    chosen = build_weekly_members(weekly, default_store_root(), reference, history, SF_COUNTY)
    members, model_key, reused = chosen.members, chosen.model_key, chosen.reused
    t_members = time.perf_counter() - t0
    references, t_smc = [], 0.0
    if not args.no_smc:
        references, t_smc = smc_reference(history, config, args.seed)
    result = run_realtime_backtest(history, members, config, references=references)
    summary = summarize(result)
    variants = {} if args.quick else design_variants(history, members, config)
    out = {
        **summary,
        "variants": variants,
        "seconds": {"members": round(t_members, 2), "nf_smc": round(t_smc, 2),
                    "backtest": round(result.seconds, 2),
                    "total": round(t_members + t_smc + result.seconds, 2)},
        "flow_model": {"key": model_key, "reused": reused},
        "data": {"first_day": str(history.dates[0].date()), "last_day": str(history.origin.date()),
                 "population": history.population,
                 "reference_places": len(reference),
                 "reference_last_day": (str(next(iter(reference.values())).origin.date())
                                        if reference else None)},
        "quick": args.quick,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}",
        "python": sys.version.split()[0],
        "command": "python -m bench.backtest " + " ".join(argv if argv is not None
                                                          else sys.argv[1:]),
    }
    path = Path(args.out) if args.out else RESULTS / ("backtest-quick.json" if args.quick
                                                      else "backtest.json")
    atomic_write_json(path, out)
    for target, by_forecaster in summary["by_target"].items():
        for name, s in by_forecaster.items():
            rel = " ".join(f"{k}={v:.3f}" for k, v in s["relative_wis_vs_baseline"].items()
                           if v is not None)
            print(f"{target:5s} {name:22s} {rel}  cov {s['coverage50']:.2f}/{s['coverage90']:.2f}")
    print(f"{summary['n_origins']} origins ({summary['origins']['first']} … "
          f"{summary['origins']['last']}), invalid values {summary['invalid_values']}, "
          f"backtest {result.seconds:.1f} s → {path}")
    return out


if __name__ == "__main__":
    main()
