"""Windowed (context, target) training data built from simulated ensembles.

A sample is a run of R + 1 consecutive *kept* (observed) times of one trajectory:

* forward:  context = observations at the R kept times before the target time,
            target  = the true state at the last of the R + 1 times;
* backward: context = observations at the R kept times after the target time,
            target  = the true state at the first of the R + 1 times.

Context rows are in chronological order in both directions; each row is the observed values
followed by one time channel ``t_obs - t_target`` (negative forward, positive backward). Under
dropout the kept times are irregular, and the time channel is what tells the model how far each
observation is from the target. With ``absolute_time`` (vehicle datasets only) a second time
channel ``t_obs`` follows: the vehicle's dynamics depend on the clock (the steering forcing
cos(c2·t) and the switch at t = 5.5), and without it the model has to guess the clock from noisy
positions: measured on the dropout set before the bifurcation, backward estimates were 14× wider
along the track than the posterior given the observation times (docs/estimation.md). SIR windows
keep the relative channel only: an epidemic's start is not observed, and the SIR reference
treats the window's position along the epidemic as unknown. Trajectories with fewer than R + 1
kept times give no sample; there is no padding, so ``mask`` is all True in the built datasets (it
exists for consumers that feed shorter contexts, e.g. real data at the start of a series).

Targets are the state (SIR: S, I, R; vehicle: p_x, p_y) or, for SIR with a parameter prior,
state + parameters (S, I, R, beta, gamma) for joint estimation. They are always stored in
original units; a model whose flow works in other coordinates (``EstimatorConfig.target_transform``,
e.g. the SIR log-ratio) gets statistics of the transformed training targets from
``train_validation_split(ds, target_transform)``, and ``Standardization`` applies the transform.

The train/validation split is by trajectory (windows of one trajectory overlap, so a split by
window would leak), and the standardization stored with a dataset is computed on its training
trajectories only; ``split_by_trajectory(ds, ds.meta.val_fraction, ds.meta.seed)`` reproduces that
split exactly. Files are written atomically and carry a format version, the config, the seed,
the package version and a sha256 of the tensor contents that is verified on load.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

import pipeline
from pipeline.errors import ConfigError, DatasetError
from pipeline.io import atomic_open, sha256_file
from pipeline.models.standardization import STATS_FIELDS, Standardization, compute_standardization
from pipeline.progress import ProgressReporter, SilentProgress
from pipeline.systems import sir as sir_system
from pipeline.names import (COMPARTMENTS, DEFAULT_VAL_FRACTION, DEFAULT_WINDOW, DIRECTIONS,
                            PARAMETERS)
from pipeline.models.context_transforms import SIR_LOG_INFECTIOUS, apply_context_transform
from pipeline.systems import vehicle as vehicle_system
from pipeline.systems import waves as waves_system

FORMAT = "flowcast.windowed-dataset"
FORMAT_VERSION = 1
TARGET_KINDS = ("state", "state+params")
SPLITS = ("all", "train", "validation")
SIR_DATASETS = ("sir-single", "sir-multi", "sir-sf")
VEHICLE_DATASETS = ("vehicle-full", "vehicle-dropout", "vehicle-sparse")
# The multi-wave prior (pipeline.systems.waves) seen through the S/I/R conversion: the weekly
# forecast's joint models train on it (one prior with the forecast's flow member).
WAVE_DATASETS = ("sf-waves",)
WAVE_TARGET_FEATURES = (*COMPARTMENTS, "beta")
WAVE_TRAJECTORIES = 2000
DATASET_NAMES = SIR_DATASETS + VEHICLE_DATASETS + WAVE_DATASETS
TIME_FEATURE = "t_obs-t_target"
ABSOLUTE_TIME_FEATURE = "t_obs"
_TENSOR_FIELDS = ("context", "mask", "target", "trajectory", "target_time")


# --------------------------------------------------------------------------- configuration

@dataclass(frozen=True)
class DatasetConfig:
    """What to simulate and how to window it. ``n_trajectories=None`` = the named preset's size."""

    name: str
    direction: str = "forward"
    target: str = "state"
    window: int = DEFAULT_WINDOW
    seed: int = 0
    vehicle_model: str = "paper"
    val_fraction: float = DEFAULT_VAL_FRACTION
    n_trajectories: int | None = None
    absolute_time: bool | None = None  # None: the system's default (vehicle yes, SIR no)

    def __post_init__(self) -> None:
        if self.name not in DATASET_NAMES:
            raise ConfigError(f"unknown dataset config {self.name!r}; known: {list(DATASET_NAMES)}")
        if self.absolute_time is None:
            object.__setattr__(self, "absolute_time", default_absolute_time(self.name))
        _check_choice("direction", self.direction, DIRECTIONS)
        _check_choice("target", self.target, TARGET_KINDS)
        _check_choice("vehicle_model", self.vehicle_model, vehicle_system.MODELS)
        if self.window < 1:
            raise ConfigError(f"window={self.window} must be >= 1")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ConfigError(f"val_fraction={self.val_fraction} must be in [0, 1)")
        if self.n_trajectories is not None and self.n_trajectories < 1:
            raise ConfigError(f"n_trajectories={self.n_trajectories} must be >= 1")
        if self.target == "state+params" and self.name not in ("sir-multi", "sir-sf",
                                                               *WAVE_DATASETS):
            raise ConfigError("target 'state+params' needs varying parameters (sir-multi, "
                              f"sir-sf, sf-waves); {self.name!r} has none to estimate")
        if self.name in WAVE_DATASETS and self.target != "state+params":
            raise ConfigError(f"{self.name!r} windows have the joint target (S, I, R, beta); "
                              f"target {self.target!r} is not built")
        if self.absolute_time and self.name in SIR_DATASETS:
            raise ConfigError(f"absolute_time=True for {self.name!r}: SIR windows carry the "
                              "relative time only (an epidemic's start is not observed)")

    @property
    def system(self) -> str:
        if self.name in WAVE_DATASETS:
            return "waves"
        return "sir" if self.name in SIR_DATASETS else "vehicle"

    def system_config(self) -> sir_system.SIRPrior | vehicle_system.VehicleConfig:
        """The SIR prior or vehicle config this dataset simulates (size override applied)."""
        base: sir_system.SIRPrior | vehicle_system.VehicleConfig
        if self.system == "waves":
            raise ConfigError(f"{self.name!r} simulates the multi-wave prior: use wave_prior()")
        if self.system == "sir":
            base = sir_system.get_prior(self.name)
        else:
            base = vehicle_system.get_vehicle_config(self.name, self.vehicle_model)
        if self.n_trajectories is not None:
            base = dataclasses.replace(base, n_trajectories=self.n_trajectories)
        return base

    def wave_prior(self) -> waves_system.WavePrior:
        """The multi-wave prior of an ``sf-waves`` dataset (the forecast member's)."""
        if self.system != "waves":
            raise ConfigError(f"{self.name!r} is not a multi-wave dataset")
        return waves_system.WavePrior()

    @property
    def trajectories(self) -> int:
        """How many trajectories the dataset simulates."""
        if self.n_trajectories is not None:
            return self.n_trajectories
        if self.system == "waves":
            return WAVE_TRAJECTORIES
        return self.system_config().n_trajectories


def default_absolute_time(name: str) -> bool:
    """Whether the named dataset's windows carry the ``t_obs`` channel by default (module doc)."""
    return name in VEHICLE_DATASETS


def _check_choice(field: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ConfigError(f"{field}={value!r}, expected one of {list(allowed)}")


# --------------------------------------------------------------------------- standardization

# --------------------------------------------------------------------------- dataset types

@dataclass(frozen=True)
class DatasetMeta:
    """Provenance of a windowed dataset; ``config`` is the simulated system's config as plain data."""

    system: str
    config_name: str
    direction: str
    target_kind: str
    context_features: tuple[str, ...]
    target_features: tuple[str, ...]
    window: int
    seed: int
    val_fraction: float
    split: str
    n_trajectories: int
    n_observed_points: int
    n_observed_values: int
    config: dict[str, Any]
    package_version: str
    format_version: int
    data_sha256: str

    def as_dict(self) -> dict[str, Any]:
        # JSON round trip: tuples -> lists, only plain types (loadable with weights_only=True).
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> DatasetMeta:
        names = [f.name for f in dataclasses.fields(cls)]
        missing = [n for n in names if n not in raw]
        if missing:
            raise KeyError(", ".join(missing))
        values = {n: raw[n] for n in names}
        values["context_features"] = tuple(values["context_features"])
        values["target_features"] = tuple(values["target_features"])
        return cls(**values)


@dataclass(frozen=True)
class WindowedDataset:
    """``context (W, R, C)`` float32, ``mask (W, R)`` bool, ``target (W, D)`` float32,
    ``trajectory (W,)`` int64 (source trajectory of each window), ``target_time (W,)`` float64,
    ``stats`` (fitted on training trajectories), ``meta``."""

    context: Tensor
    mask: Tensor
    target: Tensor
    trajectory: Tensor
    target_time: Tensor
    stats: Standardization
    meta: DatasetMeta

    def __len__(self) -> int:
        return int(self.context.shape[0])

    def subset(self, index: Tensor, split: str) -> WindowedDataset:
        """The windows selected by ``index`` (bool mask or indices), same stats, new split label."""
        parts = {f: getattr(self, f)[index] for f in _TENSOR_FIELDS}
        draft = dataclasses.replace(self, **parts,
                                    meta=dataclasses.replace(self.meta, split=split))
        return with_data_hash(draft)


def dataset_sha256(ds: WindowedDataset) -> str:
    """sha256 over names, dtypes, shapes and bytes of all tensors (data and standardization)."""
    digest = hashlib.sha256()
    named = [(f, getattr(ds, f)) for f in _TENSOR_FIELDS] + list(ds.stats.as_dict().items())
    for name, tensor in named:
        array = tensor.detach().cpu().contiguous().numpy()
        digest.update(f"{name}|{array.dtype.str}|{tuple(array.shape)};".encode())
        digest.update(array.reshape(-1).view(np.uint8))
    if ds.stats.target_transform != "identity":  # identity datasets keep their earlier hashes
        digest.update(f"target_transform|{ds.stats.target_transform};".encode())
    return digest.hexdigest()


def with_data_hash(ds: WindowedDataset) -> WindowedDataset:
    meta = dataclasses.replace(ds.meta, data_sha256=dataset_sha256(ds))
    return dataclasses.replace(ds, meta=meta)


# --------------------------------------------------------------------------- windowing

def window_indices(kept: Tensor, window: int) -> tuple[Tensor, Tensor]:
    """All runs of ``window + 1`` consecutive kept times within one trajectory.

    ``kept (N, T)`` bool. Returns ``trajectory (W,)`` and ``time_index (W, window + 1)``
    (ascending within a row). Vectorized: the kept points are flattened in (trajectory, time)
    order, and a run starting at flat position j is valid when points j and j + window belong
    to the same trajectory (then so do all points between them).
    """
    traj, time_index = kept.nonzero(as_tuple=True)  # row-major: sorted by trajectory, then time
    n_points = traj.numel()
    if n_points <= window:
        empty = torch.empty(0, dtype=torch.long)
        return empty, torch.empty((0, window + 1), dtype=torch.long)
    starts = torch.arange(n_points - window)
    starts = starts[traj[starts] == traj[starts + window]]
    offsets = starts.unsqueeze(1) + torch.arange(window + 1)
    return traj[starts], time_index[offsets]


def make_windows(times: Tensor, observations: Tensor, kept: Tensor, states: Tensor,
                 parameters: Tensor | None, direction: str, window: int,
                 absolute_time: bool = False) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Cut windows from any ensemble on a shared time grid.

    ``times (T,)``, ``observations (N, T, C_obs)``, ``kept (N, T)`` bool, ``states (N, T, D)``
    (the target variables), ``parameters (N, P)``, ``(N, T, P)`` (per time) or None (appended to
    the target, at the target's time when per time).
    Returns ``context (W, R, C_obs + 1 [+ 1 with absolute_time])`` float32, ``mask (W, R)``,
    ``target (W, D [+ P])`` float32, ``trajectory (W,)`` int64, ``target_time (W,)`` float64.
    """
    _check_choice("direction", direction, DIRECTIONS)
    traj, time_index = window_indices(kept, window)
    if direction == "forward":
        context_index, target_index = time_index[:, :window], time_index[:, window]
    else:
        context_index, target_index = time_index[:, 1:], time_index[:, 0]
    times64 = times.to(torch.float64)
    target_time = times64[target_index]
    time_channels = time_features(times64[context_index], target_time, absolute_time)
    observed = observations[traj.unsqueeze(1), context_index].to(torch.float32)
    context = torch.cat([observed, time_channels.to(torch.float32)], dim=-1)
    target = states[traj, target_index].to(torch.float32)
    if parameters is not None:
        chosen = parameters[traj, target_index] if parameters.dim() == 3 else parameters[traj]
        target = torch.cat([target, chosen.to(torch.float32)], dim=-1)
    mask = torch.ones(context.shape[:2], dtype=torch.bool)
    return context, mask, target, traj, target_time


def time_features(obs_times: Tensor, target_time: Tensor, absolute_time: bool) -> Tensor:
    """The time channels of context rows, ``(..., R, 1 or 2)``: ``t_obs - t_target`` and, with
    ``absolute_time``, ``t_obs``. ``obs_times (..., R)``, ``target_time (...)``. The one place
    the datasets and every estimate decide the time layout."""
    relative = obs_times - target_time.unsqueeze(-1)
    channels = [relative, obs_times] if absolute_time else [relative]
    return torch.stack(channels, dim=-1)


# --------------------------------------------------------------------------- splitting

def validation_trajectories(trajectory_ids: Tensor, val_fraction: float, seed: int) -> Tensor:
    """The trajectory ids held out for validation: a seeded random ``val_fraction`` of the ids
    (rounded, at least one when ``val_fraction > 0``, and always leaving one for training)."""
    ids = torch.unique(trajectory_ids)
    if val_fraction <= 0.0:
        return ids[:0]
    if not val_fraction < 1.0:
        raise ConfigError(f"val_fraction={val_fraction} must be in [0, 1)")
    if ids.numel() < 2:
        raise DatasetError(f"cannot split {ids.numel()} trajectory(ies) into training and "
                           "validation: need at least 2")
    n_val = min(max(1, round(val_fraction * ids.numel())), ids.numel() - 1)
    permutation = torch.randperm(ids.numel(), generator=torch.Generator().manual_seed(seed))
    return ids[permutation[:n_val]]


def split_by_trajectory(ds: WindowedDataset, val_fraction: float, seed: int,
                        target_transform: str | None = None
                        ) -> tuple[WindowedDataset, WindowedDataset]:
    """(train, validation) with no trajectory in both; both carry stats fitted on train, in the
    coordinates of ``target_transform`` (None: the one ``ds.stats`` uses; pass the model's
    ``EstimatorConfig.target_transform``). The targets themselves stay in original units."""
    is_validation = torch.isin(ds.trajectory, validation_trajectories(ds.trajectory, val_fraction,
                                                                       seed))
    train_index = ~is_validation
    stats = compute_standardization(ds.context[train_index], ds.mask[train_index],
                                    ds.target[train_index],
                                    target_transform or ds.stats.target_transform)
    with_stats = dataclasses.replace(ds, stats=stats)
    return with_stats.subset(train_index, "train"), with_stats.subset(is_validation, "validation")


def train_validation_split(ds: WindowedDataset, target_transform: str | None = None
                           ) -> tuple[WindowedDataset, WindowedDataset]:
    """The split the dataset's stored standardization was fitted on; ``target_transform`` as in
    :func:`split_by_trajectory`."""
    return split_by_trajectory(ds, ds.meta.val_fraction, ds.meta.seed, target_transform)


# --------------------------------------------------------------------------- assembling

def _assemble(*, system: str, config_name: str,
              system_config: sir_system.SIRPrior | vehicle_system.VehicleConfig | dict[str, Any],
              seed: int, direction: str,
              target_kind: str, window: int, val_fraction: float, context_features: tuple[str, ...],
              target_features: tuple[str, ...], n_trajectories: int, n_observed_points: int,
              n_observed_values: int, windows: tuple[Tensor, ...]) -> WindowedDataset:
    context, mask, target, trajectory, target_time = windows
    if context.shape[0] == 0:
        raise DatasetError(f"{config_name}: no trajectory has {window + 1} kept times, so no "
                           f"window of {window} observations + target can be cut")
    is_validation = torch.isin(trajectory, validation_trajectories(trajectory, val_fraction, seed))
    train = ~is_validation
    stats = compute_standardization(context[train], mask[train], target[train])
    meta = DatasetMeta(
        system=system, config_name=config_name, direction=direction, target_kind=target_kind,
        context_features=context_features, target_features=target_features, window=window,
        seed=seed, val_fraction=val_fraction, split="all", n_trajectories=n_trajectories,
        n_observed_points=n_observed_points, n_observed_values=n_observed_values,
        config=json.loads(json.dumps(system_config if isinstance(system_config, dict)
                                     else dataclasses.asdict(system_config))),
        package_version=pipeline.__version__, format_version=FORMAT_VERSION, data_sha256="")
    return with_data_hash(WindowedDataset(context, mask, target, trajectory, target_time, stats, meta))


def windows_from_sir(ensemble: sir_system.SIREnsemble, direction: str = "forward",
                     target: str = "state", window: int = DEFAULT_WINDOW,
                     val_fraction: float = DEFAULT_VAL_FRACTION) -> WindowedDataset:
    """Windowed dataset of an SIR ensemble (every day observed); split seed = ensemble seed."""
    _check_choice("target", target, TARGET_KINDS)
    if target == "state+params" and ensemble.prior.parameters_fixed:
        raise ConfigError(f"target 'state+params' needs varying parameters; prior "
                          f"{ensemble.prior.name!r} fixes beta and gamma")
    # Time-varying beta: the target is the beta in effect at the target time.
    parameters = ((ensemble.parameter_paths if ensemble.beta_path is not None
                   else ensemble.parameters) if target == "state+params" else None)
    kept = torch.ones(ensemble.observations.shape[:2], dtype=torch.bool)
    windows = make_windows(ensemble.times, ensemble.observations, kept, ensemble.states,
                           parameters, direction, window)
    features = COMPARTMENTS + (PARAMETERS if parameters is not None else ())
    prior = dataclasses.replace(ensemble.prior, n_trajectories=ensemble.n_trajectories)
    return _assemble(
        system="sir", config_name=ensemble.prior.name, system_config=prior, seed=ensemble.seed,
        direction=direction, target_kind=target, window=window, val_fraction=val_fraction,
        context_features=tuple(f"{c}_obs" for c in COMPARTMENTS) + (TIME_FEATURE,),
        target_features=features, n_trajectories=ensemble.n_trajectories,
        n_observed_points=int(kept.sum()), n_observed_values=ensemble.n_observed_values,
        windows=windows)


def windows_from_vehicle(ensemble: vehicle_system.VehicleEnsemble, direction: str = "forward",
                         target: str = "state", window: int = DEFAULT_WINDOW,
                         val_fraction: float = DEFAULT_VAL_FRACTION,
                         absolute_time: bool = False) -> WindowedDataset:
    """Windowed dataset of kept vehicle positions; target = true position (p_x, p_y)."""
    _check_choice("target", target, TARGET_KINDS)
    if target != "state":
        raise ConfigError("vehicle datasets support target 'state' only (p_x, p_y); the switch "
                          "psi is not a parameter to estimate")
    windows = make_windows(ensemble.times, ensemble.observations, ensemble.kept,
                           ensemble.states[..., :2], None, direction, window, absolute_time)
    config = dataclasses.replace(ensemble.config, n_trajectories=ensemble.n_trajectories)
    n_points = ensemble.n_points
    return _assemble(
        system="vehicle", config_name=ensemble.config.name, system_config=config,
        seed=ensemble.seed, direction=direction, target_kind=target, window=window,
        val_fraction=val_fraction,
        context_features=(tuple(f"{c}_obs" for c in vehicle_system.OBSERVED_NAMES)
                          + (TIME_FEATURE,) + ((ABSOLUTE_TIME_FEATURE,) if absolute_time else ())),
        target_features=vehicle_system.OBSERVED_NAMES, n_trajectories=ensemble.n_trajectories,
        n_observed_points=n_points, n_observed_values=2 * n_points, windows=windows)


def windows_from_waves(ensemble: waves_system.WaveEnsemble, direction: str = "forward",
                       window: int = DEFAULT_WINDOW, val_fraction: float = DEFAULT_VAL_FRACTION,
                       seed: int = 0) -> WindowedDataset:
    """Joint windows of a multi-wave ensemble seen through the S/I/R conversion
    (:func:`pipeline.systems.waves.sir_view`): context = the R observed S/I/R rows before
    (forward) or after (backward) the target day, with I on the log scale of
    ``sir-log-infectious`` (:mod:`pipeline.models.context_transforms`; the models trained on
    these windows read raw windows through the same transform); target = the observed S, I, R
    of the target day and β^obs, the transmission rate per observed susceptible (γ = 1/L is
    fixed by the conversion and not a target). ``seed`` draws each trajectory's earlier
    reported share and the train/validation split."""
    view = waves_system.sir_view(ensemble, seed)
    sir = torch.from_numpy(view.sir)
    n_traj, n_days = sir.shape[:2]
    times = torch.arange(n_days, dtype=torch.float64)
    kept = torch.ones((n_traj, n_days), dtype=torch.bool)
    beta = torch.from_numpy(view.beta)[..., None]
    context, mask, target, trajectory, target_time = make_windows(
        times, sir, kept, sir, beta, direction, window)
    # A target day with no case reported in its window (I = 0) has no log-ratio; the model's
    # draws are strictly positive (one case is 1e-6 of SF), so those windows are dropped.
    keep = (target > 0).all(dim=-1)
    context, mask, target = context[keep], mask[keep], target[keep]
    trajectory, target_time = trajectory[keep], target_time[keep]
    context = apply_context_transform(SIR_LOG_INFECTIOUS, context)
    prior = dataclasses.asdict(ensemble.prior) | {"n_trajectories": n_traj,
                                                  "removed_before": list(
                                                      waves_system.REMOVED_BEFORE_RANGE)}
    return _assemble(
        system="waves", config_name="sf-waves", system_config=prior, seed=seed,
        direction=direction, target_kind="state+params", window=window,
        val_fraction=val_fraction,
        context_features=("S_obs", "log_I_obs", "R_obs", TIME_FEATURE),
        target_features=WAVE_TARGET_FEATURES, n_trajectories=n_traj,
        n_observed_points=int(kept.sum()), n_observed_values=int(sir.numel()),
        windows=(context, mask, target, trajectory, target_time))


def progress_total(config: DatasetConfig) -> int:
    """Units ``build_dataset`` reports: one per simulation step plus one for windowing."""
    if config.system == "waves":
        return 1
    return config.system_config().n_steps + 1


def build_dataset_from_config(config: DatasetConfig,
                              progress: ProgressReporter | None = None) -> WindowedDataset:
    reporter = progress or SilentProgress()
    if config.system == "waves":
        ensemble = waves_system.simulate_waves(config.wave_prior(), config.trajectories,
                                               config.seed)
        ds = windows_from_waves(ensemble, config.direction, config.window, config.val_fraction,
                                config.seed)
        reporter.advance(1, windows=len(ds))
        return ds
    system_config = config.system_config()
    if isinstance(system_config, sir_system.SIRPrior):
        sir_ensemble = sir_system.simulate_ensemble(system_config, seed=config.seed,
                                                    progress=reporter)
        ds = windows_from_sir(sir_ensemble, config.direction, config.target, config.window,
                              config.val_fraction)
    else:
        vehicle_ensemble = vehicle_system.simulate_vehicle(system_config, seed=config.seed,
                                                           progress=reporter)
        # absolute_time is never None after DatasetConfig.__post_init__
        ds = windows_from_vehicle(vehicle_ensemble, config.direction, config.target,
                                  config.window, config.val_fraction, bool(config.absolute_time))
    reporter.advance(1, windows=len(ds))
    return ds


def build_dataset(name: str, direction: str = "forward", target: str = "state",
                  window: int = DEFAULT_WINDOW, seed: int = 0,
                  progress: ProgressReporter | None = None, *, vehicle_model: str = "paper",
                  val_fraction: float = DEFAULT_VAL_FRACTION,
                  n_trajectories: int | None = None) -> WindowedDataset:
    """Simulate the named config (sir-single, sir-multi, vehicle-full, vehicle-dropout,
    vehicle-sparse) and window it. Deterministic from ``seed``."""
    config = DatasetConfig(name=name, direction=direction, target=target, window=window,
                           seed=seed, vehicle_model=vehicle_model, val_fraction=val_fraction,
                           n_trajectories=n_trajectories)
    return build_dataset_from_config(config, progress)


# --------------------------------------------------------------------------- save / load

def save_dataset(ds: WindowedDataset, path: str | os.PathLike[str]) -> str:
    """Write ``ds`` atomically (tensors + plain Python types only); returns the file's sha256."""
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "tensors": {f: getattr(ds, f).detach().cpu().contiguous() for f in _TENSOR_FIELDS},
        "stats": {**{k: v.detach().cpu().contiguous() for k, v in ds.stats.as_dict().items()},
                  "target_transform": ds.stats.target_transform},
        "meta": ds.meta.as_dict(),
    }
    with atomic_open(path, "wb") as handle:
        torch.save(payload, handle)
    return sha256_file(path)


def load_dataset(path: str | os.PathLike[str], *, system: str | None = None,
                 config_name: str | None = None, direction: str | None = None,
                 target: str | None = None, window: int | None = None,
                 vehicle_model: str | None = None,
                 absolute_time: bool | None = None) -> WindowedDataset:
    """Read a dataset written by :func:`save_dataset` and verify it.

    Raises ``DatasetError`` naming the file when it is missing, unreadable (damaged, truncated,
    not a torch file), not a flowcast dataset, of another format version, internally
    inconsistent, altered (content hash), or when it does not match the keyword expectations.
    """
    file = Path(path)
    if not file.is_file():
        raise DatasetError(f"dataset file {file} does not exist")
    try:
        payload = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises RuntimeError, EOFError, UnpicklingError, ...
        raise DatasetError(f"dataset file {file} is damaged or truncated and cannot be read "
                           f"({type(exc).__name__}: {exc})") from exc
    marker = payload.get("format") if isinstance(payload, dict) else None
    if marker != FORMAT:
        raise DatasetError(f"dataset file {file} is not a flowcast windowed dataset "
                           f"(format marker {marker!r}, expected {FORMAT!r})")
    version = payload.get("format_version")
    if version != FORMAT_VERSION:
        raise DatasetError(f"dataset file {file} has format version {version!r}; this flowcast "
                           f"({pipeline.__version__}) reads version {FORMAT_VERSION}: rebuild it "
                           "with `flowcast simulate`")
    ds = _dataset_from_payload(file, payload)
    stored_hash = ds.meta.data_sha256
    actual_hash = dataset_sha256(ds)
    if stored_hash != actual_hash:
        raise DatasetError(f"dataset file {file} is damaged: content sha256 {actual_hash[:12]}… "
                           f"differs from the recorded {str(stored_hash)[:12]}…")
    expected = {"system": system, "config_name": config_name, "direction": direction,
                "target_kind": target, "window": window}
    for field, wanted in expected.items():
        if wanted is not None and getattr(ds.meta, field) != wanted:
            raise DatasetError(f"dataset file {file} has {field}={getattr(ds.meta, field)!r}, "
                               f"but {wanted!r} was asked for")
    if vehicle_model is not None and ds.meta.config.get("model") != vehicle_model:
        raise DatasetError(f"dataset file {file} has vehicle model "
                           f"{ds.meta.config.get('model')!r}, but {vehicle_model!r} was asked for")
    has_clock = ABSOLUTE_TIME_FEATURE in ds.meta.context_features
    if absolute_time is not None and has_clock != absolute_time:
        raise DatasetError(f"dataset file {file} has context features "
                           f"{list(ds.meta.context_features)}, but a model "
                           f"{'with' if absolute_time else 'without'} the absolute time channel "
                           f"{ABSOLUTE_TIME_FEATURE!r} was asked for: rebuild it with "
                           "`flowcast simulate`")
    return ds


def _payload_section(file: Path, payload: dict[str, Any], name: str) -> dict[str, Any]:
    section = payload.get(name)
    if not isinstance(section, dict):
        raise DatasetError(f"dataset file {file} lacks its 'tensors', 'stats' or 'meta' section")
    return section


def _dataset_from_payload(file: Path, payload: dict[str, Any]) -> WindowedDataset:
    tensors, stats_raw, meta_raw = (_payload_section(file, payload, name)
                                    for name in ("tensors", "stats", "meta"))
    for section, names, raw in (("tensors", _TENSOR_FIELDS, tensors),
                                ("stats", STATS_FIELDS, stats_raw)):
        for name in names:
            if not isinstance(raw.get(name), Tensor):
                raise DatasetError(f"dataset file {file}: {section}.{name} is missing or "
                                   "not a tensor")
    try:
        meta = DatasetMeta.from_dict(meta_raw)
    except (KeyError, TypeError) as exc:
        raise DatasetError(f"dataset file {file}: metadata field(s) missing or invalid: "
                           f"{exc}") from exc
    # Files written before target transforms existed hold identity statistics.
    stats = Standardization(*(stats_raw[name] for name in STATS_FIELDS),
                            target_transform=str(stats_raw.get("target_transform", "identity")))
    ds = WindowedDataset(*(tensors[name] for name in _TENSOR_FIELDS), stats=stats, meta=meta)
    _check_shapes(file, ds)
    return ds


def _check_shapes(file: Path, ds: WindowedDataset) -> None:
    if ds.context.dim() != 3:
        raise DatasetError(f"dataset file {file} is inconsistent: context has shape "
                           f"{tuple(ds.context.shape)}, expected (N, R, C)")
    n, window, channels = ds.context.shape
    n_targets = len(ds.meta.target_features)
    problems = []
    if window != ds.meta.window:
        problems.append(f"context window {window} != meta.window {ds.meta.window}")
    if channels != len(ds.meta.context_features):
        problems.append(f"context has {channels} channels, meta names "
                        f"{len(ds.meta.context_features)}")
    expected_shapes = {"mask": (n, window), "target": (n, n_targets), "trajectory": (n,),
                       "target_time": (n,)}
    for name, shape in expected_shapes.items():
        if tuple(getattr(ds, name).shape) != shape:
            problems.append(f"{name} has shape {tuple(getattr(ds, name).shape)}, expected {shape}")
    if ds.mask.dtype != torch.bool:
        problems.append(f"mask has dtype {ds.mask.dtype}, expected torch.bool")
    try:
        flow_targets = ds.stats.transform.flow_features(n_targets)
    except ConfigError as exc:
        raise DatasetError(f"dataset file {file} is inconsistent: {exc}") from exc
    for name, tensor in ds.stats.as_dict().items():
        size = channels if name.startswith("context") else flow_targets
        if tuple(tensor.shape) != (size,):
            problems.append(f"stats.{name} has shape {tuple(tensor.shape)}, expected ({size},)")
        elif name.endswith("std") and not bool(torch.all(tensor > 0)):
            problems.append(f"stats.{name} has non-positive entries")
    if problems:
        raise DatasetError(f"dataset file {file} is inconsistent: " + "; ".join(problems))


def describe(ds: WindowedDataset) -> dict[str, Any]:
    """A small summary (for the CLI and logs)."""
    n_validation = int(torch.isin(ds.trajectory, validation_trajectories(
        ds.trajectory, ds.meta.val_fraction, ds.meta.seed)).sum()) if ds.meta.split == "all" else 0
    return {"config": ds.meta.config_name, "direction": ds.meta.direction,
            "target": ds.meta.target_kind, "window": ds.meta.window, "windows": len(ds),
            "validation_windows": n_validation, "trajectories": ds.meta.n_trajectories,
            "observed_points": ds.meta.n_observed_points,
            "observed_values": ds.meta.n_observed_values,
            "context_shape": tuple(ds.context.shape), "target_shape": tuple(ds.target.shape),
            "data_sha256": ds.meta.data_sha256}
