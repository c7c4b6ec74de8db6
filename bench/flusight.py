"""FluSight's influenza rounds, forecast in real time beside every team → bench/results/flusight.json.

The same engine and discipline as the COVID rounds (:mod:`bench.nhsn`, :mod:`pipeline.backtest.
hub_rounds`): every round of the shared FluSight data (``../shared/data/flusight``: 59 releases
2023-09-27 … 2025-06-18, two seasons) from the vintage released by its due date only, nowcast,
forecast by the published members, combined, reconciled, scored against the latest vintage.

* ``validation``: every round's file (weekly admissions: 23 quantiles and the hub's 100
  integer sample paths; the rate-change pmf; the peak targets where FluSight's config lists the
  round's season weeks, i.e. 2025-26 only) written with FluSight's ``tasks.json`` and validated
  against it (``n_files``, ``n_errors``, ``no_round``: reference dates the hub has no round
  for), then read back by the hubverse's own reader (``hubdata``: ``rows_read``).
* ``pairwise_relative_wis.{all, h0 … h3, "2023-24", "2024-25", US, states}``: ``wk inc flu
  hosp`` among the 16 teams (``FluSight-baseline`` = 1, horizons 0–3, the teams' rounds), with
  ``FluSight-ensemble``'s beside it and every team's (``teams``); the weekly flow alone and the
  other members in ``members_and_variants``.
* ``coverage50``/``coverage95`` over horizons 0–3.
* ``rate_change``: RPS and log score of the rate-change pmf (horizons 0–3) against the
  observed category, beside the climatology of the earlier seasons (the hub data hold no
  team's pmf); ``peak``: WIS of the peak's quantiles and log score of the peak week's pmf,
  beside the earlier seasons' climatology, over the rounds of each complete season.

The flu releases are imported with ``accept_revisions``: 27 of the 59 are otherwise held for
one Louisiana revision of a 2022 week (the per-location revision rule is issue 39's).

    python -m bench.flusight
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "flusight"
BASELINE = "FluSight-baseline"
ENSEMBLE = "FluSight-ensemble"


def _parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--hub", default=str(SHARED), help="the FluSight data (time series, "
                                                      "forecasts, hub-config)")
    p.add_argument("--out", default=None, help="output JSON path")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--reuse-backtest", default=None, metavar="PICKLE",
                   help="keep the backtest's result in PICKLE and read it from there when it "
                        "exists (to re-score without re-forecasting; same data and code)")
    return p.parse_args(argv)


def season(reference: Any) -> str:
    import pandas as pd

    start = pd.Timestamp(reference).year - (pd.Timestamp(reference).month < 8)
    return f"{start}-{str(start + 1)[2:]}"


def boards(scores: Any, target: str) -> dict[str, Any]:
    """Pairwise relative WIS of every model (FluSight-baseline = 1): overall, per horizon,
    per season, the US and the states."""
    from pipeline.evaluation.hub_leaderboard import LeaderboardConfig, hub_leaderboard

    scores = scores.assign(season=scores["reference_date"].map(season))
    config = LeaderboardConfig(target=target, baseline=BASELINE)
    out: dict[str, Any] = {}
    for name, cfg, by in (("all", config, ()), ("by_horizon", config, ("horizon",)),
                          ("by_season", config, ("season",)),
                          ("US", LeaderboardConfig(target=target, baseline=BASELINE,
                                                   locations="US"), ()),
                          ("states", LeaderboardConfig(target=target, baseline=BASELINE,
                                                       locations="states"), ())):
        out[name] = hub_leaderboard(scores, cfg, None, by=by).to_dict(orient="records")
    return out


def relative(board: dict[str, Any], model: str) -> dict[str, float | None]:
    """``model``'s relative WIS overall, per horizon (``h0`` …), per season, US, states."""
    def pick(rows: list[dict[str, Any]]) -> float | None:
        hit = [r for r in rows if r["model_id"] == model]
        return float(hit[0]["relative_wis"]) if hit else None

    out: dict[str, float | None] = {"all": pick(board["all"])}
    for r in board["by_horizon"]:
        if r["model_id"] == model:
            out[f"h{int(r['horizon'])}"] = float(r["relative_wis"])
    for r in board["by_season"]:
        if r["model_id"] == model:
            out[str(r["season"])] = float(r["relative_wis"])
    out["US"], out["states"] = pick(board["US"]), pick(board["states"])
    return out


def validate_round_files(result: Any, targets: Any, hub: Path) -> dict[str, Any]:
    """Every round's file written with FluSight's config, validated, read back by hubdata."""
    import shutil

    import hubdata
    import pandas as pd

    from pipeline.outputs.derived_round import derived_round_frame
    from pipeline.outputs.hub_conform import NoHubRoundError
    from pipeline.outputs.hub_tasks import target_model_task, task_values
    from pipeline.outputs.hubverse_round import (CDC_HUB_MODEL_ID, compound_sample_ids,
                                                 load_model_metadata, write_hub_round)
    from pipeline.outputs.hubverse_validation import HubValidationError, load_tasks_config

    tasks = load_tasks_config(hub / "hub-config" / "tasks.json")
    metadata = load_model_metadata(Path(__file__).resolve().parents[1] / "pipeline" / "outputs" / "model_metadata"
                                   / f"{CDC_HUB_MODEL_ID}.yml")
    n_files, errors, no_round, rows, notes = 0, [], [], 0, set()
    with tempfile.TemporaryDirectory(prefix="flusight-rounds-") as tmp:
        root = Path(tmp)
        shutil.copytree(hub / "hub-config", root / "hub-config")
        for i, rnd in enumerate(result.rounds):
            peak_task = target_model_task(tasks, rnd.reference.date(), "peak week inc flu hosp")
            peak_weeks = None if peak_task is None else [
                str(v) for v in task_values(peak_task["output_type"]["pmf"]["output_type_id"])]
            frame = pd.concat([result.round_frame(i), derived_round_frame(targets, i,
                                                                          peak_weeks)],
                              ignore_index=True)
            try:
                written = write_hub_round(compound_sample_ids(frame), hub_dir=root,
                                          model_id=CDC_HUB_MODEL_ID, tasks=tasks,
                                          metadata=metadata)
            except NoHubRoundError:
                no_round.append(str(rnd.reference.date()))
                continue
            except HubValidationError as error:
                errors.append(f"{rnd.reference.date()}: {error}")
                continue
            n_files += 1
            rows += len(written.frame)
            notes.update(n.split(":")[0] + ": " + n.split(": ", 1)[1].split(" (")[0]
                         for n in written.notes)
        table = hubdata.connect_hub(root).get_dataset().to_table()
        back = table.to_pandas()
    return {"n_files": n_files, "n_errors": len(errors), "errors": errors[:5],
            "no_round": no_round, "rows_written": rows, "hubdata": {
                "rows_read": len(back), "files": int(back["reference_date"].nunique()),
                "targets": sorted(back["target"].astype(str).unique()),
                "same_rows": len(back) == rows},
            "notes": sorted(notes)}


CLIMATOLOGY = ("climatology of the earlier seasons in the round's vintage (the hub data hold "
               "no team's pmf or peak forecast, FluSight-baseline's included)")


def derived_scores(targets: Any) -> dict[str, Any]:
    """Rate change (RPS, log score) and peak (WIS of the intensity, log score of the week),
    ours with the climatology's as ``baseline``, over the location-rounds observed; by season
    (and, for the rate change, by horizon)."""
    import numpy as np

    from pipeline.evaluation.categorical import log_score, ranked_probability_score
    from pipeline.evaluation.summary import score_cells

    seasons = np.array([season(r) for r in targets.references])
    every = np.ones(len(seasons), dtype=bool)

    def rate(mask: Any, k: Any = slice(None)) -> dict[str, Any]:
        obs = np.where(mask[None, :, None], targets.rate_observed, -1)[:, :, k]
        ok = obs >= 0

        def scores(pmf: Any) -> dict[str, float]:
            return {"rps": float(np.mean(ranked_probability_score(pmf[:, :, k], obs)[ok])),
                    "log_score": float(np.mean(log_score(pmf[:, :, k], obs)[ok]))}

        return scores(targets.rate) | {"baseline": scores(targets.rate_climatology),
                                       "n": int(ok.sum())}

    def peak(mask: Any) -> dict[str, Any]:
        seen = mask[None, :] & np.isfinite(targets.peak_observed) & \
            (targets.peak_week_observed >= 0) & np.isfinite(targets.peak_climatology).all(-1)
        week = np.where(seen, targets.peak_week_observed, -1)

        def scores(q: Any, pmf: Any) -> dict[str, float]:
            wis = score_cells(q, np.where(seen, targets.peak_observed, np.nan),
                              targets.levels).wis
            usable = np.where(seen[..., None], pmf, 1.0 / pmf.shape[-1])
            return {"wis": float(np.mean(wis[seen])),
                    "log_score": float(np.mean(log_score(usable, week)[seen]))}

        return scores(targets.peak, targets.peak_week) | {
            "baseline": scores(targets.peak_climatology, targets.peak_week_climatology),
            "n": int(seen.sum())}

    return {"rate_change": rate(every) | {
                "baseline_is": CLIMATOLOGY,
                "by_season": {s: rate(seasons == s) for s in sorted(set(seasons))},
                "by_horizon": {f"h{h}": rate(every, k) for k, h in enumerate((0, 1, 2, 3))}},
            "peak": peak(every) | {
                "baseline_is": CLIMATOLOGY, "rounds": "every round, scored once its season is "
                "complete in the latest release",
                "by_season": {s: peak(seasons == s) for s in sorted(set(seasons))}}}


def _backtest(vintages: Any, rounds: Any, latest: Any, seed: int) -> tuple[Any, float, float]:
    """Every round in real time: the published members (the context flow and gbqr), and as
    variants the weekly flow alone, with the seasonal member (the rule published until 2026-11)
    and with the hub baseline or growth-qr, the two flows (published until 2026-12-01), the
    context flow alone and with the other members, and skill-weighted averages; seconds to
    build the members and to forecast."""
    import dataclasses

    from pipeline.backtest.config import (Variant, bound_variants, letting_go_variants,
                                          skill_weighted_variants, tracking_rate_variants)
    from pipeline.backtest.hub_rounds import HubBacktestConfig, run_hub_rounds
    from pipeline.data.hub.nhsn_vintages import HOSP_FLU
    from pipeline.members.boosting import DEEP_GBQR, deep_trees, the_gbqr
    from pipeline.members.published import HubMembersConfig, build_hub_members
    from pipeline.training.model_store import default_store_root

    started = time.perf_counter()
    # no ED-share vintage of influenza in the shared data: the seasonal member reads the
    # admissions' own earlier seasons (its climatology left empty)
    members = build_hub_members(HubMembersConfig(boosting_beside=True),
                                default_store_root(), vintages, (),
                                target=HOSP_FLU, seasonal_own_seasons=True)
    gbqr = the_gbqr(members.published)
    deep = dataclasses.replace(gbqr, name=DEEP_GBQR, config=deep_trees(gbqr.config))
    t_members = time.perf_counter() - started
    reach = HubBacktestConfig().combine      # the published rule (the hub's 95 % outer interval)
    pair = ("nf-weekly", "seasonal")        # COVID-19's admissions pair
    variants = (Variant("v-flow-alone", reach, ("nf-weekly",)),
                Variant("v-nf-weekly+seasonal (published for influenza until 2026-11)", reach,
                        pair),
                Variant("v-flow+seasonal+baseline", reach, (*pair, "hub-baseline")),
                Variant("v-flow+growth-qr", reach, ("nf-weekly", "growth-qr")),
                Variant("v-flow+seasonal+growth-qr", reach, (*pair, "growth-qr")),
                # the context flow (issue 38), alone and in the ED share's published pair
                Variant("v-nf-context alone", reach, ("nf-context",)),
                Variant("v-nf-context+seasonal", reach, ("nf-context", "seasonal")),
                Variant("v-nf-context+growth-qr", reach, ("nf-context", "growth-qr")),
                Variant("v-nf-context+nf-weekly+seasonal", reach,
                        ("nf-context", "nf-weekly", "seasonal")),
                # the pooled gradient-boosted member (issue 51) beside the flows (the published
                # pair, nf-context + gbqr, since 2026-12-01), equally weighted, and the members
                # weighted by their skill on the rounds already scored
                Variant("v-nf-context+nf-weekly (published for influenza until 2026-12-01)",
                        reach, ("nf-context", "nf-weekly")),
                Variant("v-nf-context+nf-weekly+gbqr", reach,
                        ("nf-context", "nf-weekly", "gbqr")),
                Variant(f"v-nf-context+{deep.name} (31 leaves at rate 0.1, California's)",
                        reach, ("nf-context", deep.name)),
                Variant("v-nf-context+nf-weekly+gbqr+growth-qr", reach,
                        ("nf-context", "nf-weekly", "gbqr", "growth-qr")),
                *skill_weighted_variants(reach, ("nf-context", "gbqr")),
                *skill_weighted_variants(reach, ("nf-context", "nf-weekly", "gbqr")),
                *skill_weighted_variants(reach, ("nf-context", "nf-weekly", "gbqr", "growth-qr",
                                                 "seasonal"), ("inverse-wis",)),
                # the published rule's bound on falls (issue 51): off, and on rises too
                *bound_variants(reach),
                *tracking_rate_variants(reach),
                *letting_go_variants(reach),
                Variant("v-log-mixture, no online calibration",
                        dataclasses.replace(reach, calibration="none")))
    result = run_hub_rounds(rounds, latest, members.published,
                            HubBacktestConfig(variants=variants, seed=seed),
                            references=(*members.references, deep))
    return result, t_members, time.perf_counter() - started - t_members


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = _parse(argv)
    import pandas as pd

    from pipeline.backtest.hub_result import summary_by_horizon
    from pipeline.combine.combiner import PUBLISHED
    from pipeline.data.hub.nhsn_vintages import HOSP_FLU
    from pipeline.data.hub.target_import import import_hub_time_series
    from pipeline.data.hub.team_forecasts import quantile_table, read_hub_forecasts, \
        read_target_data
    from pipeline.evaluation.hub_leaderboard import score_quantile_forecasts
    from pipeline.hub_round.run import load_vintages
    from pipeline.io import atomic_write_json
    from pipeline.outputs.derived_round import derive_targets
    from pipeline.panels.hub import hub_rounds

    hub = Path(args.hub)
    started = time.perf_counter()
    # FluSight's releases into the cache; its revisions accepted (module docstring)
    import_hub_time_series(hub, if_empty=True, accept_revisions=True)
    vintages = load_vintages(HOSP_FLU)
    rounds = hub_rounds(vintages)
    latest = vintages[-1][1]
    reuse = Path(args.reuse_backtest) if args.reuse_backtest else None
    if reuse is not None and reuse.exists():
        import pickle

        result = pickle.loads(reuse.read_bytes())
        t_members, t_backtest = 0.0, time.perf_counter() - started
    else:
        result, t_members, t_backtest = _backtest(vintages, rounds, latest, args.seed)
        if reuse is not None:
            import pickle

            reuse.write_bytes(pickle.dumps(result))
    print(f"{len(rounds)} rounds forecast in {t_backtest:.0f} s", flush=True)

    truth = read_target_data(hub / "time-series.parquet", HOSP_FLU)
    truth = truth[truth["value"].notna()]      # weeks the latest release leaves empty
    teams = score_quantile_forecasts(quantile_table(read_hub_forecasts(
        hub / "hub-forecasts.parquet", targets=[HOSP_FLU])), truth.assign(target=HOSP_FLU))
    team_rounds = set(pd.to_datetime(teams["reference_date"]))
    ours = result.scores()
    ours = ours[pd.to_datetime(ours["reference_date"]).isin(team_rounds)]
    per_model = {}
    for name in sorted(set(ours["model_id"])):
        board = boards(pd.concat([teams, ours[ours["model_id"] == name]], ignore_index=True),
                       HOSP_FLU)
        per_model[name] = relative(board, name) | {
            "coverage": summary_by_horizon(result, name)["h0-3"]}
    published = boards(pd.concat([teams, ours[ours["model_id"] == PUBLISHED]],
                                 ignore_index=True), HOSP_FLU)
    coverage = summary_by_horizon(result, PUBLISHED)
    scored = result.summary(PUBLISHED, [h for h in result.horizons if h >= 0])

    locations = pd.read_csv(hub / "locations.csv", dtype={"location": str})
    population = {str(p): float(n) for p, n in zip(locations["location"],
                                                    locations["population"])}
    targets = derive_targets(result, latest, population, seed=args.seed)
    derived = derived_scores(targets)
    validation = validate_round_files(result, targets, hub)
    # the online calibration's cost: WIS over the same average uncalibrated (horizons 0-3),
    # of the published forecast and each variant of its members
    costs = result.calibration_cost([h for h in result.horizons if h >= 0],
                                    (PUBLISHED, *result.variants_of_members()))
    out = {
        "target": HOSP_FLU,
        "pairwise_relative_wis": relative(published, PUBLISHED),
        "ensemble_relative_wis": relative(published, ENSEMBLE),
        "coverage50": coverage["h0-3"]["coverage50"],
        "coverage95": coverage["h0-3"]["coverage95"],
        # their 95 % moving-block bootstrap intervals over the rounds (horizons 0-3)
        "coverage50_interval": scored["coverage50_interval"],
        "coverage95_interval": scored["coverage95_interval"],
        "coverage_by_horizon": coverage,
        # coverage (with its bootstrap interval) by the phase of the epidemic at each origin
        "by_phase": scored["by_regime"],
        # the online calibration's cost: published WIS over the same average uncalibrated
        # (horizons 0-3), over every round and in the worst window of 15 consecutive rounds
        "calibration_cost_by_window": costs[PUBLISHED],
        "calibration_cost_variants": {n: c for n, c in costs.items() if n != PUBLISHED},
        # the published bound on falls, and each forecaster's share of quantiles beyond it
        # (the rounds' weekly steps; the published forecast after its reconciliation)
        "plausibility": (result.backtest.plausibility() if result.backtest.bounds is not None
                         else {"bound": None, "why": "a proportion: not bounded"}),
        "rank": [r["model_id"] for r in published["all"]].index(PUBLISHED) + 1,
        "n_models": len(published["all"]),
        "teams": {r["model_id"]: {"relative_wis": float(r["relative_wis"]),
                                  "n_forecasts": int(r["n_forecasts"]),
                                  "n_rounds": int(r["n_rounds"])} for r in published["all"]},
        "teams_by_season": published["by_season"],
        "members_and_variants": per_model,
        "reconciliation": result.reconciliation(),
        "rate_change": derived["rate_change"],
        "peak": derived["peak"],
        "validation": validation,
        "n_rounds": len(rounds), "n_rounds_with_teams": len(team_rounds),
        "n_locations": len(result.places),
        "rounds": {"first": str(rounds[0].reference.date()),
                   "last": str(rounds[-1].reference.date())},
        "data": "FluSight time-series.parquet imported with accept_revisions (27 of 59 "
                "releases are otherwise held for one Louisiana revision of 2022)",
        "seconds": {"members": round(t_members, 1), "backtest_rounds": round(t_backtest, 1),
                    "total": round(time.perf_counter() - started, 1)},
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}",
        "python": sys.version.split()[0],
        "command": "python -m bench.flusight " + " ".join(argv if argv is not None
                                                          else sys.argv[1:]),
    }
    print(f"published pairwise relative WIS {out['pairwise_relative_wis']} (rank "
          f"{out['rank']} of {out['n_models']}); ensemble {out['ensemble_relative_wis']}")
    print(f"coverage {out['coverage50']:.3f} {out['coverage50_interval']}/"
          f"{out['coverage95']:.3f} {out['coverage95_interval']}; validation "
          f"{validation['n_files']} files, {validation['n_errors']} errors, hubdata "
          f"{validation['hubdata']['rows_read']} rows")
    for name in ("rate_change", "peak"):
        part = derived[name]
        print(f"{name}: " + ", ".join(f"{k} {part[k]:.4g} (baseline {part['baseline'][k]:.4g})"
                                      for k in part["baseline"]) + f", n {part['n']}")
    for name, m in per_model.items():
        print(f"  {name:40s} all {m['all']}  " + " ".join(
            f"{k}={v:.3f}" for k, v in m.items() if k.startswith("h") and v is not None))
    path = Path(args.out) if args.out else RESULTS / "flusight.json"
    atomic_write_json(path, json.loads(json.dumps(out, default=str)))
    print(f"→ {path}")
    return out


if __name__ == "__main__":
    main()
