"""The models the tables need: the ``fast`` presets under a per-model wall-clock budget, trained
once through :func:`pipeline.training.fit.fit_preset` and cached as checkpoints under
``Locations.work``, keyed by model and budget (a re-run with the same budgets only loads them)."""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import torch
from torch import Tensor

from pipeline.inference.estimate import assemble_context, draw_noise, uses_absolute_time
from pipeline.models.estimator import ConditionalEstimator
from pipeline.paper.config import ENCODERS, BenchConfig, Locations
from pipeline.training.presets import TrainingPreset
from pipeline.names import DIRECTIONS


class RequiredModel(NamedTuple):
    """One model of the tables; ``dataset`` overrides the preset's data (Table 1)."""

    preset: str
    encoder: str
    direction: str
    dataset: str | None = None


def required_models() -> list[RequiredModel]:
    """Every model the tables need, in run order."""
    models = [RequiredModel("vehicle", "transformer", "forward", "vehicle-full")]
    models += [RequiredModel("vehicle", e, d) for d in DIRECTIONS for e in ENCODERS]
    models += [RequiredModel(p, e, d) for p in ("sir-single", "sir-multi")
               for d in DIRECTIONS for e in ENCODERS]
    return models


def training_budget(preset_name: str, cfg: BenchConfig) -> float:
    if preset_name.startswith("vehicle") and cfg.vehicle_train_budget_s is not None:
        return cfg.vehicle_train_budget_s
    return cfg.train_budget_s


def bench_preset(model: RequiredModel, cfg: BenchConfig) -> TrainingPreset:
    """The ``fast`` preset of ``model`` with the run's data size, time budget and threads."""
    from pipeline.training.presets import get_preset

    preset = get_preset(model.preset, model.encoder, recipe="fast", direction=model.direction,
                        seed=cfg.seed)
    dataset = preset.dataset
    if model.dataset is not None:
        dataset = dataclasses.replace(dataset, name=model.dataset)
    if cfg.n_trajectories is not None:
        dataset = dataclasses.replace(dataset, n_trajectories=cfg.n_trajectories[dataset.name])
    train = dataclasses.replace(preset.train, time_budget_s=training_budget(model.preset, cfg),
                                num_threads=torch.get_num_threads())
    if cfg.train_iterations is not None:
        train = dataclasses.replace(train, iterations=cfg.train_iterations, eval_every=10)
    return dataclasses.replace(preset, dataset=dataset, train=train)


def trained_estimator(model: RequiredModel, cfg: BenchConfig,
                      locations: Locations) -> ConditionalEstimator:
    """Load the cached checkpoint, or train it (fast recipe, time budget) and cache it."""
    from pipeline.errors import CheckpointError
    from pipeline.training.checkpoints import load_checkpoint
    from pipeline.training.datasets import build_dataset_from_config, train_validation_split
    from pipeline.training.fit import fit_preset

    preset = bench_preset(model, cfg)
    budget = training_budget(model.preset, cfg)
    run_dir = (locations.work / ("quick" if cfg.quick else "full")
               / f"{preset.dataset.name}-{preset.run_name}-{budget:g}s")
    checkpoint = run_dir / "model.pt"
    if checkpoint.is_file():
        try:
            return load_checkpoint(checkpoint, expected_config=preset.estimator).estimator
        except CheckpointError as exc:  # e.g. trained before the vehicle's t_obs channel
            print(f"  stale checkpoint, retraining: {exc}", flush=True)
    print(f"  training {run_dir.name} ...", flush=True)
    train_ds, val_ds = train_validation_split(build_dataset_from_config(preset.dataset),
                                              preset.estimator.target_transform)
    fit_preset(preset, train_ds, val_ds, run_dir)
    # The checkpoint is the trained model bit for bit; reading it back gives a fresh run the
    # same estimator a cached run gets.
    return load_checkpoint(checkpoint, expected_config=preset.estimator).estimator


@torch.no_grad()
def model_samples(estimator: ConditionalEstimator, values: Tensor, times: Tensor, target: Tensor,
                  n: int, seed: int) -> Tensor:
    """(B, n, D) draws for B windows (values (B,R,C), absolute times (B,R), target (B,))."""
    mask = torch.ones(times.shape, dtype=torch.bool)
    context = assemble_context(values.double(), times.double(), mask, target.double(),
                               uses_absolute_time(estimator))
    eps = draw_noise((len(target), n, estimator.features), seed)
    return estimator.noise_to_data(eps, context, mask).double()


def _train_one(job: tuple[RequiredModel, BenchConfig, Locations, int]) -> str:
    model, cfg, locations, threads = job
    torch.set_num_threads(threads)
    trained_estimator(model, cfg, locations)
    return f"{model.preset}/{model.dataset or ''}/{model.encoder}/{model.direction}"


def pretrain(cfg: BenchConfig, locations: Locations, jobs: int, threads_per_job: int = 1,
             systems: tuple[str, ...] = ("vehicle", "sir")) -> None:
    """Train the models the tables need (those of ``systems``), ``jobs`` at a time in separate
    processes of ``threads_per_job`` threads; cached ones load instantly, so the table run that
    follows only evaluates."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    models = [m for m in required_models() if m.preset.split("-")[0] in systems]
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
        futures = [pool.submit(_train_one, (m, cfg, locations, threads_per_job)) for m in models]
        for future in as_completed(futures):
            print(f"  ready: {future.result()}", flush=True)
