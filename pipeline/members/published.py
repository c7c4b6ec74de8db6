"""The one place the published forecast's members are chosen, for any panel.

* ``hub-baseline`` — the flat Forecast Hub baseline: in the log-scale average it damps the trend
  members' growth at the longer horizons (cross-county backtest, variant without it: relative
  WIS at four weeks 0.84 against 0.79);
* ``gbqr`` — gradient-boosted quantile regression pooled over the cell's panel (San Francisco
  with California's other counties; the counties together; the hub's 53 locations), in the
  place of ``growth-qr`` (the growth regression, published until 2026-11-29, scored beside):
  San Francisco 0.693 against 0.752, the counties 0.765 against 0.773, better at horizons 2–4
  in both (``bench/results/backtest.json``, ``backtest_counties.json``; the hub rounds score
  both beside their own members);
* ``nf-growth`` — the conditional flow trained on the multi-wave prior (model store);
* ``nf-real`` — that flow fine-tuned, on the calendar of
  :func:`~pipeline.members.nf.refit.refit_dates`, on the real windows known by each refit
  date of :func:`finetune_pool`. Without such places there is no nf-real (one series alone is
  too few windows to fine-tune a flow on).

AutoETS is scored beside them as a reference, not a member (cross-county relative WIS 1.17:
worse than the baseline it would be averaged with).
"""
from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pandas as pd

from pipeline.members.base import Member
from pipeline.members.isolation import Dropped
from pipeline.members.nf.flow import SyntheticWindows, stored_flow
from pipeline.members.nf.growth import GrowthModelConfig, NFGrowthMember
from pipeline.members.nf.real import (NF_REAL, FineTuneConfig, FineTunedGrowthMember,
                                      fit_finetuned_member)
from pipeline.members.nf.refit import refit_dates
from pipeline.members.seasonal import SEASONAL, SeasonalConfig, SeasonalGrowthMember
from pipeline.members.nf.weekly import NF_WEEKLY, WeeklyFlowConfig, WeeklyFlowMember
from pipeline.members.nf.context import (NF_CONTEXT, ContextFlowConfig, ContextFlowMember,
                                         ContextRefitConfig,
                                         TrainingPool, fit_context_member)
from pipeline.members.nf.context_features import ContextChannels, ContextSources
from pipeline.data.hub.locations import POPULATION
from pipeline.members.boosting import GBQR, BoostingConfig, PooledBoostingMember, deep_trees
from pipeline.members.growth_regression import (GROWTH_QR, GrowthRegressionConfig,
                                                PooledGrowthMember)
from pipeline.members.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.errors import ConfigError
from pipeline.panels.history import EpiHistory, History
from pipeline.panels.hub import is_share
from pipeline.panels.panel import Panel
from pipeline.progress import ProgressReporter
from pipeline.training.digests import DataDigests

log = logging.getLogger(__name__)

PooledMember = Literal["gbqr", "growth-qr"]

# The hub baseline resamples its differences; 10,000 draws per forecast (reichlab: 100,000) keep
# the Monte Carlo error of its 1 % quantile under 0.1 percentage points of level, at a tenth of
# the cost over the thousands of cells of a panel and the nowcast's completions.
BASELINE_SAMPLES = 10_000


@dataclass(frozen=True)
class MembersConfig:
    """The published members' settings: the flow's (``growth``), growth-qr's (``regression``),
    gbqr's (``boosting``: :func:`deep_trees`), nf-real's refits (``finetune``), which members
    run, and the draws per forecast of each flow (500 keep the Monte Carlo error of the 5 %/95 %
    quantiles near 2 % of the spread, at half the cost of 1,000 over a panel's many cells)."""

    growth: GrowthModelConfig = field(default_factory=GrowthModelConfig)
    regression: GrowthRegressionConfig = field(default_factory=GrowthRegressionConfig)
    boosting: BoostingConfig = field(default_factory=lambda: deep_trees(BoostingConfig()))
    # the member pooled over the panel's places: gbqr, or growth-qr (published until 2026-11-29)
    pooled: PooledMember = GBQR
    finetune: FineTuneConfig = field(default_factory=FineTuneConfig)
    include_nf: bool = True
    include_real: bool = True
    flow_samples: int = 500
    baseline_samples: int = BASELINE_SAMPLES

    def __post_init__(self) -> None:
        if self.pooled not in (GBQR, GROWTH_QR):
            raise ConfigError(f"MembersConfig.pooled={self.pooled!r}: use {GBQR} or {GROWTH_QR}")


@dataclass(frozen=True, eq=False)
class ChosenMembers:
    """The members, and the flow member's store entry (``model_key``, ``reused``)."""

    members: list[Member]
    model_key: str | None
    reused: bool
    dropped: tuple[Dropped, ...] = ()     # a member that could not be built, a refit replaced


def pooled_member(config: MembersConfig) -> Member:
    """The average's member pooled over the panel's places (``config.pooled``)."""
    if config.pooled == GBQR:
        return PooledBoostingMember(config.boosting)
    return PooledGrowthMember(config.regression)


def finetune_pool(panel: Panel) -> list[EpiHistory]:
    """The places nf-real is fine-tuned on: the panel's references (a place forecast beside
    California's counties), else its own places when it has several (the counties); a place
    alone has too few windows."""
    places = (panel.references if panel.references
              else panel.histories if len(panel.histories) > 1 else {})
    return [h for h in places.values() if isinstance(h, EpiHistory)]


def build_members(config: MembersConfig, store_root: Path, panel: Panel,
                  origins: Sequence[pd.Timestamp], progress: ProgressReporter | None = None, *,
                  newest_refits_first: bool = False) -> ChosenMembers:
    """The published members of ``panel`` forecast at ``origins`` (module docstring): the
    flows trained or reused from the model store, nf-real refitted at the refit dates among
    ``origins``. ``newest_refits_first``: see
    :func:`~pipeline.members.nf.real.fit_finetuned_member`."""
    members: list[Member] = [HubBaseline(HubBaselineConfig(n_samples=config.baseline_samples)),
                             pooled_member(config)]
    if not config.include_nf:
        return ChosenMembers(members, None, False)
    synthetic = SyntheticWindows(config.growth, DataDigests(store_root))
    stored = stored_flow(config.growth, store_root, progress=progress,
                                         synthetic=synthetic)
    flow = NFGrowthMember(stored.estimator, config.growth, n_samples=config.flow_samples)
    members.append(flow)
    pool = finetune_pool(panel)
    dates = refit_dates(list(origins), config.finetune.refit_every_weeks)
    if not (config.include_real and pool and dates):
        return ChosenMembers(members, stored.key, stored.reused)
    target = panel.count_target
    try:
        refits = fit_finetuned_member(flow, synthetic, pool, dates, config.finetune, store_root,
                                      progress, newest_first=newest_refits_first)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as error:  # noqa: BLE001 - isolation: the refits alone are lost
        log.warning("nf-real could not be built and is left out: %s", error, exc_info=True)
        return ChosenMembers(members, stored.key, stored.reused, (Dropped(
            "member", target, NF_REAL, f"refits failed: {type(error).__name__}: {error}"),))
    members.append(refits)
    return ChosenMembers(members, stored.key, stored.reused,
                         newest_refit_fallbacks(refits, target))


def newest_refit_fallbacks(refits: FineTunedGrowthMember | ContextFlowMember, target: str
                           ) -> tuple[Dropped, ...]:
    """The refits of ``refits`` (nf-real, nf-context) that diverged and were replaced, where
    that matters to the newest forecast: a refit date after the newest refit that trained."""
    newest = max(refits.models, default=None)
    return tuple(Dropped("refit", target, f"{refits.name} {date.date()}", why)
                 for date, why in refits.fallbacks.items() if newest is None or date > newest)


# ------------------------------------------------------------------- the hub's weekly panels


@dataclass(frozen=True)
class HubMembersConfig:
    """The hub forecast's members: the weekly flow (``flow``), its refits (``finetune``), the
    seasonal member, and which of them the published average takes: ``published`` names them
    (the others are scored beside it)."""

    flow: WeeklyFlowConfig = field(default_factory=WeeklyFlowConfig)
    context: ContextFlowConfig = field(default_factory=ContextFlowConfig)
    context_refit: ContextRefitConfig = field(default_factory=ContextRefitConfig)
    # the context flow's seeds, mixed (pipeline.members.nf.context "Seeds")
    context_seeds: int = 3
    # What the context flow reads, per disease, from the three-seed ablations: COVID-19's waves
    # do not keep to the calendar, and its flow without the season scored better at every
    # horizon and in both periods on both targets (admissions 0.783 against 0.811, 0.528
    # against 0.591 with the ED climatology, 0.887 against 0.898 before it; the ED share 0.635
    # against 0.677); influenza's do, and its flow scored 0.642 with the season against 0.689
    # without it (2023-24 0.834 / 0.901, 2024-25 0.555 / 0.590) (bench/results/nhsn.json
    # "ablations", "influenza"). ``context_channels_own_seasons``: admissions whose climatology
    # is their own earlier seasons (influenza).
    context_channels: ContextChannels = ContextChannels(season=False)
    context_channels_own_seasons: ContextChannels = ContextChannels()
    # lr 1e-3: the lowest mean best validation NLL over the design rounds' 12 refit dates × 3
    # seeds (2.717 against 2.744 at 5e-4 and 2.860 at 2.5e-4; lower in 26 of 36 refits), none
    # diverging with the early stop (bench/results/replay.json "refits")
    finetune: FineTuneConfig = field(default_factory=lambda: FineTuneConfig(
        revision_days=14, min_windows=200, lr=1e-3))
    seasonal: SeasonalConfig = field(default_factory=SeasonalConfig)
    regression: GrowthRegressionConfig = field(default_factory=GrowthRegressionConfig)
    # gbqr on both signals (other_signal_of), None: not built; built where an average takes
    # it, and with ``boosting_beside`` everywhere (the benches)
    boosting: BoostingConfig | None = field(default_factory=BoostingConfig)
    boosting_beside: bool = False
    # Admissions, all three hubs: the context flow (its seeds mixed) and gbqr (since
    # 2026-12-01), against the four members published before (+ nf-weekly, seasonal;
    # docs/forecasting.md "Two members for admissions"): COVID-19's 44 rounds 0.773 against
    # 0.775 (with the ED climatology 0.488 against 0.525; before it 0.882 against 0.870), its
    # worst window of 15 origins 1.025 against 1.040; RSV's 43 rounds 0.760 against 0.769,
    # better at every horizon (bench/results/nhsn.json, rsv.json); FluSight (below)
    published: tuple[str, ...] = (NF_CONTEXT, GBQR)
    # A share (the ED visits): the context flow, refitted globally on the share's own windows
    # since 2022-10 with admissions and the climatology as context, with the seasonal member:
    # 0.618 over the 15 ED rounds, against nf-real + seasonal's 0.647 (0.612 while the flow
    # read the season, whose flow alone scored 0.677 against 0.635 now). With gbqr 0.601 (on
    # its own signal 0.586), but the 95 % interval then covers 0.926 [0.906, 0.937] (0.931
    # [0.914, 0.939]) against 0.947 [0.933, 0.958]: skill bought with coverage, not taken
    published_share: tuple[str, ...] = (NF_CONTEXT, SEASONAL)
    # Admissions whose seasonal member reads their own earlier seasons (influenza: no ED
    # vintage): the same pair. Over FluSight's 59 rounds it ties the two flows published
    # before (0.643 each; 2023-24 0.745 against 0.779, 2024-25 0.600 against 0.583), with
    # coverage 0.48 / 0.94 against 0.47 / 0.93; one rule for every hub's admissions
    # (bench/results/flusight.json)
    published_own_seasons: tuple[str, ...] = (NF_CONTEXT, GBQR)
    flow_samples: int = 1000
    baseline_samples: int = BASELINE_SAMPLES
    # A round from an empty model store trains its members in a background process too,
    # from the other end (pipeline.hub_round.member_training); the same models either way.
    # Off for toy sizes, where starting a second Python costs more than their training.
    background_training: bool = True


def published_names(config: HubMembersConfig, target: str, *, refitted: bool,
                    own_seasons: bool = False) -> tuple[str, ...]:
    """The members of ``target``'s published average (``config.published``; ``published_share``
    for a share; ``published_own_seasons`` for admissions whose seasonal member reads their own
    earlier seasons): the weekly flow stands in for its refit while no refit date has come
    (``refitted`` False)."""
    published = (config.published_share if is_share(target)
                 else config.published_own_seasons if own_seasons else config.published)
    if refitted or NF_REAL not in published:
        return published
    return tuple(dict.fromkeys(NF_WEEKLY if n == NF_REAL else n for n in published))


def context_channels(config: HubMembersConfig, own_seasons: bool) -> ContextChannels:
    """What the context flow reads: ``context_channels``, or ``context_channels_own_seasons``
    where its climatology is the target's own earlier seasons (influenza)."""
    return config.context_channels_own_seasons if own_seasons else config.context_channels


@dataclass(frozen=True, eq=False)
class HubMembers:
    """The published members and the others scored beside them; the flow's store entry."""

    published: list[Member]
    references: list[Member]
    model_key: str
    reused: bool
    dropped: tuple[Dropped, ...] = ()
    # the seconds each member took to build (train, or read back from the model store)
    seconds: dict[str, float] = field(default_factory=dict)
    # the published average as planned (a refit of nf-real in it): what a member dropped
    # from it changed in the submission (HubRun.in_submission)
    planned: tuple[str, ...] = ()


def context_sources(target: str, climatology: Sequence[tuple[pd.Timestamp, Panel]],
                    other_signal: Sequence[tuple[pd.Timestamp, Panel]] | None = None
                    ) -> ContextSources:
    """What the context flow of ``target`` reads beside its own weeks: the other signal (by
    default the ED share, the ``climatology``, for admissions; none for the share itself), the
    climatology and the locations' populations."""
    if other_signal is None:
        other_signal = () if is_share(target) else climatology
    return ContextSources(tuple(other_signal), tuple(climatology), POPULATION)


def other_signal_of(target: str, climatology: Sequence[tuple[pd.Timestamp, Panel]],
                    other_signal: Sequence[tuple[pd.Timestamp, Panel]] | None,
                    own_seasons: bool) -> tuple[tuple[pd.Timestamp, Panel], ...]:
    """The other signal's vintages the members read beside ``target`` (the ED share beside
    admissions, admissions beside the share; ``other_signal`` where given, none by default
    where the climatology is the target's own seasons)."""
    if own_seasons:
        return tuple(other_signal or ())
    return tuple(context_sources(target, climatology, other_signal).other)


def context_pool(target: str, vintages: Sequence[tuple[pd.Timestamp, Panel]],
                 climatology: Sequence[tuple[pd.Timestamp, Panel]],
                 other_signal: Sequence[tuple[pd.Timestamp, Panel]] | None,
                 own_seasons: bool) -> TrainingPool:
    """The context flow's own pool: the target's vintages, its climatology the seasonal
    member's — the ED share's, or with ``own_seasons`` the target's own earlier seasons as each
    vintage released them (influenza: without it the flow's climatology channels were never
    known; three seeds scored 0.642 with them against 0.693 without over FluSight's 59 rounds,
    0.834 / 0.555 against 0.758 / 0.669 in 2023-24 / 2024-25: one earlier season misleads,
    two help)."""
    if own_seasons:
        return TrainingPool(vintages, context_sources(target, vintages, other_signal or ()))
    return TrainingPool(vintages, context_sources(target, climatology, other_signal))


def fit_hub_context(config: HubMembersConfig, store_root: Path, target: str,
                    vintages: Sequence[tuple[pd.Timestamp, Panel]],
                    climatology: Sequence[tuple[pd.Timestamp, Panel]],
                    other_signal: Sequence[tuple[pd.Timestamp, Panel]] | None,
                    own_seasons: bool, *, newest_first: bool = False) -> ContextFlowMember:
    """``target``'s context flow (:func:`~pipeline.members.nf.context.fit_context_member`):
    its seeds pre-trained and refitted on its pool (:func:`context_pool`)."""
    return fit_context_member(
        config.context, config.context_refit,
        [context_pool(target, sorted(vintages, key=lambda v: v[0]), climatology, other_signal,
                      own_seasons)],
        store_root, channels=context_channels(config, own_seasons),
        n_samples=config.flow_samples, n_seeds=config.context_seeds, newest_first=newest_first)


def build_hub_members(config: HubMembersConfig, store_root: Path,
                      refit_vintages: Sequence[tuple[pd.Timestamp, Panel]],
                      climatology: Sequence[tuple[pd.Timestamp, Panel]],
                      progress: ProgressReporter | None = None, *,
                      target: str,
                      other_signal: Sequence[tuple[pd.Timestamp, Panel]] | None = None,
                      seasonal_own_seasons: bool = False,
                      newest_first: bool = False) -> HubMembers:
    """The hub forecast's members (docs/forecasting.md "The hub forecast"): the weekly flow
    (model store), that flow fine-tuned at the refit dates among the vintages' last weeks on
    the windows of the vintage of each (``nf-real``), the context flow refitted globally on
    the same calendar (``nf-context``, :mod:`pipeline.members.nf.context`: its other signal is
    ``other_signal``, by default the ``climatology`` for admissions and none for the share),
    the seasonal member on the ``climatology`` vintages (the ED-visit share), the hub baseline
    and growth-qr pooled over the 53 locations (and gbqr on both signals,
    :func:`other_signal_of`, where ``config.boosting`` is given); :func:`published_names`
    chooses the average's
    members for ``target``. ``seasonal_own_seasons``: the seasonal member reads the target's own
    earlier seasons instead of the ``climatology`` (influenza: no ED vintage in FluSight's
    data). ``newest_first``: the refits latest first (:mod:`pipeline.hub_round.
    member_training`); the same members either way."""
    started = time.perf_counter()
    synthetic = SyntheticWindows(config.flow, DataDigests(store_root))
    stored = stored_flow(config.flow, store_root, progress=progress,
                                         synthetic=synthetic)
    flow = WeeklyFlowMember(stored.estimator, config.flow, n_samples=config.flow_samples)
    seconds = {NF_WEEKLY: time.perf_counter() - started}
    vintages = sorted(refit_vintages, key=lambda v: v[0])

    def known_at(date: pd.Timestamp) -> list[History]:
        """The newest vintage whose data end by ``date``: at a round's origin, its own."""
        released = [panel for _, panel in vintages if panel.last_date <= date]
        return list(released[-1].histories.values()) if released else []

    dates = refit_dates(sorted({panel.last_date for _, panel in vintages}),
                        config.finetune.refit_every_weeks)
    members: list[Member] = [
        flow, (SeasonalGrowthMember((), config.seasonal) if seasonal_own_seasons else
               SeasonalGrowthMember(tuple(climatology), config.seasonal,
                                    climatology_required=True)),
        HubBaseline(HubBaselineConfig(n_samples=config.baseline_samples)),
        PooledGrowthMember(config.regression)]
    planned = published_names(config, target, refitted=True, own_seasons=seasonal_own_seasons)
    if config.boosting is not None and (config.boosting_beside or GBQR in planned):
        members.append(PooledBoostingMember(config.boosting, other=other_signal_of(
            target, climatology, other_signal, seasonal_own_seasons)))
    dropped: list[Dropped] = []
    started = time.perf_counter()
    try:
        context = fit_hub_context(config, store_root, target, vintages, climatology,
                                  other_signal, seasonal_own_seasons, newest_first=newest_first)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as error:  # noqa: BLE001 - isolation: the context flow alone is lost
        log.warning("nf-context could not be built and is left out: %s", error, exc_info=True)
        dropped.append(Dropped("member", target, NF_CONTEXT,
                               f"training failed: {type(error).__name__}: {error}"))
    else:
        members.append(context)
        dropped += newest_refit_fallbacks(context, target)
    seconds[NF_CONTEXT] = time.perf_counter() - started
    refitted = False
    if dates:
        started = time.perf_counter()
        try:
            refits = fit_finetuned_member(flow, synthetic, [], dates, config.finetune,
                                          store_root, progress, known_at=known_at,
                                          newest_first=newest_first)
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as error:  # noqa: BLE001 - isolation: the refits alone are lost
            log.warning("nf-real could not be built and is left out: %s", error, exc_info=True)
            dropped.append(Dropped("member", target, NF_REAL,
                                   f"refits failed: {type(error).__name__}: {error}"))
        else:
            members.append(refits)
            refitted = True
            dropped += newest_refit_fallbacks(refits, target)
        seconds[NF_REAL] = time.perf_counter() - started
    lost = {d.name for d in dropped}     # a member that could not be built: the rest average
    published = tuple(n for n in published_names(config, target, refitted=refitted,
                                                 own_seasons=seasonal_own_seasons)
                      if n not in lost)
    unknown = [n for n in published if n not in {m.name for m in members}]
    if unknown:
        raise ConfigError(f"the hub forecast's published members {unknown} are not among "
                          f"{[m.name for m in members]}")
    return HubMembers([m for m in members if m.name in published],
                      [m for m in members if m.name not in published], stored.key,
                      stored.reused, tuple(dropped), seconds,
                      planned=planned)
