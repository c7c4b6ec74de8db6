"""The refits of a trained flow on real windows, one path for every flow member that learns from
real data (``nf-real``: :mod:`~pipeline.members.nf.real`; ``nf-context``:
:mod:`~pipeline.members.nf.context`).

* **Calendar.** Refits fall every k-th week from a fixed Saturday (:data:`REFIT_EPOCH`), not on
  every k-th origin of a run: runs that start on different days (the weekly forecast, the
  cross-county backtest, a replay from mid-period) refit on the same dates with the same
  windows, so they share the stored models. A cell at origin o is forecast by the refit of
  the latest date ≤ o.
* **Windows.** The real windows known at the refit date (cut by the member), validation a
  seeded share of the places, the training places' windows mixed with synthetic ones from
  the prior (``synthetic_share`` of the whole), so the refit keeps the prior's coverage of
  situations the real data have not shown. Too few windows (or one place): no refit.
* **Training.** A copy of the base flow trained further with the member's optimiser settings
  (:meth:`RefitSettings.train_config`), the best validation state kept.
* **Store.** Each refit is kept in the model store (key: the member's identity of the refit and
  the windows' hashes); the hashes are kept in the store's digests by the windows' inputs, so a
  week whose refits are stored cuts no window; a refit is loaded at its first forecast
  (:class:`StoredRefit`).
* **Divergence.** A refit that diverges is recorded beside the store (the next run does not
  train it again) and left out: its forecasts come from the previous refit, or the base flow,
  and the member says so (``fallbacks``).
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Generic, Protocol, TypeVar

import numpy as np
import pandas as pd
import torch

from pipeline.errors import CheckpointError, TrainingDivergedError
from pipeline.members.nf.flow import CHECKPOINT_NAME, RealWindows
from pipeline.models.estimator import ConditionalEstimator, EstimatorConfig
from pipeline.panels.targets import DAYS_PER_WEEK
from pipeline.progress import ProgressReporter, SilentProgress
from pipeline.training.checkpoints import load_checkpoint, save_checkpoint
from pipeline.training.datasets import WindowedDataset, validation_trajectories, with_data_hash
from pipeline.training.digests import DataDigests, Digests
from pipeline.training.model_store import ModelStore, StoreEntry
from pipeline.training.trainer import TrainConfig, train

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------- calendar

REFIT_EPOCH = pd.Timestamp("2020-01-04")


def refit_dates(origins: Sequence[pd.Timestamp], every_weeks: int) -> list[pd.Timestamp]:
    """The origins that fall on the refit calendar (every ``every_weeks`` weeks from
    :data:`REFIT_EPOCH`): the days the member is refitted."""
    return [o for o in origins
            if (o - REFIT_EPOCH).days % (DAYS_PER_WEEK * every_weeks) == 0]


def latest_refit_date(origin: pd.Timestamp, every_weeks: int) -> pd.Timestamp:
    """The last day of the refit calendar on or before ``origin``: the refit whose model a
    forecast at ``origin`` uses."""
    origin = pd.Timestamp(origin).normalize()
    return origin - pd.Timedelta(days=(origin - REFIT_EPOCH).days % (DAYS_PER_WEEK * every_weeks))


def refit_for(dates: Iterable[pd.Timestamp], origin: pd.Timestamp) -> pd.Timestamp | None:
    """The latest of the refit ``dates`` on or before ``origin`` (None: before the first)."""
    earlier = [r for r in dates if r <= origin]
    return max(earlier) if earlier else None


# ----------------------------------------------------------------------------------- windows


class RefitSettings(Protocol):
    """What a member's refit settings give the refit path: the windows' cutoff and mix, the
    least windows worth a refit, the seed, an identity (part of the store keys) and the
    trainer's settings."""

    @property
    def revision_days(self) -> int: ...

    @property
    def synthetic_share(self) -> float: ...

    @property
    def val_fraction(self) -> float: ...

    @property
    def min_windows(self) -> int: ...

    @property
    def seed(self) -> int: ...

    def identity(self) -> dict[str, object]: ...

    def train_config(self) -> TrainConfig: ...


def real_dataset(real: RealWindows, like: WindowedDataset, name: str) -> WindowedDataset:
    """Real windows in the synthetic dataset's standardization and metadata (the refitted flow
    is the same model)."""
    return with_data_hash(WindowedDataset(
        torch.from_numpy(np.ascontiguousarray(real.context)),
        torch.from_numpy(np.ascontiguousarray(real.mask)),
        torch.from_numpy(np.ascontiguousarray(real.target)), torch.from_numpy(real.place),
        torch.zeros(len(real.place), dtype=torch.float64), like.stats,
        dataclasses.replace(like.meta, config_name=name)))


def mixed_windows(real: RealWindows, synthetic: WindowedDataset, settings: RefitSettings
                  ) -> tuple[WindowedDataset, WindowedDataset] | None:
    """(train, validation): the training places' real windows mixed with synthetic ones
    (``synthetic_share`` of the whole), and the held-out places' real windows; None when the
    real windows are fewer than ``min_windows`` or come from one place."""
    if len(real.place) < settings.min_windows or len(np.unique(real.place)) < 2:
        return None
    held = validation_trajectories(torch.from_numpy(real.place), settings.val_fraction,
                                   settings.seed).numpy()
    is_val = np.isin(real.place, held)
    n_train = int((~is_val).sum())
    n_synth = int(round(n_train * settings.synthetic_share / (1 - settings.synthetic_share)))
    pick = torch.from_numpy(np.random.default_rng(settings.seed).choice(
        len(synthetic), min(n_synth, len(synthetic)), replace=False))
    offset = int(real.place.max()) + 1
    mixed = RealWindows(
        np.concatenate([real.context[~is_val], synthetic.context[pick].numpy()]),
        np.concatenate([real.mask[~is_val], synthetic.mask[pick].numpy()]),
        np.concatenate([real.target[~is_val], synthetic.target[pick].numpy()]),
        np.concatenate([real.place[~is_val], offset + np.arange(len(pick))]))
    validation = RealWindows(real.context[is_val], real.mask[is_val], real.target[is_val],
                             real.place[is_val])
    return (real_dataset(mixed, synthetic, "real+synthetic"),
            real_dataset(validation, synthetic, "real"))


def _digests(windows: tuple[WindowedDataset, WindowedDataset] | None) -> Digests:
    if windows is None:
        return {"skipped": "too few real windows"}
    train_ds, val_ds = windows
    return {"train_sha256": train_ds.meta.data_sha256,
            "validation_sha256": val_ds.meta.data_sha256}


# ----------------------------------------------------------------------------------- a refit


def refit_copy(base: ConditionalEstimator, train_ds: WindowedDataset, val_ds: WindowedDataset,
               config: TrainConfig) -> ConditionalEstimator:
    """A copy of ``base`` trained further on the refit's windows (best validation state)."""
    model = copy.deepcopy(base)
    model.train()
    train(model, train_ds, val_ds, config)
    model.eval()
    return model


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


def estimator_of(refit: Refit) -> ConditionalEstimator:
    return refit.estimator if isinstance(refit, StoredRefit) else refit


@dataclass(frozen=True)
class RefitJob:
    """One refit to fetch or train: its ``label`` (the member's name for its refits), what its
    windows are cut from (``windows_key``: the digests' key) and the member's identity of the
    refit (``identity``: the store key, beside the windows' hashes)."""

    label: str
    date: pd.Timestamp
    windows_key: tuple[object, ...]
    identity: Mapping[str, object]


def stored_refit(job: RefitJob, base: ConditionalEstimator, expected: EstimatorConfig,
                 windows: Callable[[], tuple[WindowedDataset, WindowedDataset] | None],
                 settings: RefitSettings, store_root: Path) -> StoredRefit | None:
    """The refit of ``job`` from the model store, trained first if absent (``windows``: its
    (train, validation) windows, cut only then); None when the windows are too few. A
    divergence is recorded beside the store and raised (:class:`TrainingDivergedError`) on
    every run after, without training again."""
    digests = DataDigests(store_root)
    hashes = digests.get_or_compute(job.windows_key, lambda: _digests(windows()))
    if "skipped" in hashes:
        return None

    def build(out_dir: Path) -> dict[str, object]:
        cut = windows()
        if cut is None or _digests(cut) != hashes:
            raise CheckpointError(f"the {job.label} refit windows of {job.date.date()} do not "
                                  f"match their recorded digests in {store_root}")
        model = refit_copy(base, *cut, settings.train_config())
        save_checkpoint(out_dir / CHECKPOINT_NAME, model, config=expected, stats=model.stats,
                        data_sha256=hashes["train_sha256"], extra={"kind": job.label})
        return {}

    key = {**job.identity, "validation_sha256": hashes["validation_sha256"]}
    store = ModelStore(store_root)

    def attempt() -> Digests:
        """Train the refit into the store once; a divergence is an outcome kept beside it."""
        try:
            store.get_or_build(key, hashes["train_sha256"], build)
        except TrainingDivergedError as error:
            return {"diverged": str(error)}
        return {"trained": hashes["train_sha256"]}

    outcome = digests.get_or_compute((f"{job.label} outcome", *job.windows_key), attempt)
    if "diverged" in outcome:
        raise TrainingDivergedError(outcome["diverged"])
    return StoredRefit.of(store.get_or_build(key, hashes["train_sha256"], build), expected)


# -------------------------------------------------------------------------------- the dates

M = TypeVar("M")


@dataclass(frozen=True)
class Refits(Generic[M]):
    """The refits made on a calendar: ``models`` by date, and the dates whose refit diverged
    (``diverged``: why)."""

    models: dict[pd.Timestamp, M]
    diverged: dict[pd.Timestamp, str] = field(default_factory=dict)

    @property
    def fallbacks(self) -> dict[pd.Timestamp, str]:
        """Each diverged date, why, and what its forecasts use instead."""
        return fallbacks_of(self.models, self.diverged)


def refit_each(dates: Sequence[pd.Timestamp], fit: Callable[[pd.Timestamp], M | None], *,
               name: str, newest_first: bool = False,
               progress: ProgressReporter | None = None) -> Refits[M]:
    """``fit(date)`` at every refit date (None: no refit then). ``newest_first``: the latest
    date first (a second process filling the same store from the other end,
    :mod:`pipeline.training.background`); the models are the same either way. A date whose
    refit diverges is left out and recorded with what its forecasts use instead."""
    progress = progress or SilentProgress()
    models: dict[pd.Timestamp, M] = {}
    diverged: dict[pd.Timestamp, str] = {}
    for date in (sorted(dates, reverse=True) if newest_first else dates):
        try:
            made = fit(date)
        except TrainingDivergedError as error:
            log.warning("%s refit %s diverged; its forecasts use the one before: %s", name,
                        date.date(), error)
            diverged[date] = str(error)
            continue
        if made is not None:
            models[date] = made
            progress.advance(1, refit=str(date.date()))
    return Refits(models, diverged)


def fallbacks_of(models: Mapping[pd.Timestamp, object], diverged: Mapping[pd.Timestamp, str]
                 ) -> dict[pd.Timestamp, str]:
    """Each diverged date's reason and the refit its forecasts use instead."""
    def previous(date: pd.Timestamp) -> str:
        earlier = [d for d in models if d < date]
        return f"the refit of {max(earlier).date()}" if earlier else "the base flow"

    return {date: f"{why}; forecasts from {previous(date)} instead"
            for date, why in sorted(diverged.items())}
