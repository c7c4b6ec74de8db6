"""Training loop for conditional estimators: Adam, LR schedules, validation, best state, stop rules.

Reading of the paper (section "Training"): Adam, 10,000 iterations, batch 2,048, constant
learning rate 1e-3, maximum likelihood (plus the optional kinetic terms), Gaussian noise added to
the context windows (sigma = 1.0 vehicle, 0.01 SIR). The paper says nothing about validation
frequency, clipping or stopping; those are ours:

* An *iteration* is one Adam step on a batch drawn **with replacement** from the training split
  by a ``torch.Generator`` seeded from ``TrainConfig.seed`` (the paper trains by iterations, not
  epochs, so sampling with replacement is the natural reading).
* Every ``eval_every`` iterations (and after the last) the negative log-likelihood is computed on
  a fixed validation subset (drawn once from the seed), both in standardized units (what the loss
  optimizes) and in original units (``NLL_orig = NLL_std + sum(log target_std)``, the change of
  variables of the per-dimension affine standardization, minus the mean log|det du/dy| of the
  validation targets when the model has a target transform).
* The state with the lowest validation NLL is kept in memory, returned, and loaded into the
  estimator at the end; nothing is written here (see :func:`train_and_save`).
* A non-finite loss or gradient norm, a non-finite validation NLL, or a validation NLL that stays
  ``divergence_margin`` nats above the best for ``divergence_patience`` evaluations stops the run
  with :class:`~pipeline.errors.TrainingDivergedError` naming the iteration and the value.
* Gradients are clipped to ``grad_clip_norm`` (global L2 norm). At norm 10 this never binds in
  a healthy run of our models (measured norms are O(1)) and only caps rare spikes.

Reproducibility: the batch indices, the context noise and the validation subset come from
generators seeded by ``TrainConfig.seed``; any incidental use of the global RNG inside the model
(e.g. dropout) runs inside ``torch.random.fork_rng`` seeded from the same seed, so the caller's
global RNG state is untouched. On CPU with a fixed thread count the same seed then gives the
identical history and weights (tested). ``torch.use_deterministic_algorithms`` is not switched
on: it is process-global state, and the CPU kernels these models use (linear, attention,
scan, Adam) are already deterministic; on GPU a caller wanting bit-exact runs must set it.
"""
from __future__ import annotations

import contextlib
import copy
import csv
import dataclasses
import io
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor, nn

from pipeline.errors import ConfigError, TrainingDivergedError
from pipeline.io import atomic_open, atomic_write_json, atomic_write_text
from pipeline.models.estimator import ConditionalEstimator, EstimatorConfig, add_context_noise
from pipeline.progress import ProgressReporter, SilentProgress
from pipeline.models.standardization import Standardization
from pipeline.training.datasets import WindowedDataset
from pipeline.training.kinetic import KineticWeights, kinetic_loss

Schedule = Literal["constant", "cosine", "onecycle"]
StopReason = Literal["completed", "target_reached", "time_budget", "plateau"]

# Validation NLL is evaluated in chunks of this many windows to bound the encoder's memory.
_EVAL_CHUNK = 8192


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings. Defaults are the paper's recipe (constant lr 1e-3, batch 2048).

    ``schedule``: ``constant`` (paper); ``cosine`` = linear warm-up over ``warmup_fraction`` of the
    iterations to ``lr`` then cosine decay to ``final_lr_fraction * lr``; ``onecycle`` = PyTorch's
    OneCycleLR (cosine up over ``warmup_fraction``, cosine down to ``lr * final_lr_fraction``).
    ``early_stop_patience``: stop after that many evaluations without a validation improvement of
    at least ``early_stop_min_delta`` nats (None = never). ``target_val_nll`` (standardized units)
    and ``time_budget_s`` stop early too (used by the time-to-accuracy benchmark). A time budget
    also compresses a decaying schedule: its progress is the larger of the iteration and the
    elapsed-time fractions, so a run cut by the clock ends annealed instead of mid-decay.
    ``num_threads``: torch intra-op threads during training (None = leave as is).
    """

    iterations: int = 10_000
    batch_size: int = 2048
    lr: float = 1e-3
    schedule: Schedule = "constant"
    warmup_fraction: float = 0.05
    final_lr_fraction: float = 0.01
    grad_clip_norm: float | None = 10.0
    eval_every: int = 100
    val_subset_size: int = 8192
    context_noise_sigma: float = 0.0
    seed: int = 0
    early_stop_patience: int | None = None
    early_stop_min_delta: float = 1e-3
    target_val_nll: float | None = None
    time_budget_s: float | None = None
    divergence_margin: float = 10.0
    divergence_patience: int = 3
    num_threads: int | None = None

    def __post_init__(self) -> None:
        positive = {"iterations": self.iterations, "batch_size": self.batch_size, "lr": self.lr,
                    "eval_every": self.eval_every, "val_subset_size": self.val_subset_size,
                    "divergence_margin": self.divergence_margin,
                    "divergence_patience": self.divergence_patience}
        for name, value in positive.items():
            if not value > 0:
                raise ConfigError(f"TrainConfig.{name}={value!r} must be > 0")
        if self.schedule not in ("constant", "cosine", "onecycle"):
            raise ConfigError(f"TrainConfig.schedule={self.schedule!r}: expected 'constant', "
                              "'cosine' or 'onecycle'")
        if not 0.0 <= self.warmup_fraction < 1.0:
            raise ConfigError(f"TrainConfig.warmup_fraction={self.warmup_fraction} not in [0, 1)")
        if not 0.0 < self.final_lr_fraction <= 1.0:
            raise ConfigError(f"TrainConfig.final_lr_fraction={self.final_lr_fraction} "
                              "not in (0, 1]")
        if self.context_noise_sigma < 0:
            raise ConfigError(f"TrainConfig.context_noise_sigma={self.context_noise_sigma} < 0")
        if self.grad_clip_norm is not None and self.grad_clip_norm <= 0:
            raise ConfigError(f"TrainConfig.grad_clip_norm={self.grad_clip_norm} must be > 0")
        if self.early_stop_patience is not None and self.early_stop_patience < 1:
            raise ConfigError(f"TrainConfig.early_stop_patience={self.early_stop_patience} < 1")
        if self.time_budget_s is not None and self.time_budget_s <= 0:
            raise ConfigError(f"TrainConfig.time_budget_s={self.time_budget_s} must be > 0")
        if self.num_threads is not None and self.num_threads < 1:
            raise ConfigError(f"TrainConfig.num_threads={self.num_threads} < 1")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ConfigError(f"unknown TrainConfig fields: {sorted(unknown)}")
        return cls(**data)


@dataclass(frozen=True)
class EvalRecord:
    """One validation point: the mean training loss since the previous point, the validation NLL
    (standardized and original units), the learning rate, and the wall-clock since the start."""

    iteration: int
    wall_s: float
    train_loss: float
    val_nll: float
    val_nll_original: float
    lr: float


@dataclass
class TrainResult:
    history: list[EvalRecord]
    best_val_nll: float
    best_val_nll_original: float
    best_iteration: int
    best_state: dict[str, Tensor]
    stop_reason: StopReason
    iterations_run: int
    wall_s: float
    config: TrainConfig = field(repr=False)

    def history_dicts(self) -> list[dict[str, float]]:
        return [asdict(r) for r in self.history]


# ----------------------------------------------------------------------------- learning rate


def lr_factor(config: TrainConfig, iteration: int, elapsed_s: float = 0.0) -> float:
    """Multiplier of ``config.lr`` for the step taken at 0-based ``iteration``, ``elapsed_s``
    seconds into a run (only read under a time budget)."""
    if config.schedule == "constant":
        return 1.0
    warmup = max(1, round(config.warmup_fraction * config.iterations))
    floor = config.final_lr_fraction
    if config.schedule == "onecycle":
        # Like torch's OneCycleLR with anneal 'cos': start at lr/25, cosine up, cosine down.
        start = 1.0 / 25.0
        if iteration < warmup:
            return start + (1.0 - start) * 0.5 * (1.0 - math.cos(math.pi * iteration / warmup))
    elif iteration < warmup:  # cosine: linear warm-up from lr/warmup to lr
        return (iteration + 1) / warmup
    progress = (iteration - warmup) / max(1, config.iterations - warmup)
    if config.time_budget_s is not None:
        progress = max(progress, elapsed_s / config.time_budget_s)
    progress = min(1.0, progress)
    return floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * progress))


# ----------------------------------------------------------------------------- data


@dataclass(frozen=True)
class _Tensors:
    context: Tensor  # standardized, (N, R, C)
    mask: Tensor  # (N, R) bool
    target: Tensor  # standardized, (N, D)


def _standardized(ds: WindowedDataset) -> _Tensors:
    """Standardize a dataset once with its own (training-split) statistics; padding rows stay 0."""
    stats = ds.stats
    context = stats.standardize_context(ds.context, ds.mask)
    return _Tensors(context.float().contiguous(), ds.mask.bool().contiguous(),
                    stats.standardize_target(ds.target).float().contiguous())


def _subset(tensors: _Tensors, size: int, generator: torch.Generator) -> _Tensors:
    n = tensors.target.shape[0]
    if n <= size:
        return tensors
    index = torch.randperm(n, generator=generator)[:size].sort().values
    return _Tensors(tensors.context[index], tensors.mask[index], tensors.target[index])


# ----------------------------------------------------------------------------- loss


def _batch_loss(estimator: ConditionalEstimator, target: Tensor, context: Tensor, mask: Tensor,
                kinetic: KineticWeights | None) -> Tensor:
    """Mean training loss of a standardized batch: NLL, plus the kinetic terms when enabled."""
    if kinetic is None or kinetic.is_plain_likelihood and kinetic.nll == 1.0:
        return -estimator.standardized_log_prob(target, context, mask).mean()
    return kinetic_loss(estimator, target, context, mask, kinetic)


@torch.no_grad()
def evaluate_nll(estimator: ConditionalEstimator, context: Tensor, mask: Tensor,
                 target: Tensor) -> float:
    """Mean NLL (standardized units) of standardized (context, mask, target), chunked."""
    was_training = estimator.training
    estimator.eval()
    total = 0.0
    try:
        for start in range(0, target.shape[0], _EVAL_CHUNK):
            stop = start + _EVAL_CHUNK
            lp = estimator.standardized_log_prob(target[start:stop], context[start:stop],
                                                 mask[start:stop])
            total += float(lp.double().sum())
    finally:
        estimator.train(was_training)
    return -total / target.shape[0]


# ----------------------------------------------------------------------------- the loop


@contextlib.contextmanager
def _torch_threads(n: int | None) -> Iterator[None]:
    if n is None:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _check_finite_step(iteration: int, loss: Tensor, grad_norm: Tensor) -> None:
    if not torch.isfinite(loss):
        raise TrainingDivergedError(f"training loss became {float(loss)} at iteration "
                                    f"{iteration}; stopped, nothing saved")
    if not torch.isfinite(grad_norm):
        raise TrainingDivergedError(f"gradient norm became {float(grad_norm)} at iteration "
                                    f"{iteration} (loss {float(loss):.4g}); stopped, nothing saved")


class _DivergenceWatch:
    """Flags a validation NLL that is non-finite, or stays far above the best for a while."""

    def __init__(self, margin: float, patience: int) -> None:
        self.margin, self.patience, self.strikes = margin, patience, 0

    def update(self, iteration: int, val_nll: float, best: float) -> None:
        if not math.isfinite(val_nll):
            raise TrainingDivergedError(f"validation NLL became {val_nll} at iteration "
                                        f"{iteration}; stopped, nothing saved")
        self.strikes = self.strikes + 1 if val_nll > best + self.margin else 0
        if self.strikes >= self.patience:
            raise TrainingDivergedError(
                f"training diverged: validation NLL {val_nll:.4g} at iteration {iteration} is "
                f"more than {self.margin} nats above the best {best:.4g} for {self.strikes} "
                "evaluations in a row; stopped, nothing saved")


def train(estimator: ConditionalEstimator, train_ds: WindowedDataset, val_ds: WindowedDataset,
          config: TrainConfig,
          kinetic: KineticWeights | None = None,
          progress: ProgressReporter | None = None) -> TrainResult:
    """Train ``estimator`` in place on ``train_ds``; return the history and the best state.

    ``train_ds`` / ``val_ds`` are :class:`pipeline.training.datasets.WindowedDataset` sharing the
    training-split standardization (``val_ds.stats`` is ignored: ``train_ds.stats`` is used
    for both). ``estimator`` must expose ``standardized_log_prob(target, context, mask)`` on
    standardized tensors. ``kinetic`` (:class:`pipeline.training.kinetic.KineticWeights`) adds the
    kinetic terms when its lambda_2 or lambda_3 is positive. At return the estimator holds the
    best state (lowest validation NLL) and is in eval mode.
    """
    progress = progress or SilentProgress()
    stats = train_ds.stats
    train_t = _standardized(train_ds)
    val_t = _standardized(_with_stats(val_ds, stats))
    if train_t.target.shape[0] == 0 or val_t.target.shape[0] == 0:
        raise ConfigError(f"empty split: {train_t.target.shape[0]} training and "
                          f"{val_t.target.shape[0]} validation windows")
    batch_gen = torch.Generator().manual_seed(config.seed)
    val_t = _subset(val_t, config.val_subset_size, torch.Generator().manual_seed(config.seed + 1))
    log_target_scale = _original_nll_offset(stats, val_t.target)

    with _torch_threads(config.num_threads), torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        return _run(estimator, train_t, val_t, stats, log_target_scale, batch_gen, config,
                    kinetic, progress)


def _original_nll_offset(stats: Standardization, standardized_target: Tensor) -> float:
    """NLL in original units minus NLL in standardized units on the validation targets:
    sum(log target_std) for the affine standardization; under a target transform (e.g. the SIR
    log-ratio) also minus the mean log|det du/dy| of the targets, which varies with y."""
    offset = float(torch.log(stats.target_std.double()).sum())
    if stats.target_transform == "identity":
        return offset
    targets = stats.unstandardize_target(standardized_target.double())
    return offset - float(stats.transform.log_abs_det(targets).mean())


def _with_stats(ds: WindowedDataset, stats: Standardization) -> WindowedDataset:
    return dataclasses.replace(ds, stats=stats)


def _run(estimator: ConditionalEstimator, train_t: _Tensors, val_t: _Tensors,
         stats: Standardization, log_target_scale: float, batch_gen: torch.Generator,
         config: TrainConfig, kinetic: KineticWeights | None,
         progress: ProgressReporter) -> TrainResult:
    optimizer = torch.optim.Adam(estimator.parameters(), lr=config.lr)
    n_train = train_t.target.shape[0]
    history: list[EvalRecord] = []
    best_nll, best_iter, best_state = math.inf, 0, _copy_state(estimator)
    watch = _DivergenceWatch(config.divergence_margin, config.divergence_patience)
    since_improvement, loss_sum, loss_count = 0, 0.0, 0
    stop_reason: StopReason = "completed"
    estimator.train()
    # getattr: wrappers exposing only standardized_log_prob (tests) train as relative-time models
    time_channels = 2 if getattr(estimator, "absolute_time", False) else 1
    start = time.perf_counter()
    iteration = 0
    for iteration in range(1, config.iterations + 1):
        index = torch.randint(0, n_train, (config.batch_size,), generator=batch_gen)
        context, mask = train_t.context[index], train_t.mask[index]
        if config.context_noise_sigma > 0:
            # The paper's sigma is in data units; the context is standardized already.
            context = add_context_noise(context, mask, config.context_noise_sigma, batch_gen,
                                        channel_std=stats.context_std,
                                        time_channels=time_channels)
        lr_now = config.lr * lr_factor(config, iteration - 1, time.perf_counter() - start)
        for group in optimizer.param_groups:
            group["lr"] = lr_now
        loss = _batch_loss(estimator, train_t.target[index], context, mask, kinetic)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = _grad_norm(estimator, config.grad_clip_norm)
        _check_finite_step(iteration, loss.detach(), grad_norm)
        optimizer.step()
        loss_value = float(loss.detach())
        loss_sum, loss_count = loss_sum + loss_value, loss_count + 1
        if iteration % config.eval_every and iteration != config.iterations:
            progress.advance(1, loss=loss_value)
            continue

        val_nll = evaluate_nll(estimator, val_t.context, val_t.mask, val_t.target)
        watch.update(iteration, val_nll, best_nll)
        history.append(EvalRecord(iteration, time.perf_counter() - start, loss_sum / loss_count,
                                  val_nll, val_nll + log_target_scale, lr_now))
        loss_sum, loss_count = 0.0, 0
        progress.advance(1, loss=loss_value, val=val_nll)
        if val_nll < best_nll - config.early_stop_min_delta:
            since_improvement = 0
        else:
            since_improvement += 1
        if val_nll < best_nll:
            best_nll, best_iter, best_state = val_nll, iteration, _copy_state(estimator)
        stop = _stop_reason(config, best_nll, since_improvement, time.perf_counter() - start)
        if stop is not None:
            stop_reason = stop
            break
    wall = time.perf_counter() - start
    estimator.load_state_dict(best_state)
    estimator.eval()  # as a loaded checkpoint is: ready for estimation
    return TrainResult(history=history, best_val_nll=best_nll,
                       best_val_nll_original=best_nll + log_target_scale, best_iteration=best_iter,
                       best_state=best_state, stop_reason=stop_reason, iterations_run=iteration,
                       wall_s=wall, config=config)


def _grad_norm(estimator: nn.Module, clip: float | None) -> Tensor:
    params = [p for p in estimator.parameters() if p.grad is not None]
    if clip is not None:
        return nn.utils.clip_grad_norm_(params, clip)
    return torch.linalg.vector_norm(torch.stack([g.norm() for p in params
                                                 if (g := p.grad) is not None]))


def _stop_reason(config: TrainConfig, best_nll: float, since_improvement: int,
                 elapsed: float) -> StopReason | None:
    if config.target_val_nll is not None and best_nll <= config.target_val_nll:
        return "target_reached"
    if config.time_budget_s is not None and elapsed >= config.time_budget_s:
        return "time_budget"
    if config.early_stop_patience is not None and since_improvement >= config.early_stop_patience:
        return "plateau"
    return None


def _copy_state(module: nn.Module) -> dict[str, Tensor]:
    return {k: v.detach().clone() for k, v in copy.copy(module.state_dict()).items()}


# ----------------------------------------------------------------------------- outputs


_HISTORY_FIELDS = tuple(f.name for f in fields(EvalRecord))


def history_to_csv(history: Sequence[EvalRecord]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(_HISTORY_FIELDS)
    for record in history:
        writer.writerow([repr(getattr(record, name)) for name in _HISTORY_FIELDS])
    return buffer.getvalue()


def history_from_csv(text: str) -> list[EvalRecord]:
    rows = list(csv.DictReader(io.StringIO(text)))
    return [EvalRecord(iteration=int(r["iteration"]),
                       **{k: float(r[k]) for k in _HISTORY_FIELDS if k != "iteration"})
            for r in rows]


def save_history(history: Sequence[EvalRecord], csv_path: str | Path,
                 json_path: str | Path | None = None) -> None:
    """Write the history as CSV (one row per evaluation) and, optionally, JSON (atomic)."""
    atomic_write_text(csv_path, history_to_csv(history))
    if json_path is not None:
        atomic_write_json(json_path, [asdict(r) for r in history])


def plot_loss_curves(history: Sequence[EvalRecord], path: str | Path,
                     title: str = "training and validation loss") -> None:
    """PNG of training loss and validation NLL (standardized units) against iteration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    iterations = [r.iteration for r in history]
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=120)
    ax.plot(iterations, [r.train_loss for r in history],
            label="training loss (mean since last eval)")
    ax.plot(iterations, [r.val_nll for r in history], label="validation NLL")
    if history:
        best = min(history, key=lambda r: r.val_nll)
        ax.scatter([best.iteration], [best.val_nll], color="black", zorder=3,
                   label=f"best {best.val_nll:.3f} @ {best.iteration}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("NLL (standardized units, nats)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_open(path, "wb") as handle:
        fig.savefig(handle, format="png")
    plt.close(fig)


def train_and_save(estimator: ConditionalEstimator, train_ds: WindowedDataset,
                   val_ds: WindowedDataset, config: TrainConfig, kinetic: KineticWeights | None,
                   out_dir: str | Path, *, estimator_config: EstimatorConfig,
                   extra: Mapping[str, object] | None = None,
                   progress: ProgressReporter | None = None,
                   on_trained: Callable[[TrainResult], None] | None = None) -> TrainResult:
    """Train, then (only on success) write ``model.pt``, ``history.csv/json``, ``loss.png``.

    ``extra`` is recorded beside the training's own metadata; presets are trained through
    :func:`pipeline.training.fit.fit_preset`, which records the preset there as
    ``extra["preset"]`` (what ``flowcast estimate``/``rollout`` read: dataset, direction,
    window) with the rest of the metadata every flowcast checkpoint carries.

    A :class:`TrainingDivergedError` propagates before anything is written, so a diverged run
    never leaves a checkpoint behind (nor replaces a previous good one).
    """
    from pipeline.training.checkpoints import save_checkpoint

    result = train(estimator, train_ds, val_ds, config, kinetic, progress)
    if on_trained is not None:
        on_trained(result)
    out = Path(out_dir)
    save_checkpoint(out / "model.pt", estimator, config=estimator_config, stats=train_ds.stats,
                    history=result.history_dicts(), data_sha256=train_ds.meta.data_sha256,
                    extra={"train_config": config.to_dict(),
                           "kinetic": asdict(kinetic) if kinetic is not None else None,
                           "best_val_nll": result.best_val_nll,
                           "best_val_nll_original": result.best_val_nll_original,
                           "best_iteration": result.best_iteration,
                           "stop_reason": result.stop_reason, **(extra or {})})
    save_history(result.history, out / "history.csv", out / "history.json")
    plot_loss_curves(result.history, out / "loss.png")
    return result
