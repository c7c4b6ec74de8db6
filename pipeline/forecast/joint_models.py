"""Steps 2–3: a synthetic ensemble of the multi-wave prior — the published forecast's flow member
trains on the same prior (:mod:`pipeline.systems.waves`) — seen through the S/I/R conversion and
cut into forward and backward windows whose target is the joint (S, I, R, β); γ = 1/L is fixed
by the conversion's window. Then the pair of joint estimators trained on it, or reused from the
model store (:mod:`pipeline.training.model_store`, key = training config + training-data hash).
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from pipeline.errors import CheckpointError
from pipeline.forecast.config import ForecastConfig
from pipeline.forecast.results import TrainedModels, TrainingData
from pipeline.io import sha256_bytes
from pipeline.models.estimator import ConditionalEstimator
from pipeline.names import DIRECTIONS, Direction
from pipeline.progress import ProgressReporter
from pipeline.systems.waves import simulate_waves
from pipeline.training.checkpoints import LoadedCheckpoint, load_checkpoint
from pipeline.training.datasets import (WindowedDataset, train_validation_split,
                                        windows_from_waves)
from pipeline.training.fit import fit_preset
from pipeline.training.model_store import ModelStore, StoreEntry, model_key
from pipeline.training.presets import ENCODER_CHOICES

log = logging.getLogger(__name__)


# Bump when the windows cut from an ensemble change: the data part of the model-store key is the
# ensemble's hash with this tag (the windows are a deterministic function of both).
WINDOWS_VERSION = "sf-waves-windows-1"


def simulate_training_data(config: ForecastConfig,
                           progress: ProgressReporter | None = None) -> TrainingData:
    """One synthetic ensemble of the flow member's prior (the preset's size and seed) and its
    hash. The forward and backward windows are cut from it only when a model is trained
    (:func:`training_windows`): a run that reuses its models skips that work."""
    dataset = config.resolved.presets["forward"].dataset
    ensemble = simulate_waves(config.resolved.prior, dataset.trajectories, seed=dataset.seed)
    if progress is not None:
        progress.advance(1, trajectories=dataset.trajectories)
    digest = sha256_bytes(WINDOWS_VERSION.encode() + ensemble.cases.tobytes()
                          + ensemble.log_beta.tobytes() + ensemble.susceptible.tobytes())
    return TrainingData(ensemble=ensemble, seed=dataset.seed, data_sha256=digest,
                        n_trajectories=dataset.trajectories)


def training_windows(config: ForecastConfig, data: TrainingData, direction: Direction
                     ) -> tuple[WindowedDataset, WindowedDataset]:
    """(train, validation) windows of ``direction``, standardized in the coordinates of the
    model's flow (its target transform)."""
    preset = config.resolved.presets[direction]
    ds = windows_from_waves(data.ensemble, direction=direction, window=preset.dataset.window,
                            val_fraction=preset.dataset.val_fraction, seed=data.seed)
    return train_validation_split(ds, preset.estimator.target_transform)


def train_or_reuse_models(config: ForecastConfig, data: TrainingData, *, retrain: bool = False,
                          store_root: Path | None = None,
                          progress: ProgressReporter | None = None) -> TrainedModels:
    """Forward + backward joint estimators, from the store unless config or data changed."""
    store = ModelStore(store_root or config.store_root)

    def build(out_dir: Path) -> dict[str, object]:
        return {"best_val_nll": {d: _train_direction(config, data, d, out_dir / d, progress)
                                 for d in DIRECTIONS}}

    entry = store.get_or_build(config.training_identity(), data.data_sha256, build,
                               retrain=retrain)
    return load_models(config, entry)


def models_stored(config: ForecastConfig, data: TrainingData,
                  store_root: Path | None = None) -> bool:
    """Whether the store holds a valid pair for ``config`` and ``data`` (nothing to train)."""
    store = ModelStore(store_root or config.store_root)
    return store.get(model_key(config.training_identity(), data.data_sha256)) is not None


def _train_direction(config: ForecastConfig, data: TrainingData, direction: Direction,
                     out_dir: Path, progress: ProgressReporter | None) -> float:
    train_ds, val_ds = training_windows(config, data, direction)
    result = fit_preset(config.resolved.presets[direction], train_ds, val_ds, out_dir,
                        progress=progress, extra={"forecast_preset": config.preset})
    log.info("trained %s model: best validation NLL %.3f at iteration %d (%s)", direction,
             result.best_val_nll_original, result.best_iteration, result.stop_reason)
    return float(result.best_val_nll_original)


def load_models(config: ForecastConfig, entry: StoreEntry) -> TrainedModels:
    """The forward/backward pair of a model-store entry, checked against the presets' configs."""
    loaded = {d: _load_direction(config, entry, d) for d in DIRECTIONS}
    return TrainedModels(
        forward=_estimator(loaded["forward"]), backward=_estimator(loaded["backward"]),
        key=entry.key, reused=entry.reused, path=entry.path,
        histories={d: list(loaded[d].meta.history) for d in DIRECTIONS},
        best_val_nll={d: float(loaded[d].meta.extra.get("best_val_nll_original", float("nan")))
                      for d in DIRECTIONS},
        encoder=config.training.encoder)


def _load_direction(config: ForecastConfig, entry: StoreEntry,
                    direction: Direction) -> LoadedCheckpoint:
    path = entry.path / direction / "model.pt"
    loaded = load_checkpoint(path, expected_config=config.resolved.presets[direction].estimator)
    # Both directions share one architecture, so the config check cannot tell a swapped pair
    # apart; the direction recorded at training time can.
    recorded = loaded.meta.extra.get("direction")
    if recorded is not None and recorded != direction:
        raise CheckpointError(f"{path} is a {recorded} model (checkpoint metadata direction) in "
                              f"the {direction} slot: forward and backward checkpoints swapped; "
                              "retrain (--retrain)")
    if not isinstance(loaded.estimator, ConditionalEstimator):
        raise CheckpointError(f"{path} does not hold a conditional estimator")
    loaded.estimator.eval()
    return loaded


def _estimator(loaded: LoadedCheckpoint) -> ConditionalEstimator:
    assert isinstance(loaded.estimator, ConditionalEstimator)  # checked by _load_direction
    return loaded.estimator


def cached_variant_models(config: ForecastConfig, data: TrainingData, *,
                          store_root: Path | None = None) -> dict[str, TrainedModels]:
    """The other encoder variants (paper Table 5 columns) already in the model store for the
    same preset, recipe and training data — e.g. trained by ``flows.scale_out``. Never trains."""
    store = ModelStore(store_root or config.store_root)
    out = {}
    for encoder in ENCODER_CHOICES:
        if encoder == config.training.encoder:
            continue
        variant = dataclasses.replace(
            config, training=dataclasses.replace(config.training, encoder=encoder))
        entry = store.get(model_key(variant.training_identity(), data.data_sha256))
        if entry is not None:
            out[encoder] = load_models(variant, entry)
    return out
