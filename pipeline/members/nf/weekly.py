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
decoding gives 0 < A_h < N S_{h−1} (:func:`~pipeline.members.nf.model.decode_paths`).
"""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pandas as pd
import torch
from numpy.typing import NDArray

import pipeline
from pipeline.errors import ConfigError
from pipeline.members.base import MemberForecast, quantiles_of_samples
from pipeline.members.nf.model import (HALF_CASE, LEVEL_SCALE, RealWindows, cell_noise,
                                       decode_paths, single_thread)
from pipeline.models.encoders import EncoderConfig, MLPEncoderConfig
from pipeline.models.estimator import (ConditionalEstimator, EstimatorConfig,
                                       make_estimator_config)
from pipeline.panels.history import History, WeeklyHistory
from pipeline.panels.panel import Cells
from pipeline.panels.targets import DAYS_PER_WEEK, TargetError
from pipeline.systems.waves import WavePrior, simulate_waves
from pipeline.training.datasets import (FORMAT_VERSION, DatasetMeta, WindowedDataset,
                                        compute_standardization, dataset_sha256)

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
class WeeklyFlowConfig:
    """The weekly member's prior, admissions layer, coordinates, network and optimiser (the
    model-store key is built from this)."""

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
    hidden_features: int = 128
    flow_layers: int = 5
    flow_hidden: int = 64
    iterations: int = 2500
    batch_size: int = 1024
    lr: float = 3e-3
    val_fraction: float = 0.1
    seed: int = 0

    kind: ClassVar[str] = NF_WEEKLY

    def __post_init__(self) -> None:
        if not 2 <= self.min_weeks <= self.context_weeks or self.horizon_weeks < 1:
            raise ConfigError(f"WeeklyFlowConfig: need 2 <= min_weeks <= context_weeks and "
                              f"horizon_weeks >= 1, got {self}")
        if not 0 <= self.short_share < 1:
            raise ConfigError(f"WeeklyFlowConfig.short_share={self.short_share} not in [0, 1)")

    def identity(self) -> dict[str, object]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def estimator_config(self) -> EstimatorConfig:
        encoder = EncoderConfig(kind="mlp", embedding_features=32,
                                mlp=MLPEncoderConfig(hidden_features=self.hidden_features))
        return make_estimator_config(self.horizon_weeks, 3, self.context_weeks, encoder,
                                     layers=self.flow_layers, hidden_features=self.flow_hidden)

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


def _logit(p: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.log(p) - np.log1p(-p)


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
    logits = _logit((window + HALF_CASE) / (population[:, None] * s_prev))
    return (logits[:, 2:] - logits[:, 1:2]).astype(np.float32)


def weekly_dataset(config: WeeklyFlowConfig) -> WindowedDataset:
    """Windows at every week of every trajectory of the prior (a share shortened)."""
    admissions, population = simulate_admissions(config)
    m, n_weeks = admissions.shape
    k, h = config.context_weeks, config.horizon_weeks
    origins = np.arange(k, n_weeks - h)
    trajectory = np.repeat(np.arange(m), origins.size)
    t = np.tile(origins, m)
    series = admissions[trajectory[:, None], t[:, None] + np.arange(-k + 1, 1)[None, :]]
    rng = np.random.default_rng(config.seed + 7)
    short = rng.random(len(series)) < config.short_share
    keep = rng.integers(config.min_weeks, k + 1, len(series))
    series = np.where(short[:, None] & (np.arange(k)[None, :] < (k - keep)[:, None]), np.nan,
                      series)
    context, mask = context_rows(series, k)
    counted = np.concatenate([np.zeros((m, 1)), np.cumsum(admissions, axis=1)], axis=1)
    window = admissions[trajectory[:, None], t[:, None] + np.arange(-1, h + 1)[None, :]]
    with np.errstate(invalid="ignore", divide="ignore"):
        target = weekly_targets(window, counted[trajectory, t - 1], population[trajectory])
    ok = np.isfinite(target).all(axis=1)
    context_t, mask_t = torch.from_numpy(context[ok]), torch.from_numpy(mask[ok])
    target_t = torch.from_numpy(target[ok])
    meta = DatasetMeta(
        system="waves", config_name="hub-weekly", direction="forward", target_kind="growth",
        context_features=("log_week_rel", "log_week_level", "t_week"),
        target_features=tuple(f"z_week{s}" for s in range(1, h + 1)), window=k,
        seed=config.seed, val_fraction=config.val_fraction, split="all", n_trajectories=m,
        n_observed_points=int(admissions.size), n_observed_values=int(admissions.size),
        config=config.identity(), package_version=pipeline.__version__,
        format_version=FORMAT_VERSION, data_sha256="")
    draft = WindowedDataset(context_t, mask_t, target_t, torch.from_numpy(trajectory[ok]),
                            torch.from_numpy(t[ok].astype(np.float64)),
                            compute_standardization(context_t, mask_t, target_t), meta)
    return dataclasses.replace(draft, meta=dataclasses.replace(
        meta, data_sha256=dataset_sha256(draft)))


def _weekly(history: History, name: str) -> WeeklyHistory:
    if not isinstance(history, WeeklyHistory):
        raise TargetError(f"{name} reads weekly counts; a daily series needs the daily flow")
    return history


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
        weekly = [_weekly(h, self.name) for h in histories]
        series = np.stack([_window(h.cases, self.config.context_weeks) for h in weekly])
        last = series[:, -1]
        if not np.isfinite(last).all():
            bad = weekly[int(np.flatnonzero(~np.isfinite(last))[0])]
            raise TargetError(f"{self.name}: the week ending {bad.origin.date()} is missing "
                              "(the origin's week must be reported or nowcast)")
        context, mask = context_rows(series, self.config.context_weeks)
        eps = cell_noise(seeds, self.n_samples, self.estimator.features)
        context_t, mask_t = torch.from_numpy(context), torch.from_numpy(mask)
        with torch.no_grad(), single_thread():
            z = torch.cat([self.estimator.noise_to_data(eps[i:i + chunk], context_t[i:i + chunk],
                                                        mask_t[i:i + chunk])
                           for i in range(0, len(weekly), chunk)]).double().numpy()
        population = np.array([h.population for h in weekly], dtype=np.int64)[:, None]
        s = np.array([h.susceptible_at_weeks()[-2:] if len(h) > 1
                      else np.r_[1.0, h.susceptible_at_weeks()] for h in weekly])
        paths = decode_paths(z, last[:, None], s[:, :1], s[:, 1:], population)
        rate = np.array([not h.depletes for h in weekly])
        if rate.any():          # a rate leaves S at 1: each week's share against all N
            base = _logit((last[rate, None] + HALF_CASE) / population[rate])[..., None]
            share = 1.0 / (1.0 + np.exp(-(z[rate] + base)))
            paths[rate] = np.stack([1.0 - share, share, np.zeros_like(share)], axis=-1)
        return paths

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Count quantiles ``(B, H, Q)`` of every cell from its sampled paths (kept)."""
        if max(horizons) > self.max_horizon or min(horizons) < 1:
            raise TargetError(f"{self.name} forecasts weeks 1 … {self.max_horizon}, "
                              f"not {horizons}")
        paths = self.sample_paths(cells.histories, cells.seeds)[:, :, [h - 1 for h in horizons]]
        counts = paths[..., 1] * cells.populations[:, None, None] - HALF_CASE
        return MemberForecast(np.maximum(quantiles_of_samples(counts, levels), 0.0),
                              paths=paths)

    def real_windows(self, histories: Sequence[History], cutoff: pd.Timestamp) -> RealWindows:
        """Every (place, week) window of ``histories`` whose target weeks end by ``cutoff``
        (the fine-tuned member's training windows), weeks before a series began masked."""
        k, h = self.config.context_weeks, self.config.horizon_weeks
        contexts, masks, targets, places = [], [], [], []
        for index, history in enumerate(_weekly(x, self.name) for x in histories):
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


def _window(cases: NDArray[np.float64], k_weeks: int) -> NDArray[np.float64]:
    """The last ``k_weeks`` counts, NaN before the series began."""
    out = np.full(k_weeks, np.nan)
    take = min(len(cases), k_weeks)
    out[k_weeks - take:] = cases[len(cases) - take:]
    return out
