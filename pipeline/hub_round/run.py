"""A round of the CDC COVID-19 Forecast Hub as a typed library run: NHSN admissions and the
NSSP ED share of the US, the 50 states, DC and Puerto Rico, forecast from every vintage in the
cache, the newest round published as the hub's file.

1. **Data** (:mod:`pipeline.data.hub.nhsn`): the disease's two targets live from data.cdc.gov with
   cache fallback (or the cache only), every vintage kept; the locations the gate skipped are
   named in the run and the report.
2. **Rounds** (:func:`~pipeline.panels.hub.hub_rounds`): one per cached vintage; the newest is
   this week's round, the earlier ones its real-time track record — the same method, from the
   data as released then (:mod:`pipeline.backtest.hub_rounds`).
3. **Members** (:func:`~pipeline.members.published.build_hub_members`): for admissions the
   weekly flow and the seasonal member averaged, for the ED share the flow refitted on the
   share's windows and the seasonal member; the others scored beside.
4. **What could not be published** (:class:`~pipeline.members.isolation.Dropped`, on
   ``HubRun.dropped``): a member that failed (the engine's guard), a refit that diverged, a
   location the gate skipped, a target with no release for this round (left out of the file,
   with its age): the round is then *degraded*, and says so.
5. **Publish** (:mod:`pipeline.hub_round.publish`): the round's file
   ``model-output/<model>/<reference date>-<model>.csv`` with its metadata, validated against
   the hub's ``tasks.json``, the report, the track record's scores.
"""
from __future__ import annotations

import datetime as dt
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import pandas as pd

from pipeline.backtest.hub_result import HubRoundsResult
from pipeline.backtest.hub_rounds import HubBacktestConfig, run_hub_rounds
from pipeline.backtest.memo import ForecastMemo
from pipeline.data.core.cache import data_dir
from pipeline.data.hub.nhsn import NHSNConfig, NHSNProvenance, load_nhsn
from pipeline.data.hub.nhsn_vintages import cached_weekly_vintages, disease_targets
from pipeline.errors import ConfigError, OfflineError
from pipeline.members.boosting import BoostingConfig
from pipeline.members.nf.real import FineTuneConfig
from pipeline.members.nf.context import TINY_CONTEXT_FLOW, TINY_CONTEXT_REFIT
from pipeline.members.published import HubMembersConfig, build_hub_members
from pipeline.members.nf.weekly import WeeklyFlowConfig
from pipeline.outputs.hub_calendar import HubCalendar
from pipeline.outputs.hub_conform import NoHubRoundError, no_round_error
from pipeline.outputs.hubverse_round import CDC_HUB_MODEL_ID
from pipeline.outputs.hubverse_validation import load_tasks_config
from pipeline.hub_round.member_training import hub_member_training, target_inputs
from pipeline.members.isolation import Dropped
from pipeline.panels.hub import hub_rounds, panel_of, reference_date_for
from pipeline.panels.panel import Panel
from pipeline.progress import ProgressReporter, SilentProgress
from pipeline.training.model_store import MODELS_FOLDER

log = logging.getLogger(__name__)
HUB_CONFIG_ENV = "FLOWCAST_HUB_CONFIG"
SHARED_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
DEFAULT_HUB_CONFIG = SHARED_DATA / "nhsn" / "hub-config"
Disease = Literal["covid", "flu", "rsv"]
# Whether the seasonal member's climatology is the disease's ED share (COVID-19: NSSP's
# vintages, measured on the 44 design rounds, bench/results/nhsn.json) or the admissions' own
# earlier seasons (influenza: FluSight's data hold no ED vintage; measured on its 59 rounds,
# bench/results/flusight.json; RSV as COVID-19: its NSSP ED share holds seasons from 2022-10
# while its admissions begin 2024-11, bench/results/rsv.json)
SEASONAL_READS_ED_SHARE: dict[Disease, bool] = {"covid": True, "flu": False, "rsv": True}
# each disease's hub config beside the checkout: the CDC COVID-19 hub's, FluSight's, the RSV
# hub's (CDCgov/rsv-forecast-hub)
DEFAULT_HUB_CONFIGS: dict[str, Path] = {"covid": DEFAULT_HUB_CONFIG,
                                        "flu": SHARED_DATA / "flusight" / "hub-config",
                                        "rsv": SHARED_DATA / "rsv" / "hub-config"}
HubPreset = Literal["default", "tiny"]


@dataclass(frozen=True)
class HubPresetConfig:
    """What a preset names: the members, and the rounds' settings."""

    members: HubMembersConfig = field(default_factory=HubMembersConfig)
    rounds: HubBacktestConfig = field(default_factory=HubBacktestConfig)


HUB_PRESETS: dict[str, HubPresetConfig] = {
    "default": HubPresetConfig(),
    # Seconds, for tests and smoke runs: a small flow, a short refit, fewer draws, and a
    # calibration burn-in of 8 weeks before the first round, not a year (a cold tiny round
    # forecasts 11 origins a place, not 55).
    "tiny": HubPresetConfig(
        HubMembersConfig(
            flow=WeeklyFlowConfig(n_trajectories=150, iterations=40, batch_size=256,
                                  hidden_features=16, flow_layers=2, flow_hidden=16),
            finetune=FineTuneConfig(revision_days=14, min_windows=50, iterations=20,
                                    batch_size=128),
            context=TINY_CONTEXT_FLOW, context_refit=TINY_CONTEXT_REFIT, context_seeds=1,
            boosting=BoostingConfig(n_estimators=10),
            flow_samples=200, baseline_samples=2000, background_training=False),
        HubBacktestConfig(burn_in_weeks=8)),
}


def hub_preset(preset: str) -> HubPresetConfig:
    if preset not in HUB_PRESETS:
        raise ConfigError(f"hub preset {preset!r}: use one of {sorted(HUB_PRESETS)}")
    return HUB_PRESETS[preset]


def hub_members_preset(preset: str) -> HubMembersConfig:
    """The preset's members alone (a test or bench that builds members itself)."""
    return hub_preset(preset).members


@dataclass(frozen=True)
class HubRunConfig:
    """One hub round: the disease, where the data come from (``live``: data.cdc.gov with cache
    fallback; ``cache``: offline), the members, the rounds' settings, the model's id and where
    the hub's ``tasks.json`` is (to validate the file against)."""

    disease: Disease = "covid"
    data_source: Literal["live", "cache"] = "live"
    members: HubMembersConfig = field(default_factory=HubMembersConfig)
    rounds: HubBacktestConfig = field(default_factory=HubBacktestConfig)
    model_id: str = CDC_HUB_MODEL_ID
    output_dir: str = "reports"
    hub_config: str | None = None
    seed: int = 0
    # the Wednesday the round is due (a replay's week): a target whose newest release serves
    # an older round is not current; None: the newest round any target serves
    due: dt.date | None = None
    # the flowcast data folder (cache, model store, memo), set at the edge (the CLI, the
    # flow, a replay's week); None: $FLOWCAST_DATA_DIR or ./data, read when the round runs
    data_dir: str | None = None

    @classmethod
    def of_preset(cls, preset: str, **fields: Any) -> HubRunConfig:
        """The preset's members and rounds' settings (:data:`HUB_PRESETS`), with ``fields``
        (any other field of the config)."""
        chosen = hub_preset(preset)
        return cls(members=chosen.members, rounds=chosen.rounds, **fields)

    def __post_init__(self) -> None:
        if self.disease not in ("covid", "flu", "rsv"):
            raise ConfigError(f"disease {self.disease!r}: use covid, flu or rsv")
        if self.data_source not in ("live", "cache"):
            raise ConfigError(f"data source {self.data_source!r}: use live or cache")

    @property
    def data_folder(self) -> Path:
        """The data folder the round reads and writes (:attr:`data_dir`)."""
        return data_dir(self.data_dir)

    @property
    def seasonal_own_seasons(self) -> bool:
        """Whether the seasonal member (and the context flow's climatology) reads the
        admissions' own earlier seasons, not the ED share (:data:`SEASONAL_READS_ED_SHARE`)."""
        return not SEASONAL_READS_ED_SHARE[self.disease]

    def hub_config_dir(self) -> Path | None:
        """The hub's ``hub-config`` folder: the option, ``$FLOWCAST_HUB_CONFIG``, or the
        disease's hub data beside the checkout (:data:`DEFAULT_HUB_CONFIGS`); None when none
        is there. A folder given (the option or the variable) without a ``tasks.json`` is a
        :class:`ConfigError`, never passed over for the default: the file would be validated
        against another hub's rules."""
        for given, name in ((self.hub_config, "hub_config"),
                            (os.environ.get(HUB_CONFIG_ENV), f"${HUB_CONFIG_ENV}")):
            if given:
                if not (Path(given) / "tasks.json").is_file():
                    raise ConfigError(f"{name} {given}: no readable tasks.json in the folder "
                                      "(give the hub's hub-config folder)")
                return Path(given)
        default = DEFAULT_HUB_CONFIGS.get(self.disease)
        return default if default and (default / "tasks.json").is_file() else None

    def calendar(self) -> HubCalendar | None:
        """The hub's calendar (its ``tasks.json``'s rounds and their deadlines); None without
        a hub config."""
        folder = self.hub_config_dir()
        if folder is None:
            return None
        return HubCalendar.of_tasks(load_tasks_config(folder / "tasks.json"), self.disease,
                                    f"the {self.disease} hub")

    def due_round(self, calendar: HubCalendar | None) -> dt.date | None:
        """The round due ``self.due`` (None when no day is given): the hub calendar's round
        open that day (:meth:`HubCalendar.round_for`), or the weekly round without a hub
        config. A day the hub has no round open (FluSight off season) is
        :class:`NoHubRoundError`, before any work."""
        if self.due is None:
            return None
        if calendar is None:
            return reference_date_for(pd.Timestamp(self.due)).date()
        found = calendar.round_for(self.due)
        if found is None:
            raise NoHubRoundError(f"the {self.disease} hub has no round open on {self.due} "
                                  f"({calendar.describe()}): no round written")
        return found


@dataclass(frozen=True, eq=False)
class HubRun:
    """The round's forecasts of each target (its track record with them), where the data came
    from, and the seconds each step took."""

    config: HubRunConfig
    results: dict[str, HubRoundsResult]
    provenance: dict[str, NHSNProvenance]
    model_key: str
    model_reused: bool
    seconds: dict[str, float]
    # what the round left out (members, locations, targets) or replaced (refits), and why
    dropped: tuple[Dropped, ...] = ()
    # the round due ``config.due`` by the hub's calendar (None: no day given)
    due_reference: dt.date | None = None
    # per target, its seconds in all and each member's (target_seconds)
    target_seconds: dict[str, dict[str, float]] = field(default_factory=dict)
    # per target, the members of its published average as planned (HubMembers.planned)
    planned: dict[str, tuple[str, ...]] = field(default_factory=dict)

    @property
    def reference_date(self) -> dt.date:
        """The round's reference date: the one due ``config.due`` by the hub's calendar, else
        the newest round any target's release serves."""
        if self.due_reference is not None:
            return self.due_reference
        if self.config.due is not None:
            return reference_date_for(pd.Timestamp(self.config.due)).date()
        return max(r.rounds[-1].reference for r in self.results.values()).date()

    @property
    def published_targets(self) -> tuple[str, ...]:
        """The targets whose newest round is this round (the others have no current
        release: they are left out of the file, and said in ``dropped``)."""
        reference = pd.Timestamp(self.reference_date)
        return tuple(t for t, r in self.results.items() if r.rounds[-1].reference == reference)

    def in_submission(self, item: Dropped) -> bool:
        """Whether ``item`` changed the submission as planned: a target left out, or a member
        of the published average (or its refit) left out or replaced. A member scored beside
        the average (nf-real of the hub) is named in ``dropped`` but leaves the file as it
        was; a location left out is the gate's, said apart."""
        if item.what in ("target", "location"):
            return item.what == "target"
        member = item.name.split(" ")[0]       # a refit is named "<member> <date>"
        return member in self.planned.get(item.target, ())

    @property
    def degraded(self) -> bool:
        """Whether the round left a target or a published member out (or replaced the refit
        of one)."""
        return any(self.in_submission(d) for d in self.dropped)

    def degraded_message(self) -> str:
        """The run state's message: what was left out of the submission and why, targets
        first."""
        order = {"target": 0, "member": 1, "refit": 2, "location": 3}
        lines = [d.line() for d in sorted(self.dropped, key=lambda d: order[d.what])
                 if self.in_submission(d)]
        return "; ".join(lines)

    @property
    def stale(self) -> bool:
        """A live run that fell back to the cache (data.cdc.gov unreachable); a run from the
        cache by choice is not stale."""
        return self.config.data_source == "live" and any(
            p.from_cache for p in self.provenance.values())

    def held(self) -> dict[str, dict[str, str]]:
        """Per target, the locations whose revision waits for review, and how the round
        treats each (forecast from its accepted series, or left out)."""
        return {p.target: dict(p.held) for p in self.provenance.values() if p.held}

    def skipped(self) -> dict[str, dict[str, str]]:
        """Per target, the locations left out of this round and why."""
        return {t: dict(r.rounds[-1].panel.skipped) for t, r in self.results.items()}


def memo_path(config: HubRunConfig, target: str) -> Path:
    """The memo of the target's member forecasts: a round's cells are forecast once (each round
    from its own vintage, so next week's run forecasts only the new round)."""
    slug = target.replace(" ", "-")
    return config.data_folder / "forecast-memo" / f"hub-{config.disease}-{slug}.npz"


def _save(memo: ForecastMemo) -> None:
    try:
        memo.save()
    except OSError as error:        # a cache: the round stands, the next run re-forecasts
        log.warning("could not write the forecast memo %s: %s", memo.path, error)


def load_vintages(target: str, folder: Path | None = None) -> list[tuple[pd.Timestamp, Panel]]:
    """Every cached vintage of ``target`` in the data ``folder`` as (release date, panel),
    oldest first."""
    return [(v.as_of, panel_of(v)) for v in cached_weekly_vintages(target, folder)]


def run_hub_round(config: HubRunConfig, progress: ProgressReporter | None = None) -> HubRun:
    """The round (module docstring); the newest cached vintage is this week's."""
    progress = progress or SilentProgress()
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    calendar = config.calendar()
    due_reference = config.due_round(calendar)      # off season: said before any work
    serving = calendar.serving if calendar is not None else reference_date_for
    targets = disease_targets(config.disease)
    provenance, missing = _load(config)
    for loaded in provenance.values():     # their notes: pipeline.data.hub.nhsn logs them
        if loaded.skipped:
            log.warning("%s: locations left out: %s", loaded.target,
                        "; ".join(f"{p} ({why})" for p, why in loaded.skipped.items()))
    vintages = {t: load_vintages(t, config.data_folder) if t in provenance else []
                for t in targets}
    seconds["data"] = time.perf_counter() - started
    if due_reference is None and calendar is not None:      # off season: before any forecast
        require_open_round(calendar, vintages, config.disease)
    # the ED share's vintages are COVID-19's seasonal climatology (none released yet: no
    # seasonal forecast); influenza's seasonal member reads the admissions' own earlier seasons
    # (FluSight's data hold no influenza ED vintage: SEASONAL_READS_ED_SHARE)
    inputs = target_inputs(vintages)
    dropped = [Dropped("target", t, t, f"no release of it yet ({missing[t]})") for t in missing]
    results: dict[str, HubRoundsResult] = {}
    model_key, reused = "", True
    per_target: dict[str, dict[str, float]] = {}
    planned: dict[str, tuple[str, ...]] = {}
    store_root = config.data_folder / MODELS_FOLDER
    cold = any(not memo_path(config, t.target).is_file() for t in inputs)
    with hub_member_training(config.members, store_root, inputs, config.seasonal_own_seasons,
                             needed=cold):
        for target in inputs:
            started = time.perf_counter()
            members = build_hub_members(config.members, store_root, target.vintages,
                                        target.climatology, progress, target=target.target,
                                        seasonal_own_seasons=config.seasonal_own_seasons,
                                        other_signal=target.other_signal)
            model_key, reused = members.model_key, reused and members.reused
            planned[target.target] = members.planned
            memo = ForecastMemo.load(memo_path(config, target.target))
            result = results[target.target] = run_hub_rounds(
                hub_rounds(target.vintages, serving), target.vintages[-1][1],
                [memo.wrap(m, config.rounds.n_samples) for m in members.published],
                config.rounds,
                references=[memo.wrap(m, config.rounds.n_samples) for m in members.references],
                progress=progress)
            _save(memo)
            published = {m.name for m in members.published}
            dropped += [*members.dropped, *(
                Dropped("member", target.target, name, why)
                for name, why in result.dropped_members().items() if name in published)]
            seconds[target.target] = time.perf_counter() - started
            per_target[target.target] = target_seconds(seconds[target.target], members.seconds,
                                                       result)
    dropped += stale_targets(results, due_reference)
    dropped += [Dropped("location", t, place, why)
                for t, r in results.items() for place, why in r.rounds[-1].panel.skipped.items()]
    for item in dropped:
        if item.what != "location":
            log.warning("the round left out %s", item.line())
    return HubRun(config, results, provenance, model_key, reused, seconds, tuple(dropped),
                  due_reference, target_seconds=per_target, planned=planned)


def require_open_round(calendar: HubCalendar,
                       vintages: dict[str, list[tuple[pd.Timestamp, Panel]]], disease: str
                       ) -> None:
    """Raise :class:`NoHubRoundError` when the newest round the vintages serve (the round a
    run with no due day publishes) is none of the hub's: known from the data's dates alone,
    before any member is trained or any cell forecast."""
    released = [v[-1][0] for v in vintages.values() if v]
    if not released:
        return
    newest = max(calendar.serving(as_of) for as_of in released).date()
    if newest not in calendar.references:
        raise no_round_error(f"the {disease} hub", newest,
                             [str(r) for r in calendar.references])


def target_seconds(total: float, built: dict[str, float], result: HubRoundsResult
                   ) -> dict[str, float]:
    """A target's seconds in a round: ``total``, and each member's, built (trained or read
    back from the model store) and forecast (its cells read back from the memo or forecast):
    where a warm round spends its time."""
    forecast = result.backtest.seconds
    names = (*result.backtest.members, *result.backtest.references)
    return {"total": round(total, 1)} | {
        name: round(built.get(name, 0.0) + forecast.get(name, 0.0), 1) for name in names}


def _load(config: HubRunConfig) -> tuple[dict[str, NHSNProvenance], dict[str, str]]:
    """The disease's targets loaded (live with cache fallback, or the cache), and the targets
    with no release at all and why; with none of them: the error naming the import."""
    offline = config.data_source == "cache"
    try:
        return dict(load_nhsn(NHSNConfig(disease=config.disease, data_dir=config.data_folder),
                              offline=offline).provenance), {}
    except OfflineError as error:
        first = error
    provenance: dict[str, NHSNProvenance] = {}
    missing: dict[str, str] = {}
    for target in disease_targets(config.disease):     # each alone: which one has none?
        try:
            loaded = load_nhsn(NHSNConfig(disease=config.disease, targets=(target,),
                                          data_dir=config.data_folder), offline=offline)
            provenance |= loaded.provenance
        except OfflineError as error:
            missing[target] = str(error).split(" in ")[0]
    if not provenance:
        raise first
    return provenance, missing


def stale_targets(results: dict[str, HubRoundsResult], due_reference: dt.date | None
                  ) -> list[Dropped]:
    """The targets whose newest release serves an older round than this one (the round due,
    ``due_reference``, else the newest any target serves): left out of the file, with their
    age."""
    if not results:
        return []
    newest = max(r.rounds[-1].reference for r in results.values())
    reference = pd.Timestamp(due_reference) if due_reference is not None else newest
    out = []
    for target, result in results.items():
        last = result.rounds[-1]
        if last.reference < reference:
            weeks = (reference - last.reference).days // 7
            out.append(Dropped("target", target, target,
                               f"no current release: the newest, of {last.as_of.date()}, is "
                               f"{weeks} week{'s' if weeks != 1 else ''} old (it serves the "
                               f"round of {last.reference.date()}, not {reference.date()})"))
    return out
