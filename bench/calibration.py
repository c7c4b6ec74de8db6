"""Intervals that hold when the epidemic turns, and results that survive a retrain →
bench/results/calibration.json.

**Panels.** The published forecast (equal-weight log-mixture of the members, then the online
interval calibration per phase of the epidemic, :class:`pipeline.combine.recalibration.
IntervalTracker`) against the rule published until 2026-11 (the log average alone), on the
design panels: California's counties ≥ 100k (the latest shared CDPH vintage, every Saturday
origin with four weeks of truth), San Francisco's DataSF series (its track record) and the hub's
44 NHSN admissions rounds (95 % interval there). Per panel and phase of the epidemic at the
origin (rising, flat, falling: the last two weekly counts known then; and each place's largest
10 % of weekly counts): 50 %/90 % coverage (with its 95 % moving-block bootstrap interval over
origins, pipeline.evaluation.bootstrap) and relative WIS (the geometric mean over places of
Σ WIS / Σ WIS of the hub baseline; San Francisco's own ratio).

**Seeds.** The flows (the flow member, its refits) and the joint pair trained from 3 seeds
(``ForecastConfig.seed``; seed 0 is the product's): the published relative WIS on the counties
and San Francisco, the report's rollouts of the SF series (the 28- and 7-day rolling
rollouts: the largest median I over the observed peak, the share of days in the 90 % band) and
its trouble checks (rollout overshoot, SMC collapse, β not updated from its prior).

    python -m bench.calibration                 # panels and seeds 0, 1, 2
    python -m bench.calibration --seeds 0       # panels and one seed
    python -m bench.calibration --seeds ""      # panels only (the seeds' figures kept)
    python -m bench.calibration --joint-iterations 9000   # the rollouts with a longer-trained
                                                          # joint pair (an experiment)
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
REGIMES = ("rising", "flat", "falling", "largest10")
BEFORE = "before (log average, no recalibration)"
PEAK, COVER = "max_median_I_over_max_observed_I", "share_observed_I_in_90_band"


def _regime_rows(s: dict[str, Any], key: str, outer: str) -> dict[str, Any]:
    """One forecaster's summary (pipeline.evaluation.summary) per regime and overall."""
    rows = {r: s["by_regime"][r] | {"relative_wis": s["by_regime"][r][key]} for r in REGIMES}
    rows["all"] = s | {"relative_wis": s[key]["all"]}
    keys = ("coverage50", outer, "coverage50_interval", f"{outer}_interval", "relative_wis",
            "n_scored")
    return {r: {k: v[k] for k in keys} for r, v in rows.items()}


def panel_summary(summary: dict[str, Any], key: str, outer: str = "coverage90"
                  ) -> dict[str, Any]:
    """The published forecast per regime and overall, with the rule before beside it."""
    published = _regime_rows(summary["published"], key, outer)
    before = _regime_rows(summary[BEFORE], key, outer)
    published["all"]["relative_wis_before"] = before["all"]["relative_wis"]
    return published | {"before": before}


def counties(config: Any) -> tuple[dict[str, Any], float]:
    from pipeline.backtest.config import Variant
    from pipeline.combine.combiner import LOG_AVERAGE
    from pipeline.data.california.cdph import find_vintage_files, read_vintages
    from pipeline.forecast.county_skill import county_backtest
    from pipeline.training.model_store import default_store_root

    vintage = read_vintages(find_vintage_files(SHARED / "cdph"))[-1]
    result, _ = county_backtest(vintage, config, default_store_root(),
                                variants=(Variant(BEFORE, LOG_AVERAGE),))
    summary = result.summary()["by_target"]["cases"]
    return panel_summary(summary, "gmean_relative_wis"), summary["published"][
        "gmean_relative_wis"]["all"]


def san_francisco(config: Any) -> tuple[dict[str, Any], float]:
    from pipeline.backtest.config import Variant
    from pipeline.backtest.track_record import track_record
    from pipeline.combine.combiner import LOG_AVERAGE
    from pipeline import forecast as fc
    from pipeline.forecast.sources import SF_COUNTY, load_sf_history, reference_panel
    from pipeline.training.model_store import default_store_root

    history = load_sf_history(fc.DataSourceConfig(kind="cache"))
    record = dataclasses.replace(config.track_record_config(),
                                 variants=(Variant(BEFORE, LOG_AVERAGE),))
    made = track_record(reference_panel(SF_COUNTY, history), SF_COUNTY,
                        record, default_store_root(), scored_only=True)
    summary = made.summary()["by_target"]["cases"]
    return panel_summary(summary, "relative_wis_vs_baseline"), summary["published"][
        "relative_wis_vs_baseline"]["all"]


def nhsn() -> dict[str, Any]:
    """The hub's admissions rounds: coverage 50 %/95 % and Σ WIS / Σ WIS of the re-implemented
    hub baseline, per regime, published against the rule before."""
    from pipeline.backtest.config import Variant
    from pipeline.backtest.hub_rounds import HubBacktestConfig, run_hub_rounds
    from pipeline.combine.combiner import LOG_AVERAGE, PUBLISHED
    from pipeline.data.hub.target_import import import_hub_time_series
    from pipeline.hub_round.run import load_vintages
    from pipeline.members.published import HubMembersConfig, build_hub_members
    from pipeline.panels.hub import ED_COVID, HOSP_COVID, hub_rounds
    from pipeline.training.model_store import default_store_root

    import_hub_time_series(SHARED / "nhsn", if_empty=True)
    vintages, climatology = load_vintages(HOSP_COVID), load_vintages(ED_COVID)
    members = build_hub_members(HubMembersConfig(), default_store_root(), vintages, climatology,
                                target=HOSP_COVID)
    before = dataclasses.replace(LOG_AVERAGE, beyond_reach="reachable-members")
    result = run_hub_rounds(hub_rounds(vintages), vintages[-1][1], members.published,
                            HubBacktestConfig(variants=(Variant(BEFORE, before),)),
                            references=members.references)
    forecast_weeks = tuple(h for h in result.horizons if h >= 0)
    summary = {name: result.summary(name, forecast_weeks) for name in (PUBLISHED, BEFORE)}
    return panel_summary(summary, "relative_wis_vs_baseline", outer="coverage95") | {
        "horizons": "0-3 (hub)", "n_rounds": len(result.rounds)}


def report_checks(models: Any, recent: Any, sir: Any, config: Any,
                  rolled: dict[Any, Any]) -> list[str]:
    """The trouble checks the weekly report runs, on the same rollouts, filter and β track."""
    import numpy as np

    from pipeline.forecast.steps import parameter_track, seeded_smc
    from pipeline.report import checks

    observed = sir.values[:, 1]
    alerts = [checks.rollout_overshoot(
        f"{direction} {every}-day rollout",
        np.nanquantile(result.samples[..., 1].numpy(), 0.5, axis=0), observed,
        dates=sir.dates, anchors=result.anchors, direction=direction)
        for (direction, every), result in rolled.items()]
    smc = seeded_smc(models, recent.history, sir, config)
    alerts.append(checks.ess_collapse(smc.result.ess[0].numpy(), config.smc.particles,
                                      smc.dates))
    track = parameter_track(models, sir, config)
    beta = track[(track["direction"] == "forward") & (track["component"] == "beta")]
    alerts.append(checks.prior_not_updated(
        "β", beta["q0.05"].to_numpy(), beta["q0.95"].to_numpy(),
        config.resolved.prior.beta_range, pd_dates(beta["date"])))
    return [a for a in alerts if a]


def pd_dates(values: Any) -> Any:
    import pandas as pd

    return pd.DatetimeIndex(pd.to_datetime(values))


def sf_rollouts(config: Any) -> dict[str, Any]:
    """The report's SF rollouts and trouble checks with ``config``'s joint pair (trained or
    reused): per view the peak ratio and the 90 % band's coverage; a rollout that fails is
    recorded with its error."""
    from bench.rollouts_sf import _view_scores
    from pipeline.errors import FlowcastError
    from pipeline.forecast.joint_models import simulate_training_data, train_or_reuse_models
    from pipeline.forecast.nowcasting import nowcast_recent_days
    from pipeline.forecast.sources import load_series, series_to_sir, sir_arrays
    from pipeline.forecast.steps import rollouts

    series = load_series(config.data)
    recent = nowcast_recent_days(series, series_to_sir(series), config.nowcast,
                                 config.step_seed("nowcast"))
    sir = sir_arrays(recent.sir_frame)
    models = train_or_reuse_models(config, simulate_training_data(config))
    out: dict[str, Any] = {"models": {"key": models.key, "reused": models.reused}}
    try:
        rolled = rollouts(models, sir, config)
    except FlowcastError as error:
        return out | {"error": str(error)}
    return out | {"rollouts": {f"{d}_{every}d": _view_scores(result.samples, sir.values[:, 1])
                               for (d, every), result in rolled.items()},
                  "trouble_checks": report_checks(models, recent, sir, config, rolled)}


def seed_run(seed: int) -> dict[str, Any]:
    """One training seed: published skill on both panels, the SF rollouts and the report's
    trouble checks."""
    from pipeline import forecast as fc

    started = time.perf_counter()
    config = fc.resolve_config("default", seed=seed, data=fc.DataSourceConfig(kind="cache"))
    county_panel, county_wis = counties(config)
    sf_panel, sf_wis = san_francisco(config)
    return {"seed": seed, "counties_published_relative_wis": county_wis,
            "sf_published_relative_wis": sf_wis,
            "coverage": {"counties": {r: county_panel[r] for r in (*REGIMES, "all")},
                         "sf": {r: sf_panel[r] for r in (*REGIMES, "all")}},
            **sf_rollouts(config), "seconds": round(time.perf_counter() - started, 1)}


def longer_training(seed: int, iterations: int) -> dict[str, Any]:
    """The SF rollouts with the joint pair trained ``iterations`` steps per direction instead of
    the preset's (the published skill does not depend on the joint pair)."""
    from pipeline import forecast as fc

    started = time.perf_counter()
    config = fc.resolve_config("default", seed=seed, data=fc.DataSourceConfig(kind="cache"))
    config = dataclasses.replace(config, training=dataclasses.replace(
        config.training, iterations=iterations, background_members=False))
    return {"seed": seed, "iterations": iterations, **sf_rollouts(config),
            "seconds": round(time.perf_counter() - started, 1)}


def rollout_bounds(values: list[dict[str, Any]]) -> dict[str, float]:
    """The worst peak ratio and band coverage over the seeds, 28-day rollouts (the issue's
    bounds) and 7-day ones beside them."""
    out = {}
    for every, prefix in ((28, "rollout"), (7, "rollout_7d")):
        views = [v["rollouts"][f"{d}_{every}d"] for v in values for d in ("forward", "backward")]
        if not views:
            continue
        out[f"{prefix}_peak_ratio_max"] = max(r[PEAK] for r in views)
        out[f"{prefix}_cover_min"] = min(r[COVER] for r in views)
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--no-panels", action="store_true", help="the seeds only")
    parser.add_argument("--joint-iterations", type=int, default=None,
                        help="instead: the seeds' SF rollouts with the joint pair trained this "
                             "many steps (an experiment; → joint_iterations.<N>)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    from pipeline import forecast as fc
    from pipeline.data.california.cdph import find_vintage_files
    from pipeline.data.california.cdph_source import import_cdph_exports
    from pipeline.forecast.sources import import_exports
    from pipeline.io import atomic_write_json

    import_exports([str(SHARED / "datasf")], if_empty=True)
    import_cdph_exports(find_vintage_files(SHARED / "cdph"), if_empty=True,
                        accept_revisions=True)
    path = Path(args.out) if args.out else RESULTS / "calibration.json"
    out: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    command = "python -m bench.calibration " + " ".join(argv if argv is not None
                                                         else sys.argv[1:])
    if args.joint_iterations is not None:
        runs = {str(seed): longer_training(seed, args.joint_iterations)
                for seed in (int(s) for s in args.seeds.split(",") if s)}
        out.setdefault("joint_iterations", {})[str(args.joint_iterations)] = {
            "command": command, "seed_runs": runs}
        atomic_write_json(path, out)
        print(json.dumps(runs, indent=1))
        return out
    out.update({"machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}",
                "python": sys.version.split()[0], "command": command})
    started = time.perf_counter()
    if not args.no_panels:
        config = fc.resolve_config("default", data=fc.DataSourceConfig(kind="cache"))
        out["panels"] = {"counties": counties(config)[0], "sf": san_francisco(config)[0],
                         "nhsn": nhsn()}
        out["panels_seconds"] = round(time.perf_counter() - started, 1)
        out["panels_command"] = command
        atomic_write_json(path, out)
        for name, panel in out["panels"].items():
            print(name, {r: (round(v.get("coverage50", 0), 3),
                             round(v.get("coverage90", v.get("coverage95", 0)), 3),
                             round(v["relative_wis"], 4))
                         for r, v in panel.items() if isinstance(v, dict) and r != "before"})
    runs = dict(out.get("seed_runs", {}))
    seeds = [int(s) for s in args.seeds.split(",") if s]
    for seed in seeds:
        runs[str(seed)] = seed_run(seed)
        print(f"seed {seed}: {runs[str(seed)]}", flush=True)
        out["seed_runs"] = runs
        atomic_write_json(path, out)
    if seeds:                       # --seeds "": the panels only, the seeds' figures kept
        values = list(runs.values())
        county = [v["counties_published_relative_wis"] for v in values]
        sf = [v["sf_published_relative_wis"] for v in values]
        out["seeds"] = {
            "command": command, "n": len(values), "seeds": sorted(runs),
            "relative_wis_spread": max(max(county) - min(county), max(sf) - min(sf)),
            "relative_wis_spread_counties": max(county) - min(county),
            "relative_wis_spread_sf": max(sf) - min(sf),
            **rollout_bounds([v for v in values if "rollouts" in v]),
            "rollout_errors": {v["seed"]: v["error"] for v in values if "error" in v},
            "trouble_checks": {v["seed"]: v.get("trouble_checks") for v in values}}
    atomic_write_json(path, out)
    print(json.dumps(out.get("seeds", {}), indent=1))
    return out


if __name__ == "__main__":
    main()
