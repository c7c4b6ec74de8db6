"""What the context flow (:mod:`pipeline.members.nf.context`) trains on: its settings, its
pre-training windows (the weekly flow's prior with the real-context channels at 0) and the real
windows known at each refit date (:mod:`pipeline.members.nf.context_features`). The flow
machinery trains and stores it (:mod:`pipeline.members.nf.flow`); the refit path mixes, refits
and stores its refits (:mod:`pipeline.members.nf.refit`)."""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np
import pandas as pd
import torch

import pipeline
from pipeline.errors import ConfigError
from pipeline.members.nf.context_features import (ContextChannels, ContextSources, WindowInputs,
                                                  context_windows, empty_windows,
                                                  fixed_channels, joined, known_by,
                                                  n_channels, vintage_windows)
from pipeline.members.nf.flow import FlowNetwork, RealWindows
from pipeline.members.nf.weekly import (ADMISSIONS_PRIOR, WeeklyFlowConfig, prior_dataset,
                                        prior_windows)
from pipeline.models.encoders import EncoderConfig, MLPEncoderConfig, TransformerEncoderConfig
from pipeline.models.estimator import EstimatorConfig
from pipeline.models.standardization import Standardization
from pipeline.panels.panel import Panel
from pipeline.training.datasets import (FORMAT_VERSION, DatasetMeta, WindowedDataset,
                                        compute_standardization, validation_trajectories)
from pipeline.training.trainer import TrainConfig

NF_CONTEXT = "nf-context"
EncoderKind = Literal["mlp", "transformer"]


@dataclass(frozen=True)
class ContextFlowConfig(FlowNetwork):
    """The prior (the weekly flow's, fewer trajectories: the real windows carry the rest), the
    window and the encoder (``mlp`` or ``transformer``) beside the flow's settings
    (:class:`~pipeline.members.nf.flow.FlowNetwork`; the model-store key is built from this)."""

    prior: WeeklyFlowConfig = field(default_factory=lambda: WeeklyFlowConfig(
        n_trajectories=2000, prior=ADMISSIONS_PRIOR))
    context_weeks: int = 8
    horizon_weeks: int = 5
    encoder: EncoderKind = "mlp"
    embedding_features: int = 32
    iterations: int = 1500

    kind: ClassVar[str] = NF_CONTEXT

    def __post_init__(self) -> None:
        if self.context_weeks < 2 or self.horizon_weeks < 1 or self.encoder not in (
                "mlp", "transformer"):
            raise ConfigError(f"invalid ContextFlowConfig {self}")

    @property
    def channels(self) -> int:
        return n_channels(self.horizon_weeks)

    def estimator_config(self) -> EstimatorConfig:
        encoder = (EncoderConfig(kind="mlp", embedding_features=self.embedding_features,
                                 mlp=MLPEncoderConfig(hidden_features=self.hidden_features))
                   if self.encoder == "mlp" else
                   EncoderConfig(kind="transformer", embedding_features=self.embedding_features,
                                 transformer=TransformerEncoderConfig(
                                     d_model=32, heads=4, encoder_layers=2, decoder_layers=1,
                                     feedforward_features=64)))
        return self.network(self.horizon_weeks, self.channels, self.context_weeks, encoder)

    def build_dataset(self) -> WindowedDataset:
        return synthetic_dataset(self)

    def split(self, dataset: WindowedDataset) -> tuple[WindowedDataset, WindowedDataset]:
        """(train, validation) by trajectory, the dataset's own stats kept (the hand-scaled
        channels must stay (x − 0) / 1)."""
        held = torch.isin(dataset.trajectory, validation_trajectories(
            dataset.trajectory, self.val_fraction, self.seed))
        return dataset.subset(~held, "train"), dataset.subset(held, "validation")

    def train_config(self) -> TrainConfig:
        return TrainConfig(iterations=self.iterations, batch_size=self.batch_size, lr=self.lr,
                           schedule="cosine", eval_every=max(1, self.iterations // 10),
                           seed=self.seed + 1)


@dataclass(frozen=True)
class ContextRefitConfig:
    """The refit calendar and optimiser (module docstring)."""

    refit_every_weeks: int = 4
    revision_days: int = 14
    iterations: int = 400
    batch_size: int = 512
    lr: float = 5e-4
    synthetic_share: float = 0.3
    val_fraction: float = 0.2
    min_windows: int = 500
    patience: int = 3
    seed: int = 0

    def __post_init__(self) -> None:
        if (self.refit_every_weeks < 1 or self.revision_days < 0 or self.iterations < 1
                or not 0 <= self.synthetic_share < 1 or not 0 < self.val_fraction < 1):
            raise ConfigError(f"invalid ContextRefitConfig {self}")

    def identity(self) -> dict[str, object]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

    def train_config(self) -> TrainConfig:
        """Ten evaluations; a refit stops after ``patience`` of them without improving on its
        held-out places (a few hundred windows overfit fast; the best state is kept)."""
        return TrainConfig(iterations=self.iterations, batch_size=self.batch_size, lr=self.lr,
                           schedule="cosine", eval_every=max(1, self.iterations // 10),
                           seed=self.seed + 11, early_stop_patience=self.patience,
                           divergence_margin=1e3)


# Seconds, for tests and smoke runs: a small prior and network, short refits.
TINY_CONTEXT_FLOW = ContextFlowConfig(
    prior=WeeklyFlowConfig(n_trajectories=150, prior=ADMISSIONS_PRIOR), hidden_features=16,
    embedding_features=8, flow_layers=2, flow_hidden=16, iterations=40, batch_size=256)
TINY_CONTEXT_REFIT = ContextRefitConfig(iterations=20, batch_size=128, min_windows=50)


# ------------------------------------------------------------------------------ pre-training


def fixed_standardization(context: torch.Tensor, mask: torch.Tensor, target: torch.Tensor,
                          horizon_weeks: int) -> Standardization:
    """The standardization of the windows, the hand-scaled channels as (x − 0) / 1."""
    stats = compute_standardization(context, mask, target)
    fixed = fixed_channels(horizon_weeks)
    mean, std = stats.context_mean.clone(), stats.context_std.clone()
    mean[fixed], std[fixed] = 0.0, 1.0
    return dataclasses.replace(stats, context_mean=mean, context_std=std)


def synthetic_dataset(config: ContextFlowConfig) -> WindowedDataset:
    """The prior's windows (module docstring) at every week of every trajectory, a share
    shortened to 2 … K weeks (as the weekly flow's) so that short series are served."""
    k, h = config.context_weeks, config.horizon_weeks
    windows = prior_windows(config.prior, k, h, config.seed)
    n = len(windows.series)
    inputs = WindowInputs(windows.series, np.full_like(windows.series, np.nan),
                          np.zeros(n, dtype="datetime64[ns]"), np.full((n, h, 3), np.nan),
                          windows.population[windows.trajectory])
    context, mask = context_windows(inputs, ContextChannels(season=False))
    meta = DatasetMeta(
        system="waves", config_name="hub-context", direction="forward", target_kind="growth",
        context_features=tuple(f"context_{c}" for c in range(config.channels)),
        target_features=tuple(f"z_week{s}" for s in range(1, h + 1)), window=k,
        seed=config.seed, val_fraction=config.val_fraction, split="all",
        n_trajectories=windows.n_trajectories, n_observed_points=windows.n_values,
        n_observed_values=windows.n_values, config=config.identity(),
        package_version=pipeline.__version__, format_version=FORMAT_VERSION, data_sha256="")
    return prior_dataset(windows, context, mask, meta,
                         lambda c, m, t: fixed_standardization(c, m, t, h))


# ------------------------------------------------------------------------------------ refits


@dataclass(frozen=True, eq=False)
class TrainingPool:
    """A series the flow learns from: its vintages by release date and the sources its context
    reads (the target's own pool; an extra one such as influenza admissions of the same
    places, whose context has no other signal or climatology, and whose own season is not COVID-19's:
    ``channels`` leaves those out of its windows)."""

    vintages: Sequence[tuple[pd.Timestamp, Panel]]
    sources: ContextSources = ContextSources()
    channels: ContextChannels = ContextChannels()      # what its windows may show


def read_at(pools: Sequence[TrainingPool], date: pd.Timestamp
            ) -> list[tuple[TrainingPool, Panel]]:
    """The vintage each pool's refit at ``date`` reads: the first pool's whose data end by
    ``date`` (the round's own), every other pool's newest released by then."""
    target = [(a, p) for a, p in sorted(pools[0].vintages, key=lambda v: v[0])
              if p.last_date <= date]
    if not target:
        return []
    released = target[-1][0]
    read = [(pool, target[-1][1] if i == 0 else known_by(pool.vintages, released))
            for i, pool in enumerate(pools)]
    return [(pool, panel) for pool, panel in read if panel is not None]


def refit_inputs(pools: Sequence[TrainingPool], date: pd.Timestamp) -> list[object]:
    """What the refit windows of ``date`` are cut from (:func:`refit_windows`): each pool's
    vintage read then and its sources as released by that vintage — not the later ones."""
    return [(panel, pool.sources.released_by(panel.as_of), dataclasses.asdict(pool.channels))
            for pool, panel in read_at(pools, date)]


def refit_windows(pools: Sequence[TrainingPool], date: pd.Timestamp, revision_days: int,
                  config: ContextFlowConfig, channels: ContextChannels) -> RealWindows:
    """The real windows known at refit ``date`` (the vintages of :func:`read_at`), cut
    ``revision_days`` before ``date``."""
    cutoff = date - pd.Timedelta(days=revision_days)
    parts, offset = [], 0
    for pool, panel in read_at(pools, date):
        parts.append(vintage_windows(panel, pool.sources, cutoff, config.context_weeks,
                                     config.horizon_weeks, channels.both(pool.channels),
                                     place_offset=offset))
        offset += len(panel.histories)
    return joined(parts) if parts else empty_windows(config.context_weeks, config.horizon_weeks)
