"""Flow-seeded rollouts: the joint flow's estimate at an anchor, carried forward by the prior's
own dynamics.

A chained rollout (:mod:`pipeline.inference.rollout`) feeds a one-step flow its own draws for up
to 28 days. The multi-wave prior's transmission rate reverts towards its mean by a few per cent
a day (θ in :class:`pipeline.systems.waves.WavePrior`); a one-step flow learns that drift only
roughly, and chaining it 28 times turns the error into a trend. Trained from three seeds, the
same chained model followed SF's Omicron rise to its peak and then kept growing, to 2.3, 3.1 and
4.0 times the observed peak (``bench/results/calibration.json``, ``seeds``): what it showed
depended on the training run.

Here the flow does what it is trained and checked to do, estimate the state and β from the
R observations before the anchor, and the days after it follow the prior the flow was trained
on, as the NF-seeded SMC's forecast does (:mod:`pipeline.inference.hybrid`):

* P draws of (S, I, R, β) from the forward joint flow at the anchor's first day; each becomes a
  particle of :class:`pipeline.inference.smc_models.WaveRenewalModel`, with the last L days'
  new cases spread in the shape of the L reports before the anchor (weekday pattern divided
  out) and its own reversion level μ, speed θ, volatility σ and importation ι drawn from the
  prior, jumps at the prior's rate;
* each later day is one step of that model for every path of every segment at once;
* the reported I is what the series would hold, the L-day sum of negative-binomial reports
  NB(N·I, L·k) over N, with k the dispersion of the 56 daily reports before the anchor
  (``SeededRolloutConfig.reporting_noise``; off, it is the model's I). S, R and β are the
  model's (the cumulative count's reporting noise is a tiny share of it). Day 0 is the flow's
  draw itself: the flow already estimates the series' own I.

Only forward: the prior's dynamics run forward in time. Backward rollouts stay chained.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.inference.estimate import (Estimator, assemble_context, context_window_length,
                                         sample_conditional, target_dim, uses_absolute_time)
from pipeline.inference.hybrid import wave_model, wave_particles
from pipeline.inference.rollout import RolloutResult, rolling_anchor_indices, segments_to_series
from pipeline.inference.smc import owned_planar
from pipeline.inference.smc_models import reporting_pattern
from pipeline.progress import ProgressReporter, SilentProgress
from pipeline.systems.waves import WavePrior

MIN_PATTERN_DAYS = 14   # reporting_pattern's least: two whole centred weeks


@dataclass(frozen=True)
class SeededRolloutConfig:
    """``n_paths`` per segment, ``seed``; the reporting pattern is read from the
    ``pattern_days`` days before each anchor; ``reporting_noise`` draws the reported I."""

    n_paths: int = 200
    seed: int = 0
    pattern_days: int = 56
    reporting_noise: bool = True

    def __post_init__(self) -> None:
        if self.n_paths < 1:
            raise ConfigError(f"SeededRolloutConfig.n_paths={self.n_paths} must be >= 1")
        if self.pattern_days < MIN_PATTERN_DAYS:
            raise ConfigError(f"SeededRolloutConfig.pattern_days={self.pattern_days} must be "
                              f">= {MIN_PATTERN_DAYS}")


def seeded_paths(estimator: Estimator, times: np.ndarray, values: np.ndarray,
                 anchors: Sequence[int], horizon: int, prior: WavePrior,
                 config: SeededRolloutConfig = SeededRolloutConfig(), *,
                 window_length: int | None = None,
                 progress: ProgressReporter | None = None) -> Tensor:
    """``(S, P, horizon, 4)`` paths of (S, I, R, β), one segment per anchor.

    ``times (T,)`` whole days, ``values (T, 3)`` the observed S/I/R series; segment s predicts
    days ``anchors[s] … anchors[s] + horizon − 1`` (an anchor may be T: the days after the
    series) from the R rows before it.
    """
    times, values = _checked_series(times, values)
    if target_dim(estimator) != 4:
        raise ConfigError("a flow-seeded rollout needs the joint (S, I, R, beta) flow; the "
                          f"estimator predicts {target_dim(estimator)} components")
    if horizon < 1:
        raise ConfigError(f"flow-seeded rollout: horizon={horizon} must be >= 1")
    length = window_length or context_window_length(estimator, 5)
    starts = np.asarray(anchors, dtype=np.int64)
    lag = prior.window_days
    first = first_anchor(length, prior)
    if starts.size == 0 or starts.min() < first or starts.max() > len(times):
        raise ConfigError(f"flow-seeded rollout: anchors must lie in [{first}, {len(times)}] "
                          f"(R = {length} rows and L = {lag} days of reports before each), got "
                          f"{starts.tolist()[:5]}")
    progress = progress or SilentProgress()
    generator = torch.Generator().manual_seed(config.seed)
    draws = _flow_draws(estimator, times, values, starts, length, config.n_paths,
                        generator)                                              # (S, P, 4)
    reports = daily_reports(values, prior.population)
    shape, dispersion = _reporting_before(reports, starts, lag, config.pattern_days, prior)
    model = wave_model(prior, float(prior.population), dispersion, forecasting=True)
    x = owned_planar(wave_particles(draws, shape, prior, generator), torch.float64)
    out = torch.empty((*draws.shape[:2], horizon, 4), dtype=torch.float32)
    out[:, :, 0] = draws.float()
    progress.advance(1)
    for day in range(1, horizon):
        x = model.transition(x, float(day), 1.0, generator)
        out[:, :, day] = x[..., :4].float()
        if config.reporting_noise:
            out[:, :, day, 1] = (model.sample_window_reports(x, generator)
                                 / prior.population).float()
        progress.advance(1)
    if not bool(torch.isfinite(out).all()):
        raise ConfigError("the flow-seeded rollout produced non-finite values")
    return out


def seeded_rolling_rollout(estimator: Estimator, times: np.ndarray, values: np.ndarray,
                           every: int, prior: WavePrior,
                           config: SeededRolloutConfig = SeededRolloutConfig(), *,
                           names: Sequence[str] | None = None, window_length: int | None = None,
                           progress: ProgressReporter | None = None) -> RolloutResult:
    """Forward segments re-anchored on the observed series every ``every`` days, at the chained
    rolling rollout's anchors (:func:`pipeline.inference.rollout.rolling_rollout`; the first
    needs L + 1 days of reports too): samples ``(P, T, 4)`` aligned with ``times``, NaN before
    the first anchor."""
    length = window_length or context_window_length(estimator, 5)
    anchors = rolling_anchor_indices(len(times), first_anchor(length, prior), every, "forward")
    samples = seeded_paths(estimator, times, values, anchors, every, prior, config,
                           window_length=length, progress=progress)
    target_idx = np.asarray(anchors)[:, None] + np.arange(every)[None]
    full = segments_to_series(samples, target_idx, target_idx < len(times), len(times))
    return RolloutResult(direction="forward", times=np.asarray(times, dtype=np.float64),
                         samples=full, names=_labels(names), anchors=tuple(anchors))


def seeded_future_rollout(estimator: Estimator, times: np.ndarray, values: np.ndarray,
                          horizon: int, prior: WavePrior,
                          config: SeededRolloutConfig = SeededRolloutConfig(), *,
                          names: Sequence[str] | None = None,
                          window_length: int | None = None) -> RolloutResult:
    """The ``horizon`` days after the series: samples ``(P, horizon, 4)``."""
    samples = seeded_paths(estimator, times, values, [len(times)], horizon, prior, config,
                           window_length=window_length)[0]
    future = float(times[-1]) + 1.0 + np.arange(horizon, dtype=np.float64)
    return RolloutResult(direction="forward", times=future, samples=samples, names=_labels(names))


def first_anchor(window_length: int, prior: WavePrior) -> int:
    """The first day a segment can start: R context rows and L days of reports before it."""
    return max(window_length, prior.window_days + 1)


def daily_reports(values: np.ndarray, population: int) -> np.ndarray:
    """``(T,)`` cases reported each day, N·(S_{t−1} − S_t) of the conversion (day 0 unknown:
    NaN); the conversion's S falls by exactly each day's reports."""
    s = np.asarray(values, dtype=np.float64)[:, 0]
    return np.concatenate([[np.nan], population * -np.diff(s)])


def _checked_series(times: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2 or values.shape != (len(times), 3):
        raise ConfigError(f"flow-seeded rollout: values must be the (T, 3) S/I/R series with "
                          f"T = {len(times)}, got {values.shape}")
    if len(times) > 1 and not np.allclose(np.diff(times), 1.0):
        raise ConfigError("flow-seeded rollout: the prior steps whole days; times must be "
                          "consecutive days")
    if not np.isfinite(values).all():
        raise ConfigError("flow-seeded rollout: the series has missing values (NaN)")
    return times, values


def _flow_draws(estimator: Estimator, times: np.ndarray, values: np.ndarray, anchors: np.ndarray,
                length: int, n_paths: int, generator: torch.Generator) -> Tensor:
    """(S, P, 4) joint-flow draws for the first day of each segment, from the R rows before."""
    rows = anchors[:, None] + np.arange(-length, 0)[None]                     # (S, R)
    target = torch.as_tensor(times[anchors - 1] + 1.0)
    context = assemble_context(torch.as_tensor(values[rows]), torch.as_tensor(times[rows]),
                               torch.ones(rows.shape, dtype=torch.bool), target,
                               uses_absolute_time(estimator))
    return sample_conditional(estimator, context, torch.ones(rows.shape, dtype=torch.bool),
                              n_paths, generator).double()


def _reporting_before(reports: np.ndarray, anchors: np.ndarray, lag: int, pattern_days: int,
                      prior: WavePrior) -> tuple[Tensor, Tensor]:
    """Per anchor, from the reports before it only: the shape of the last L days' new cases
    ``(S, L)`` (weekday pattern divided out, rows summing to 1) and the reports' dispersion
    ``(S,)``. Anchors with fewer than 14 days of reports get no weekday pattern and the
    prior's middle dispersion (the geometric midpoint of its range)."""
    days = np.minimum(pattern_days, anchors - 1)                 # day 0 has no report
    factors = torch.ones((len(anchors), 7), dtype=torch.float64)
    dispersion = torch.full((len(anchors),), math.sqrt(prior.dispersion[0] * prior.dispersion[1]),
                            dtype=torch.float64)
    for n in np.unique(days[days >= MIN_PATTERN_DAYS]):           # a few lengths, near the start
        group = np.flatnonzero(days == n)
        windows = torch.as_tensor(reports[anchors[group][:, None] + np.arange(-n, 0)[None]])
        factors[group], dispersion[group] = reporting_pattern(windows.clamp(min=0.0), int(n))
    position = torch.arange(-lag, 0) % 7          # the factor of the L days before the anchor
    last = torch.as_tensor(reports[anchors[:, None] + np.arange(-lag, 0)[None]]).clamp(min=0.0)
    before = (last + 0.5) / factors[:, position]
    return before / before.sum(1, keepdim=True), dispersion


def _labels(names: Sequence[str] | None) -> tuple[str, ...]:
    return tuple(names) if names is not None else ("S", "I", "R", "beta")
