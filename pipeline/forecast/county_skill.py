"""Step ``county-skill``: the published method's skill across California's counties.

The weekly report shows the place's own track record (its real-time backtest) beside the same
method's on every California county with at least 100,000 people, from the cached CDPH vintage
(:func:`county_backtest`, the design set of the published forecast: the one backtest,
:mod:`pipeline.backtest.backtest`, on the counties' panel).
The summary is kept under ``<data dir>/county_skill/`` keyed by the vintage's contents and the
weekly forecast's member settings: a weekly run recomputes it only when either changed (a new
CDPH download, another model), and its models are the weekly run's own (shared through the
model store). Without CDPH data in the cache there is no county skill, and the report says so.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.data.california.cdph import CDPHVintage
from pipeline.data.california.cdph_source import CDPHConfig, load_cdph_vintage
from pipeline.backtest.config import BacktestConfig, Variant
from pipeline.backtest.backtest import OneVintage, run_backtest
from pipeline.backtest.result import BacktestResult
from pipeline.members.base import Member
from pipeline.members.published import ChosenMembers, build_members
from pipeline.panels.california import county_panel, select_counties
from pipeline.panels.panel import Panel, weekly_origins
from pipeline.panels.targets import HORIZONS_WEEKS
from pipeline.errors import OfflineError
from pipeline.forecast.config import ForecastConfig
from pipeline.forecast.results import CountySkill
from pipeline.io import atomic_write_json
from pipeline.progress import ProgressReporter, start_phase

log = logging.getLogger(__name__)
FOLDER = "county_skill"
SCORED = ("published", "hub-baseline", "gbqr", "growth-qr", "nf-growth", "nf-real")


MIN_HISTORY_WEEKS = 8


def county_backtest_config(config: ForecastConfig, variants: Sequence[Variant] = ()
                           ) -> BacktestConfig:
    """The county backtest's settings: the weekly run's combiner, the run's seed."""
    return BacktestConfig(seed=config.seed, combine=config.track_record.combine,
                          variants=tuple(variants))


def skill_key(vintage: CDPHVintage, backtest: BacktestConfig, config: ForecastConfig) -> str:
    """What determines the county skill: the vintage's rows and the members' settings."""
    rows = pd.util.hash_pandas_object(vintage.frame, index=False).to_numpy().tobytes()
    settings = json.dumps({"backtest": dataclasses.asdict(backtest),
                           "members": dataclasses.asdict(config.track_record_config())},
                          sort_keys=True, default=str)
    return hashlib.sha256(rows + settings.encode()).hexdigest()


def _from_summary(summary: dict[str, Any], vintage: str) -> CountySkill:
    by_target = summary["by_target"]
    published = {t: by_target[t]["published"] for t in by_target}
    return CountySkill(
        vintage=vintage, n_counties=int(summary["n_places"]),
        n_origins=int(summary["n_origins"]), first_origin=summary["origins"]["first"],
        last_origin=summary["origins"]["last"],
        relative_wis={t: {n: dict(by_target[t][n]["gmean_relative_wis"]) for n in SCORED
                          if n in by_target[t]} for t in by_target},
        share_beating_baseline={t: float(p["share_beating_baseline"]["all"])
                                for t, p in published.items()},
        coverage={t: (float(p["coverage50"]), float(p["coverage90"]))
                  for t, p in published.items()})


def county_backtest(vintage: CDPHVintage, config: ForecastConfig, store_root: Path, *,
                    counties: Sequence[str] | None = None, variants: Sequence[Variant] = (),
                    references: Sequence[Member] = (), progress: ProgressReporter | None = None
                    ) -> tuple[BacktestResult, ChosenMembers]:
    """The published method at every county of ``vintage`` (or ``counties``) and Saturday
    origin with four weeks of truth (the latest ``recent_origins`` of the run's track record
    when it sets them), its members' models the weekly run's own (shared through
    the model store), with the ``variants`` and ``references`` scored beside it."""
    record = config.track_record_config()
    panel, origins = panel_and_origins(vintage, counties, record.recent_origins)
    if progress is not None:
        start_phase(progress, "members' models", None)
    chosen = build_members(record.members, store_root, panel, origins, progress)
    result = run_backtest(OneVintage(panel), chosen.members, origins,
                          county_backtest_config(config, variants), references=references,
                          progress=progress)
    return result, chosen


def county_skill(config: ForecastConfig, progress: ProgressReporter | None = None
                 ) -> CountySkill | None:
    """The published method's cross-county skill on the cached CDPH vintage (module docstring);
    None without CDPH data."""
    try:
        vintage = load_cdph_vintage(CDPHConfig(data_dir=config.data.folder), offline=True)
    except OfflineError as exc:
        log.warning("no county skill: %s", exc)
        return None
    path = skill_path(vintage, config)
    as_of = str(vintage.as_of.date())
    if path.is_file():
        try:
            return dataclasses.replace(_from_summary(json.loads(path.read_text()), as_of),
                                       reused=True)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("recomputing the county skill: %s is unreadable (%s)", path, exc)
    started = time.perf_counter()
    result, _ = county_backtest(vintage, config, config.store_root, progress=progress)
    summary = result.summary()
    atomic_write_json(path, summary | {"vintage": as_of,
                                       "seconds": time.perf_counter() - started})
    return _from_summary(summary, as_of)


def skill_path(vintage: CDPHVintage, config: ForecastConfig) -> Path:
    """Where the county skill of this vintage and these settings is kept."""
    return config.data.folder / FOLDER / f"{skill_key(vintage, county_backtest_config(config), config)[:24]}.json"


def panel_and_origins(vintage: CDPHVintage, counties: Sequence[str] | None = None,
                      recent_origins: int | None = None) -> tuple[Panel, list[pd.Timestamp]]:
    """The counties' panel and the weekly origins the county skill forecasts from: every one,
    or the latest ``recent_origins`` (the run's track record's setting: a smoke run's short
    record)."""
    panel = county_panel(vintage, select_counties(vintage, counties=counties))
    origins = weekly_origins(panel.dates, min_history_weeks=MIN_HISTORY_WEEKS,
                             horizon_weeks=max(HORIZONS_WEEKS))
    return panel, origins if recent_origins is None else origins[-recent_origins:]


def train_county_members(config: ForecastConfig, store_root: Path,
                         progress: ProgressReporter | None = None) -> None:
    """Train (into the model store) the models :func:`county_skill` will use, unless the cached
    vintage's skill is kept already or there is no CDPH data (then it needs none); the latest
    refits first (:mod:`pipeline.forecast.member_training`)."""
    try:
        vintage = load_cdph_vintage(CDPHConfig(data_dir=config.data.folder), offline=True)
    except OfflineError:
        return
    if skill_path(vintage, config).is_file():
        return
    record = config.track_record_config()
    panel, origins = panel_and_origins(vintage, recent_origins=record.recent_origins)
    build_members(record.members, store_root, panel, origins, progress,
                  newest_refits_first=True)
