"""Cross-county real-time backtest → bench/results/backtest_counties.json.

Every California county with at least 100,000 people in the latest shared CDPH vintage
(``../shared/data/cdph``), at every Saturday origin with four weeks of truth (from eight weeks
into the data; the vintage's last 14 days, still filling in, are cut). Each county × origin sees
its own county's data up to the origin, and the pooled members (growth-qr, nf-real) every
county's data up to the origin, nothing later (:mod:`pipeline.backtest.backtest`).

Per target (weekly cases, I) × forecaster: the geometric mean over counties of each county's
relative WIS against the COVID-19 Forecast Hub baseline, per horizon and overall; the share of
counties beating the baseline; 50 %/90 % coverage; PIT histogram; per-county ratios. Beside the
published forecast: every member alone, AutoETS (reference), and the design variants (other
combiners, member subsets), on the same cells; the published forecast by year of origin.

    python -m bench.backtest_counties                 # latest shared vintage
    python -m bench.backtest_counties --vintage PATH  # another covid19cases_test.csv

``seconds.members`` trains or loads the members' models (the flow, nf-real's refits: cached in
the model store); ``seconds.backtest`` forecasts every cell with the published members and
combines them (the published forecast's backtest); ``seconds.references_and_variants`` the
AutoETS reference and the design variants on top; ``seconds.wall`` all of it.
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
SHARED_CDPH = Path(__file__).resolve().parents[2] / "shared" / "data" / "cdph"


def _parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--vintage", default=None, help="a CDPH covid19cases_test.csv (default: the "
                   "latest under ../shared/data/cdph)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="output JSON path")
    return p.parse_args(argv)


MEMBERS = ("hub-baseline", "gbqr", "nf-growth", "nf-real")     # the published average's


def design_variants() -> tuple[Any, ...]:
    """The alternatives scored beside the published combiner (docs/forecasting.md)."""
    from pipeline.backtest.config import (Variant, bound_variants, letting_go_variants,
                                          tracking_rate_variants)
    from pipeline.combine.combiner import LOG_AVERAGE, CombineConfig

    from bench.backtest import gbqr_variants

    long = 1_000                       # every past scored origin
    uncalibrated = CombineConfig(calibration="none")
    return (
        Variant("v-log-average (published until 2026-11)", LOG_AVERAGE),
        Variant("v-log-mixture, no recalibration", uncalibrated),
        Variant("v-mixture (linear pool), no recalibration", CombineConfig(
            scale="mixture", calibration="none")),
        Variant("v-log-average + the online calibration", CombineConfig(scale="log")),
        *tracking_rate_variants(CombineConfig()),
        *letting_go_variants(CombineConfig()),
        # each phase its own adaptive conformal step (a rare phase moves as fast as a common one)
        Variant("v-online calibration, per-regime step", CombineConfig(tracking_step="per-regime")),
        Variant("v-linear-average", CombineConfig(scale="linear", calibration="none")),
        Variant("v-stacking-12-origins", CombineConfig(scale="log", calibration="none",
                                                       weights="stacking", stacking_step=0.1)),
        Variant("v-inverse-wis-all-origins", CombineConfig(
            scale="log", calibration="none", weights="inverse-wis", window_origins=long)),
        Variant("v-recal-widen-only", CombineConfig(scale="log", calibration="widen-only",
                                                    calibration_window_origins=52)),
        Variant("v-recal-scale-all-origins", CombineConfig(
            scale="log", calibration="scale", calibration_window_origins=long)),
        Variant("v-recal-bias-scale-regime", CombineConfig(scale="log",
                                                           calibration="bias-scale-regime")),
        *(Variant(f"v-without-{m}", members=tuple(n for n in MEMBERS if n != m))
          for m in MEMBERS),
        # growth-qr, the pooled member published until 2026-11-29: in gbqr's place, and beside
        Variant("v-growth-qr for gbqr (published until 2026-11-29)",
                members=tuple("growth-qr" if n == "gbqr" else n for n in MEMBERS)),
        Variant("v-with-growth-qr", members=(*MEMBERS, "growth-qr")),
        *gbqr_variants(MEMBERS, prefix="v-"),
        # the published rule's bound on falls (issue 51): left off, and put on rises too
        *bound_variants(CombineConfig()),
    )


def by_year(result: Any, forecasters: list[str]) -> dict[str, Any]:
    """Geometric-mean relative WIS (all horizons, cases) of ``forecasters`` by year of origin."""
    import dataclasses

    import numpy as np

    years = sorted({o.year for o in result.origins})
    out: dict[str, Any] = {}
    for year in years:
        keep = np.array([o.year == year for o in result.origins])
        part = dataclasses.replace(result, reported=keep).reported_only()
        summary = part.summary()["by_target"]["cases"]
        out[str(year)] = {"n_origins": int(keep.sum())} | {
            n: summary[n]["gmean_relative_wis"] for n in forecasters}
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = _parse(argv)
    from pipeline.data.california.cdph import find_vintage_files, read_cdph_csv, read_vintages
    from pipeline.forecast import resolve_config
    from pipeline.forecast.county_skill import county_backtest
    from pipeline.io import atomic_write_json
    from pipeline.members.autoets import AutoETSMember
    from pipeline.members.growth_regression import PooledGrowthMember
    from pipeline.progress import rich_progress
    from pipeline.training.model_store import default_store_root

    from bench.backtest import CASES_ONLY, gbqr_references
    from pipeline.members.boosting import SHALLOW_GBQR

    vintage = (read_cdph_csv(args.vintage) if args.vintage
               else read_vintages(find_vintage_files(SHARED_CDPH))[-1])
    # the weekly run's own members and models (its seeds included), so the county backtest
    # scores exactly what the weekly forecast publishes and shares its stored models
    config = resolve_config("default", seed=args.seed)
    started = time.perf_counter()
    with rich_progress("cross-county backtest") as progress:
        result, chosen = county_backtest(vintage, config, default_store_root(),
                                         variants=design_variants(),
                                         references=(AutoETSMember(), PooledGrowthMember(),
                                                     *gbqr_references()),
                                         progress=progress)
    t_all = time.perf_counter() - started
    t_members = t_all - sum(result.seconds.values())
    counties, origins = result.places, result.origins
    t_backtest = t_all - t_members
    summary = result.summary()
    reference_forecasters = ["published", *result.members, "autoets", "growth-qr", CASES_ONLY,
                             SHALLOW_GBQR]
    out = {
        **summary,
        "by_year": by_year(result, reference_forecasters),
        "vintage": {"as_of": str(vintage.as_of.date()), "source": vintage.source},
        "seconds": {"members": round(t_members, 2),
                    # the published forecast: its members at every cell and their combination
                    "backtest": round(sum(result.seconds[n] for n in (*result.members,
                                                                      "combine")), 2),
                    "references_and_variants": round(result.seconds["autoets"]
                                                     + result.seconds["growth-qr"]
                                                     + result.seconds[CASES_ONLY]
                                                     + result.seconds[SHALLOW_GBQR]
                                                     + result.seconds["variants"], 2),
                    "wall": round(t_backtest, 2), "parts": summary["seconds"]},
        "flow_model": {"key": chosen.model_key, "reused": chosen.reused},
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}",
        "python": sys.version.split()[0],
        "command": "python -m bench.backtest_counties " + " ".join(
            argv if argv is not None else sys.argv[1:]),
    }
    target = Path(args.out) if args.out else RESULTS / "backtest_counties.json"
    atomic_write_json(target, out)
    for target_name, by_forecaster in summary["by_target"].items():
        for name, s in by_forecaster.items():
            g = s["gmean_relative_wis"]
            print(f"{target_name:5s} {name:28s} " + " ".join(
                f"{k}={g[k]:.3f}" for k in ("h1", "h2", "h3", "h4", "all"))
                + f"  beat {s['share_beating_baseline']['all']:.2f}"
                + f"  cov {s['coverage50']:.2f}/{s['coverage90']:.2f}")
    print(f"{len(counties)} counties × {len(origins)} origins; members' models {t_members:.1f} s"
          f", backtest {out['seconds']['backtest']:.1f} s (with references and variants "
          f"{t_backtest:.1f} s) → {target}")
    return out


if __name__ == "__main__":
    main()
