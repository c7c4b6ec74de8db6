"""The flow member fine-tuned on real series known by the origin (``nf-real``).

The flow member (:mod:`pipeline.members.nf.growth`) learns growth only from the synthetic
multi-wave prior. Real epidemics have habits the prior does not: how long a wave keeps growing,
how plateaus hold, how fast a decline flattens. This member starts from the same trained flow
and, at every refit date r (every ``refit_every_weeks`` weeks), is fine-tuned on the real
windows of every place of the panel whose four target weeks had ended ``revision_days`` before
r (their counts had settled; the days just before r were still filling in), mixed with as many
synthetic windows from the prior (so the fine-tuned flow keeps the prior's coverage of
situations the real data have not shown yet). A forecast at origin o uses the model of the
latest refit date ≤ o: nothing after the origin enters it.

Windows: the same scale-free contexts and valid-by-construction targets as the synthetic ones
(:func:`pipeline.members.nf.model.context_features`, :func:`~.growth_targets`), one per day of
each place, in the synthetic model's standardization (the fine-tuned flow is the same model).
Validation: a seeded fifth of the places, for the best-state choice of the trainer.
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from numpy.typing import NDArray

from pipeline.members.base import Member, MemberForecast
from pipeline.members.nf.model import (CHECKPOINT_NAME, FlowModelConfig, RealWindows,
                                       SyntheticWindows)
from pipeline.fingerprint import fingerprint
from pipeline.panels.history import History
from pipeline.panels.panel import Cells, Panel
from pipeline.panels.targets import DAYS_PER_WEEK
from pipeline.errors import CheckpointError, ConfigError, TrainingDivergedError
from pipeline.models.estimator import ConditionalEstimator, EstimatorConfig
from pipeline.progress import ProgressReporter, SilentProgress
from pipeline.training.checkpoints import load_checkpoint, save_checkpoint
from pipeline.training.datasets import WindowedDataset, dataset_sha256, validation_trajectories
from pipeline.training.digests import DataDigests, Digests
from pipeline.training.model_store import ModelStore, StoreEntry
from pipeline.training.trainer import TrainConfig, train

NF_REAL = "nf-real"
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FineTuneConfig:
    """Refit schedule and optimiser of the fine-tuning (module docstring)."""

    refit_every_weeks: int = 4
    revision_days: int = 14
    iterations: int = 300
    batch_size: int = 512
    lr: float = 5e-4
    synthetic_share: float = 0.5
    val_fraction: float = 0.2
    min_windows: int = 500
    seed: int = 0
    # Stop when the validation loss has not improved for this many evaluations (a tenth of the
    # iterations each) and keep the best state: a refit whose loss rises ends there instead of
    # diverging (bench/results/replay.json "refits")
    early_stop_patience: int | None = 2
    grad_clip_norm: float = 1.0

    def __post_init__(self) -> None:
        if (self.refit_every_weeks < 1 or self.revision_days < 0 or self.iterations < 1
                or not 0 <= self.synthetic_share < 1 or not 0 < self.val_fraction < 1
                or self.grad_clip_norm <= 0
                or (self.early_stop_patience is not None and self.early_stop_patience < 1)):
            raise ConfigError(f"invalid FineTuneConfig {self}")

    def identity(self) -> dict[str, object]:
        return json.loads(json.dumps(dataclasses.asdict(self)))


class FlowMember(Member, Protocol):
    """A flow member that can be fine-tuned: its trained estimator and settings, its reach, and
    the windows it would train on from real series (the daily flow's, the weekly one's)."""

    @property
    def estimator(self) -> ConditionalEstimator: ...

    @property
    def config(self) -> FlowModelConfig: ...

    @property
    def max_horizon(self) -> int: ...

    def real_windows(self, histories: Sequence[History], cutoff: pd.Timestamp
                     ) -> RealWindows: ...


# Refits fall on a fixed calendar (every k-th week from this Saturday), not on every k-th origin
# of a run: runs that start on different days, the weekly forecast and the cross-county
# backtest, refit on the same dates with the same windows, so they share the stored models.
REFIT_EPOCH = pd.Timestamp("2020-01-04")


def refit_dates(origins: Sequence[pd.Timestamp], every_weeks: int) -> list[pd.Timestamp]:
    """The origins that fall on the refit calendar (every ``every_weeks`` weeks from
    :data:`REFIT_EPOCH`): the days the member is refitted."""
    return [o for o in origins
            if (o - REFIT_EPOCH).days % (7 * every_weeks) == 0]


def latest_refit_date(origin: pd.Timestamp, every_weeks: int) -> pd.Timestamp:
    """The last day of the refit calendar on or before ``origin``: the refit whose model a
    forecast at ``origin`` uses."""
    origin = pd.Timestamp(origin).normalize()
    return origin - pd.Timedelta(days=(origin - REFIT_EPOCH).days % (DAYS_PER_WEEK * every_weeks))


def _dataset(context: NDArray[np.float32], mask: NDArray[np.bool_], target: NDArray[np.float32],
             trajectory: NDArray[np.int64], like: WindowedDataset) -> WindowedDataset:
    """Windows in the synthetic dataset's standardization and metadata."""
    context_t = torch.from_numpy(np.ascontiguousarray(context))
    draft = WindowedDataset(context_t, torch.from_numpy(np.ascontiguousarray(mask)),
                            torch.from_numpy(np.ascontiguousarray(target)),
                            torch.from_numpy(trajectory),
                            torch.zeros(len(trajectory), dtype=torch.float64), like.stats,
                            dataclasses.replace(like.meta, config_name="real-windows"))
    return dataclasses.replace(draft, meta=dataclasses.replace(
        draft.meta, data_sha256=dataset_sha256(draft)))


def training_windows(real: RealWindows, synthetic: WindowedDataset, config: FineTuneConfig
                     ) -> tuple[WindowedDataset, WindowedDataset]:
    """(train, validation): real windows (validation: a seeded share of the places) mixed with
    synthetic ones in the ratio ``synthetic_share``."""
    context, mask, target, place = real
    held = validation_trajectories(torch.from_numpy(place), config.val_fraction,
                                   config.seed).numpy()
    is_val = np.isin(place, held)
    n_synth = int(round((~is_val).sum() * config.synthetic_share / (1 - config.synthetic_share)))
    rng = np.random.default_rng(config.seed)
    pick = rng.choice(len(synthetic), size=min(n_synth, len(synthetic)), replace=False)
    synth_context = synthetic.context[torch.from_numpy(pick)].numpy()
    synth_mask = synthetic.mask[torch.from_numpy(pick)].numpy()
    synth_target = synthetic.target[torch.from_numpy(pick)].numpy()
    offset = int(place.max()) + 1
    train_ds = _dataset(np.concatenate([context[~is_val], synth_context]),
                        np.concatenate([mask[~is_val], synth_mask]),
                        np.concatenate([target[~is_val], synth_target]),
                        np.concatenate([place[~is_val], offset + np.arange(len(pick))]),
                        synthetic)
    return train_ds, _dataset(context[is_val], mask[is_val], target[is_val], place[is_val],
                              synthetic)


def finetune(base: ConditionalEstimator, train_ds: WindowedDataset, val_ds: WindowedDataset,
             config: FineTuneConfig) -> ConditionalEstimator:
    """A copy of ``base`` trained at most ``config.iterations`` more steps, gradients clipped,
    stopped when the validation loss stops improving (best validation state)."""
    model = copy.deepcopy(base)
    model.train()
    train(model, train_ds, val_ds, train_config(config))
    model.eval()
    return model


def train_config(config: FineTuneConfig) -> TrainConfig:
    """The trainer's settings of a refit: cosine schedule, ten evaluations, clipped, early
    stop."""
    return TrainConfig(iterations=config.iterations, batch_size=config.batch_size, lr=config.lr,
                       schedule="cosine", eval_every=max(1, config.iterations // 10),
                       seed=config.seed + 11, grad_clip_norm=config.grad_clip_norm,
                       early_stop_patience=config.early_stop_patience)


@dataclass(frozen=True, eq=False)
class StoredRefit:
    """A refit's model in the model store, loaded at its first forecast: a run whose forecasts
    the memo holds (:mod:`pipeline.backtest.memo`) loads only the refits it forecasts with. The
    memo knows it by its store key and version (the version's name carries the hash of its
    files, so a model rebuilt with other weights is another version)."""

    key: str
    version: str
    expected: EstimatorConfig
    _path: Path

    @classmethod
    def of(cls, entry: StoreEntry, expected: EstimatorConfig) -> StoredRefit:
        return cls(entry.key, entry.path.name, expected, entry.path)

    @functools.cached_property
    def estimator(self) -> ConditionalEstimator:
        return load_checkpoint(self._path / CHECKPOINT_NAME,
                               expected_config=self.expected).estimator


Refit = ConditionalEstimator | StoredRefit


@dataclass(frozen=True, eq=False)
class FineTunedGrowthMember:
    """``models[r]``: the flow fine-tuned at refit date r; a cell at origin o is forecast by the
    model of the latest r ≤ o (the synthetic flow before the first refit)."""

    base: FlowMember
    models: Mapping[pd.Timestamp, Refit]
    name: str = NF_REAL
    # the refit dates whose fine-tuning diverged, and what their forecasts use instead
    fallbacks: Mapping[pd.Timestamp, str] = dataclasses.field(default_factory=dict)

    @property
    def max_horizon(self) -> int:
        return self.base.max_horizon

    def refit_for(self, origin: pd.Timestamp) -> pd.Timestamp | None:
        """The latest refit date on or before ``origin`` (None: before the first refit)."""
        dates = [r for r in self.models if r <= origin]
        return max(dates) if dates else None

    @functools.cached_property
    def _base_key(self) -> str:
        return fingerprint(self.base)

    def cell_identity(self, origin: pd.Timestamp, panel: Panel) -> object:
        """What a cell at ``origin`` is forecast with (:class:`~pipeline.members.base.
        KeyedByCell`): the base flow and the refit of its origin, not the later refits (a
        round's refit leaves the earlier rounds' keys as they were)."""
        refit = self.refit_for(origin)
        return (self.name, self._base_key, refit, None if refit is None else self.models[refit])

    def model_for(self, origin: pd.Timestamp) -> FlowMember:
        refit = self.refit_for(origin)
        if refit is None:
            return self.base
        model = self.models[refit]
        estimator = model.estimator if isinstance(model, StoredRefit) else model
        return dataclasses.replace(self.base, estimator=estimator)  # type: ignore[type-var]

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Every cell through the model of its origin's refit, the cells of each refit in one
        batch (the sample paths kept, as the base member's)."""
        refits = [self.refit_for(o) for o in cells.origins]
        count = np.empty((len(cells), len(horizons), len(levels)))
        paths: NDArray[np.float64] | None = None
        for refit in dict.fromkeys(refits):
            index = [i for i, r in enumerate(refits) if r == refit]
            member = self.base if refit is None else self.model_for(refit)
            made = member.forecast(cells.subset(index), horizons, levels)
            count[index] = made.count
            if made.paths is not None:
                if paths is None:
                    paths = np.empty((len(cells), *made.paths.shape[1:]))
                paths[index] = made.paths
        return MemberForecast(count, paths=paths)


def fit_finetuned_member(base: FlowMember, synthetic: SyntheticWindows,
                         histories: Sequence[History], dates: Sequence[pd.Timestamp],
                         config: FineTuneConfig, store_root: Path | None = None,
                         progress: ProgressReporter | None = None, *,
                         newest_first: bool = False,
                         known_at: Callable[[pd.Timestamp], Sequence[History]] | None = None
                         ) -> FineTunedGrowthMember:
    """Fine-tune at each refit date on ``histories`` as they stood then (module docstring);
    with ``store_root`` every model is kept in the model store (key: the configs and the
    windows' hash), so a rerun on the same data trains nothing, and the windows' hashes in the
    store's digests (:mod:`pipeline.training.digests`), so it cuts no windows either.
    ``newest_first``: fine-tune the latest date first (a second process filling the same store
    from the other end, :mod:`pipeline.forecast.member_training`); the models are the same
    either way. ``known_at``: the places' data as released by a date (a source with vintages:
    a refit learns from the vintage of its date, not from later revisions of it).

    A refit that still diverges is left out: its forecasts come from the previous refit (or
    the base flow), recorded in ``fallbacks``; with a store the divergence is recorded too,
    so the next run does not train it again."""
    progress = progress or SilentProgress()
    models: dict[pd.Timestamp, Refit] = {}
    diverged: dict[pd.Timestamp, str] = {}
    for date in (sorted(dates, reverse=True) if newest_first else dates):
        known = (list(known_at(date)) if known_at is not None
                 else [h.up_to(date) for h in histories if h.dates[0] <= date])
        windows = functools.cache(functools.partial(
            _refit_windows, base, known, date - pd.Timedelta(days=config.revision_days),
            synthetic, config))
        try:
            if store_root is None:
                cut = windows()
                if cut is not None:
                    models[date] = finetune(base.estimator, *cut, config)
            else:
                stored = _stored_finetune(base, known, date, synthetic, config, store_root,
                                          windows)
                if stored is not None:
                    models[date] = stored
        except TrainingDivergedError as error:
            log.warning("nf-real refit %s diverged; its forecasts use the one before: %s",
                        date.date(), error)
            diverged[date] = str(error)
        if date in models:
            progress.advance(1, refit=str(date.date()))
    return FineTunedGrowthMember(base, models, fallbacks={
        date: f"{why}; forecasts from {_previous(models, date)} instead"
        for date, why in sorted(diverged.items())})


def _previous(models: Mapping[pd.Timestamp, Refit], date: pd.Timestamp) -> str:
    earlier = [d for d in models if d < date]
    return f"the refit of {max(earlier).date()}" if earlier else "the base flow"


def _refit_windows(base: FlowMember, known: Sequence[History], cutoff: pd.Timestamp,
                   synthetic: SyntheticWindows, config: FineTuneConfig
                   ) -> tuple[WindowedDataset, WindowedDataset] | None:
    """A refit's (train, validation) windows; None when the places known then have too few."""
    real = base.real_windows(known, cutoff)
    if len(real.place) < config.min_windows or len(np.unique(real.place)) < 2:
        return None
    return training_windows(real, synthetic.dataset, config)


def _refit_digests(windows: tuple[WindowedDataset, WindowedDataset] | None) -> Digests:
    if windows is None:
        return {"skipped": "too few real windows"}
    train_ds, val_ds = windows
    return {"train_sha256": train_ds.meta.data_sha256,
            "validation_sha256": val_ds.meta.data_sha256}


def _stored_finetune(base: FlowMember, known: Sequence[History], date: pd.Timestamp,
                     synthetic: SyntheticWindows, config: FineTuneConfig, store_root: Path,
                     windows: Callable[[], tuple[WindowedDataset, WindowedDataset] | None]
                     ) -> StoredRefit | None:
    """The refit at ``date`` from the store (fine-tuned first if absent); None when skipped."""
    inputs = ("nf-real windows", config.identity(), base.config.identity(),
              synthetic.data_sha256, date, [h.fingerprint() for h in known])
    digests = DataDigests(store_root).get_or_compute(inputs, lambda: _refit_digests(windows()))
    if "skipped" in digests:
        return None

    def build(out_dir: Path) -> dict[str, object]:
        cut = windows()
        if cut is None or _refit_digests(cut) != digests:
            raise CheckpointError(f"the refit windows of {date.date()} do not match their "
                                  f"recorded digests in {store_root}")
        model = finetune(base.estimator, *cut, config)
        save_checkpoint(out_dir / CHECKPOINT_NAME, model, config=base.config.estimator_config(),
                        stats=model.stats, data_sha256=digests["train_sha256"],
                        extra={"kind": NF_REAL})
        return {}

    key = {NF_REAL: config.identity(), base.config.kind: base.config.identity(),
           "validation_sha256": digests["validation_sha256"]}
    store = ModelStore(store_root)

    def attempt() -> Digests:
        """Train the refit into the store once; a divergence is an outcome kept beside it."""
        try:
            store.get_or_build(key, digests["train_sha256"], build)
        except TrainingDivergedError as error:
            return {"diverged": str(error)}
        return {"trained": digests["train_sha256"]}

    outcome = DataDigests(store_root).get_or_compute(("nf-real outcome", *inputs), attempt)
    if "diverged" in outcome:
        raise TrainingDivergedError(outcome["diverged"])
    entry = store.get_or_build(key, digests["train_sha256"], build)
    return StoredRefit.of(entry, base.config.estimator_config())
