"""The one machinery of the flow members: a conditional MAF trained on a config's windows and
kept in the model store, sampled cell by cell (each cell from its own seed, through the flows
of its origin), its draws decoded into weekly S, I, R paths valid by construction, and their
count quantiles.

The members on top keep only what they model (pyro's split between inference and models):
:mod:`~pipeline.members.nf.growth` (daily cases, ``nf-growth``), :mod:`~pipeline.members.nf.weekly`
(a weekly count, ``nf-weekly``), :mod:`~pipeline.members.nf.context` (a weekly count with real
context, ``nf-context``); their refits (``nf-real``, ``nf-context``) share
:mod:`~pipeline.members.nf.refit`. A fourth flow is a config (:class:`FlowConfig`: its windows,
network and optimiser) and a member that cuts its cells' context rows and decodes its draws.

**Coordinates** shared by every flow: a target z_h = logit f_h − logit f_0 with
f_h = (C_h + ½) / (N S_{h−1}), the share of the remaining susceptibles counted in week h (C_0 the
week ending at the origin, S_{−1} the share a week before it). Decoding inverts it week by week,
C_h = N S_{h−1} sigmoid(z_h + logit f_0), S_h = S_{h−1} − C_h / N, so every sampled week has
0 < C_h < N S_{h−1}: S, I, R stay in [0, 1], S never rises and R never falls. A rate (the ED
share) does not deplete: S stays 1 and each week is a share of all N. (Decoded counts carry the
½-case continuity offset of the encoding.)
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, NamedTuple, Protocol

import numpy as np
import torch
from numpy.typing import NDArray

from pipeline.members.base import MemberForecast, quantiles_of_samples
from pipeline.models.encoders import EncoderConfig, MLPEncoderConfig
from pipeline.models.estimator import (ConditionalEstimator, EstimatorConfig, build_estimator,
                                       make_estimator_config)
from pipeline.panels.history import History, WeeklyHistory
from pipeline.panels.panel import Cells
from pipeline.panels.targets import TargetError
from pipeline.progress import ProgressReporter
from pipeline.training.checkpoints import load_checkpoint, save_checkpoint
from pipeline.training.datasets import WindowedDataset, split_by_trajectory
from pipeline.training.digests import DataDigests
from pipeline.training.model_store import ModelStore
from pipeline.training.trainer import TrainConfig, TrainResult, train

HALF_CASE = 0.5
LEVEL_SCALE = 10.0
CHECKPOINT_NAME = "nf_growth.pt"


class FlowConfig(Protocol):
    """What the machinery needs of a flow member's settings: a name, an identity (the model
    store's key), the training windows and their split, the network and its optimiser."""

    kind: ClassVar[str]

    @property
    def seed(self) -> int: ...

    def identity(self) -> dict[str, object]: ...

    def estimator_config(self) -> EstimatorConfig: ...

    def build_dataset(self) -> WindowedDataset: ...

    def split(self, dataset: WindowedDataset) -> tuple[WindowedDataset, WindowedDataset]: ...

    def train_config(self) -> TrainConfig: ...


@dataclass(frozen=True)
class FlowNetwork:
    """The settings every flow member shares: its MLP encoder's width, the MAF's layers and
    width, and the optimiser of its training on the prior's windows (validation: a seeded share
    of the trajectories). A member's config adds what it models (prior, window, horizon) and
    may override the defaults; its identity is the model store's key."""

    hidden_features: int = 128
    flow_layers: int = 5
    flow_hidden: int = 64
    iterations: int = 3000
    batch_size: int = 1024
    lr: float = 3e-3
    val_fraction: float = 0.1
    seed: int = 0

    def identity(self) -> dict[str, object]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def network(self, features: int, channels: int, window: int,
                encoder: EncoderConfig | None = None) -> EstimatorConfig:
        """The estimator over ``features`` targets given ``window`` context rows of
        ``channels`` (default encoder: an MLP with a 32-wide embedding)."""
        encoder = encoder or EncoderConfig(
            kind="mlp", embedding_features=32,
            mlp=MLPEncoderConfig(hidden_features=self.hidden_features))
        return make_estimator_config(features, channels, window, encoder,
                                     layers=self.flow_layers, hidden_features=self.flow_hidden)

    def split(self, dataset: WindowedDataset) -> tuple[WindowedDataset, WindowedDataset]:
        return split_by_trajectory(dataset, self.val_fraction, self.seed)

    def train_config(self) -> TrainConfig:
        return TrainConfig(iterations=self.iterations, batch_size=self.batch_size, lr=self.lr,
                           schedule="cosine", eval_every=max(1, self.iterations // 20),
                           seed=self.seed + 1)


class RealWindows(NamedTuple):
    """Windows cut from real series: context ``(W, R, C)``, its mask ``(W, R)`` (False: a row
    before the series began), target ``(W, D)`` and the index of the place each came from."""

    context: NDArray[np.float32]
    mask: NDArray[np.bool_]
    target: NDArray[np.float32]
    place: NDArray[np.int64]


# ---------------------------------------------------------------------------------- training


@dataclass(frozen=True, eq=False)
class SyntheticWindows:
    """The training windows of ``config`` (:meth:`FlowConfig.build_dataset`), simulated and cut
    only when a model trains on them; their hash (a model-store key's data part) comes from the
    store's training-data digests (:mod:`pipeline.training.digests`) when ``digests`` is given
    and they hold it."""

    config: FlowConfig
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


def train_flow(config: FlowConfig, dataset: WindowedDataset | None = None,
               progress: ProgressReporter | None = None
               ) -> tuple[ConditionalEstimator, TrainResult]:
    """The flow trained on ``dataset`` (default: the config's windows); best validation state."""
    dataset = dataset if dataset is not None else config.build_dataset()
    train_ds, val_ds = config.split(dataset)
    estimator = build_estimator(config.estimator_config(), train_ds.stats, seed=config.seed + 2)
    result = train(estimator, train_ds, val_ds, config.train_config(), progress=progress)
    return estimator, result


@dataclass(frozen=True, eq=False)
class StoredFlow:
    """A trained flow from the model store: its key, whether it was there already, and its best
    validation NLL (original units)."""

    estimator: ConditionalEstimator
    key: str
    reused: bool
    best_val_nll: float


def stored_flow(config: FlowConfig, store_root: Path, *, retrain: bool = False,
                progress: ProgressReporter | None = None,
                synthetic: SyntheticWindows | None = None) -> StoredFlow:
    """The trained flow from the model store (key: the config's identity and the windows'
    hash), trained only when the store has no valid entry. ``synthetic``: the caller's
    :class:`SyntheticWindows` of ``config`` (default: new ones, hashed through the store's
    digests), so that the windows are cut at most once."""
    synthetic = synthetic or SyntheticWindows(config, DataDigests(store_root))

    def build(out_dir: Path) -> dict[str, object]:
        estimator, result = train_flow(config, synthetic.dataset, progress)
        save_checkpoint(out_dir / CHECKPOINT_NAME, estimator, config=config.estimator_config(),
                        stats=estimator.stats, history=result.history_dicts(),
                        data_sha256=synthetic.dataset.meta.data_sha256,
                        extra={"kind": config.kind, "flow_config": config.identity(),
                               "best_val_nll_original": result.best_val_nll_original})
        return {"best_val_nll": result.best_val_nll_original}

    entry = ModelStore(store_root).get_or_build({config.kind: config.identity()},
                                                synthetic.data_sha256, build, retrain=retrain)
    loaded = load_checkpoint(entry.path / CHECKPOINT_NAME,
                             expected_config=config.estimator_config())   # in eval mode
    return StoredFlow(loaded.estimator, entry.key, entry.reused,
                      float(loaded.meta.extra.get("best_val_nll_original", float("nan"))))


# ---------------------------------------------------------------------------------- sampling


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


Flows = tuple[ConditionalEstimator, ...]


def sample_cells(flows: Sequence[Flows], context: NDArray[np.float32],
                 mask: NDArray[np.bool_], seeds: Sequence[int], n_samples: int,
                 features: int, chunk: int = 16) -> NDArray[np.float64]:
    """Draws ``z (B, n, D)`` of B cells: cell b from ``seeds[b]`` through ``flows[b]`` (one
    flow, or a seeds' mixture in equal shares: draw j from flow j mod K), given its context
    rows ``(B, R, C)`` and mask ``(B, R)``. The cells of one set of flows go through them in
    calls of ``chunk`` cells (16 cells × 1,000 draws a call: 2.3× faster on the CPU than 256,
    whose activations no longer fit the cache)."""
    eps = cell_noise(seeds, n_samples, features)
    z = np.empty(eps.shape, dtype=np.float64)
    groups: dict[int, list[int]] = {}
    for b, cell_flows in enumerate(flows):
        groups.setdefault(id(cell_flows), []).append(b)
    with torch.no_grad(), single_thread():
        for index in groups.values():
            members = flows[index[0]]
            shares = [np.arange(k, n_samples, len(members)) for k in range(len(members))]
            for start in range(0, len(index), chunk):
                part = index[start:start + chunk]
                c, m = torch.from_numpy(context[part]), torch.from_numpy(mask[part])
                rows = np.asarray(part)[:, None]
                for flow, draws in zip(members, shares):
                    z[rows, draws[None, :]] = flow.noise_to_data(
                        eps[part][:, torch.from_numpy(draws)], c, m).double().numpy()
    return z


# ---------------------------------------------------------------------------------- decoding


def logit(p: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.log(p) - np.log1p(-p)


def reported_share(week_cases: NDArray[np.float64], susceptible: NDArray[np.float64],
                   population: int | NDArray[np.int64] | NDArray[np.float64]
                   ) -> NDArray[np.float64]:
    """f = (C + ½) / (N S): the share of the susceptibles reported in a week."""
    return (week_cases + HALF_CASE) / (population * susceptible)


def decode_paths(z: NDArray[np.float64], last_week_cases: float | NDArray[np.float64],
                 s_before: float | NDArray[np.float64], s_origin: float | NDArray[np.float64],
                 population: int | NDArray[np.int64]) -> NDArray[np.float64]:
    """Weekly S, I, R sample paths ``(..., n, H, 3)`` from targets ``z (..., n, H)``; I = C_h / N
    (the reporting window is one week), S_h = S_{h−1} − C_h / N, R = 1 − S − I. The other
    arguments are scalars or ``(..., 1)`` arrays (one value per history of a batch)."""
    base = logit(reported_share(np.asarray(last_week_cases, dtype=np.float64),
                                np.asarray(s_before, dtype=np.float64), population))
    susceptible = np.broadcast_to(np.asarray(s_origin, dtype=np.float64), z.shape[:-1]).copy()
    paths = np.empty(z.shape + (3,))
    for h in range(z.shape[-1]):                  # sequential weeks, vectorized over paths
        share = 1.0 / (1.0 + np.exp(-(z[..., h] + base)))
        infectious = susceptible * share
        susceptible = susceptible - infectious
        paths[..., h, :] = np.stack([susceptible, infectious, 1.0 - susceptible - infectious],
                                    axis=-1)
    return paths


def decode_weekly(z: NDArray[np.float64], histories: Sequence[WeeklyHistory]
                  ) -> NDArray[np.float64]:
    """Weekly S, I, R paths ``(B, n, H, 3)`` of weekly histories from ``z (B, n, H)``: a count
    depletes S; a rate keeps S at 1, each week a share of N."""
    last = np.array([h.cases[-1] for h in histories])
    population = np.array([h.population for h in histories], dtype=np.int64)[:, None]
    s = np.array([h.susceptible_at_weeks()[-2:] if len(h) > 1
                  else np.r_[1.0, h.susceptible_at_weeks()] for h in histories])
    paths = decode_paths(z, last[:, None], s[:, :1], s[:, 1:], population)
    rate = np.array([not h.depletes for h in histories])
    if rate.any():
        base = logit((last[rate, None] + HALF_CASE) / population[rate])[..., None]
        share = 1.0 / (1.0 + np.exp(-(z[rate] + base)))
        paths[rate] = np.stack([1.0 - share, share, np.zeros_like(share)], axis=-1)
    return paths


# ----------------------------------------------------------------------------- weekly cells


def as_weekly(history: History, name: str) -> WeeklyHistory:
    if not isinstance(history, WeeklyHistory):
        raise TargetError(f"{name} reads weekly counts; a daily series needs the daily flow")
    return history


def weekly_cells(histories: Sequence[History], name: str) -> list[WeeklyHistory]:
    """The cells' weekly histories; a daily one, or a missing origin week, is an error."""
    weekly = [as_weekly(h, name) for h in histories]
    missing = [h for h in weekly if not np.isfinite(h.cases[-1])]
    if missing:
        raise TargetError(f"{name}: the week ending {missing[0].origin.date()} is missing "
                          "(the origin's week must be reported or nowcast)")
    return weekly


def last_weeks(cases: NDArray[np.float64], k_weeks: int) -> NDArray[np.float64]:
    """The last ``k_weeks`` counts, NaN before the series began."""
    out = np.full(k_weeks, np.nan)
    take = min(len(cases), k_weeks)
    out[k_weeks - take:] = cases[len(cases) - take:]
    return out


# -------------------------------------------------------------------------------- quantiles


def path_forecast(paths: NDArray[np.float64], cells: Cells, horizons: tuple[int, ...],
                  levels: NDArray[np.float64], *, offset: float = HALF_CASE) -> MemberForecast:
    """Count quantiles ``(B, H, Q)`` of the weekly paths ``(B, n, H_max, 3)`` at ``horizons``
    (I·N less the continuity ``offset``, at least 0), the paths kept (the hub's samples)."""
    paths = paths[:, :, [h - 1 for h in horizons]]
    counts = paths[..., 1] * cells.populations[:, None, None] - offset
    return MemberForecast(np.maximum(quantiles_of_samples(counts, levels), 0.0), paths=paths)


def check_horizons(name: str, horizons: tuple[int, ...], max_horizon: int) -> None:
    if max(horizons) > max_horizon or min(horizons) < 1:
        raise TargetError(f"{name} forecasts weeks 1 … {max_horizon}, not {horizons}")
