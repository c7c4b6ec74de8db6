"""Rollouts: chain forward (or backward) estimates, feeding each path's predictions back as context.

Paper, "Generating Conditional Embeddings": "we can utilize this conditioning operation
recursively, estimating future states and then using these predicted states for conditioning …
We call this paradigm rollout". The COVID-19 figures show rollouts with *rolling windows* that
re-anchor on observed data every W = 7 or 28 days, with 2σ bands.

Design:

* **Ensemble of paths.** A rollout propagates P sample paths. At every step each path draws one
  value from the flow conditioned on *its own* last R rows (observed rows, then its own earlier
  predictions), so the spread of the paths carries the accumulated uncertainty; bands are
  per-step statistics over paths. The batch dimension is paths × segments: one flow call per step
  for all of them (no Python loop over paths or segments).
* **What is fed back.** The model was trained on contexts of *observations* (state + N(0, σ²)
  noise), while it predicts the *state*. Feeding back the bare state would show the model cleaner
  contexts than it ever saw; ``RolloutConfig.feedback_noise_sigma`` adds fresh N(0, σ²) noise to
  the fed-back state, so each path is a simulated sequence of future observations (ancestral
  sampling of the chain). The CLI sets σ to the observation noise of the model's training data;
  0 feeds back the state itself. The reported samples are always the predicted states (no noise).
* **Validity.** The reported states are the flow's draws, so they are exactly as valid as the
  model makes them: a model with ``target_transform="sir-log-ratio"`` (the SF forecast's) draws
  S, I, R on the open simplex with β, γ > 0 by construction, at every step of every path. The
  fed-back rows are deliberately *not* put through that transform: they stand for observations,
  and the training contexts were observations = state + N(0, σ²) on each compartment,
  unclipped (``pipeline.systems.sir.observe``), so e.g. an observed I slightly below 0 near
  I ≈ 0 is a context the model has seen. Adding the noise in log-ratio coordinates instead
  would give multiplicative, level-dependent noise, a context distribution the model never saw
  (at SF's I ≈ 1e-3 with σ = 5e-4 no single log-space σ matches it). Only the states must
  be valid; they are.
* **Joint models** (target = state + β, γ): only the first C components (the observed columns)
  are fed back; the parameter draws stay in the per-step samples.
* **Backward** rollouts mirror forward ones: the context is the R rows after the target, and the
  predicted row is inserted in front of them.
* **Rolling windows** (:func:`rolling_rollout`): over a whole observed series, anchors every W
  steps: forward, segment j predicts indices ``R + jW … R + (j+1)W − 1`` from the observed rows
  ``R + jW − R … R + jW − 1``; backward mirrors this from the end. Every segment is an independent
  rollout started on observed data; all segments run in one batch.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.inference.estimate import (Draws, Estimator, ObservationWindow, assemble_context, check_direction,
                               context_window_length, draw_noise, noise_dim, target_dim,
                               uses_absolute_time)
from pipeline.progress import ProgressReporter, SilentProgress

BAND_QUANTILES: tuple[float, ...] = (0.02275, 0.15866, 0.5, 0.84134, 0.97725)


@dataclass(frozen=True)
class RolloutConfig:
    """``n_paths`` sample paths; ``feedback_noise_sigma`` and ``noise_persistence`` (see
    module doc); ``seed``."""

    n_paths: int = 200
    feedback_noise_sigma: float = 0.0
    seed: int = 0
    noise_persistence: float = 0.0

    def __post_init__(self) -> None:
        if self.n_paths < 1:
            raise ConfigError(f"RolloutConfig.n_paths={self.n_paths} must be >= 1")
        if not 0.0 <= self.noise_persistence <= 1.0:
            raise ConfigError(f"RolloutConfig.noise_persistence={self.noise_persistence} must "
                              "lie in [0, 1]")
        if not self.feedback_noise_sigma >= 0:
            raise ConfigError(f"RolloutConfig.feedback_noise_sigma={self.feedback_noise_sigma} "
                              "must be >= 0")


@dataclass(frozen=True, eq=False)
class RolloutResult(Draws):
    """Sample paths ``samples (P, H, D)`` at ``times (H,)`` (NaN where nothing was predicted).

    ``anchors``: for rolling rollouts, the series index of the first prediction of each segment.
    """

    direction: str
    times: np.ndarray
    samples: Tensor
    names: tuple[str, ...]
    anchors: tuple[int, ...] = ()

    def band(self, n_sigma: float = 2.0) -> tuple[Tensor, Tensor]:
        """mean ∓ n_sigma · std per step and component (the paper's 2σ bands)."""
        return self.mean - n_sigma * self.std, self.mean + n_sigma * self.std

    def quantiles(self, levels: Sequence[float] = BAND_QUANTILES) -> Tensor:
        """(Q, H, D) per-step quantiles over paths."""
        return self.quantiles_over_draws(levels)

    def summary_frame(self, levels: Sequence[float] = BAND_QUANTILES) -> pd.DataFrame:
        """Long table: time, component, mean, std, lower_2sigma, upper_2sigma, q<level>..."""
        lower, upper = self.band(2.0)
        quantiles = self.quantiles(levels)
        frames = []
        for d, name in enumerate(self.names):
            columns = {"time": self.times, "component": name,
                       "mean": self.mean[:, d].numpy(), "std": self.std[:, d].numpy(),
                       "lower_2sigma": lower[:, d].numpy(), "upper_2sigma": upper[:, d].numpy()}
            for level, values in zip(levels, quantiles[:, :, d], strict=True):
                columns[f"q{level:g}"] = values.numpy()
            frames.append(pd.DataFrame(columns))
        return pd.concat(frames, ignore_index=True)


def propagate_paths(estimator: Estimator, anchor_times: Tensor, anchor_values: Tensor,
                    target_times: Tensor, direction: str, config: RolloutConfig,
                    progress: ProgressReporter | None = None) -> Tensor:
    """Run S independent rollouts of P paths each; returns samples ``(S, P, H, D)``.

    ``anchor_times (S, R)`` and ``anchor_values (S, R, C)``: the observed rows each rollout starts
    from, in increasing time order (R = the model's window). ``target_times (S, H)``: the times
    to predict, in the order they are predicted (increasing forward, decreasing backward).
    One flow call per step for all S·P paths.
    """
    check_direction(direction)
    progress = progress or SilentProgress()
    n_seg, window, n_obs = anchor_values.shape
    horizon = target_times.shape[1]
    paths = config.n_paths
    dim = target_dim(estimator)          # components per draw, original units
    eps_dim = noise_dim(estimator)       # the flow's noise (D - 1 under the SIR log-ratio)
    if dim < n_obs:
        raise ConfigError(f"the model predicts {dim} components but the context has {n_obs} "
                          "observed columns: cannot feed predictions back")
    _check_target_order(anchor_times, target_times, direction)
    generator = torch.Generator().manual_seed(config.seed)
    batch = n_seg * paths
    # Rows of every path: (S·P, R, C) values; times are shared by the paths of a segment.
    values = anchor_values.double().repeat_interleave(paths, dim=0)
    times = anchor_times.double().repeat_interleave(paths, dim=0)
    mask = torch.ones((batch, window), dtype=torch.bool)
    targets = target_times.double().repeat_interleave(paths, dim=0)                     # (S·P, H)
    absolute_time = uses_absolute_time(estimator)
    out = torch.empty((batch, horizon, dim), dtype=torch.float32)
    rho = config.noise_persistence
    eps = draw_noise((batch, 1, eps_dim), generator)
    with torch.no_grad():
        for step in range(horizon):
            t_target = targets[:, step]
            context = assemble_context(values, times, mask, t_target, absolute_time)
            if step > 0:
                fresh = draw_noise((batch, 1, eps_dim), generator)
                eps = fresh if rho == 0.0 else rho * eps + math.sqrt(1.0 - rho * rho) * fresh
            draw = estimator.noise_to_data(eps, context, mask)[:, 0]                 # (S·P, D)
            out[:, step] = draw
            fed_back = draw[:, :n_obs].double()
            if config.feedback_noise_sigma > 0:
                fed_back = fed_back + config.feedback_noise_sigma * torch.randn(
                    fed_back.shape, generator=generator, dtype=torch.float64)
            values, times = _shift_in(values, times, fed_back, t_target, direction)
            progress.advance(1)
    if not bool(torch.isfinite(out).all()):
        raise ConfigError("the rollout produced non-finite values (the model left its training "
                          "range); shorten the horizon or re-anchor more often")
    return out.reshape(n_seg, paths, horizon, dim)


def _check_target_order(anchor_times: Tensor, target_times: Tensor, direction: str) -> None:
    steps = torch.diff(torch.cat([anchor_times[:, -1:] if direction == "forward"
                                  else anchor_times[:, :1], target_times], dim=1), dim=1)
    ok = (steps > 0).all() if direction == "forward" else (steps < 0).all()
    if not bool(ok):
        raise ConfigError(f"{direction} rollout: target times must move away from the anchor "
                          "window, strictly monotonically")


def _shift_in(values: Tensor, times: Tensor, new_values: Tensor, new_time: Tensor,
              direction: str) -> tuple[Tensor, Tensor]:
    """Drop the row farthest from the next target and add the newly predicted row."""
    if direction == "forward":
        return (torch.cat([values[:, 1:], new_values[:, None]], dim=1),
                torch.cat([times[:, 1:], new_time[:, None]], dim=1))
    return (torch.cat([new_values[:, None], values[:, :-1]], dim=1),
            torch.cat([new_time[:, None], times[:, :-1]], dim=1))


def rollout(estimator: Estimator, window: ObservationWindow, horizon: int, step: float,
            direction: str = "forward", config: RolloutConfig = RolloutConfig(), *,
            names: Sequence[str] | None = None, window_length: int | None = None,
            progress: ProgressReporter | None = None) -> RolloutResult:
    """Roll out ``horizon`` steps of size ``step`` from one window of observations.

    Forward: targets ``window.target_time + k·step``, k = 0 … horizon−1 (the first one is the
    window's own target); backward: ``window.target_time − k·step``. The window must hold at
    least the model's R rows (the R nearest the target are used).
    """
    window.check_direction(direction)
    if horizon < 1 or not step > 0:
        raise ConfigError(f"rollout: horizon={horizon} must be >= 1 and step={step} > 0")
    length = window_length or context_window_length(estimator, window.n_rows)
    if window.n_rows < length:
        raise ConfigError(f"rollout: the window has {window.n_rows} rows, the model needs {length}")
    rows = slice(-length, None) if direction == "forward" else slice(0, length)
    sign = 1.0 if direction == "forward" else -1.0
    targets = window.target_time + sign * step * np.arange(horizon)
    samples = propagate_paths(
        estimator, torch.as_tensor(window.times[rows])[None], torch.as_tensor(window.values[rows])[None],
        torch.as_tensor(targets)[None], direction, config, progress)[0]
    dim = samples.shape[-1]
    labels = tuple(names) if names is not None else tuple(f"x{d}" for d in range(dim))
    order = np.argsort(targets)  # report in increasing time for both directions
    return RolloutResult(direction=direction, times=targets[order], samples=samples[:, order],
                         names=labels)


def rolling_anchor_indices(n_times: int, window: int, every: int, direction: str) -> list[int]:
    """Series index of the first prediction of each rolling segment (see module doc)."""
    check_direction(direction)
    if every < 1 or window < 1:
        raise ConfigError(f"window_every={every} and window={window} must be >= 1")
    if n_times <= window:
        raise ConfigError(f"the series has {n_times} rows; at least window + 1 = {window + 1} "
                          "are needed for a rolling rollout")
    if direction == "forward":
        return list(range(window, n_times, every))
    return list(range(n_times - 1 - window, -1, -every))


def rolling_rollout(estimator: Estimator, times: np.ndarray, values: np.ndarray, every: int,
                    direction: str = "forward", config: RolloutConfig = RolloutConfig(), *,
                    names: Sequence[str] | None = None, window_length: int | None = None,
                    progress: ProgressReporter | None = None) -> RolloutResult:
    """Re-anchor on the observed series every ``every`` steps; bands over the whole series.

    ``times (T,)`` increasing, ``values (T, C)`` observed. Returns samples ``(P, T, D)`` aligned
    with ``times``; the R rows that are never predicted (the first R forward, the last R
    backward) are NaN. ``anchors`` lists each segment's first predicted index.
    """
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2 or len(values) != len(times):
        raise ConfigError(f"rolling_rollout: values must be (T, C) with T = {len(times)}, got "
                          f"{values.shape}")
    if not (np.diff(times) > 0).all():
        raise ConfigError("rolling_rollout: times must be strictly increasing")
    if not np.isfinite(values).all():
        raise ConfigError("rolling_rollout: the series has missing values (NaN); fill or drop them")
    length = window_length or context_window_length(estimator, 5)
    anchors = rolling_anchor_indices(len(times), length, every, direction)
    sign = 1 if direction == "forward" else -1
    offsets = np.arange(every) * sign
    # Segments whose last steps run past the series end are clipped afterwards; their target
    # times past the end are extrapolated on the mean step so the batch stays rectangular.
    target_idx = np.asarray(anchors)[:, None] + offsets[None]                      # (S, W)
    valid = (target_idx >= 0) & (target_idx < len(times))
    mean_step = float(np.mean(np.diff(times)))
    padded_times = np.concatenate([times[0] - mean_step * np.arange(every, 0, -1), times,
                                   times[-1] + mean_step * np.arange(1, every + 1)])
    target_times = padded_times[target_idx + every]
    if direction == "forward":
        window_idx = np.asarray(anchors)[:, None] + np.arange(-length, 0)[None]
    else:
        window_idx = np.asarray(anchors)[:, None] + np.arange(1, length + 1)[None]
    samples = propagate_paths(estimator, torch.as_tensor(times[window_idx]),
                              torch.as_tensor(values[window_idx]), torch.as_tensor(target_times),
                              direction, config, progress)                          # (S, P, W, D)
    full = segments_to_series(samples, target_idx, valid, len(times))
    labels = tuple(names) if names is not None else tuple(f"x{d}" for d in range(full.shape[-1]))
    return RolloutResult(direction=direction, times=times, samples=full, names=labels,
                         anchors=tuple(anchors))


def segments_to_series(samples: Tensor, target_idx: np.ndarray, valid: np.ndarray,
                       n_times: int) -> Tensor:
    """``samples (S, P, W, D)`` of S segments placed on a series of ``n_times`` steps: ``(P, T,
    D)``, segment s's step w at index ``target_idx[s, w]`` where ``valid``, NaN elsewhere."""
    full = torch.full((samples.shape[1], n_times, samples.shape[-1]), float("nan"))
    seg, col = np.nonzero(valid)
    full[:, torch.as_tensor(target_idx[seg, col])] = samples[seg, :, col].permute(1, 0, 2).float()
    return full
