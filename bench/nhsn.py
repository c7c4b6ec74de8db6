"""The CDC COVID-19 Forecast Hub's rounds, forecast in real time → bench/results/nhsn.json.

Every round the shared hub data have a vintage for (``../shared/data/nhsn``: 44 admissions
rounds 2024-11-23 … 2025-09-27, 15 ED-share rounds from 2025-06-21): each round from the vintage
released by its due date only, nowcast, forecast by the members, combined, reconciled
(:mod:`pipeline.backtest.hub_rounds`), written as the hub's file, scored against the latest
vintage, and ranked among every team of the hub by pairwise relative WIS (Cramer et al. 2022;
``CovidHub-baseline`` = 1) on the forecasts both made, horizons 0–3, with the hub's exclusions;
also by period (``teams_by_period``): the rounds due before the first ED vintage, where the
seasonal member and gbqr have no ED share to read, and those from it on. Coverage
(``coverage50``, ``coverage95``) is over horizons 0–3, the ones the hub scores;
``coverage_by_horizon`` has −1 too.

Beside the published forecast: every member alone, the variants (the members the issue named —
hub baseline, growth-qr, the flows — and others), and the published design with the seasonal
member's climatology taken from a later vintage for the rounds before the ED share was released
(``*-pseudo``: not real time, reported for what it would have been).

``seconds``: ``backtest`` (this design backtest of admissions: members built, every round and
variant), and from the command line in a fresh data folder ``scratch`` (import, training, every
round, publish), ``round`` (the next run, models and past rounds stored) and
``round_without_memo``.

    python -m bench.nhsn                  # both targets, every round
    python -m bench.nhsn --target hosp    # admissions only
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "nhsn"
TEAM_MODEL = "flowcast-nfhub"


def _parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--target", choices=("hosp", "ed", "both"), default="both")
    p.add_argument("--hub", default=str(SHARED), help="the hub data (time series, forecasts)")
    p.add_argument("--out", default=None, help="output JSON path")
    p.add_argument("--files", default=None,
                   help="write every round's hub file under DIR/model-output/<model>/")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--flusight", default=str(SHARED.parent / "flusight"),
                   help="FluSight's data (the influenza ablation's extra windows)")
    p.add_argument("--no-ablations", action="store_true", help="skip the context flow's ablations")
    p.add_argument("--no-transformer", action="store_true",
                   help="skip the transformer-encoder ablation (its pre-training is the slowest)")
    p.add_argument("--keep-other", action="store_true",
                   help="with one --target: keep the other target's figures already in the "
                        "output file (the two targets run as two commands)")
    p.add_argument("--influenza", action="store_true",
                   help="instead: the context flow alone on FluSight's rounds (→ influenza)")
    p.add_argument("--no-timing", action="store_true",
                   help="skip the command-line runs that time a round (seconds.round, scratch)")
    return p.parse_args(argv)


def timed_rounds(hub: Path) -> dict[str, float]:
    """``flowcast forecast --hub covid`` offline in a fresh data folder, as a new user runs it:
    ``scratch`` (import of the hub's data, the weekly flow trained, every round forecast, the
    round published), then ``round`` (the next week's run: models and past rounds' forecasts
    stored) and ``round_without_memo`` (models stored, every round re-forecast)."""
    import shutil
    import subprocess
    import tempfile

    flowcast = str(Path(sys.executable).with_name("flowcast"))
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="flowcast-hub-") as tmp:
        env = {**os.environ, "FLOWCAST_DATA_DIR": f"{tmp}/data",
               "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1"}
        forecast = [flowcast, "forecast", "--hub", "covid", "--data-source", "cache",
                    "--output-dir", f"{tmp}/reports"]
        for name, commands in (
                ("scratch", [[flowcast, "data", "import", str(hub / "time-series.parquet")],
                             forecast]),
                ("round", [forecast]), ("round_without_memo", [forecast])):
            if name == "round_without_memo":
                shutil.rmtree(f"{tmp}/data/forecast-memo")
            started = time.perf_counter()
            for command in commands:
                subprocess.run(command, env=env, check=True, stdout=subprocess.DEVNULL)
            out[name] = round(time.perf_counter() - started, 1)
            print(f"hub round from the command line, {name}: {out[name]} s", flush=True)
    return out


def leaderboards(ours: Any, teams: Any, target: str, exclusions: Any,
                 climatology_from: Any = None) -> dict[str, Any]:
    """Pairwise relative WIS of every model with ours added: overall, by horizon, US, states,
    and (``climatology_from``: the first climatology vintage's release) by period — the rounds
    due before it, where the seasonal member has no climatology yet, and those from it on."""
    import numpy as np
    import pandas as pd

    from pipeline.evaluation.hub_leaderboard import LeaderboardConfig, hub_leaderboard
    from pipeline.panels.hub import DUE_DAYS_BEFORE_REFERENCE

    scores = pd.concat([teams, ours], ignore_index=True)
    if climatology_from is not None:
        due = scores["reference_date"] - pd.Timedelta(days=DUE_DAYS_BEFORE_REFERENCE)
        scores = scores.assign(period=np.where(due >= pd.Timestamp(climatology_from),
                                               "with climatology", "before climatology"))
    out: dict[str, Any] = {}
    for name, config, by in (
            ("all", LeaderboardConfig(target=target), ()),
            ("by_horizon", LeaderboardConfig(target=target), ("horizon",)),
            ("US", LeaderboardConfig(target=target, locations="US"), ()),
            ("states", LeaderboardConfig(target=target, locations="states"), ()),
            *((("by_period", LeaderboardConfig(target=target), ("period",)),)
              if climatology_from is not None else ())):
        table = hub_leaderboard(scores, config, exclusions, by=by)
        out[name] = table.to_dict(orient="records")
    return out


def relative(board: dict[str, Any], model: str) -> dict[str, float | None]:
    """A model's relative WIS overall and per horizon from :func:`leaderboards`."""
    rows = {r["model_id"]: r for r in board["all"] if "horizon" not in r}
    out: dict[str, float | None] = {"all": _value(rows.get(model))}
    for r in board["by_horizon"]:
        if r["model_id"] == model:
            out[f"h{int(r['horizon'])}"] = float(r["relative_wis"])
    for part in ("US", "states"):
        out[part] = _value({r["model_id"]: r for r in board[part]}.get(model))
    for r in board.get("by_period", []):
        if r["model_id"] == model:
            out[str(r["period"])] = float(r["relative_wis"])
    return out


def _value(row: dict[str, Any] | None) -> float | None:
    return None if row is None else float(row["relative_wis"])


def influenza_vintages(flusight: Path) -> list[Any]:
    """FluSight's influenza admissions of the same 53 places, one panel per release."""
    import pandas as pd

    from pipeline.data.hub.locations import POPULATION
    from pipeline.panels.hub import vintage_panel

    frame = pd.read_parquet(flusight / "time-series.parquet")
    out = []
    for as_of in sorted(frame["as_of"].unique()):
        released = pd.Timestamp(str(as_of))
        rows = frame[frame["as_of"] == as_of].rename(columns={"observation": "value"})
        out.append((released, vintage_panel(rows, "wk inc flu hosp", POPULATION, released)))
    return out


def influenza_figure(args: argparse.Namespace) -> dict[str, Any]:
    """The context flow alone on FluSight's rounds (influenza admissions of the 53 places), in
    real time from each round's release, against every FluSight team (``FluSight-baseline``
    = 1), overall and per season. Its climatology is influenza's own history (weeks from
    2022-02) as released by the round; there is no other signal."""
    import numpy as np
    import pandas as pd

    from bench.flusight import boards
    from pipeline.backtest.hub_result import summary_by_horizon
    from pipeline.backtest.hub_rounds import HubBacktestConfig, run_hub_rounds
    from pipeline.data.hub.locations import POPULATION
    from pipeline.data.hub.team_forecasts import quantile_table, read_hub_forecasts, \
        read_target_data
    from pipeline.evaluation.hub_leaderboard import score_quantile_forecasts
    from pipeline.members.hub_baseline import HubBaseline, HubBaselineConfig
    from pipeline.members.nf.context import TrainingPool, fit_context_member
    from pipeline.members.nf.context_features import ContextChannels, ContextSources
    from pipeline.members.published import HubMembersConfig, context_channels
    from pipeline.panels.hub import hub_rounds
    from pipeline.training.model_store import default_store_root

    started = time.perf_counter()
    flusight, target = Path(args.flusight), "wk inc flu hosp"
    vintages = influenza_vintages(flusight)
    config = HubMembersConfig()
    pool = TrainingPool(vintages, ContextSources((), tuple(vintages), POPULATION))
    member = fit_context_member(config.context, config.context_refit, [pool],
                                default_store_root(),
                                channels=context_channels(config, own_seasons=True),
                                n_seeds=config.context_seeds)
    # the season, which COVID-19's two targets score better without (``ablations``)
    no_season = fit_context_member(config.context, config.context_refit, [pool],
                                   default_store_root(), channels=ContextChannels(season=False),
                                   name="nf-context-no-season", n_seeds=config.context_seeds)
    rounds = hub_rounds(vintages)
    result = run_hub_rounds(rounds, vintages[-1][1], [member],
                            HubBacktestConfig(seed=args.seed, reconcile="never"),
                            references=[HubBaseline(HubBaselineConfig(n_samples=10_000)),
                                        no_season])
    truth = read_target_data(flusight / "time-series.parquet", target)
    truth = truth[np.isfinite(truth["value"].to_numpy(dtype=np.float64))]   # unreported weeks
    teams = score_quantile_forecasts(quantile_table(read_hub_forecasts(
        flusight / "hub-forecasts.parquet", targets=[target])), truth.assign(target=target))
    # FluSight's own leaderboards (bench.flusight), with one of ours beside every team
    mine, alone = (boards(pd.concat([teams, result.scores([m.name])], ignore_index=True), target)
                   for m in (member, no_season))

    def relative(board: dict[str, Any], name: str) -> float:
        return next(float(r["relative_wis"]) for r in board["all"] if r["model_id"] == name)

    def seasons(board: dict[str, Any], name: str) -> dict[str, float]:
        return {str(r["season"]): float(r["relative_wis"])
                for r in board["by_season"] if r["model_id"] == name}

    return {"command": "python -m bench.nhsn --influenza", "member": member.name,
            "relative_wis": relative(mine, member.name), "n_rounds": len(rounds),
            "by_season": seasons(mine, member.name),
            "teams": {str(r["model_id"]): float(r["relative_wis"]) for r in mine["all"]},
            "teams_by_season": mine["by_season"],
            "coverage": summary_by_horizon(result, member.name)["h0-3"],
            "ablations": {"without the season": {
                "relative_wis": relative(alone, no_season.name),
                "by_season": seasons(alone, no_season.name),
                "coverage": summary_by_horizon(result, no_season.name)["h0-3"]}},
            "refits": len(member.models), "seconds": round(time.perf_counter() - started, 1)}


def ablation_members(target: str, vintages: list[Any], climatology: list[Any],
                     other: list[Any], args: argparse.Namespace) -> list[tuple[str, Any]]:
    """The context flow's seeds one by one, and the flow with each context group it reads left
    out in turn and each it leaves out added (the season, for COVID-19), with the transformer
    encoder, without refits (the prior alone) and, for admissions,
    with influenza windows added: ``(label, member)``, each scored beside the members under
    its own name. Every ablation mixes the same seeds as the published member (one seed is
    too noisy to resolve a channel: the seeds alone differ by 0.06 or more)."""
    import dataclasses

    from pipeline.members.nf.context import TrainingPool, fit_context_member
    from pipeline.members.nf.context_features import ContextChannels
    from pipeline.members.published import HubMembersConfig, context_channels, context_sources
    from pipeline.panels.hub import is_share
    from pipeline.training.model_store import default_store_root

    config = HubMembersConfig()
    pool = TrainingPool(vintages, context_sources(target, climatology, other))
    store = default_store_root()
    published = context_channels(config, own_seasons=False)

    def fit(name: str, pools: list[Any], channels: Any = published,
            flow: Any = config.context, refit: Any = config.context_refit,
            n_seeds: int = config.context_seeds) -> Any:
        return fit_context_member(flow, refit, pools, store, channels=channels, name=name,
                                  n_samples=500 - 500 % n_seeds, n_seeds=n_seeds)

    out: list[tuple[str, Any]] = []
    for k in range(config.context_seeds):
        out.append((f"seed {k} alone", fit(
            f"nf-context-seed-{k}", [pool],
            flow=dataclasses.replace(config.context, seed=config.context.seed + k),
            refit=dataclasses.replace(config.context_refit, seed=config.context_refit.seed + k),
            n_seeds=1)))
    for group in ("other_signal", "season", "climatology", "scale"):
        # each group the published flow reads left out in turn; one it leaves out, added
        if getattr(published, group):
            channels = dataclasses.replace(published, **{group: False})
            out.append((f"without {group.replace('_', ' ')}",
                        fit(f"nf-context-no-{group}", [pool], channels)))
        else:
            out.append((f"with {group.replace('_', ' ')}", fit(
                f"nf-context-with-{group}", [pool],
                dataclasses.replace(published, **{group: True}))))
    if not args.no_transformer:
        out.append(("transformer encoder", fit(
            "nf-context-transformer", [pool],
            flow=dataclasses.replace(config.context, encoder="transformer"))))
    prior = fit("nf-context-prior-only", [pool])
    out.append(("prior only (no refit)", dataclasses.replace(prior, models={})))
    if not is_share(target) and (Path(args.flusight) / "time-series.parquet").exists():
        flu = TrainingPool(influenza_vintages(Path(args.flusight)), context_sources(
            target, (), ()), ContextChannels(other_signal=False, season=False,
                                             climatology=False))
        out.append(("with influenza windows", fit("nf-context-influenza", [pool, flu])))
    return out


def gbqr_variants(reach: Any, names: list[str], own_signal: str) -> list[Any]:
    """gbqr beside the published members ``names``: on the target's own signal alone
    (``own_signal``) or with LightGBM's own trees (California's) in place of the published
    gbqr, or each put in where the average leaves it out (the ED share)."""
    from pipeline.backtest.config import Variant
    from pipeline.members.boosting import DEEP_GBQR

    without = [n for n in names if n != "gbqr"]
    own = Variant("v-published, gbqr on its own signal", reach, (*without, own_signal))
    deep = Variant(f"v-published, {DEEP_GBQR} (31 leaves at rate 0.1, California's)", reach,
                   (*without, DEEP_GBQR))
    if "gbqr" in names:
        return [own, deep]
    return [Variant("v-published+gbqr", reach, (*names, "gbqr")), own, deep]


def run_target(target: str, args: argparse.Namespace, climatology: list[Any], teams: Any,
               exclusions: Any) -> tuple[dict[str, Any], Any]:
    """The target's figures, and its rounds' result (the files of ``--files``)."""
    import dataclasses

    import numpy as np
    import pandas as pd

    from pipeline.backtest.config import (Variant, bound_variants, letting_go_variants,
                                          skill_weighted_variants, tracking_rate_variants)
    from pipeline.backtest.hub_result import RECONCILED, UNRECONCILED, summary_by_horizon
    from pipeline.backtest.hub_rounds import HubBacktestConfig, run_hub_rounds
    from pipeline.combine.combiner import LOG_AVERAGE, PUBLISHED, UNCALIBRATED
    from pipeline.hub_round.run import load_vintages
    from pipeline.members.boosting import (DEEP_GBQR, BoostingConfig, PooledBoostingMember,
                                           deep_trees, the_gbqr)
    from pipeline.members.published import HubMembersConfig, build_hub_members
    from pipeline.members.seasonal import SeasonalGrowthMember
    from pipeline.panels.hub import HOSP_COVID, hub_rounds, is_share
    from pipeline.training.model_store import default_store_root

    started = time.perf_counter()
    vintages = load_vintages(target)
    rounds = hub_rounds(vintages)
    latest = vintages[-1][1]
    other = load_vintages(HOSP_COVID) if is_share(target) else climatology
    members = build_hub_members(HubMembersConfig(boosting_beside=True),
                                default_store_root(), vintages,
                                climatology, target=target, other_signal=other)
    t_members = time.perf_counter() - started
    ablated = [] if args.no_ablations else ablation_members(target, vintages, climatology,
                                                           other, args)
    t_ablations = time.perf_counter() - started - t_members
    # gbqr on the target's own signal alone (issue 51: the published gbqr reads both)
    own_signal = PooledBoostingMember(BoostingConfig(), name="gbqr-own-signal")
    gbqr = the_gbqr((*members.published, *members.references))
    deep = dataclasses.replace(gbqr, name=DEEP_GBQR, config=deep_trees(gbqr.config))
    first_ed = climatology[0]
    pseudo = SeasonalGrowthMember(((pd.Timestamp("2000-01-01"), first_ed[1]),),
                                  name="seasonal-pseudo")
    names = [m.name for m in members.published]
    reach = HubBacktestConfig().combine      # the published rule (the hub's 95 % outer interval)
    variants = (
        Variant("v-flow-alone", reach, ("nf-weekly",)),
        Variant("v-issue-members (baseline, growth-qr, flows)", reach,
                ("hub-baseline", "growth-qr", "nf-weekly", "nf-real")),
        Variant("v-published+hub-baseline", reach, (*names, "hub-baseline")),
        Variant("v-published+growth-qr", reach, (*names, "growth-qr")),
        Variant("v-nf-real+seasonal (published for the ED share)", reach,
                ("nf-real", "seasonal")),
        Variant("v-nf-weekly+seasonal (published for admissions until 2026-11)", reach,
                ("nf-weekly", "seasonal")),
        Variant("v-nf-context+seasonal", reach, ("nf-context", "seasonal")),
        Variant("v-nf-context+nf-weekly+seasonal", reach,
                ("nf-context", "nf-weekly", "seasonal")),
        Variant("v-nf-context+nf-real+seasonal", reach, ("nf-context", "nf-real", "seasonal")),
        Variant("v-nf-context alone", reach, ("nf-context",)),
        Variant("v-log-average (the rule published until 2026-11)",
                dataclasses.replace(LOG_AVERAGE, beyond_reach="reachable-members")),
        Variant("v-log-mixture, no online calibration",
                dataclasses.replace(reach, calibration="none")),
        # the published rule's bound on falls (issue 51): left off, and put on rises too
        *bound_variants(reach),
        *tracking_rate_variants(reach),
        *letting_go_variants(reach),
        Variant("v-linear-average", dataclasses.replace(reach, scale="linear")),
        # the seasonal member's climatology from a later vintage, in the four-member average
        # published for admissions until 2026-12-01 (the pair has no seasonal member)
        Variant("v-nf-context+nf-weekly+seasonal-pseudo+gbqr (ED climatology from a later "
                "vintage)", reach, ("nf-context", "nf-weekly", "seasonal-pseudo", "gbqr")),
        # the pooled gradient-boosted member (issue 51): on the target's own signal alone, and
        # beside the share's members; the admissions' averages published before the pair
        # (nf-context + gbqr since 2026-12-01) and the pair for the share; equally weighted,
        # and the members weighted by their skill on the rounds already scored
        *gbqr_variants(reach, names, own_signal.name),
        Variant("v-nf-context+nf-weekly+seasonal+gbqr (published for admissions until "
                "2026-12-01)", reach, ("nf-context", "nf-weekly", "seasonal", "gbqr")),
        Variant("v-nf-context+gbqr", reach, ("nf-context", "gbqr")),
        Variant("v-nf-context+nf-weekly+gbqr", reach, ("nf-context", "nf-weekly", "gbqr")),
        Variant("v-nf-context+seasonal+gbqr", reach, ("nf-context", "seasonal", "gbqr")),
        *skill_weighted_variants(reach, ("nf-context", "gbqr")),
        *skill_weighted_variants(reach, ("nf-context", "seasonal", "gbqr")),
        *skill_weighted_variants(reach, ("nf-weekly", "seasonal", "gbqr", "nf-context",
                                         "growth-qr"), ("inverse-wis",)),
    )
    built = {m.name for m in (*members.published, *members.references)} | {
        pseudo.name, own_signal.name, deep.name}
    variants = tuple(v for v in variants if set(v.members or ()) <= built
                     and not (v.combine == reach and set(v.members or ()) == set(names)))
    result = run_hub_rounds(rounds, latest, members.published,
                            HubBacktestConfig(variants=variants, seed=args.seed),
                            references=(*members.references, pseudo, own_signal, deep,
                                        *[m for _, m in ablated]))
    t_backtest = time.perf_counter() - started - t_members - t_ablations
    ours = ours_all = result.scores()
    board_names = [PUBLISHED, UNRECONCILED, RECONCILED, *[m.name for m in members.published],
                   *[m.name for m in (*members.references, pseudo, own_signal, deep)],
                   *[v.name for v in variants]]
    ours = ours[ours["model_id"].isin(board_names)]
    per_model = {}
    for name in board_names:
        if name not in set(ours["model_id"]):
            continue
        board = leaderboards(ours[ours["model_id"] == name], teams, target, exclusions,
                             first_ed[0])
        scored_h = result.summary(name, [h for h in result.horizons if h >= 0])
        per_model[name] = relative(board, name) | {
            "coverage": summary_by_horizon(result, name),
            "coverage50_interval": scored_h["coverage50_interval"],
            "coverage95_interval": scored_h["coverage95_interval"]}
    published = leaderboards(ours[ours["model_id"] == PUBLISHED], teams, target, exclusions,
                             first_ed[0])
    coverage = per_model[PUBLISHED]["coverage"]
    scored = result.summary(PUBLISHED, [h for h in result.horizons if h >= 0])
    wis = ours_all[ours_all["horizon"] >= 0].groupby("model_id")["wis"].sum()
    ablations = {}
    for label, member in ablated:
        board = leaderboards(ours_all[ours_all["model_id"] == member.name], teams, target,
                             exclusions, first_ed[0])
        ablations[label] = {"member": member.name} | relative(board, member.name) | {
            "coverage": summary_by_horizon(result, member.name)}
    for name in ("nf-context", "nf-weekly", "seasonal", PUBLISHED):
        if name in per_model:            # the table's reference rows
            ablations.setdefault(f"[{name}]", {"member": name} | {
                k: v for k, v in per_model[name].items()})
    # the online calibration's cost: WIS over the same average uncalibrated (horizons 0-3),
    # of the published forecast and each variant of its members
    costs = result.calibration_cost([h for h in result.horizons if h >= 0],
                                    (PUBLISHED, *result.variants_of_members()))
    return {
        "target": target,
        "pairwise_relative_wis": relative(published, PUBLISHED),
        "coverage50": coverage["h0-3"]["coverage50"],
        "coverage95": coverage["h0-3"]["coverage95"],
        "coverage50_interval": scored["coverage50_interval"],
        "coverage95_interval": scored["coverage95_interval"],
        # coverage (with its bootstrap interval) by the phase of the epidemic at each origin
        "by_phase": scored["by_regime"],
        # the online calibration's cost: published WIS over the same average uncalibrated
        # (horizons 0-3, every round and location, both reconciled)
        "calibration_cost": float(wis[PUBLISHED] / wis[UNCALIBRATED]),
        # the same over every round and in the worst window of 15 consecutive rounds
        "calibration_cost_by_window": costs[PUBLISHED],
        "calibration_cost_variants": {n: c for n, c in costs.items() if n != PUBLISHED},
        # the published bound on falls, and each forecaster's share of quantiles beyond it
        # (the rounds' weekly steps; the published forecast after its reconciliation)
        "plausibility": (result.backtest.plausibility() if result.backtest.bounds is not None
                         else {"bound": None, "why": "a proportion: not bounded"}),
        "coverage_by_horizon": coverage,
        "ablations": ablations,
        "n_rounds": len(rounds), "n_locations": len(result.places),
        "rounds": {"first": str(rounds[0].reference.date()),
                   "last": str(rounds[-1].reference.date())},
        "teams": {r["model_id"]: {"relative_wis": float(r["relative_wis"]),
                                  "n_forecasts": int(r["n_forecasts"]),
                                  "n_rounds": int(r["n_rounds"])}
                  for r in published["all"]},
        "teams_by_horizon": published["by_horizon"],
        "climatology_from": str(pd.Timestamp(first_ed[0]).date()),
        "teams_by_period": published["by_period"],
        "members_and_variants": per_model,
        # the gap before reconciling; where the published forecast was reconciled (where
        # that scored better on the outcomes known at the round), beside both ways
        "reconciliation": result.reconciliation(),
        "seconds": {"members": round(t_members, 1), "ablation_members": round(t_ablations, 1),
                    "backtest_rounds": round(t_backtest, 1),
                    "parts": {k: round(v, 1) for k, v in result.seconds.items()}},
    }, result


def write_round_files(results: dict[str, Any], folder: Path, hub: Path) -> int:
    """Every round's hub file of the published forecast (both targets where both have the
    round) under ``folder/model-output/<model>/``, validated against the hub's tasks.json as
    the hub round writes its own; returns the number of files."""
    import pandas as pd

    from pipeline.outputs.hubverse_round import (CDC_HUB_MODEL_ID, compound_sample_ids,
                                                 load_model_metadata, write_hub_round)
    from pipeline.outputs.hubverse_validation import load_tasks_config

    tasks = load_tasks_config(hub / "hub-config" / "tasks.json")
    metadata = load_model_metadata(Path(__file__).resolve().parents[1] / "pipeline" / "outputs" / "model_metadata" /
                                   f"{CDC_HUB_MODEL_ID}.yml")
    by_round: dict[pd.Timestamp, list[pd.DataFrame]] = {}
    for result in results.values():
        for index, rnd in enumerate(result.rounds):
            by_round.setdefault(rnd.reference, []).append(result.round_frame(index))
    for frames in by_round.values():
        write_hub_round(compound_sample_ids(pd.concat(frames, ignore_index=True)),
                        hub_dir=folder, model_id=CDC_HUB_MODEL_ID, tasks=tasks,
                        metadata=metadata)
    return len(by_round)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = _parse(argv)
    from pipeline.data.hub.team_forecasts import read_excluded_locations, read_hub_forecasts, \
        quantile_table, read_target_data
    from pipeline.data.hub.target_import import import_hub_time_series
    from pipeline.evaluation.hub_leaderboard import score_quantile_forecasts
    from pipeline.hub_round.run import load_vintages
    from pipeline.io import atomic_write_json
    from pipeline.panels.hub import ED_COVID, HOSP_COVID

    if args.influenza:
        path = Path(args.out) if args.out else RESULTS / "nhsn.json"
        kept = json.loads(path.read_text()) if path.exists() else {}
        kept["influenza"] = influenza_figure(args)
        print(json.dumps({k: v for k, v in kept["influenza"].items()
                          if k not in ("teams_by_season",)}, indent=1, default=str))
        atomic_write_json(path, json.loads(json.dumps(kept, default=str)))
        return kept
    hub = Path(args.hub)
    import_hub_time_series(hub, if_empty=True)          # the hub's vintages into the cache
    climatology = load_vintages(ED_COVID)
    exclusions = read_excluded_locations(hub / "excluded_locations.toml")
    out: dict[str, Any] = {}
    rounds: dict[str, Any] = {}
    targets = {"hosp": [HOSP_COVID], "ed": [ED_COVID], "both": [HOSP_COVID, ED_COVID]}
    for target in targets[args.target]:
        truth = read_target_data(hub / "time-series.parquet", target)
        teams = score_quantile_forecasts(quantile_table(read_hub_forecasts(
            hub / "hub-forecasts.parquet", targets=[target])), truth.assign(target=target))
        out[target], rounds[target] = run_target(target, args, climatology, teams,
                                                 exclusions)
        s = out[target]
        print(f"{target}: published pairwise relative WIS {s['pairwise_relative_wis']}, "
              f"coverage {s['coverage50']:.2f}/{s['coverage95']:.2f}")
        for name, m in s["members_and_variants"].items():
            print(f"  {name:60s} all {m['all']}  " + " ".join(
                f"{k}={v:.3f}" for k, v in m.items() if k.startswith("h") and v is not None))
    if args.files:
        written = write_round_files(rounds, Path(args.files), hub)
        print(f"{written} round files → {Path(args.files) / 'model-output'}")
    timing = {} if args.no_timing else timed_rounds(hub)
    if HOSP_COVID in out:
        out[HOSP_COVID]["seconds"] |= timing | {"backtest": round(out[HOSP_COVID]["seconds"][
            "members"] + out[HOSP_COVID]["seconds"]["backtest_rounds"], 1)}
    path = Path(args.out) if args.out else RESULTS / "nhsn.json"
    command = "python -m bench.nhsn " + " ".join(argv if argv is not None else sys.argv[1:])
    for target in out:
        out[target]["command"] = command        # each target's own run
    before = json.loads(path.read_text()) if path.exists() else {}
    if args.keep_other and args.target != "both" and before:
        if HOSP_COVID not in out:
            out[HOSP_COVID] = {k: v for k, v in before.items()
                               if k not in ("ed_visits", "machine", "python")}
        if ED_COVID not in out:
            out[ED_COVID] = before.get("ed_visits")
    result = {"command": command, **out.get(HOSP_COVID, {}),
              "ed_visits": out.get(ED_COVID),
              "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}",
              "python": sys.version.split()[0]}
    if "influenza" in before:           # another command's figure (--influenza): kept
        result["influenza"] = before["influenza"]
    atomic_write_json(path, json.loads(json.dumps(result, default=str)))
    print(f"→ {path}")
    return result


if __name__ == "__main__":
    main()
