"""The daily flow member ``nf-growth``: a conditional MAF over the next four weeks of reported
cases, its coordinates and its training windows from the multi-wave prior; trained, stored,
sampled and decoded by the flow machinery (:mod:`pipeline.members.nf.flow`).

This is the paper's forward estimate with the target times moved past the last observation: a
masked autoregressive flow, conditioned on an embedding of the last R days of observations,
estimates the joint density of the weekly case counts 1–4 weeks after the origin. It is trained
only on the multi-wave synthetic prior (:mod:`pipeline.systems.waves`), so nothing it learns
comes from the SF series; the backtest's origins see it as a fixed model.

Coordinates, chosen so that the model reads the trend and its samples are valid by construction:

* context (scale-free): row k of the R-day window is log(C7_{t−k} + ½) − log(C7_t + ½), the
  7-day case sum k days before the origin t relative to the latest one, with the time channel
  −k; a second channel carries the latest level log(C7_t + ½) / 10 (reporting noise depends on
  it; the prior makes every level rise and fall, so it carries no direction);
* target: the flows' z_h = logit(f_h) − logit(f_0) (:mod:`pipeline.members.nf.flow`), with C_h
  the 7-day case sum h weeks after the origin. (Its decoded counts keep the ½-case continuity
  offset of the encoding: subtracting it could make a count negative.)
"""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import pandas as pd
import torch
from numpy.typing import NDArray

import pipeline
from pipeline.errors import ConfigError
from pipeline.members.base import MemberForecast
from pipeline.members.nf.flow import (HALF_CASE, LEVEL_SCALE, FlowNetwork, RealWindows,
                                      check_horizons, decode_paths, logit, path_forecast,
                                      reported_share, sample_cells, stored_flow)
from pipeline.models.estimator import ConditionalEstimator, EstimatorConfig
from pipeline.panels.history import EpiHistory, History
from pipeline.panels.panel import Cells
from pipeline.panels.targets import DAYS_PER_WEEK, TargetError
from pipeline.progress import ProgressReporter
from pipeline.systems.waves import WaveEnsemble, WavePrior, simulate_waves
from pipeline.training.datasets import (FORMAT_VERSION, DatasetMeta, WindowedDataset,
                                        compute_standardization, with_data_hash)

NF_GROWTH = "nf-growth"
N_WEEKS = 4


@dataclass(frozen=True)
class GrowthModelConfig(FlowNetwork):
    """The member's data settings beside the flow's (:class:`~pipeline.members.nf.flow.
    FlowNetwork`); the model-store key is built from this."""

    context_days: int = 42
    n_trajectories: int = 4000
    origin_stride_days: int = 3
    prior: WavePrior = field(default_factory=WavePrior)

    kind: ClassVar[str] = NF_GROWTH        # the model store's name for these models

    def __post_init__(self) -> None:
        if self.context_days < DAYS_PER_WEEK:
            raise ConfigError(f"GrowthModelConfig.context_days={self.context_days} < 7")
        first = self.context_days + DAYS_PER_WEEK
        if self.prior.days - self.prior.burn_in_days < first + N_WEEKS * DAYS_PER_WEEK:
            raise ConfigError("GrowthModelConfig: the prior's trajectories are too short for "
                              f"{self.context_days} context days plus {N_WEEKS} weeks")

    @property
    def first_origin(self) -> int:
        """Earliest origin (day index) with a full context and the week before it."""
        return self.context_days + DAYS_PER_WEEK - 1

    def estimator_config(self) -> EstimatorConfig:
        return self.network(N_WEEKS, 3, self.context_days)

    def build_dataset(self) -> WindowedDataset:
        return growth_dataset(self)


def trailing_week_sums(cases: NDArray[np.integer] | NDArray[np.floating]) -> NDArray[np.float64]:
    """7-day trailing sums along the last axis; the first six days have no full week (NaN)."""
    c = np.asarray(cases, dtype=np.float64)
    cumulative = np.concatenate([np.zeros(c.shape[:-1] + (1,)), np.cumsum(c, axis=-1)], axis=-1)
    sums = cumulative[..., DAYS_PER_WEEK:] - cumulative[..., :-DAYS_PER_WEEK]
    pad = np.full(c.shape[:-1] + (DAYS_PER_WEEK - 1,), np.nan)
    return np.concatenate([pad, sums], axis=-1)


def context_features(week_sums: NDArray[np.float64], origins: NDArray[np.intp],
                     context_days: int) -> NDArray[np.float32]:
    """(W, R, 3) context rows for windows ending at ``origins`` of ``week_sums (W, T)``."""
    offsets = np.arange(context_days - 1, -1, -1)                        # k = R-1 … 0
    rows = origins[:, None] - offsets[None, :]
    log_sums = np.log(np.take_along_axis(week_sums, rows, axis=1) + HALF_CASE)
    latest = log_sums[:, -1:]
    relative = log_sums - latest
    level = np.broadcast_to(latest / LEVEL_SCALE, relative.shape)
    time = np.broadcast_to(-offsets.astype(np.float64), relative.shape)
    return np.stack([relative, level, time], axis=-1).astype(np.float32)


def growth_targets(week_sums: NDArray[np.float64], susceptible: NDArray[np.float64],
                   origins: NDArray[np.intp], population: int) -> NDArray[np.float32]:
    """(W, 4) targets z_h = logit f_h − logit f_0 (module docstring) of windows at ``origins``."""
    ends = origins[:, None] + DAYS_PER_WEEK * np.arange(0, N_WEEKS + 1)[None, :]   # weeks 0..4
    week_cases = np.take_along_axis(week_sums, ends, axis=1)
    s_origin = np.take_along_axis(susceptible, origins[:, None], axis=1)
    s_before = np.take_along_axis(susceptible, origins[:, None] - DAYS_PER_WEEK, axis=1)
    # S falls by (C + ½) / N a week, as decoding has it, so decode(encode(x)) is exact.
    reported = np.cumsum(week_cases[:, 1:-1] + HALF_CASE, axis=1) / population
    s_start = np.concatenate([s_before, s_origin, s_origin - reported], axis=1)  # S_{h-1}, h=0..4
    logits = logit(reported_share(week_cases, s_start, population))
    return (logits[:, 1:] - logits[:, :1]).astype(np.float32)


def _origins(config: GrowthModelConfig, n_days: int) -> NDArray[np.intp]:
    last = n_days - 1 - N_WEEKS * DAYS_PER_WEEK
    return np.arange(config.first_origin, last + 1, config.origin_stride_days)


def build_growth_dataset(ensemble: WaveEnsemble, config: GrowthModelConfig) -> WindowedDataset:
    """Windows (context, target) at every ``origin_stride_days``-th origin of every trajectory."""
    week_sums = trailing_week_sums(ensemble.cases)
    m, n_days = ensemble.cases.shape
    per_trajectory = _origins(config, n_days)
    origins = np.tile(per_trajectory, m)
    trajectory = np.repeat(np.arange(m), per_trajectory.size)
    context = context_features(week_sums[trajectory], origins, config.context_days)
    with np.errstate(invalid="ignore", divide="ignore"):
        target = growth_targets(week_sums[trajectory], ensemble.susceptible[trajectory], origins,
                                ensemble.prior.population)
    # A few explosive trajectories report more cases than susceptibles remain (reporting noise
    # on a depleted S): their share has no logit, and such windows are nothing like SF; drop them.
    finite = np.isfinite(target).all(axis=1)
    context, target = context[finite], target[finite]
    origins, trajectory = origins[finite], trajectory[finite]
    context_t, target_t = torch.from_numpy(context), torch.from_numpy(target)
    mask = torch.ones(context_t.shape[:2], dtype=torch.bool)
    stats = compute_standardization(context_t, mask, target_t)
    meta = DatasetMeta(
        system="waves", config_name="sf-waves", direction="forward", target_kind="growth",
        context_features=("log_week_sum_rel", "log_week_sum_level", "t_obs_minus_origin"),
        target_features=tuple(f"z_week{h}" for h in range(1, N_WEEKS + 1)),
        window=config.context_days, seed=config.seed, val_fraction=config.val_fraction,
        split="all", n_trajectories=m, n_observed_points=int(ensemble.cases.size),
        n_observed_values=int(ensemble.cases.size),
        config=json.loads(json.dumps(dataclasses.asdict(ensemble.prior))),
        package_version=pipeline.__version__, format_version=FORMAT_VERSION, data_sha256="")
    return with_data_hash(WindowedDataset(context_t, mask, target_t,
                                          torch.from_numpy(trajectory),
                                          torch.from_numpy(origins.astype(np.float64)), stats,
                                          meta))


def growth_dataset(config: GrowthModelConfig) -> WindowedDataset:
    """The member's training windows: simulated from the prior with the config's seed."""
    return build_growth_dataset(simulate_waves(config.prior, config.n_trajectories, config.seed),
                                config)


@dataclass(frozen=True, eq=False)
class NFGrowthMember:
    """Forecast member: samples the trained flow at each cell's origin and decodes weekly
    paths (coordinates: the module docstring)."""

    estimator: ConditionalEstimator
    config: GrowthModelConfig
    name: str = NF_GROWTH
    n_samples: int = 1000

    @property
    def max_horizon(self) -> int:
        """The flow forecasts exactly the next ``N_WEEKS`` weeks."""
        return N_WEEKS

    def sample_paths(self, histories: Sequence[History], seeds: Sequence[int],
                     chunk: int = 16) -> NDArray[np.float64]:
        """Weekly S, I, R paths ``(B, n_samples, 4, 3)`` at origin + 7h, h = 1..4, of B daily
        histories (e.g. every county × origin of a backtest), history b drawn from
        ``seeds[b]`` (:func:`~pipeline.members.nf.flow.sample_cells`)."""
        daily = [h for h in histories if isinstance(h, EpiHistory)]
        if len(daily) != len(histories):
            raise TargetError(f"{self.name}: the flow reads daily case counts; a weekly series "
                              "needs the weekly flow")
        needed = self.config.context_days + DAYS_PER_WEEK
        short = [h for h in daily if len(h) < needed]
        if short:
            raise TargetError(f"{self.name}: needs {needed} days of history, got "
                              f"{len(short[0])} (origin {short[0].origin.date()})")
        cases = np.stack([h.cases[-needed:] for h in daily])
        week_sums = trailing_week_sums(cases)
        origins = np.full(len(daily), needed - 1)
        context = context_features(week_sums, origins, self.config.context_days)
        mask = np.ones(context.shape[:2], dtype=bool)
        flows = (self.estimator,)
        z = sample_cells([flows] * len(daily), context, mask, seeds, self.n_samples,
                         self.estimator.features, chunk)
        s_before = np.array([h.S[-1 - DAYS_PER_WEEK] for h in daily])[:, None]
        s_origin = np.array([h.S[-1] for h in daily])[:, None]
        population = np.array([h.population for h in daily], dtype=np.int64)[:, None]
        return decode_paths(z, week_sums[:, -1:], s_before, s_origin, population)

    def real_windows(self, histories: Sequence[History], cutoff: pd.Timestamp) -> RealWindows:
        """Every daily window of ``histories`` whose last target week ends on or before
        ``cutoff`` (nf-real's training windows), in this member's coordinates."""
        config = self.config
        contexts, targets, places = [], [], []
        for index, history in enumerate(histories):
            if not isinstance(history, EpiHistory):
                raise TargetError(f"{self.name}: real windows are cut from daily series")
            end = int(np.searchsorted(history.dates.to_numpy(dtype=np.int64), cutoff.value,
                                      side="right")) - 1
            last_origin = end - N_WEEKS * DAYS_PER_WEEK
            if last_origin < config.first_origin:
                continue
            origins = np.arange(config.first_origin, last_origin + 1)
            sums = np.repeat(trailing_week_sums(history.cases)[None], origins.size, axis=0)
            context = context_features(sums, origins, config.context_days)
            with np.errstate(invalid="ignore", divide="ignore"):
                target = growth_targets(sums, np.repeat(history.S[None], origins.size, axis=0),
                                        origins, history.population)
            finite = np.isfinite(target).all(axis=1) & np.isfinite(context).all(axis=(1, 2))
            contexts.append(context[finite])
            targets.append(target[finite])
            places.append(np.full(int(finite.sum()), index, dtype=np.int64))
        if not contexts:
            return RealWindows(np.empty((0, config.context_days, 3), np.float32),
                               np.empty((0, config.context_days), bool),
                               np.empty((0, N_WEEKS), np.float32), np.empty(0, np.int64))
        context = np.concatenate(contexts)
        return RealWindows(context, np.ones(context.shape[:2], dtype=bool),
                           np.concatenate(targets), np.concatenate(places))

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Weekly count quantiles ``(B, H, Q)`` of every cell from its sampled paths (kept)."""
        check_horizons(self.name, horizons, self.max_horizon)
        # the daily flow's counts keep the continuity offset (as it was scored in the paper)
        return path_forecast(self.sample_paths(cells.histories, cells.seeds), cells, horizons,
                             levels, offset=0.0)


def default_nf_member(store_root: Path | None = None,
                      config: GrowthModelConfig = GrowthModelConfig(),
                      progress: ProgressReporter | None = None) -> NFGrowthMember:
    """The product's flow member, from the weekly forecast's model store (trained if absent)."""
    if store_root is None:
        from pipeline.training.model_store import default_store_root

        store_root = default_store_root()
    stored = stored_flow(config, store_root, progress=progress)
    return NFGrowthMember(stored.estimator, config)
