"""Nowcasting from real vintages: the delay model, its held-out coverage, and nowcast-then-forecast
against today's method (drop the last 14 days) and the truncated data as is.

``python -m bench.nowcast [--completions 32] [--seed 0] [--quick]`` → ``bench/results/nowcast.json``
(``--quick``: 8 counties, ``nowcast-quick.json``).

1. **Delay model** (:mod:`pipeline.data.california.delays`) on the chain of consecutive CDPH vintages, every
   county: completeness by lag 0–28 of the pooled county at the latest era (median, 50 % and 90 %
   intervals of the posterior), the beta-binomial precision, and the Laplace evidence of a few
   prior scales (the defaults' neighbours).
2. **Held-out vintage pairs**: for each earlier vintage, the model fitted without its link, then
   every pair that starts at it (every later vintage), counties ≥ 100k, lags 0–28: coverage of the
   central 50 % / 90 % predictive intervals of the earlier count given the later one, per day
   and per 7-day week (weeks ending 0, 7, 14, 21 days before the vintage).
3. **Real-time nowcast-then-forecast**: at each vintage with a later one, every county ≥ 100k,
   from that vintage's data exactly as the weekly run would (delay model from the vintage pairs
   known then; for the first vintage, which has none, from the pairs of the later ones —
   marked), K completions forecast from the last Saturday ≤ the data date and mixed; against
   the same forecaster after dropping the last 14 days (origin = last Saturday ≤ D − 14, the
   horizons extended to the same target weeks) and on the truncated data as is. Two
   forecasters, each on every method:

   * ``published`` — the weekly run's published forecast
     (:class:`pipeline.combine.combiner.Ensemble`, members chosen by
     :func:`pipeline.members.published.build_members`): hub-baseline, growth-qr pooled
     over the vintage's counties less their last 14 days (the run's reference places; each
     county's own left out), nf-growth, and nf-real fine-tuned on the vintage's county windows
     at the latest refit date ≤ each origin (model store); each member mixed over the
     completions, then the members' log average (the run's order). The flows forecast four
     weeks, and drop-14's origin is two weeks earlier, so its hub weeks 2 and 3 are five and
     six weeks ahead: there ``drop14`` has no forecast (not scored), and
     ``drop14_reachable_members`` is the log average of hub-baseline and growth-qr (a
     different forecaster, reported beside it);
   * ``autoets`` — AutoETS on every method (reaches any week), as before, with the variant
     ``nowcast_with_partial_week`` (the current week's days in the data used).

   Scored (WIS of weekly cases) against the latest vintage on the hub weeks −1..3 of each data
   date; per hub horizon the geometric mean over county × vintage cells of the WIS ratios
   (``n_ratio_cells``: the cells each is over), and published / AutoETS per method.
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

from pipeline.data.california.cdph import CDPHVintage, find_vintage_files, read_vintages
from pipeline.data.california.delays import DelayModel, DelayModelConfig, fit_delay_model
from pipeline.data.california.vintage_pairs import RevisionPairs, revision_pairs
from pipeline.members.autoets import AutoETSMember
from pipeline.nowcast.completions import (CompletedHistories, NowcastConfig, complete_histories,
                                       nowcast_history)
from pipeline.backtest.track_record import TrackRecordConfig
from pipeline.combine.combiner import CombineConfig, Ensemble
from pipeline.members.base import reach
from pipeline.members.nf.refit import latest_refit_date
from pipeline.members.published import build_members
from pipeline.nowcast.hub_weeks import HUB_HORIZONS, hub_weeks, last_saturday
from pipeline.nowcast.then_forecast import (Forecaster, nowcast_then_forecast_places,
                                            truncated_forecasts)
from pipeline.nowcast.completions import week_sums
from pipeline.panels.history import EpiHistory, history_from_county
from pipeline.panels.panel import Panel
from pipeline.panels.targets import DAYS_PER_WEEK, HUB_QUANTILE_LEVELS
from pipeline.evaluation.scoring import interval_coverage, weighted_interval_score
from pipeline.forecast import resolve_config
from pipeline.forecast.sources import SETTLED_DAYS
from pipeline.io import atomic_write_json
from pipeline.progress import rich_progress
from pipeline.training.model_store import default_store_root

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


def week_truth(final: EpiHistory, ends: list[pd.Timestamp]) -> np.ndarray:
    pos = final.dates.get_indexer(pd.DatetimeIndex(ends))
    return np.array([final.cases[p - DAYS_PER_WEEK + 1:p + 1].sum() for p in pos],
                    dtype=np.float64)


def vintage_forecasts(forecaster: Forecaster, histories: dict[str, EpiHistory],
                      completed: dict[str, CompletedHistories], data_date: pd.Timestamp,
                      levels: np.ndarray, seed: int, seconds: dict[str, float], pool: Panel, *,
                      drop14_reachable: Forecaster | None = None,
                      partial_week: bool = False) -> dict[str, dict[str, np.ndarray]]:
    """{method: {county: (H, Q)}} of one forecaster at one vintage, every county in one batch
    per method; ``seconds[method]`` accumulates the time each took."""
    calls: dict[str, Any] = {
        "nowcast": lambda: {c: f.quantiles for c, f in nowcast_then_forecast_places(
            completed, data_date, forecaster, levels, seed, panel=pool).items()},
        "drop14": lambda: truncated_forecasts(histories, data_date, forecaster, levels, seed,
                                              drop_days=14, panel=pool),
        "as_is": lambda: truncated_forecasts(histories, data_date, forecaster, levels, seed,
                                             drop_days=0, panel=pool)}
    if partial_week:
        calls["nowcast_with_partial_week"] = lambda: {
            c: f.quantiles for c, f in nowcast_then_forecast_places(
                completed, data_date, forecaster, levels, seed, partial_week=True,
                panel=pool).items()}
    if drop14_reachable is not None:
        calls["drop14_reachable_members"] = lambda: truncated_forecasts(
            histories, data_date, drop14_reachable, levels, seed, drop_days=14, panel=pool)
    out = {}
    for method, call in calls.items():
        t = time.perf_counter()
        out[method] = call()
        seconds[method] = seconds.get(method, 0.0) + time.perf_counter() - t
    return out


def evaluate_forecasts(vintages: list[CDPHVintage], chain: RevisionPairs,
                       counties: tuple[str, ...], config: DelayModelConfig,
                       nowcast_config: NowcastConfig, record: TrackRecordConfig,
                       store_root: Path,
                       seed: int) -> dict[str, Any]:
    latest = vintages[-1]
    levels = np.asarray(HUB_QUANTILE_LEVELS)
    autoets = AutoETSMember()
    rows: list[dict[str, Any]] = []
    reported: list[dict[str, Any]] = []
    models: dict[str, str] = {}
    reach: dict[str, Any] = {}
    seconds: dict[str, dict[str, float]] = {"published": {}, "autoets": {}, "nowcast": {},
                                            "members": {}}
    for vintage in vintages[:-1]:
        model, how = delay_model_at(vintage, chain, config)
        models[str(vintage.as_of.date())] = how
        weeks = hub_weeks(vintage.as_of)
        histories = {c: history_from_county(vintage.county(c)) for c in counties}
        t = time.perf_counter()
        completed = {c: complete_histories(h, nowcast_history(h, model, county=c,
                                                               config=nowcast_config, seed=seed))
                     for c, h in histories.items()}
        seconds["nowcast"][str(vintage.as_of.date())] = round(time.perf_counter() - t, 1)
        t = time.perf_counter()
        drop_origin = last_saturday(vintage.as_of - pd.Timedelta(days=14))
        # the pooled members' places as the run has them: the vintage less its last 14 days
        pool = Panel({c: h.up_to(vintage.as_of - pd.Timedelta(days=SETTLED_DAYS))
                      for c, h in histories.items()}, name="california-counties")
        refits = sorted({latest_refit_date(o, record.members.finetune.refit_every_weeks)
                         for o in (weeks.origin, drop_origin)})
        with rich_progress(f"members at {vintage.as_of.date()}") as progress:
            chosen = build_members(record.members, store_root, pool, refits, progress)
        published = Ensemble(tuple(chosen.members))
        seconds["members"][str(vintage.as_of.date())] = round(time.perf_counter() - t, 1)
        reach[str(vintage.as_of.date())] = drop14_reach(published, weeks, drop_origin)
        forecasts = {
            "published": vintage_forecasts(
                published, histories, completed, vintage.as_of, levels, seed,
                seconds["published"], pool,
                drop14_reachable=Ensemble(published.members,
                                          CombineConfig(beyond_reach="reachable-members",
                                                        calibration="none"))),
            "autoets": vintage_forecasts(autoets, histories, completed, vintage.as_of, levels,
                                         seed, seconds["autoets"], pool, partial_week=True)}
        for county in counties:
            truth = week_truth(history_from_county(latest.county(county)),
                               [w.end for w in weeks.weeks])
            for forecaster, methods in forecasts.items():
                for method, by_county in methods.items():
                    q = by_county[county]
                    # a week beyond the forecaster's reach has no forecast (NaN): not scored
                    reached = np.flatnonzero(np.isfinite(q).all(axis=1))
                    s = score(q[reached], truth[reached], levels)
                    for i, j in enumerate(reached):
                        w = weeks.weeks[j]
                        rows.append({"vintage": str(vintage.as_of.date()), "county": county,
                                     "forecaster": forecaster, "method": method,
                                     "horizon": w.horizon, "kind": w.kind,
                                     "wis": float(s["wis"][i]), "c50": bool(s["c50"][i]),
                                     "c90": bool(s["c90"][i]), "truth": truth[j],
                                     "median": float(q[j, 11])})
            reported += reported_shares(histories[county],
                                        history_from_county(latest.county(county)),
                                        completed[county], vintage, county)
        print(f"  {vintage.as_of.date()}: {len(counties)} counties ({how}); published "
              f"{sum(seconds['published'].values()):.0f} s, autoets "
              f"{sum(seconds['autoets'].values()):.0f} s so far")
    frame = pd.DataFrame(rows)
    return {"delay_model_per_vintage": models,
            "published": summarize_scores(frame[frame["forecaster"] == "published"]),
            "autoets": summarize_scores(frame[frame["forecaster"] == "autoets"]),
            "published_vs_autoets": published_vs_autoets(frame),
            "drop14_reach": reach,
            "reported_share_of_recent_weeks": summarize_reported(pd.DataFrame(reported)),
            "n_cells": int(frame.groupby(["vintage", "county"]).ngroups),
            "seconds": {k: {m: round(x, 1) for m, x in v.items()} for k, v in seconds.items()}}


def drop14_reach(published: Ensemble, weeks: Any, drop_origin: pd.Timestamp
                 ) -> dict[str, Any]:
    """Each hub week's step from the drop-14 origin and the members that reach it."""
    out: dict[str, Any] = {"drop14_origin": str(drop_origin.date()),
                           "origin": str(weeks.origin.date())}
    for w in weeks.weeks:
        step = int((w.end - drop_origin).days // DAYS_PER_WEEK)
        out[f"horizon_{w.horizon}"] = {
            "step_from_drop14_origin": step,
            "members": [m.name for m in published.members if reach(m, (step,))]}
    return out


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


def wis_ratios(frame: pd.DataFrame, method: str, reference: str,
               key: str = "method") -> pd.Series:
    """WIS(method) / WIS(reference) of the county × vintage cells both have (finite, > 0)."""
    a = frame[frame[key] == method].set_index(["vintage", "county"])["wis"]
    b = frame[frame[key] == reference].set_index(["vintage", "county"])["wis"]
    ratio = (a / b).replace([np.inf, -np.inf], np.nan).dropna()
    return ratio[ratio > 0]


def geometric_mean_ratio(frame: pd.DataFrame, method: str, reference: str,
                         key: str = "method") -> float | None:
    """The geometric mean over the county × vintage cells both have of the WIS ratio."""
    ratio = wis_ratios(frame, method, reference, key)
    return round(float(np.exp(np.log(ratio).mean())), 3) if len(ratio) else None


RATIOS = (("nowcast", "drop14"), ("nowcast", "drop14_reachable_members"), ("nowcast", "as_is"),
          ("nowcast_with_partial_week", "drop14"))


def summarize_scores(frame: pd.DataFrame) -> dict[str, Any]:
    out: dict[str, Any] = {}
    methods = set(frame["method"])
    for h in HUB_HORIZONS:
        g = frame[frame["horizon"] == h]
        pairs = [(a, b) for a, b in RATIOS if a in methods and b in methods]
        ratios = {f"geomean_wis_ratio_{a}_vs_{b}": geometric_mean_ratio(g, a, b)
                  for a, b in pairs}
        # the cells each ratio is over (both methods scored, ratio finite and > 0)
        ratio_cells = {f"{a}_vs_{b}": int(len(wis_ratios(g, a, b))) for a, b in pairs}
        out[f"horizon_{h}"] = {
            "kinds": sorted(set(g[g["method"] == "nowcast"]["kind"])),
            **ratios,
            "n_ratio_cells": ratio_cells,
            "n_cells": {m: int(len(x)) for m, x in g.groupby("method")},
            "mean_wis": {m: round(float(x["wis"].mean()), 1) for m, x in g.groupby("method")},
            "coverage50": {m: round(float(x["c50"].mean()), 3) for m, x in g.groupby("method")},
            "coverage90": {m: round(float(x["c90"].mean()), 3) for m, x in g.groupby("method")},
            "per_vintage_ratio_vs_drop14": {
                v: geometric_mean_ratio(x, "nowcast", "drop14") for v, x in g.groupby("vintage")},
            "per_vintage_ratio_vs_as_is": {
                v: geometric_mean_ratio(x, "nowcast", "as_is") for v, x in g.groupby("vintage")},
        }
        if "drop14_reachable_members" in methods:
            out[f"horizon_{h}"]["per_vintage_ratio_vs_drop14_reachable_members"] = {
                v: geometric_mean_ratio(x, "nowcast", "drop14_reachable_members")
                for v, x in g.groupby("vintage")}
    return out


def published_vs_autoets(frame: pd.DataFrame) -> dict[str, Any]:
    """Per method and hub horizon: geometric mean of WIS(published) / WIS(AutoETS)."""
    out: dict[str, Any] = {}
    for method in ("nowcast", "drop14", "as_is"):
        g = frame[frame["method"] == method]
        out[method] = {f"horizon_{h}": geometric_mean_ratio(g[g["horizon"] == h], "published",
                                                             "autoets", key="forecaster")
                       for h in HUB_HORIZONS}
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
    record = resolve_config("default", seed=args.seed).track_record_config()
    result["forecasts"] = evaluate_forecasts(vintages, chain, counties, config, nowcast_config,
                                             record, default_store_root(), args.seed)
    result["forecasts"]["forecasters"] = {
        "published": "the weekly run's published forecast (pipeline.combine.combiner.Ensemble of "
                     "pipeline.members.published.build_members): equal-weight log-"
                     "mixture of hub-baseline, growth-qr (pooled over the vintage's counties "
                     "less their last 14 days, each county's own left out), nf-growth and "
                     "nf-real (fine-tuned on the vintage's county windows at the latest refit "
                     "date <= the origin); each member mixed over the completions, then "
                     "averaged; no online calibration (nothing scored yet at one vintage). drop14 beyond the flows' 4 weeks: missing; "
                     "drop14_reachable_members: there the log average of hub-baseline and "
                     "growth-qr (a different forecaster)",
        "autoets": "autoets (pipeline.members.autoets) on every method"}
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
    print(json.dumps({f: {h: {k: v for k, v in x.items() if k.startswith("geomean")}
                          for h, x in result["forecasts"][f].items()}
                      for f in ("published", "autoets")}, indent=1))
    return result


if __name__ == "__main__":
    main()
