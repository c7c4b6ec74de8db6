"""Nowcasting from real vintages: the delay model, its held-out coverage, and nowcast-then-forecast
against today's method (drop the last 14 days) and the truncated data as is.

``python -m bench.nowcast [--completions 32] [--seed 0] [--quick]`` → ``bench/results/nowcast.json``
(``--quick``: 8 counties, ``nowcast-quick.json``).

1. **Delay model** (:mod:`pipeline.data.delays`) on the chain of consecutive CDPH vintages, every
   county: completeness by lag 0–28 of the pooled county at the latest era (median, 50 % and 90 %
   intervals of the posterior), the beta-binomial precision, and the Laplace evidence of a few
   prior scales (the defaults' neighbours).
2. **Held-out vintage pairs**: for each earlier vintage, the model fitted without its link, then
   every pair that starts at it (every later vintage), counties ≥ 100k, lags 0–28: coverage of the
   central 50 % / 90 % predictive intervals of the earlier count given the later one, per day
   and per 7-day week (weeks ending 0, 7, 14, 21 days before the vintage).
3. **Real-time nowcast-then-forecast**: at each vintage with a later one, every county ≥ 100k,
   from that vintage's data exactly as the weekly run would (delay model from the vintage pairs
   known then; for the first vintage, which has none, from the pairs of the later ones — marked),
   K completions forecast by AutoETS from the last Saturday ≤ the data date and mixed; against
   the same forecaster after dropping the last 14 days (origin = last Saturday ≤ D − 14, the
   horizons extended to the same target weeks) and on the truncated data as is; the current
   week's days in the data are not used (as in the run; ``nowcast_with_partial_week`` uses them,
   a variant). Scored (WIS of
   weekly cases) against the latest vintage on the hub weeks −1..3 of each data date; per hub
   horizon the geometric mean over county × vintage cells of the WIS ratios.
4. **DataSF**: the vintages the project has (one shared export), so nothing to score there.
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

import numpy as np
import pandas as pd

from pipeline.data.cdph import CDPHVintage, find_vintage_files, read_vintages
from pipeline.data.delays import DelayModel, DelayModelConfig, fit_delay_model
from pipeline.data.vintage_pairs import RevisionPairs, revision_pairs
from pipeline.ensemble.autoets import AutoETSMember
from pipeline.ensemble.nowcast import NowcastConfig, complete_histories, nowcast_history
from pipeline.ensemble.nowcast_forecast import (HUB_HORIZONS, MemberForecaster, hub_weeks,
                                                nowcast_then_forecast, truncated_forecast,
                                                week_sums)
from pipeline.ensemble.targets import HUB_QUANTILE_LEVELS, DAYS_PER_WEEK, history_from_county
from pipeline.evaluation.scoring import interval_coverage, weighted_interval_score
from pipeline.io import atomic_write_json

CDPH_ROOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "cdph"
DATASF_ROOT = CDPH_ROOT.parent / "datasf"
RESULTS = Path(__file__).resolve().parent / "results"
MIN_POPULATION = 100_000
LAGS = 28
METHODS = ("nowcast", "drop14", "as_is")


def _interval(x: np.ndarray, axis: int = 0) -> dict[str, list[float]]:
    q = np.quantile(x, [0.05, 0.25, 0.5, 0.75, 0.95], axis=axis)
    return {"median": q[2].round(4).tolist(), "lo50": q[1].round(4).tolist(),
            "hi50": q[3].round(4).tolist(), "lo90": q[0].round(4).tolist(),
            "hi90": q[4].round(4).tolist()}


# --------------------------------------------------------------------------- 1. the model


def delay_model_summary(model: DelayModel, seconds: float) -> dict[str, Any]:
    curve = model.pooled_curve(400, seed=1)[:, :LAGS + 1]
    spread = model.pooled_curve(400, seed=2, new_county=True)[:, :LAGS + 1]
    return {"lags": list(range(LAGS + 1)),
            "completeness_pooled_latest_era": _interval(curve),
            "completeness_new_county_latest_era": _interval(spread),
            "era": str(model.eras[-1].date()),
            "eras": [str(e.date()) for e in model.eras],
            "precision_by_lag_at_100_cases": {
                str(lag): round(float(model.precision(100.0, lag)), 2) for lag in (0, 1, 3, 7, 14,
                                                                                   28)},
            "n_observations": model.n_observations, "capped_decreases": model.capped,
            "log_evidence": round(model.log_evidence(), 1), "fit_seconds": round(seconds, 1),
            "config": dataclasses.asdict(model.config)}


def evidence_grid(pairs: RevisionPairs, base: DelayModelConfig) -> list[dict[str, Any]]:
    rows = []
    for county_sd, era_sd in ((base.county_sd, base.era_sd_per_week),
                              (base.county_sd / 2, base.era_sd_per_week),
                              (base.county_sd * 2, base.era_sd_per_week),
                              (base.county_sd, base.era_sd_per_week / 2),
                              (base.county_sd, base.era_sd_per_week * 2)):
        config = dataclasses.replace(base, county_sd=county_sd, era_sd_per_week=era_sd)
        rows.append({"county_sd": county_sd, "era_sd_per_week": era_sd,
                     "log_evidence": round(fit_delay_model(pairs, config).log_evidence(), 1)})
        print(f"  evidence county_sd={county_sd} era_sd={era_sd}: {rows[-1]['log_evidence']}")
    return rows


# ------------------------------------------------------------------- 2. held-out pairs


def predictive_counts(model: DelayModel, pairs: RevisionPairs, n: int, seed: int
                      ) -> np.ndarray:
    """(n, rows) draws of the earlier count given the later one (beta-binomial per draw)."""
    rng = np.random.default_rng(seed)
    ratio = np.clip(model.predictive_ratio(pairs, n, seed), 1e-9, 1 - 1e-9)
    phi = model.precision(pairs.late.astype(np.float64), pairs.lag_early.astype(np.float64))
    p = rng.beta(phi * ratio, phi * (1 - ratio))
    return rng.binomial(pairs.late[None, :], p)


def coverage(draws: np.ndarray, observed: np.ndarray) -> dict[str, float]:
    lo50, hi50, lo90, hi90 = np.quantile(draws, [0.25, 0.75, 0.05, 0.95], axis=0)
    return {"coverage50": round(float(np.mean((lo50 <= observed) & (observed <= hi50))), 3),
            "coverage90": round(float(np.mean((lo90 <= observed) & (observed <= hi90))), 3),
            "n": int(observed.size)}


def held_out_pairs(vintages: list[CDPHVintage], chain: RevisionPairs, counties: tuple[str, ...],
                   config: DelayModelConfig, n: int, seed: int) -> dict[str, Any]:
    every = revision_pairs(vintages, counties=counties)
    per_era: dict[str, Any] = {}
    day_draws, day_obs, week_draws, week_obs = [], [], [], []
    for era in chain.eras:
        model = fit_delay_model(chain.without_era(era), config)
        rows = every.select((every.era == every.eras.index(era)) & (every.lag_early <= LAGS))
        draws = predictive_counts(model, rows, n, seed)
        day_draws.append(draws)
        day_obs.append(rows.early)
        keys = pd.DataFrame({"c": rows.county, "j": rows.later, "w": rows.lag_early // 7})
        groups = keys.groupby(["c", "j", "w"]).ngroup().to_numpy()
        g = groups.max() + 1
        wd = draws @ (groups[:, None] == np.arange(g)[None, :])
        wo = np.bincount(groups, weights=rows.early, minlength=g)
        weeks = keys.assign(g=groups).drop_duplicates("g").sort_values("g")["w"].to_numpy()
        week_draws.append(wd[:, weeks < 4])
        week_obs.append(wo[weeks < 4])
        per_era[str(era.date())] = {"daily": coverage(draws, rows.early),
                                    "weekly": coverage(wd[:, weeks < 4], wo[weeks < 4])}
        print(f"  held out {era.date()}: {per_era[str(era.date())]}")
    return {"per_held_out_vintage": per_era,
            "daily_lags_0_28": coverage(np.concatenate(day_draws, 1), np.concatenate(day_obs)),
            "weekly_weeks_0_3": coverage(np.concatenate(week_draws, 1),
                                         np.concatenate(week_obs)),
            "target": "50% and 90% coverage within ±7 points of nominal",
            "what": "the earlier vintage's count of a county-day (daily) or of a 7-day week "
                    "given the later vintage's, every pair starting at the held-out vintage, "
                    f"counties >= {MIN_POPULATION:,}, lags 0-{LAGS}"}


# ------------------------------------------------------------- 3. nowcast then forecast


def delay_model_at(vintage: CDPHVintage, chain: RevisionPairs,
                   config: DelayModelConfig) -> tuple[DelayModel, str]:
    """The delay model the run would have had on ``vintage``'s date (pairs known then)."""
    known = chain.known_at(vintage.as_of)
    if len(known) > 0:
        return fit_delay_model(known, config), "real time (pairs known on the data date)"
    later = chain.without_era(vintage.as_of)
    return fit_delay_model(later, config), ("no earlier vintage: pairs of the later vintages "
                                            "(not real time)")


def score(quantiles: np.ndarray, truth: np.ndarray, levels: np.ndarray) -> dict[str, np.ndarray]:
    return {"wis": weighted_interval_score(levels, quantiles, truth).wis,
            "c50": interval_coverage(levels, quantiles, truth, 0.5),
            "c90": interval_coverage(levels, quantiles, truth, 0.9)}


def evaluate_forecasts(vintages: list[CDPHVintage], chain: RevisionPairs,
                       counties: tuple[str, ...], config: DelayModelConfig,
                       nowcast_config: NowcastConfig, seed: int) -> dict[str, Any]:
    latest = vintages[-1]
    levels = np.asarray(HUB_QUANTILE_LEVELS)
    forecaster = MemberForecaster(AutoETSMember())
    rows: list[dict[str, Any]] = []
    reported: list[dict[str, Any]] = []
    models: dict[str, str] = {}
    for vintage in vintages[:-1]:
        model, how = delay_model_at(vintage, chain, config)
        models[str(vintage.as_of.date())] = how
        weeks = hub_weeks(vintage.as_of)
        for county in counties:
            history = history_from_county(vintage.county(county))
            final = history_from_county(latest.county(county))
            ends = [w.end for w in weeks.weeks]
            pos = final.dates.get_indexer(pd.DatetimeIndex(ends))
            truth = np.array([final.cases[p - DAYS_PER_WEEK + 1:p + 1].sum() for p in pos],
                             dtype=np.float64)
            nowcast = nowcast_history(history, model, county=county, config=nowcast_config,
                                      seed=seed)
            completed = complete_histories(history, nowcast)
            forecasts = {
                "nowcast": nowcast_then_forecast(completed, vintage.as_of, forecaster, levels,
                                                 seed).quantiles,
                "nowcast_with_partial_week": nowcast_then_forecast(
                    completed, vintage.as_of, forecaster, levels, seed,
                    partial_week=True).quantiles,
                "drop14": truncated_forecast(history, vintage.as_of, forecaster, levels, seed,
                                             drop_days=14),
                "as_is": truncated_forecast(history, vintage.as_of, forecaster, levels, seed,
                                            drop_days=0)}
            for method, q in forecasts.items():
                s = score(q, truth, levels)
                for j, w in enumerate(weeks.weeks):
                    rows.append({"vintage": str(vintage.as_of.date()), "county": county,
                                 "method": method, "horizon": w.horizon, "kind": w.kind,
                                 "wis": float(s["wis"][j]), "c50": bool(s["c50"][j]),
                                 "c90": bool(s["c90"][j]), "truth": truth[j],
                                 "median": float(q[j, 11])})
            reported += reported_shares(history, final, completed, vintage, county)
        print(f"  {vintage.as_of.date()}: {len(counties)} counties ({how})")
    frame = pd.DataFrame(rows)
    return {"delay_model_per_vintage": models,
            "summary": summarize_scores(frame),
            "reported_share_of_recent_weeks": summarize_reported(pd.DataFrame(reported)),
            "n_cells": int(frame.groupby(["vintage", "county"]).ngroups)}


def reported_shares(history: Any, final: Any, completed: Any, vintage: CDPHVintage,
                    county: str) -> list[dict[str, Any]]:
    """How much of each of the last four 7-day weeks had been reported: truth (the latest
    vintage) and the nowcast's estimate (observed / nowcast samples)."""
    out = []
    for back in range(4):
        end = vintage.as_of - pd.Timedelta(days=DAYS_PER_WEEK * back)
        pos = history.dates.get_loc(end)
        seen = float(history.cases[pos - 6:pos + 1].sum())
        true = float(final.cases[final.dates.get_loc(end) - 6:final.dates.get_loc(end) + 1].sum())
        estimate = seen / np.maximum(week_sums(completed, [end])[:, 0], 1.0)
        out.append({"vintage": str(vintage.as_of.date()), "county": county,
                    "week_ending_days_before": DAYS_PER_WEEK * back,
                    "true_share": seen / true if true > 0 else np.nan,
                    "nowcast_share_median": float(np.median(estimate)),
                    "in50": bool(np.quantile(estimate, 0.25) <= seen / max(true, 1.0)
                                 <= np.quantile(estimate, 0.75)),
                    "in90": bool(np.quantile(estimate, 0.05) <= seen / max(true, 1.0)
                                 <= np.quantile(estimate, 0.95))})
    return out


def summarize_reported(frame: pd.DataFrame) -> dict[str, Any]:
    out = {}
    for back, g in frame.groupby("week_ending_days_before"):
        out[f"week_ending_{back}_days_before"] = {
            "true_share_median": round(float(g["true_share"].median()), 3),
            "true_share_range": [round(float(g["true_share"].min()), 3),
                                 round(float(g["true_share"].max()), 3)],
            "nowcast_share_median": round(float(g["nowcast_share_median"].median()), 3),
            "coverage50": round(float(g["in50"].mean()), 3),
            "coverage90": round(float(g["in90"].mean()), 3)}
    return out


def geometric_mean_ratio(frame: pd.DataFrame, method: str, reference: str) -> float | None:
    a = frame[frame["method"] == method].set_index(["vintage", "county"])["wis"]
    b = frame[frame["method"] == reference].set_index(["vintage", "county"])["wis"]
    ratio = (a / b).replace([np.inf, -np.inf], np.nan).dropna()
    ratio = ratio[ratio > 0]
    return round(float(np.exp(np.log(ratio).mean())), 3) if len(ratio) else None


def summarize_scores(frame: pd.DataFrame) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for h in HUB_HORIZONS:
        g = frame[frame["horizon"] == h]
        out[f"horizon_{h}"] = {
            "kinds": sorted(set(g[g["method"] == "nowcast"]["kind"])),
            "geomean_wis_ratio_nowcast_vs_drop14": geometric_mean_ratio(g, "nowcast", "drop14"),
            "geomean_wis_ratio_nowcast_vs_as_is": geometric_mean_ratio(g, "nowcast", "as_is"),
            "geomean_wis_ratio_with_partial_week_vs_drop14": geometric_mean_ratio(
                g, "nowcast_with_partial_week", "drop14"),
            "mean_wis": {m: round(float(x["wis"].mean()), 1) for m, x in g.groupby("method")},
            "coverage50": {m: round(float(x["c50"].mean()), 3) for m, x in g.groupby("method")},
            "coverage90": {m: round(float(x["c90"].mean()), 3) for m, x in g.groupby("method")},
            "per_vintage_ratio_vs_drop14": {
                v: geometric_mean_ratio(x, "nowcast", "drop14") for v, x in g.groupby("vintage")},
            "per_vintage_ratio_vs_as_is": {
                v: geometric_mean_ratio(x, "nowcast", "as_is") for v, x in g.groupby("vintage")},
        }
    return out


# ------------------------------------------------------------------------------- 4. DataSF


def datasf_vintages() -> dict[str, Any]:
    exports = sorted(str(p.relative_to(DATASF_ROOT)) for p in
                     DATASF_ROOT.rglob("COVID-19_Cases_Over_Time.csv"))
    return {"case_exports": exports, "n_vintages": len(exports),
            "note": "one shared DataSF cases export (data as of 2022-03-21): no second vintage, "
                    "so no DataSF revision can be scored here; the weekly run nowcasts SF with "
                    "the CDPH delay model as a new county (its delay prior). A later DataSF "
                    "vintage will score the nowcast of this one's last weeks."}


# ------------------------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(prog="python -m bench.nowcast")
    parser.add_argument("--completions", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    vintages = read_vintages(find_vintage_files(CDPH_ROOT))
    counties = vintages[-1].counties_with_population(MIN_POPULATION)
    if args.quick:
        counties = counties[:: max(len(counties) // 8, 1)][:8]
    config = DelayModelConfig()
    chain = revision_pairs(vintages, consecutive=True)
    t = time.perf_counter()
    model = fit_delay_model(chain, config)
    print("delay model fitted", round(time.perf_counter() - t, 1), "s")
    result: dict[str, Any] = {
        "vintages": [str(v.as_of.date()) for v in vintages],
        "counties": list(counties),
        "delay_model": delay_model_summary(model, time.perf_counter() - t)}
    result["delay_model"]["evidence_grid"] = [] if args.quick else evidence_grid(chain, config)
    print("held-out vintage pairs")
    result["held_out_pairs"] = held_out_pairs(vintages, chain, counties, config, 200, args.seed)
    print("nowcast then forecast")
    nowcast_config = NowcastConfig(n_completions=args.completions)
    result["forecasts"] = evaluate_forecasts(vintages, chain, counties, config, nowcast_config,
                                             args.seed)
    result["forecasts"]["forecaster"] = "autoets (pipeline.ensemble.autoets) on every method"
    result["datasf"] = datasf_vintages()
    result["settings"] = {"completions": args.completions, "seed": args.seed,
                          "nowcast": dataclasses.asdict(nowcast_config)}
    result["machine"] = (f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}, "
                         f"python {sys.version.split()[0]}")
    result["command"] = "python -m bench.nowcast " + " ".join(argv if argv is not None
                                                               else sys.argv[1:])
    result["seconds"] = round(time.perf_counter() - started, 1)
    name = "nowcast-quick.json" if args.quick else "nowcast.json"
    atomic_write_json(RESULTS / name, result)
    print(json.dumps(result["forecasts"]["summary"], indent=1)[:3000])
    return result


if __name__ == "__main__":
    main()
