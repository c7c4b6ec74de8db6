"""Train one preset: build its estimator, train it, write its checkpoint. The one way to do it.

``flowcast train``, the paper tables (:mod:`pipeline.paper`) and the weekly forecast all train
through :func:`fit_preset`, so every checkpoint carries the same metadata in ``meta.extra``:

* ``preset``: the whole :class:`~pipeline.training.presets.TrainingPreset` as plain data (what
  ``flowcast estimate`` / ``rollout`` read: dataset, direction, window),
* ``direction``: the preset's direction (the weekly forecast checks it to catch a swapped
  forward/backward pair), ``training_preset``: the preset's ``run_name``,
* what :func:`~pipeline.training.trainer.train_and_save` records (train config, kinetic weights,
  best validation NLL, stop reason), plus the caller's ``extra``.

The estimator's initial weights come from ``preset.train.seed`` (as do the batches and the context
noise), so a preset and its data fully determine the checkpoint.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from pipeline.models.estimator import build_estimator
from pipeline.progress import ProgressReporter
from pipeline.training.datasets import WindowedDataset
from pipeline.training.presets import TrainingPreset
from pipeline.training.trainer import TrainResult, train_and_save


def fit_preset(preset: TrainingPreset, train_ds: WindowedDataset, val_ds: WindowedDataset,
               out_dir: Path, *, progress: ProgressReporter | None = None,
               extra: Mapping[str, object] | None = None) -> TrainResult:
    """Train ``preset`` on ``train_ds`` (validated on ``val_ds``) and write ``model.pt``,
    ``history.csv/json`` and ``loss.png`` to ``out_dir`` (nothing is written if training
    diverges). ``train_ds`` must be split with ``preset.estimator.target_transform``
    (:func:`~pipeline.training.datasets.train_validation_split`).

    Returns the training result; the trained estimator is the checkpoint
    (``load_checkpoint(out_dir / "model.pt")`` rebuilds it bit for bit). The preset's entries
    of the metadata (module doc) win over the caller's ``extra``: a checkpoint must not claim
    another direction than the one it was trained for."""
    estimator = build_estimator(preset.estimator, train_ds.stats, seed=preset.train.seed)
    metadata = {**dict(extra or {}), "direction": preset.dataset.direction,
                "training_preset": preset.run_name, "preset": preset.to_dict()}
    return train_and_save(estimator, train_ds, val_ds, preset.train, preset.kinetic, out_dir,
                          estimator_config=preset.estimator, progress=progress, extra=metadata)
