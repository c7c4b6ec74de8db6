"""Forward / backward state (and parameter) estimates from a window of observations.

Paper, "Generating Conditional Embeddings" and the Results figures: a conditional flow gives the
density of the state x_n given R observations *before* n (forward, p(x_n | o_{n-R..n-1})) or R
observations *after* n (backward, p(x_n | o_{n+1..n+R})). From it we report

* samples and the log-density of any candidate value (the flow's exact log-density);
* summaries: mean, standard deviation, quantiles per component;
* 1/2/3σ confidence regions "corresponding to 1, 2, and 3 base distribution standard
  deviations": the base is a conditional *diagonal* Gaussian, so its r-σ level set is the sphere
  ``eps = r·u`` (``|u| = 1``) of standard-normal noise; ``noise_to_data`` pushes that sphere
  through the conditional base (mean + scale·eps) and the flow. In 2-D (vehicle) this is a closed
  curve, in 3-D (SIR) a closed surface (we push a Fibonacci lattice of the sphere and also report
  the per-component extent, the paper's "1σ error bounds"). Note: in D dimensions the r-sphere
  encloses P(χ²_D ≤ r²) of the base mass (D=2: 39/86/99 %, D=3: 20/74/97 %), not 68/95/99.7 %.

Sampling goes through ``estimator.noise_to_data`` with standard-normal noise drawn from our own
``torch.Generator``: this is the same distribution as ``estimator.sample`` (base draw = mean +
scale·eps, then the flow) and makes every estimate reproducible from its seed without touching
global RNG state.

The context's time channels are built with :func:`pipeline.training.datasets.time_features`, the same
code the datasets use, so a window read from a CSV reaches the model exactly as training windows
did.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.names import DIRECTIONS, Direction

SIGMA_RADII: tuple[float, ...] = (1.0, 2.0, 3.0)
DEFAULT_QUANTILES: tuple[float, ...] = (0.00135, 0.02275, 0.05, 0.15866, 0.25, 0.5, 0.75,
                                        0.84134, 0.95, 0.97725, 0.99865)


class Estimator(Protocol):
    """What estimation needs from :class:`pipeline.models.estimator.ConditionalEstimator`."""

    def log_prob(self, target: Tensor, context: Tensor, mask: Tensor) -> Tensor: ...

    def noise_to_data(self, eps: Tensor, context: Tensor, mask: Tensor) -> Tensor: ...


@dataclass(frozen=True)
class ObservationWindow:
    """Observed values at given times and the time whose state is wanted.

    ``times (R,)`` and ``values (R, C)`` in the system's observed units (e.g. S, I, R proportions
    or vehicle positions); R may differ from the model's window (shorter windows are padded and
    masked, longer ones keep the R rows nearest the target). ``target_time`` must lie after all
    observation times for a forward estimate and before all of them for a backward one.
    """

    times: np.ndarray
    values: np.ndarray
    target_time: float

    def __post_init__(self) -> None:
        # Own writable copies: callers' arrays (e.g. pandas' read-only views) are never aliased.
        times = np.array(self.times, dtype=np.float64).reshape(-1)
        values = np.array(self.values, dtype=np.float64)
        if values.ndim == 1:
            values = values[:, None]
        if values.ndim != 2 or len(values) != len(times):
            raise ConfigError(f"ObservationWindow: values must be (R, C) with R = len(times) = "
                              f"{len(times)}, got shape {values.shape}")
        if len(times) == 0:
            raise ConfigError("ObservationWindow: no observations")
        if not (np.isfinite(times).all() and np.isfinite(values).all()):
            raise ConfigError("ObservationWindow: times and values must be finite (no NaN)")
        if len(times) > 1 and not (np.diff(times) > 0).all():
            raise ConfigError(f"ObservationWindow: times must be strictly increasing, got "
                              f"{times.tolist()}")
        if not math.isfinite(float(self.target_time)):
            raise ConfigError(f"ObservationWindow: target_time={self.target_time} is not finite")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "target_time", float(self.target_time))

    @property
    def n_rows(self) -> int:
        return len(self.times)

    def check_direction(self, direction: str) -> None:
        """Raise if the observations are not all before (forward) / after (backward) the target."""
        check_direction(direction)
        if direction == "forward" and not (self.times < self.target_time).all():
            raise ConfigError(f"forward estimate needs every observation time < target_time="
                              f"{self.target_time}; got times {self.times.tolist()}")
        if direction == "backward" and not (self.times > self.target_time).all():
            raise ConfigError(f"backward estimate needs every observation time > target_time="
                              f"{self.target_time}; got times {self.times.tolist()}")


def check_direction(direction: str) -> None:
    if direction not in DIRECTIONS:
        raise ConfigError(f"direction must be one of {DIRECTIONS}, got {direction!r}")


def target_dim(estimator: object) -> int:
    """D of the estimator's target in original units: ``estimator.target_features`` where it
    has one (a flow over transformed targets, e.g. the SIR log-ratio, has D - 1 noise
    dimensions), else :func:`noise_dim`."""
    features = getattr(estimator, "target_features", None)
    return int(features) if features is not None else noise_dim(estimator)


def noise_dim(estimator: object) -> int:
    """Size of the standard-normal noise ``noise_to_data`` takes: the flow's dimension, read from
    its standardization (``stats.target_mean``, fitted in the flow's coordinates)."""
    stats = getattr(estimator, "stats", None)
    mean = getattr(stats, "target_mean", None)
    if mean is None:
        raise ConfigError(f"{type(estimator).__name__} has no stats.target_mean: cannot tell the "
                          "target dimension")
    return int(torch.as_tensor(mean).reshape(-1).shape[0])


def uses_absolute_time(estimator: object) -> bool:
    """Whether the estimator's context rows carry the absolute time ``t_obs`` (vehicle models)."""
    return bool(getattr(estimator, "absolute_time", False))


def context_window_length(estimator: object, default: int) -> int:
    """R the model was trained with (``estimator.window`` if it has one), else ``default``."""
    window = getattr(estimator, "window", None)
    return int(window) if window is not None else int(default)


def assemble_context(values: Tensor, times: Tensor, mask: Tensor, target_time: Tensor,
                     absolute_time: bool = False) -> Tensor:
    """Context rows ``[observed values..., t_obs - t_target (, t_obs)]`` (B, R, C+1 or C+2),
    float32.

    ``values (B, R, C)``, ``times (B, R)``, ``mask (B, R)`` (False = padding), ``target_time (B,)``;
    ``absolute_time``: the estimator's layout (:func:`uses_absolute_time`). Padding rows are all
    zeros (the dataset convention). The time channels come from
    :func:`pipeline.training.datasets.time_features`, the function the training windows are built with.
    """
    from pipeline.training.datasets import time_features

    rows = torch.cat([values, time_features(times, target_time, absolute_time).to(values.dtype)],
                     dim=-1)
    return (rows * mask.unsqueeze(-1).to(rows.dtype)).float()


def window_context(window: ObservationWindow, direction: str, length: int,
                   absolute_time: bool = False) -> tuple[Tensor, Tensor]:
    """(context (1, length, C+1 or C+2), mask (1, length)) for one window."""
    return batch_window_context([window], direction, length, absolute_time)


def batch_window_context(windows: Sequence[ObservationWindow], direction: str,
                         length: int, absolute_time: bool = False) -> tuple[Tensor, Tensor]:
    """Context and mask of several windows (same observed columns), padded to ``length`` rows.

    Rows are in increasing time order; a window with fewer than ``length`` rows is padded with
    masked zero rows at the end (see :func:`pad_rows`); one with more keeps the ``length`` rows
    nearest the target time.
    """
    check_direction(direction)
    if not windows:
        raise ConfigError("no windows given")
    n_columns = {w.values.shape[1] for w in windows}
    if len(n_columns) != 1:
        raise ConfigError(f"windows have different numbers of observed columns: {sorted(n_columns)}")
    n_cols = n_columns.pop()
    values = torch.zeros((len(windows), length, n_cols), dtype=torch.float64)
    times = torch.zeros((len(windows), length), dtype=torch.float64)
    mask = torch.zeros((len(windows), length), dtype=torch.bool)
    for b, window in enumerate(windows):
        window.check_direction(direction)
        row_times, row_values = _nearest_rows(window, direction, length)
        rows = slice(0, len(row_times))
        values[b, rows] = torch.as_tensor(row_values)
        times[b, rows] = torch.as_tensor(row_times)
        mask[b, rows] = True
    target = torch.tensor([w.target_time for w in windows], dtype=torch.float64)
    return assemble_context(values, times, mask, target, absolute_time), mask


def _nearest_rows(window: ObservationWindow, direction: str, length: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The ``length`` rows closest in time to the target (all rows if there are fewer)."""
    if window.n_rows <= length:
        return window.times, window.values
    keep = slice(-length, None) if direction == "forward" else slice(0, length)
    return window.times[keep], window.values[keep]


@dataclass(frozen=True)
class ConfidenceRegion:
    """The image of the base distribution's r-σ sphere: ``points (K, D)`` in original units."""

    n_sigma: float
    points: Tensor

    @property
    def lower(self) -> Tensor:
        return self.points.min(dim=0).values

    @property
    def upper(self) -> Tensor:
        return self.points.max(dim=0).values


class Draws:
    """Summaries over the draws (dim 0) of ``samples``: an estimate's (n, D), a rollout's
    (P, H, D) sample paths."""

    samples: Tensor

    @property
    def mean(self) -> Tensor:
        return self.samples.mean(dim=0)

    @property
    def std(self) -> Tensor:
        return self.samples.std(dim=0)

    def quantiles_over_draws(self, levels: Sequence[float]) -> Tensor:
        """(Q, ...) empirical quantiles at ``levels``, one per draw-free index."""
        return torch.quantile(self.samples, torch.tensor(levels, dtype=self.samples.dtype),
                              dim=0)


@dataclass(frozen=True, eq=False)
class Estimate(Draws):
    """An estimate of the target at ``window.target_time``.

    ``samples (n, D)`` in original units; ``names`` label the D components; ``regions`` the
    1/2/3σ confidence regions; ``log_density(values (k, D)) -> (k,)`` evaluates the flow's
    log-density of candidate values under the same context.
    """

    direction: str
    target_time: float
    names: tuple[str, ...]
    samples: Tensor
    regions: tuple[ConfidenceRegion, ...]
    log_density: Callable[[Tensor], Tensor] = field(repr=False)
    quantile_levels: tuple[float, ...] = DEFAULT_QUANTILES

    @property
    def quantiles(self) -> Tensor:
        """(Q, D) empirical quantiles at ``quantile_levels``."""
        return self.quantiles_over_draws(self.quantile_levels)

    def summary_rows(self) -> list[dict[str, float | str]]:
        """One row per component: mean, std, quantiles, and each σ-region's extent."""
        rows: list[dict[str, float | str]] = []
        quantiles = self.quantiles
        for d, name in enumerate(self.names):
            row: dict[str, float | str] = {"component": name, "target_time": self.target_time,
                                           "direction": self.direction,
                                           "mean": float(self.mean[d]), "std": float(self.std[d])}
            for level, value in zip(self.quantile_levels, quantiles[:, d], strict=True):
                row[f"q{level:g}"] = float(value)
            for region in self.regions:
                row[f"sigma{region.n_sigma:g}_lower"] = float(region.lower[d])
                row[f"sigma{region.n_sigma:g}_upper"] = float(region.upper[d])
            rows.append(row)
        return rows


def unit_sphere_points(dim: int, n_points: int, seed: int = 0) -> Tensor:
    """Points on the unit sphere S^{dim-1} (float64, (K, dim)), evenly spread where cheap.

    dim 1: {-1, +1}; dim 2: K equally spaced angles; dim 3: a Fibonacci lattice; higher: K
    normalized Gaussian draws from ``seed``.
    """
    if dim < 1 or n_points < 2:
        raise ConfigError(f"unit_sphere_points: need dim >= 1 and n_points >= 2, got {dim}, "
                          f"{n_points}")
    if dim == 1:
        return torch.tensor([[-1.0], [1.0]], dtype=torch.float64)
    if dim == 2:
        angle = torch.arange(n_points, dtype=torch.float64) * (2 * math.pi / n_points)
        return torch.stack([angle.cos(), angle.sin()], dim=-1)
    if dim == 3:
        i = torch.arange(n_points, dtype=torch.float64) + 0.5
        z = 1.0 - 2.0 * i / n_points
        radius = (1.0 - z * z).clamp_min(0).sqrt()
        golden = math.pi * (3.0 - math.sqrt(5.0))
        phi = golden * i
        return torch.stack([radius * phi.cos(), radius * phi.sin(), z], dim=-1)
    generator = torch.Generator().manual_seed(seed)
    draws = torch.randn((n_points, dim), generator=generator, dtype=torch.float64)
    return draws / draws.norm(dim=-1, keepdim=True)


def draw_noise(shape: tuple[int, ...], seed: int | torch.Generator) -> Tensor:
    """Standard-normal noise (float32) from a seed or generator (no global RNG)."""
    generator = seed if isinstance(seed, torch.Generator) else torch.Generator().manual_seed(seed)
    return torch.randn(shape, generator=generator, dtype=torch.float32)


@torch.no_grad()
def sample_conditional(estimator: Estimator, context: Tensor, mask: Tensor, n_samples: int,
                       seed: int | torch.Generator) -> Tensor:
    """(B, n, D) draws of the estimator for a batch of contexts, reproducible from ``seed``."""
    if n_samples < 1:
        raise ConfigError(f"n_samples must be >= 1, got {n_samples}")
    eps = draw_noise((context.shape[0], n_samples, noise_dim(estimator)), seed)
    return estimator.noise_to_data(eps, context, mask)


@torch.no_grad()
def confidence_regions(estimator: Estimator, context: Tensor, mask: Tensor,
                       radii: Sequence[float] = SIGMA_RADII, n_points: int = 256) -> list[Tensor]:
    """Per radius r, ``(B, K, D)``: the base r-σ sphere pushed through the flow (see module doc)."""
    dim = noise_dim(estimator)  # the sphere lives in the base's noise space
    unit = unit_sphere_points(dim, n_points).float()
    batch = context.shape[0]
    eps = torch.cat([r * unit for r in radii])                               # (len(radii)·K, D)
    pushed = estimator.noise_to_data(eps.expand(batch, *eps.shape).contiguous(), context, mask)
    return list(pushed.split(unit.shape[0], dim=1))


def estimate(estimator: Estimator, window: ObservationWindow, direction: str = "forward",
             n_samples: int = 1000, seed: int = 0, *, names: Sequence[str] | None = None,
             window_length: int | None = None, region_points: int = 256) -> Estimate:
    """Samples, log-density, summaries and 1/2/3σ regions of the state at ``window.target_time``.

    ``direction``: ``forward`` (observations before the target) or ``backward`` (after); it must
    match the direction the model was trained for (checked by the caller that knows the
    checkpoint, e.g. the CLI). ``window_length`` is the model's R (default: the estimator's
    ``window`` attribute, else the window's own length).
    """
    window.check_direction(direction)
    length = window_length or context_window_length(estimator, window.n_rows)
    context, mask = window_context(window, direction, length, uses_absolute_time(estimator))
    samples = sample_conditional(estimator, context, mask, n_samples, seed)[0]
    if not bool(torch.isfinite(samples).all()):
        raise ConfigError(f"the estimator produced non-finite samples for the window ending at "
                          f"t={window.times[-1]} (target_time={window.target_time}); the model "
                          "may be undertrained or the window far outside its training data")
    regions = [ConfidenceRegion(r, pts[0]) for r, pts in
               zip(SIGMA_RADII, confidence_regions(estimator, context, mask,
                                                   n_points=region_points), strict=True)]
    dim = samples.shape[-1]
    labels = tuple(names) if names is not None else tuple(f"x{d}" for d in range(dim))
    if len(labels) != dim:
        raise ConfigError(f"{len(labels)} names {labels} for a {dim}-dimensional target")

    @torch.no_grad()
    def log_density(values: Tensor) -> Tensor:
        values = torch.as_tensor(values, dtype=torch.float32).reshape(-1, dim)
        k = values.shape[0]
        return estimator.log_prob(values, context.expand(k, *context.shape[1:]),
                                  mask.expand(k, *mask.shape[1:]))

    return Estimate(direction=direction, target_time=window.target_time, names=labels,
                    samples=samples, regions=tuple(regions), log_density=log_density)


@dataclass(frozen=True)
class ModelInfo:
    """What estimation needs to know about a trained model beyond its weights.

    Read from a checkpoint's ``extra["preset"]["dataset"]`` (written by ``flowcast train``):
    the dataset name gives the system, the observed and target component names and the
    observation noise; the direction is the one the model was trained for.
    """

    dataset: str
    direction: str
    observed_names: tuple[str, ...]
    target_names: tuple[str, ...]
    obs_sigma: float
    window: int

    @classmethod
    def from_dataset(cls, name: str, direction: str, target: str = "state",
                     window: int = 5) -> ModelInfo:
        from pipeline.training.datasets import DatasetConfig
        from pipeline.systems import sir, vehicle

        config = DatasetConfig(name=name, direction=direction, target=target, window=window)
        if config.system == "waves":   # the weekly forecast's joint flows: observed S/I/R, no
            # added observation noise (they predict the observed state), γ fixed (not a target)
            observed = tuple(sir.COMPARTMENTS)
            return cls(dataset=name, direction=direction, observed_names=observed,
                       target_names=(*observed, "beta"), obs_sigma=0.0, window=window)
        system = config.system_config()
        if config.system == "sir":
            observed = tuple(sir.COMPARTMENTS)
            targets = observed + (tuple(sir.PARAMETERS) if target == "state+params" else ())
        else:
            observed = targets = tuple(vehicle.OBSERVED_NAMES)
        return cls(dataset=name, direction=direction, observed_names=observed,
                   target_names=targets, obs_sigma=float(system.obs_sigma), window=window)

    @classmethod
    def from_checkpoint_extra(cls, extra: dict, path: str = "checkpoint") -> ModelInfo:
        try:
            dataset = extra["preset"]["dataset"]
            return cls.from_dataset(dataset["name"], dataset["direction"], dataset["target"],
                                    int(dataset["window"]))
        except (KeyError, TypeError) as error:
            raise ConfigError(f"{path}: the checkpoint does not record its training dataset "
                              f"(extra['preset']['dataset'], missing {error}); it was not "
                              "written by `flowcast train`") from None
