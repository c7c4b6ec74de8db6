"""The flow member's model: a conditional MAF over the next four weeks of reported cases, its
coordinates, its training windows from the multi-wave prior, and its training (or the
model store's copy); how a batch of cells samples it (:func:`cell_noise`, :func:`single_thread`).
The member that forecasts with it: :mod:`pipeline.members.nf.growth`.

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
* target: z_h = logit(f_h) − logit(f_0) with f_h = (C_h + ½) / (N S_{h−1}), the share of the
  remaining susceptibles reported in week h (C_0 the week ending at the origin, S_{−1} the
  susceptible share a week before it). Decoding inverts it week by week,
  C_h = N S_{h−1} sigmoid(z_h + logit f_0), S_h = S_{h−1} − C_h / N, so every sampled week has
  0 < C_h < N S_{h−1}: S, I, R stay in [0, 1], S never rises and R never falls. (Decoded counts
  carry the ½-case continuity offset of the encoding; it is kept rather than subtracted, because
  subtracting it could make a count negative.)
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import ClassVar, NamedTuple, Protocol
from pathlib import Path
import numpy as np
import torch
from numpy.typing import NDArray

import pipeline
from pipeline.training.checkpoints import load_checkpoint, save_checkpoint
from pipeline.training.datasets import (FORMAT_VERSION, DatasetMeta, WindowedDataset,
                               compute_standardization, dataset_sha256, split_by_trajectory)
from pipeline.errors import ConfigError
from pipeline.training.digests import DataDigests
from pipeline.training.model_store import ModelStore
from pipeline.panels.targets import DAYS_PER_WEEK
from pipeline.models.encoders import EncoderConfig, MLPEncoderConfig
from pipeline.models.estimator import (ConditionalEstimator, EstimatorConfig, build_estimator,
                                       make_estimator_config)
from pipeline.progress import ProgressReporter
from pipeline.systems.waves import WaveEnsemble, WavePrior, simulate_waves
from pipeline.training.trainer import TrainConfig, TrainResult, train

HALF_CASE = 0.5
LEVEL_SCALE = 10.0
N_WEEKS = 4
CHECKPOINT_NAME = "nf_growth.pt"


@dataclass(frozen=True)
class GrowthModelConfig:
    """The member's data, model and optimiser settings (the model-store key is built from this)."""

    context_days: int = 42
    n_trajectories: int = 4000
    origin_stride_days: int = 3
    prior: WavePrior = field(default_factory=WavePrior)
    hidden_features: int = 128
    flow_layers: int = 5
    flow_hidden: int = 64
    iterations: int = 3000
    batch_size: int = 1024
    lr: float = 3e-3
    val_fraction: float = 0.1
    seed: int = 0

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

    kind: ClassVar[str] = "nf-growth"        # the model store's name for these models

    def identity(self) -> dict[str, object]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def estimator_config(self) -> EstimatorConfig:
        return estimator_config(self)

    def build_dataset(self) -> WindowedDataset:
        return growth_dataset(self)


class FlowModelConfig(Protocol):
    """What the model store and the fine-tuning need of a flow member's settings (the daily
    :class:`GrowthModelConfig`, the weekly :class:`~pipeline.members.nf.weekly.WeeklyFlowConfig`):
    a name, an identity, the training windows, the network and its optimiser."""

    kind: ClassVar[str]

    @property
    def iterations(self) -> int: ...

    @property
    def batch_size(self) -> int: ...

    @property
    def lr(self) -> float: ...

    @property
    def val_fraction(self) -> float: ...

    @property
    def seed(self) -> int: ...

    def identity(self) -> dict[str, object]: ...

    def estimator_config(self) -> EstimatorConfig: ...

    def build_dataset(self) -> WindowedDataset: ...


class RealWindows(NamedTuple):
    """Windows cut from real series: context ``(W, R, C)``, its mask ``(W, R)`` (False: a row
    before the series began), target ``(W, D)`` and the index of the place each came from."""

    context: NDArray[np.float32]
    mask: NDArray[np.bool_]
    target: NDArray[np.float32]
    place: NDArray[np.int64]


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


def _logit(p: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.log(p) - np.log1p(-p)


def reported_share(week_cases: NDArray[np.float64], susceptible: NDArray[np.float64],
                   population: int | NDArray[np.int64]) -> NDArray[np.float64]:
    """f = (C + ½) / (N S): the share of the susceptibles reported in a week."""
    return (week_cases + HALF_CASE) / (population * susceptible)


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
    logits = _logit(reported_share(week_cases, s_start, population))
    return (logits[:, 1:] - logits[:, :1]).astype(np.float32)


def decode_paths(z: NDArray[np.float64], last_week_cases: float | NDArray[np.float64],
                 s_before: float | NDArray[np.float64], s_origin: float | NDArray[np.float64],
                 population: int | NDArray[np.int64]) -> NDArray[np.float64]:
    """Weekly S, I, R sample paths ``(..., n, 4, 3)`` from targets ``z (..., n, 4)``; I = C_h / N
    (the reporting window is one week), S_h = S_{h−1} − C_h / N, R = 1 − S − I. The other
    arguments are scalars or ``(..., 1)`` arrays (one value per history of a batch)."""
    base = _logit(reported_share(np.asarray(last_week_cases, dtype=np.float64),
                                 np.asarray(s_before, dtype=np.float64), population))
    susceptible = np.broadcast_to(np.asarray(s_origin, dtype=np.float64), z.shape[:-1]).copy()
    paths = np.empty(z.shape + (3,))
    for h in range(z.shape[-1]):                  # four sequential weeks, vectorized over paths
        share = 1.0 / (1.0 + np.exp(-(z[..., h] + base)))
        infectious = susceptible * share
        susceptible = susceptible - infectious
        paths[..., h, :] = np.stack([susceptible, infectious, 1.0 - susceptible - infectious],
                                    axis=-1)
    return paths


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
    draft = WindowedDataset(context_t, mask, target_t, torch.from_numpy(trajectory),
                            torch.from_numpy(origins.astype(np.float64)), stats, meta)
    return dataclasses.replace(draft, meta=dataclasses.replace(
        meta, data_sha256=dataset_sha256(draft)))


def estimator_config(config: GrowthModelConfig) -> EstimatorConfig:
    encoder = EncoderConfig(kind="mlp", embedding_features=32,
                            mlp=MLPEncoderConfig(hidden_features=config.hidden_features))
    return make_estimator_config(N_WEEKS, 3, config.context_days, encoder,
                                 layers=config.flow_layers, hidden_features=config.flow_hidden)


def train_config(config: FlowModelConfig) -> TrainConfig:
    return TrainConfig(iterations=config.iterations, batch_size=config.batch_size, lr=config.lr,
                       schedule="cosine", eval_every=max(1, config.iterations // 20),
                       seed=config.seed + 1)


def growth_dataset(config: GrowthModelConfig) -> WindowedDataset:
    """The member's training windows: simulated from the prior with the config's seed."""
    return build_growth_dataset(simulate_waves(config.prior, config.n_trajectories, config.seed),
                                config)


@dataclass(frozen=True, eq=False)
class SyntheticWindows:
    """The training windows of ``config`` (:meth:`FlowModelConfig.build_dataset`), simulated
    and cut only when a model trains on them; their hash (a model-store key's data part) comes
    from the store's training-data digests (:mod:`pipeline.training.digests`) when ``digests``
    is given and they hold it."""

    config: FlowModelConfig
    digests: DataDigests | None = None

    @functools.cached_property
    def dataset(self) -> WindowedDataset:
        return self.config.build_dataset()

    @functools.cached_property
    def data_sha256(self) -> str:
        if self.digests is None:
            return self.dataset.meta.data_sha256
        return self.digests.get_or_compute(
            (f"{self.config.kind} windows", self.config.identity()),
            lambda: {"data_sha256": self.dataset.meta.data_sha256})["data_sha256"]


def train_growth_model(config: FlowModelConfig, dataset: WindowedDataset | None = None,
                       progress: ProgressReporter | None = None) -> tuple[ConditionalEstimator,
                                                                           TrainResult]:
    """Train the flow on ``dataset`` (default: the config's windows); best validation state."""
    dataset = dataset if dataset is not None else config.build_dataset()
    train_ds, val_ds = split_by_trajectory(dataset, config.val_fraction, config.seed)
    estimator = build_estimator(config.estimator_config(), train_ds.stats, seed=config.seed + 2)
    result = train(estimator, train_ds, val_ds, train_config(config), progress=progress)
    return estimator, result


@dataclass(frozen=True, eq=False)
class StoredGrowthModel:
    estimator: ConditionalEstimator
    key: str
    reused: bool
    best_val_nll: float


def train_or_reuse_growth_model(config: FlowModelConfig, store_root: Path, *,
                                retrain: bool = False,
                                progress: ProgressReporter | None = None,
                                synthetic: SyntheticWindows | None = None) -> StoredGrowthModel:
    """The trained member from the model store (key: config + training-data hash), training it
    only when the store has no valid entry. ``synthetic``: the caller's
    :class:`SyntheticWindows` of ``config`` (default: new ones, hashed through the store's
    digests), so that the windows are cut at most once."""
    synthetic = synthetic or SyntheticWindows(config, DataDigests(store_root))

    def build(out_dir: Path) -> dict[str, object]:
        estimator, result = train_growth_model(config, synthetic.dataset, progress)
        save_checkpoint(out_dir / CHECKPOINT_NAME, estimator, config=config.estimator_config(),
                        stats=estimator.stats, history=result.history_dicts(),
                        data_sha256=synthetic.dataset.meta.data_sha256,
                        extra={"kind": config.kind, "growth_config": config.identity(),
                               "best_val_nll_original": result.best_val_nll_original})
        return {"best_val_nll": result.best_val_nll_original}

    entry = ModelStore(store_root).get_or_build({config.kind: config.identity()},
                                                synthetic.data_sha256, build, retrain=retrain)
    # load_checkpoint rebuilds a ConditionalEstimator in eval mode
    loaded = load_checkpoint(entry.path / CHECKPOINT_NAME,
                             expected_config=config.estimator_config())
    return StoredGrowthModel(loaded.estimator, entry.key, entry.reused,
                             float(loaded.meta.extra.get("best_val_nll_original", float("nan"))))


@contextlib.contextmanager
def single_thread() -> Iterator[None]:
    """torch on one thread for the block. The flow's layers are small (64 units): sampling
    16,000 draws at a time, one thread was 3.5× faster than two on a busy 2-core machine
    (8.4 s against 29 s for 312 cells × 1,000 draws), where two threads wait on each other."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def cell_noise(seeds: Sequence[int], n_samples: int, features: int) -> torch.Tensor:
    """``(B, n, D)`` standard-normal noise, cell b's from its own generator: a cell's draws
    never depend on which cells share its batch (one generator per cell: torch has no
    batched generator; drawing is a small part of sampling)."""
    return torch.stack([torch.randn((n_samples, features),
                                    generator=torch.Generator().manual_seed(int(seed)))
                        for seed in seeds])
