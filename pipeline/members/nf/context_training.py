"""The context flow's training (:mod:`pipeline.members.nf.context`): its settings, its
pre-training on the weekly flow's prior with the real-context channels at 0, and its refits on
the real windows known at each refit date (:mod:`pipeline.members.nf.context_features`), mixed
with synthetic ones; every model kept in the model store."""
from __future__ import annotations

import copy
import dataclasses
import functools
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
import pandas as pd
import torch

import pipeline
from pipeline.errors import CheckpointError, ConfigError
from pipeline.members.nf.context_features import (ContextChannels, ContextSources, WindowInputs,
                                                  context_windows, empty_windows,
                                                  fixed_channels, joined, known_by,
                                                  n_channels, vintage_windows)
from pipeline.members.nf.model import CHECKPOINT_NAME, RealWindows, SyntheticWindows
from pipeline.members.nf.weekly import (ADMISSIONS_PRIOR, WeeklyFlowConfig, simulate_admissions,
                                        weekly_targets)
from pipeline.models.encoders import EncoderConfig, MLPEncoderConfig, TransformerEncoderConfig
from pipeline.models.estimator import (ConditionalEstimator, EstimatorConfig, build_estimator,
                                       make_estimator_config)
from pipeline.models.standardization import Standardization
from pipeline.panels.panel import Panel
from pipeline.training.checkpoints import load_checkpoint, save_checkpoint
from pipeline.training.datasets import (FORMAT_VERSION, DatasetMeta, WindowedDataset,
                                        compute_standardization, dataset_sha256,
                                        validation_trajectories)
from pipeline.training.digests import DataDigests, Digests
from pipeline.training.model_store import ModelStore
from pipeline.training.trainer import TrainConfig, train

NF_CONTEXT = "nf-context"
EncoderKind = Literal["mlp", "transformer"]


@dataclass(frozen=True)
class ContextFlowConfig:
    """The prior (the weekly flow's, fewer trajectories: the real windows carry the rest), the
    window, the encoder (``mlp`` or ``transformer``), the flow and the pre-training optimiser
    (the model-store key is built from this)."""

    prior: WeeklyFlowConfig = field(default_factory=lambda: WeeklyFlowConfig(
        n_trajectories=2000, prior=ADMISSIONS_PRIOR))
    context_weeks: int = 8
    horizon_weeks: int = 5
    encoder: EncoderKind = "mlp"
    embedding_features: int = 32
    hidden_features: int = 128
    flow_layers: int = 5
    flow_hidden: int = 64
    iterations: int = 1500
    batch_size: int = 1024
    lr: float = 3e-3
    val_fraction: float = 0.1
    seed: int = 0

    kind: ClassVar[str] = NF_CONTEXT

    def __post_init__(self) -> None:
        if self.context_weeks < 2 or self.horizon_weeks < 1 or self.encoder not in (
                "mlp", "transformer"):
            raise ConfigError(f"invalid ContextFlowConfig {self}")

    def identity(self) -> dict[str, object]:
        return json.loads(json.dumps(dataclasses.asdict(self)))

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
        return make_estimator_config(self.horizon_weeks, self.channels, self.context_weeks,
                                     encoder, layers=self.flow_layers,
                                     hidden_features=self.flow_hidden)

    def build_dataset(self) -> WindowedDataset:
        return synthetic_dataset(self)


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
    prior = config.prior
    admissions, population = simulate_admissions(prior)
    m, n_weeks = admissions.shape
    k, h = config.context_weeks, config.horizon_weeks
    origins = np.arange(k, n_weeks - h)
    trajectory = np.repeat(np.arange(m), origins.size)
    t = np.tile(origins, m)
    series = admissions[trajectory[:, None], t[:, None] + np.arange(-k + 1, 1)[None, :]]
    rng = np.random.default_rng(config.seed + 7)
    short = rng.random(len(series)) < prior.short_share
    keep = rng.integers(prior.min_weeks, k + 1, len(series))
    series = np.where(short[:, None] & (np.arange(k)[None, :] < (k - keep)[:, None]), np.nan,
                      series)
    inputs = WindowInputs(series, np.full_like(series, np.nan),
                          np.zeros(len(series), dtype="datetime64[ns]"),
                          np.full((len(series), h, 3), np.nan), population[trajectory])
    context, mask = context_windows(inputs, ContextChannels(season=False))
    counted = np.concatenate([np.zeros((m, 1)), np.cumsum(admissions, axis=1)], axis=1)
    window = admissions[trajectory[:, None], t[:, None] + np.arange(-1, h + 1)[None, :]]
    with np.errstate(invalid="ignore", divide="ignore"):
        target = weekly_targets(window, counted[trajectory, t - 1], population[trajectory])
    ok = np.isfinite(target).all(axis=1)
    context_t, mask_t = torch.from_numpy(context[ok]), torch.from_numpy(mask[ok])
    target_t = torch.from_numpy(target[ok])
    meta = DatasetMeta(
        system="waves", config_name="hub-context", direction="forward", target_kind="growth",
        context_features=tuple(f"context_{c}" for c in range(config.channels)),
        target_features=tuple(f"z_week{s}" for s in range(1, h + 1)), window=k,
        seed=config.seed, val_fraction=config.val_fraction, split="all", n_trajectories=m,
        n_observed_points=int(admissions.size), n_observed_values=int(admissions.size),
        config=config.identity(), package_version=pipeline.__version__,
        format_version=FORMAT_VERSION, data_sha256="")
    draft = WindowedDataset(context_t, mask_t, target_t, torch.from_numpy(trajectory[ok]),
                            torch.from_numpy(t[ok].astype(np.float64)),
                            fixed_standardization(context_t, mask_t, target_t, h), meta)
    return dataclasses.replace(draft, meta=dataclasses.replace(
        meta, data_sha256=dataset_sha256(draft)))


def _split(ds: WindowedDataset, val_fraction: float, seed: int
           ) -> tuple[WindowedDataset, WindowedDataset]:
    """(train, validation) by trajectory (a place, for real windows), the dataset's own stats
    kept (the hand-scaled channels must stay (x − 0) / 1)."""
    held = torch.isin(ds.trajectory, validation_trajectories(ds.trajectory, val_fraction, seed))
    return ds.subset(~held, "train"), ds.subset(held, "validation")


def _train_config(iterations: int, batch_size: int, lr: float, seed: int,
                  patience: int | None = None) -> TrainConfig:
    """``patience``: a refit stops after that many evaluations without improving on its
    held-out places (a few hundred windows overfit fast; the best state is kept either way)."""
    return TrainConfig(iterations=iterations, batch_size=batch_size, lr=lr, schedule="cosine",
                       eval_every=max(1, iterations // 10), seed=seed,
                       early_stop_patience=patience,
                       divergence_margin=1e3 if patience is not None else 10.0)


def pretrain(config: ContextFlowConfig, dataset: WindowedDataset) -> ConditionalEstimator:
    """The flow trained on the prior's windows (best validation state)."""
    train_ds, val_ds = _split(dataset, config.val_fraction, config.seed)
    estimator = build_estimator(config.estimator_config(), dataset.stats, seed=config.seed + 2)
    train(estimator, train_ds, val_ds, _train_config(config.iterations, config.batch_size,
                                                     config.lr, config.seed + 1))
    return estimator


def stored_pretrained(config: ContextFlowConfig, store_root: Path
                      ) -> tuple[ConditionalEstimator, SyntheticWindows, str]:
    """(the pre-trained flow from the model store, trained there if absent; its windows,
    simulated only when a model trains on them; key)."""
    synthetic = SyntheticWindows(config, DataDigests(store_root))

    def build(out_dir: Path) -> dict[str, object]:
        estimator = pretrain(config, synthetic.dataset)
        save_checkpoint(out_dir / CHECKPOINT_NAME, estimator, config=config.estimator_config(),
                        stats=estimator.stats, data_sha256=synthetic.data_sha256,
                        extra={"kind": NF_CONTEXT})
        return {}

    entry = ModelStore(store_root).get_or_build({NF_CONTEXT: config.identity()},
                                                synthetic.data_sha256, build)
    loaded = load_checkpoint(entry.path / CHECKPOINT_NAME,
                             expected_config=config.estimator_config())
    return loaded.estimator, synthetic, entry.key


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


def _windowed(real: RealWindows, like: WindowedDataset, name: str) -> WindowedDataset:
    context_t = torch.from_numpy(np.ascontiguousarray(real.context))
    draft = WindowedDataset(context_t, torch.from_numpy(np.ascontiguousarray(real.mask)),
                            torch.from_numpy(np.ascontiguousarray(real.target)),
                            torch.from_numpy(real.place),
                            torch.zeros(len(real.place), dtype=torch.float64), like.stats,
                            dataclasses.replace(like.meta, config_name=name))
    return dataclasses.replace(draft, meta=dataclasses.replace(
        draft.meta, data_sha256=dataset_sha256(draft)))


def refit_datasets(real: RealWindows, synthetic: WindowedDataset, refit: ContextRefitConfig
                   ) -> tuple[WindowedDataset, WindowedDataset]:
    """(train, validation): the real windows of the training places mixed with synthetic ones
    (``synthetic_share`` of the whole), and the held-out places' real windows."""
    held = validation_trajectories(torch.from_numpy(real.place), refit.val_fraction,
                                   refit.seed).numpy()
    is_val = np.isin(real.place, held)
    n_train = int((~is_val).sum())
    n_synth = int(round(n_train * refit.synthetic_share / (1 - refit.synthetic_share)))
    pick = np.random.default_rng(refit.seed).choice(len(synthetic), min(n_synth, len(synthetic)),
                                                    replace=False)
    offset = int(real.place.max()) + 1
    mixed = RealWindows(
        np.concatenate([real.context[~is_val], synthetic.context[pick].numpy()]),
        np.concatenate([real.mask[~is_val], synthetic.mask[pick].numpy()]),
        np.concatenate([real.target[~is_val], synthetic.target[pick].numpy()]),
        np.concatenate([real.place[~is_val], offset + np.arange(len(pick))]))
    validation = RealWindows(real.context[is_val], real.mask[is_val], real.target[is_val],
                             real.place[is_val])
    return _windowed(mixed, synthetic, "real+synthetic"), _windowed(validation, synthetic, "real")


def refit_flow(base: ConditionalEstimator, train_ds: WindowedDataset, val_ds: WindowedDataset,
               refit: ContextRefitConfig) -> ConditionalEstimator:
    """A copy of ``base`` trained further on the refit's windows (best validation state)."""
    model = copy.deepcopy(base)
    model.train()
    train(model, train_ds, val_ds, _train_config(refit.iterations, refit.batch_size, refit.lr,
                                                 refit.seed + 11, refit.patience))
    model.eval()
    return model


def stored_refit(base: ConditionalEstimator, base_key: str,
                 windows: Callable[[], RealWindows], inputs: Sequence[object],
                 synthetic: SyntheticWindows, date: pd.Timestamp, config: ContextFlowConfig,
                 refit: ContextRefitConfig, channels: ContextChannels, store_root: Path
                 ) -> ConditionalEstimator | None:
    """The refit at ``date`` from the model store (trained first if absent); None when the
    places known then give fewer than ``min_windows`` windows or fewer than two places.
    ``windows`` cuts the real windows of ``inputs`` (:func:`refit_inputs`); their datasets'
    hashes are kept in the store's digests by those inputs, so a week whose refits are all
    stored cuts no window and simulates no prior (as nf-real's,
    :func:`~pipeline.members.nf.finetune.fit_finetuned_member`)."""
    @functools.cache
    def datasets() -> tuple[WindowedDataset, WindowedDataset] | None:
        real = windows()
        if len(real.place) < refit.min_windows or len(np.unique(real.place)) < 2:
            return None
        return refit_datasets(real, synthetic.dataset, refit)

    def hashed() -> Digests:
        cut = datasets()
        return ({"skipped": "too few real windows"} if cut is None else
                {"train_sha256": cut[0].meta.data_sha256,
                 "validation_sha256": cut[1].meta.data_sha256})

    digests = DataDigests(store_root).get_or_compute(
        ("nf-context refit windows", refit.identity(), config.identity(),
         synthetic.data_sha256, dataclasses.asdict(channels), date, *inputs), hashed)
    if "skipped" in digests:
        return None

    def build(out_dir: Path) -> dict[str, object]:
        if hashed() != digests:
            raise CheckpointError(f"the {NF_CONTEXT} refit windows of {date.date()} do not "
                                  f"match their recorded digests in {store_root}")
        cut = datasets()
        assert cut is not None
        model = refit_flow(base, *cut, refit)
        save_checkpoint(out_dir / CHECKPOINT_NAME, model, config=config.estimator_config(),
                        stats=model.stats, data_sha256=digests["train_sha256"],
                        extra={"kind": f"{NF_CONTEXT} refit"})
        return {}

    key = {f"{NF_CONTEXT} refit": refit.identity(), "base": base_key,
           "channels": dataclasses.asdict(channels), "date": str(date.date()),
           "validation_sha256": digests["validation_sha256"]}
    entry = ModelStore(store_root).get_or_build(key, digests["train_sha256"], build)
    return load_checkpoint(entry.path / CHECKPOINT_NAME,
                           expected_config=config.estimator_config()).estimator
