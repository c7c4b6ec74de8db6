"""Real-time backtest of the published weekly forecast → bench/results/backtest.json.

Every Saturday origin of the shared DataSF data with 4 weeks of truth (from 8 weeks into the
data), with the weekly forecast's own settings (preset ``default`` of ``pipeline.forecast.config``:
the same members, flow model, ensemble and recalibration the weekly run publishes). At each origin
every member sees the
data up to that day only; the published forecast is their quantile average with weights and a
recalibration fitted to past origins' scores only (:mod:`pipeline.backtest.backtest`).
Targets I and weekly reported cases, 1–4 weeks, 23 hub quantiles; WIS relative to the COVID-19
Forecast Hub baseline per target × horizon (never pooled across targets), 50 %/90 % coverage,
PIT histograms, and the count of invalid values in the published sample paths. The NF-seeded SMC
forecaster (``nf-smc``: the weekly run's joint flow seeding a filter on the multi-wave model,
:mod:`pipeline.members.smc`) is scored beside the members, as in the weekly run, and not
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


CASES_ONLY = "gbqr-cases-only"


def gbqr_references() -> list[Any]:
    """gbqr on the target's series alone, not reading the panel's test positivity
    (:data:`CASES_ONLY`), and gbqr with the trees published until 79ea0ca."""
    from pipeline.members.boosting import (SHALLOW_GBQR, BoostingConfig, PooledBoostingMember,
                                           deep_trees)

    return [PooledBoostingMember(deep_trees(BoostingConfig()), name=CASES_ONLY,
                                 reads_panel_signal=False),
            PooledBoostingMember(BoostingConfig(), name=SHALLOW_GBQR)]


def gbqr_variants(members: tuple[str, ...], prefix: str = "") -> tuple[Any, ...]:
    """The published average with each of :func:`gbqr_references` in gbqr's place."""
    from pipeline.backtest.config import Variant
    from pipeline.members.boosting import SHALLOW_GBQR

    def swapped(name: str) -> tuple[str, ...]:
        return tuple(name if n == "gbqr" else n for n in members)
    return (Variant(f"{prefix}{CASES_ONLY} for gbqr (without test positivity)",
                    members=swapped(CASES_ONLY)),
            Variant(f"{prefix}{SHALLOW_GBQR} for gbqr (15 leaves at rate 0.05: published "
                    "until 79ea0ca)", members=swapped(SHALLOW_GBQR)))


def design_variants() -> tuple[Any, ...]:
    """The published forecast's design choices against their alternatives, scored on the same
    origins by the one combiner (:mod:`pipeline.combine.combiner`; the SF-only design's skill
    weights and widen-only recalibration are its ``inverse-wis`` and ``widen-only`` options)."""
    from pipeline.backtest.config import (Variant, bound_variants, letting_go_variants,
                                          tracking_rate_variants)
    from pipeline.combine.combiner import LOG_AVERAGE, CombineConfig

    members = ("hub-baseline", "gbqr", "nf-growth", "nf-real")
    return (
        Variant("log average (published until 2026-11)", LOG_AVERAGE),
        Variant("log-mixture, no recalibration", CombineConfig(calibration="none")),
        *tracking_rate_variants(CombineConfig(), prefix=""),
        *letting_go_variants(CombineConfig(), prefix=""),
        Variant("linear average", CombineConfig(scale="linear", calibration="none")),
        Variant("skill weights (inverse WIS, last 12 origins)",
                CombineConfig(scale="log", calibration="none", weights="inverse-wis")),
        Variant("widen-only recalibration (the SF-only design)",
                CombineConfig(scale="log", calibration="widen-only",
                              calibration_window_origins=52)),
        Variant("recalibration that may narrow (probit-normal with bias)",
                CombineConfig(scale="log", calibration="bias-scale",
                              calibration_window_origins=52)),
        Variant("the SF-only design: AutoETS + nf-growth, skill weights, linear, widen-only",
                CombineConfig(weights="inverse-wis", scale="linear", calibration="widen-only",
                              calibration_window_origins=52), members=("autoets", "nf-growth")),
        *(Variant(f"without {m}", members=tuple(n for n in members if n != m))
          for m in members),
        # growth-qr, the pooled member published until 2026-11-29: in gbqr's place, and beside
        Variant("growth-qr for gbqr (published until 2026-11-29)",
                members=tuple("growth-qr" if n == "gbqr" else n for n in members)),
        Variant("with growth-qr", members=(*members, "growth-qr")),
        # gbqr without the counties' test positivity beside the cases (published until
        # e88096a), and with the trees published until 79ea0ca
        *gbqr_variants(members),
        # the published rule's bound on falls (issue 51): left off, and put on rises too
        *bound_variants(CombineConfig(), prefix=""),
    )


def variant_summaries(summary: dict[str, Any]) -> dict[str, Any]:
    """Per variant and target: relative WIS (h1–h4, all) and coverage."""
    names = [v.name for v in design_variants()]
    return {name: {target: {"relative_wis_vs_baseline": s[name]["relative_wis_vs_baseline"],
                            "coverage50": s[name]["coverage50"],
                            "coverage90": s[name]["coverage90"]}
                   for target, s in summary["by_target"].items() if name in s}
            for name in names}


def smc_reference(history: Any, origins: list[Any], seed: int) -> tuple[list[Any], float]:
    """The NF-seeded SMC forecaster at every origin the backtest runs (warm-up included), one
    batch of filters, with the default forecast's joint flow (trained if absent); seconds."""
    import dataclasses

    import numpy as np

    from pipeline import forecast as fc
    from pipeline.forecast.joint_models import simulate_training_data, train_or_reuse_models
    from pipeline.forecast.sources import SF_COUNTY
    from pipeline.forecast.published_forecast import smc_member
    from pipeline.members.smc import batched_smc_forecasts
    from pipeline.panels.targets import HORIZONS_WEEKS, HUB_QUANTILE_LEVELS

    t0 = time.perf_counter()
    forecast_config = fc.resolve_config("default", seed=seed)
    models = train_or_reuse_models(forecast_config, simulate_training_data(forecast_config))
    member = dataclasses.replace(smc_member(models, forecast_config),
                                 seed=forecast_config.step_seed("smc") + 1)
    scored = batched_smc_forecasts(member, history, SF_COUNTY, origins, HORIZONS_WEEKS,
                                   np.asarray(HUB_QUANTILE_LEVELS))
    return [scored], time.perf_counter() - t0


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = _parse(argv)
    import dataclasses

    from pipeline import forecast as fc
    from pipeline.backtest.track_record import track_record
    from pipeline.members.growth_regression import PooledGrowthMember
    from pipeline.data.california.cdph import find_vintage_files
    from pipeline.data.california.cdph_source import import_cdph_exports
    from pipeline.forecast.sources import (SF_COUNTY, import_exports, load_sf_history,
                                           reference_panel)
    from pipeline.io import atomic_write_json
    from pipeline.training.model_store import default_store_root

    import_exports([args.data], if_empty=True)
    if Path(args.cdph).is_dir():
        import_cdph_exports(find_vintage_files(args.cdph), if_empty=True, accept_revisions=True)
    source = fc.DataSourceConfig(kind="cache")
    history = load_sf_history(source)
    record = fc.resolve_config("default", seed=args.seed).track_record_config()
    record = dataclasses.replace(
        record, members=dataclasses.replace(record.members, include_nf=not args.no_nf))
    if not args.quick:
        record = dataclasses.replace(record, variants=design_variants())
    reported = record.origins(history, scored_only=True)
    first = reported[-6].date() if args.quick else None
    references, t_smc = [], 0.0
    if not args.no_smc:
        references, t_smc = smc_reference(history, reported, args.seed)
    if not args.quick:
        references = [*references, PooledGrowthMember(), *gbqr_references()]
    t0 = time.perf_counter()
    panel = reference_panel(SF_COUNTY, history)
    reference = panel.references
    made = track_record(panel, SF_COUNTY, record,
                        default_store_root(), references=references, scored_only=True,
                        first=first)
    result = made.result
    t_all = time.perf_counter() - t0
    summary = made.summary()
    t_members = t_all - sum(result.seconds.values())
    out = {
        **summary,
        "variants": variant_summaries(summary),
        "seconds": {"members": round(t_members, 2), "nf_smc": round(t_smc, 2),
                    "backtest": round(sum(result.seconds.values()), 2),
                    "total": round(t_all + t_smc, 2), "parts": summary["seconds"]},
        "flow_model": {"key": made.model_key, "reused": made.model_reused},
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
          f"backtest {sum(result.seconds.values()):.1f} s → {path}")
    return out


if __name__ == "__main__":
    main()
