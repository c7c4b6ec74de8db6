"""The flow member on weekly data: a conditional MAF over the next weeks of a weekly count
(NHSN hospital admissions, the NSSP ED share as a rate), trained on the multi-wave prior seen
through an admissions layer.

The daily flow member (:mod:`pipeline.members.nf.growth`) reads 42 days of reported cases. A hub
source reports one number a week, so this member reads the last K weeks; everything else is the
same model: the forward estimate of the paper with the target times moved past the last
observation, valid by construction.

**Prior.** The daily multi-wave SIRS of :mod:`pipeline.systems.waves` (its infections as shares
of the population), calmed for the admissions of 2022–25 (R nearer 1, lower volatility of the
transmission rate, smaller and more frequent jumps, faster reversion: weekly admissions rarely
grew or fell by more than ~40 % a week), seen through an **admissions layer**: each trajectory
draws a population N (log-uniform 0.5 M – 340 M: Wyoming to the US), an admission ratio ρ
(admissions per infection, log-uniform 0.002–0.03: an infection-hospitalisation ratio of
0.2–3 % in an immune population), a mean delay from infection to admission (geometric,
3–14 days) and a weekly negative-binomial dispersion k (log-uniform 30–2,000):
A_w ~ Poisson(N ρ Σ_{days of w} (infections ∗ delay)_t · G_w), G_w ~ Gamma(k, 1/k).

**Coordinates** (as the daily member, by week). Context row k (k = K−1 … 0):
log(A_{t−k} + ½) − log(A_t + ½), the latest level log(A_t + ½)/10 and the time channel −k; a
share of the training windows keeps only the last 2…K rows (the rest masked), so the model
serves the hub's first rounds, whose series are a few weeks long. Target:
z_h = logit f_h − logit f_0 with f_h = (A_h + ½) / (N S_{h−1}), S the share not yet counted;
decoding gives 0 < A_h < N S_{h−1} (:func:`~pipeline.members.nf.flow.decode_weekly`).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pandas as pd
import torch
from numpy.typing import NDArray

import pipeline
from pipeline.errors import ConfigError
from pipeline.members.base import MemberForecast
from pipeline.members.nf.flow import (HALF_CASE, LEVEL_SCALE, FlowNetwork, RealWindows,
                                      as_weekly, check_horizons, decode_weekly, last_weeks,
                                      logit, path_forecast, sample_cells, weekly_cells)
from pipeline.models.estimator import ConditionalEstimator, EstimatorConfig
from pipeline.panels.history import History, WeeklyHistory
from pipeline.panels.panel import Cells
from pipeline.models.standardization import Standardization
from pipeline.panels.targets import DAYS_PER_WEEK
from pipeline.systems.waves import WavePrior, simulate_waves
from pipeline.training.datasets import (FORMAT_VERSION, DatasetMeta, WindowedDataset,
                                        compute_standardization, with_data_hash)

NF_WEEKLY = "nf-weekly"
DELAY_LAGS = 60                    # days of the infection → admission delay kernel

# The daily prior calmed for admissions (module docstring); reversion 0.04–0.15 a day was the
# best of 0.005–0.08 (the SF prior's), 0.02–0.10 and 0.04–0.15 over the 44 design rounds.
ADMISSIONS_PRIOR = WavePrior(days=400, burn_in_days=40, reproduction_start=(0.85, 1.25),
                             reproduction_mean=(0.9, 1.15), reversion_per_day=(0.04, 0.15),
                             volatility_per_day=(0.003, 0.04), jump_sd=0.3,
                             jump_rate_per_day=1 / 90, initial_incidence=(1e-4, 2e-3),
                             importation=(1e-6, 3e-5))


@dataclass(frozen=True)
class WeeklyFlowConfig(FlowNetwork):
    """The weekly member's prior, admissions layer and coordinates beside the flow's
    (:class:`~pipeline.members.nf.flow.FlowNetwork`); the model-store key is built from this."""

    context_weeks: int = 8
    horizon_weeks: int = 5          # 1–4 and a fifth for a round whose data are two weeks behind
    n_trajectories: int = 3000
    prior: WavePrior = field(default_factory=lambda: ADMISSIONS_PRIOR)
    population: tuple[float, float] = (5e5, 3.4e8)
    admission_ratio: tuple[float, float] = (2e-3, 3e-2)
    delay_mean_days: tuple[float, float] = (3.0, 14.0)
    dispersion: tuple[float, float] = (30.0, 2000.0)
    short_share: float = 0.3
    min_weeks: int = 2
    iterations: int = 2500

    kind: ClassVar[str] = NF_WEEKLY

    def __post_init__(self) -> None:
        if not 2 <= self.min_weeks <= self.context_weeks or self.horizon_weeks < 1:
            raise ConfigError(f"WeeklyFlowConfig: need 2 <= min_weeks <= context_weeks and "
                              f"horizon_weeks >= 1, got {self}")
        if not 0 <= self.short_share < 1:
            raise ConfigError(f"WeeklyFlowConfig.short_share={self.short_share} not in [0, 1)")

    def estimator_config(self) -> EstimatorConfig:
        return self.network(self.horizon_weeks, 3, self.context_weeks)

    def build_dataset(self) -> WindowedDataset:
        return weekly_dataset(self)


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float], n: int
                 ) -> NDArray[np.float64]:
    return np.exp(rng.uniform(np.log(bounds[0]), np.log(bounds[1]), n))


def simulate_admissions(config: WeeklyFlowConfig) -> tuple[NDArray[np.float64],
                                                             NDArray[np.float64]]:
    """``(admissions (M, W), population (M,))``: the prior's weekly series (module docstring)."""
    ensemble = simulate_waves(config.prior, config.n_trajectories, config.seed)
    rng = np.random.default_rng(config.seed + 100)
    m, days = ensemble.infections.shape
    population = _log_uniform(rng, config.population, m)
    ratio = _log_uniform(rng, config.admission_ratio, m)
    p = 1.0 / rng.uniform(*config.delay_mean_days, m)
    kernel = p[:, None] * (1.0 - p[:, None]) ** np.arange(DELAY_LAGS)[None, :]
    kernel /= kernel.sum(axis=1, keepdims=True)
    n_fft = days + DELAY_LAGS          # a causal convolution per trajectory, by FFT
    delayed = np.fft.irfft(np.fft.rfft(ensemble.infections, n_fft)
                           * np.fft.rfft(kernel, n_fft), n_fft)[:, :days]
    n_weeks = (days - DELAY_LAGS) // DAYS_PER_WEEK    # days whose delay window is simulated
    weekly = delayed[:, DELAY_LAGS:DELAY_LAGS + DAYS_PER_WEEK * n_weeks].reshape(
        m, n_weeks, DAYS_PER_WEEK).sum(axis=2)
    k = _log_uniform(rng, config.dispersion, m)
    noise = rng.gamma(k[:, None], 1.0 / k[:, None], size=weekly.shape)
    mean = np.maximum(population[:, None] * ratio[:, None] * weekly * noise, 0.0)
    return rng.poisson(mean).astype(np.float64), population


def context_rows(series: NDArray[np.float64], k_weeks: int
                 ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """``(context (B, K, 3), mask (B, K))`` at the last week of each row of ``series (B, T)``;
    weeks before a series began (NaN, or before its start) are masked."""
    b, t = series.shape
    window = np.full((b, k_weeks), np.nan)
    take = min(t, k_weeks)
    window[:, k_weeks - take:] = series[:, t - take:]
    mask = np.isfinite(window)
    logs = np.log(np.where(mask, window, 0.0) + HALF_CASE)
    latest = logs[:, -1:]
    relative = np.where(mask, logs - latest, 0.0)
    level = np.where(mask, np.broadcast_to(latest / LEVEL_SCALE, relative.shape), 0.0)
    time = np.where(mask, np.broadcast_to(-np.arange(k_weeks - 1, -1, -1.0), relative.shape),
                    0.0)
    return np.stack([relative, level, time], axis=-1).astype(np.float32), mask


def weekly_targets(window: NDArray[np.float64], counted_before: NDArray[np.float64],
                   population: NDArray[np.float64], *, depletes: bool = True
                   ) -> NDArray[np.float32]:
    """``z (B, H)`` from ``window (B, H + 2)`` = the weeks −1 (before the origin), 0 … H;
    ``counted_before (B,)``: the counts before week −1 (S from the counts; 1 for a rate)."""
    counted = counted_before[:, None] + np.cumsum(window, axis=1)
    s_prev = 1.0 - np.concatenate([counted_before[:, None], counted[:, :-1]],
                                  axis=1) / population[:, None]
    if not depletes:
        s_prev = np.ones_like(s_prev)
    logits = logit((window + HALF_CASE) / (population[:, None] * s_prev))
    return (logits[:, 2:] - logits[:, 1:2]).astype(np.float32)


@dataclass(frozen=True)
class PriorWindows:
    """Windows of the prior at every week of every trajectory: ``series (W, K)`` the K weeks
    to the origin (a seeded share shortened to 2 … K weeks, NaN before), ``target (W, H)``
    (:func:`weekly_targets`), the ``trajectory`` and origin ``week`` of each, the
    trajectories' ``population``, whether a window is whole (``ok``: finite targets), and the
    size of the simulation."""

    series: NDArray[np.float64]
    target: NDArray[np.float32]
    trajectory: NDArray[np.int64]
    week: NDArray[np.int64]
    population: NDArray[np.float64]
    ok: NDArray[np.bool_]
    n_trajectories: int
    n_values: int


def prior_windows(prior: WeeklyFlowConfig, k: int, h: int, seed: int) -> PriorWindows:
    """The prior's windows of K context weeks and H target weeks; ``seed`` draws which are
    shortened (the rounds whose series are a few weeks long)."""
    admissions, population = simulate_admissions(prior)
    m, n_weeks = admissions.shape
    origins = np.arange(k, n_weeks - h)
    trajectory = np.repeat(np.arange(m), origins.size)
    t = np.tile(origins, m)
    series = admissions[trajectory[:, None], t[:, None] + np.arange(-k + 1, 1)[None, :]]
    rng = np.random.default_rng(seed + 7)
    short = rng.random(len(series)) < prior.short_share
    keep = rng.integers(prior.min_weeks, k + 1, len(series))
    series = np.where(short[:, None] & (np.arange(k)[None, :] < (k - keep)[:, None]), np.nan,
                      series)
    counted = np.concatenate([np.zeros((m, 1)), np.cumsum(admissions, axis=1)], axis=1)
    window = admissions[trajectory[:, None], t[:, None] + np.arange(-1, h + 1)[None, :]]
    with np.errstate(invalid="ignore", divide="ignore"):
        target = weekly_targets(window, counted[trajectory, t - 1], population[trajectory])
    return PriorWindows(series, target, trajectory, t, population,
                        np.asarray(np.isfinite(target).all(axis=1)), m, int(admissions.size))


def prior_dataset(windows: PriorWindows, context: NDArray[np.float32],
                  mask: NDArray[np.bool_], meta: DatasetMeta,
                  standardize: Callable[[torch.Tensor, torch.Tensor, torch.Tensor],
                                        Standardization] = compute_standardization
                  ) -> WindowedDataset:
    """The whole windows of ``windows`` with their ``context`` rows, standardized, hashed."""
    ok = windows.ok
    context_t, mask_t = torch.from_numpy(context[ok]), torch.from_numpy(mask[ok])
    target_t = torch.from_numpy(windows.target[ok])
    return with_data_hash(WindowedDataset(
        context_t, mask_t, target_t, torch.from_numpy(windows.trajectory[ok]),
        torch.from_numpy(windows.week[ok].astype(np.float64)),
        standardize(context_t, mask_t, target_t), meta))


def weekly_dataset(config: WeeklyFlowConfig) -> WindowedDataset:
    """Windows at every week of every trajectory of the prior (a share shortened)."""
    k, h = config.context_weeks, config.horizon_weeks
    windows = prior_windows(config, k, h, config.seed)
    context, mask = context_rows(windows.series, k)
    meta = DatasetMeta(
        system="waves", config_name="hub-weekly", direction="forward", target_kind="growth",
        context_features=("log_week_rel", "log_week_level", "t_week"),
        target_features=tuple(f"z_week{s}" for s in range(1, h + 1)), window=k,
        seed=config.seed, val_fraction=config.val_fraction, split="all",
        n_trajectories=windows.n_trajectories, n_observed_points=windows.n_values,
        n_observed_values=windows.n_values, config=config.identity(),
        package_version=pipeline.__version__, format_version=FORMAT_VERSION, data_sha256="")
    return prior_dataset(windows, context, mask, meta)


@dataclass(frozen=True, eq=False)
class WeeklyFlowMember:
    """Forecast member: samples the trained weekly flow at each cell's origin and decodes its
    weekly S/I/R paths (I·N the week's count)."""

    estimator: ConditionalEstimator
    config: WeeklyFlowConfig
    name: str = NF_WEEKLY
    n_samples: int = 1000

    @property
    def max_horizon(self) -> int:
        return self.config.horizon_weeks

    def sample_paths(self, histories: Sequence[History], seeds: Sequence[int],
                     chunk: int = 16) -> NDArray[np.float64]:
        """Weekly S, I, R paths ``(B, n, H, 3)`` of B weekly histories, history b drawn from
        ``seeds[b]``; a missing last week is an error (nowcast it first)."""
        weekly = weekly_cells(histories, self.name)
        k = self.config.context_weeks
        context, mask = context_rows(np.stack([last_weeks(h.cases, k) for h in weekly]), k)
        z = sample_cells([(self.estimator,)] * len(weekly), context, mask, seeds,
                         self.n_samples, self.estimator.features, chunk)
        return decode_weekly(z, weekly)

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Count quantiles ``(B, H, Q)`` of every cell from its sampled paths (kept)."""
        check_horizons(self.name, horizons, self.max_horizon)
        return path_forecast(self.sample_paths(cells.histories, cells.seeds), cells, horizons,
                             levels)

    def real_windows(self, histories: Sequence[History], cutoff: pd.Timestamp) -> RealWindows:
        """Every (place, week) window of ``histories`` whose target weeks end by ``cutoff``
        (the fine-tuned member's training windows), weeks before a series began masked."""
        k, h = self.config.context_weeks, self.config.horizon_weeks
        contexts, masks, targets, places = [], [], [], []
        for index, history in enumerate(as_weekly(x, self.name) for x in histories):
            end = int(np.searchsorted(history.dates.to_numpy(np.int64), cutoff.value,
                                      side="right")) - 1
            origins = np.arange(1, end - h + 1)
            if origins.size == 0:
                continue
            series, target, ok = cut_windows(history, origins, k, h)
            context, mask = context_rows(series, k)
            contexts.append(context[ok])
            masks.append(mask[ok])
            targets.append(target[ok])
            places.append(np.full(int(ok.sum()), index, dtype=np.int64))
        if not contexts:
            return RealWindows(np.empty((0, k, 3), np.float32), np.empty((0, k), bool),
                               np.empty((0, h), np.float32), np.empty(0, np.int64))
        return RealWindows(np.concatenate(contexts), np.concatenate(masks),
                           np.concatenate(targets), np.concatenate(places))


def cut_windows(history: WeeklyHistory, origins: NDArray[np.int64], k_weeks: int,
                horizon_weeks: int
                ) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.bool_]]:
    """At each origin (the index of a window's first target week): the ``k_weeks`` counts
    before it (NaN before the series began), the flow's targets over the ``horizon_weeks``
    (:func:`weekly_targets`), and which windows are whole (finite targets, counts and last
    context week)."""
    cases = history.cases
    padded = np.concatenate([np.full(k_weeks - 1, np.nan), cases])
    series = padded[origins[:, None] + np.arange(k_weeks)[None, :]]
    window = cases[origins[:, None] + np.arange(-1, horizon_weeks + 1)[None, :]]
    counted = (np.concatenate([[0.0], np.nancumsum(cases)])[origins - 1]
               if history.depletes else np.zeros(origins.size))
    with np.errstate(invalid="ignore", divide="ignore"):
        target = weekly_targets(window, counted, np.full(origins.size, float(history.population)),
                                depletes=history.depletes)
    whole = (np.isfinite(target).all(axis=1) & np.isfinite(window).all(axis=1)
             & np.isfinite(series[:, -1]))
    return series, target, whole
