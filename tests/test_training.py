"""Training loop: known optimum, divergence, determinism, best state, schedules, outputs."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from pipeline.models.standardization import compute_standardization
from pipeline.training.datasets import DatasetMeta, WindowedDataset
from pipeline.errors import TrainingDivergedError
from pipeline.training.kinetic import KineticWeights
from pipeline.models.encoders import EncoderConfig, MLPEncoderConfig
from pipeline.models.estimator import build_estimator, make_estimator_config
from pipeline.training.trainer import (EvalRecord, TrainConfig, _DivergenceWatch, evaluate_nll,
                               history_from_csv, history_to_csv, lr_factor, plot_loss_curves,
                               save_history, train, train_and_save)

SIGMA = 0.5  # noise of the linear-Gaussian toy problem
WINDOW, CHANNELS = 3, 2  # one observed value + the time channel


def _dataset(n: int, seed: int, split: str, stats=None) -> WindowedDataset:
    """y = 2 * mean(window values) - 1 + N(0, SIGMA^2): p(y | window) is Gaussian with a known
    entropy, so the best achievable NLL is 0.5 * log(2 pi e SIGMA^2) in original units."""
    g = torch.Generator().manual_seed(seed)
    values = 3.0 * torch.randn(n, WINDOW, 1, generator=g)
    times = torch.arange(-WINDOW, 0, dtype=torch.float32).expand(n, WINDOW).unsqueeze(-1)
    context = torch.cat([values, times], dim=-1)
    noise = SIGMA * torch.randn(n, 1, generator=g)
    target = 2.0 * values.mean(dim=(1, 2)).unsqueeze(-1) - 1.0 + noise
    mask = torch.ones(n, WINDOW, dtype=torch.bool)
    stats = stats or compute_standardization(context, mask, target)
    meta = DatasetMeta(system="toy", config_name="linear-gaussian", direction="forward",
                       target_kind="state", context_features=("x", "t"), target_features=("y",),
                       window=WINDOW, seed=seed, val_fraction=0.0, split=split, n_trajectories=n,
                       n_observed_points=n * WINDOW, n_observed_values=n * WINDOW, config={},
                       package_version="test", format_version=1, data_sha256=f"toy-{seed}")
    return WindowedDataset(context, mask, target, torch.arange(n),
                           torch.zeros(n, dtype=torch.float64),
                           stats, meta)


@pytest.fixture(scope="module")
def toy():
    train_ds = _dataset(4000, seed=1, split="train")
    val_ds = _dataset(2000, seed=2, split="validation", stats=train_ds.stats)
    return train_ds, val_ds


def _estimator_config():
    encoder = EncoderConfig(kind="mlp", embedding_features=4,
                            mlp=MLPEncoderConfig(hidden_features=16, hidden_layers=1))
    return make_estimator_config(1, CHANNELS, WINDOW, encoder, layers=2, hidden_features=8)


def _estimator(stats, seed: int = 0):
    return build_estimator(_estimator_config(), stats, seed=seed)


def test_reaches_the_gaussian_entropy_of_a_linear_gaussian_problem(toy):
    train_ds, val_ds = toy
    config = TrainConfig(num_threads=1, iterations=300, batch_size=256, lr=1e-2, schedule="cosine",
                         eval_every=50, seed=0)
    estimator = _estimator(train_ds.stats)
    result = train(estimator, train_ds, val_ds, config)
    optimum = 0.5 * math.log(2 * math.pi * math.e * SIGMA**2)  # 0.7258 nats
    assert result.history[0].train_loss > result.history[-1].train_loss + 0.3
    # The validation NLL is a 2000-sample estimate (std ≈ 0.016 nats): 0.05 is ~3 std.
    assert result.best_val_nll_original == pytest.approx(optimum, abs=0.05)
    # Original units = standardized + log(target std) (the affine change of variables).
    shift = float(torch.log(train_ds.stats.target_std).sum())
    assert result.best_val_nll_original == pytest.approx(result.best_val_nll + shift, abs=1e-6)
    # And it agrees with the estimator's own original-unit density on the validation set.
    with torch.no_grad():
        nll = -estimator.log_prob(val_ds.target, val_ds.context, val_ds.mask).double().mean()
    assert float(nll) == pytest.approx(result.best_val_nll_original, abs=1e-4)


def test_best_state_is_the_lowest_validation_point_and_is_loaded(toy):
    train_ds, val_ds = toy
    config = TrainConfig(num_threads=1, iterations=120, batch_size=64, lr=3e-2, eval_every=10,
                         seed=3)
    estimator = _estimator(train_ds.stats)
    result = train(estimator, train_ds, val_ds, config)
    best = min(result.history, key=lambda r: r.val_nll)
    assert result.best_iteration == best.iteration
    assert result.best_val_nll == best.val_nll
    stats = train_ds.stats
    val_nll = evaluate_nll(estimator, stats.standardize_context(val_ds.context, val_ds.mask),
                           val_ds.mask, stats.standardize_target(val_ds.target))
    assert val_nll == pytest.approx(result.best_val_nll, abs=1e-6)
    assert all(torch.equal(v, estimator.state_dict()[k]) for k, v in result.best_state.items())


def test_same_seed_gives_identical_history_and_weights(toy):
    train_ds, val_ds = toy
    config = TrainConfig(num_threads=1, iterations=40, batch_size=64, lr=1e-2, eval_every=10,
                         seed=7,
                         context_noise_sigma=0.3)
    runs = []
    for _ in range(2):
        estimator = _estimator(train_ds.stats, seed=5)
        result = train(estimator, train_ds, val_ds, config)
        runs.append(([(r.iteration, r.train_loss, r.val_nll) for r in result.history],
                     estimator.state_dict()))
    assert runs[0][0] == runs[1][0]
    assert all(torch.equal(runs[0][1][k], runs[1][1][k]) for k in runs[0][1])
    other = train(_estimator(train_ds.stats, seed=5), train_ds, val_ds,
                  dataclasses.replace(config, seed=8))
    assert [(r.train_loss) for r in other.history] != [loss for _, loss, _ in runs[0][0]]


class _NaNAfter(torch.nn.Module):
    """Wraps an estimator; its training log-density turns NaN from the ``k``-th call on."""

    def __init__(self, inner, k: int) -> None:
        super().__init__()
        self.inner, self.k, self.calls = inner, k, 0

    def standardized_log_prob(self, target, context, mask=None):
        out = self.inner.standardized_log_prob(target, context, mask)
        if self.training:
            self.calls += 1
            if self.calls >= self.k:
                return out * float("nan")
        return out


def test_nan_loss_stops_the_run_and_writes_nothing(toy, tmp_path):
    train_ds, val_ds = toy
    config = TrainConfig(num_threads=1, iterations=50, batch_size=32, eval_every=10, seed=0)
    model = _NaNAfter(_estimator(train_ds.stats), k=17)
    out = tmp_path / "run"
    with pytest.raises(TrainingDivergedError, match=r"loss became nan at iteration 17"):
        train_and_save(model, train_ds, val_ds, config, KineticWeights(), out,
                       estimator_config=_estimator_config())
    assert not out.exists() or not any(out.iterdir())


def test_nan_gradient_is_caught(toy):
    train_ds, val_ds = toy
    estimator = _estimator(train_ds.stats)
    first = next(estimator.parameters())
    first.register_hook(lambda grad: grad * float("inf"))
    config = TrainConfig(num_threads=1, iterations=5, batch_size=16, eval_every=5)
    with pytest.raises(TrainingDivergedError,
                       match=r"gradient norm became (nan|inf) at iteration 1"):
        train(estimator, train_ds, val_ds, config)


def test_divergence_watch_needs_a_sustained_rise():
    watch = _DivergenceWatch(margin=2.0, patience=3)
    best = -1.0
    for it, value in enumerate([0.0, 1.5, 5.0, 0.5, 5.0, 6.0], start=1):  # strikes reset at 0.5
        watch.update(it, value, best)
    with pytest.raises(TrainingDivergedError, match=r"validation NLL 7 at iteration 7 .* 3 "
                                                    r"evaluations in a row"):
        watch.update(7, 7.0, best)
    with pytest.raises(TrainingDivergedError, match="validation NLL became inf at iteration 3"):
        _DivergenceWatch(2.0, 3).update(3, math.inf, best)


def test_stop_criteria(toy):
    train_ds, val_ds = toy
    base = TrainConfig(num_threads=1, iterations=200, batch_size=64, lr=1e-2, eval_every=10, seed=0)
    reached = train(_estimator(train_ds.stats), train_ds, val_ds,
                    dataclasses.replace(base, target_val_nll=10.0))
    assert (reached.stop_reason, reached.iterations_run) == ("target_reached", 10)
    plateau = train(_estimator(train_ds.stats), train_ds, val_ds,
                    dataclasses.replace(base, early_stop_patience=2, early_stop_min_delta=100.0))
    assert (plateau.stop_reason, plateau.iterations_run) == ("plateau", 30)
    budget = train(_estimator(train_ds.stats), train_ds, val_ds,
                   dataclasses.replace(base, time_budget_s=1e-9))
    assert (budget.stop_reason, budget.iterations_run) == ("time_budget", 10)


def test_kinetic_terms_enter_the_training_loss(toy):
    train_ds, val_ds = toy
    config = TrainConfig(num_threads=1, iterations=10, batch_size=64, eval_every=10, seed=0)
    plain = train(_estimator(train_ds.stats), train_ds, val_ds, config, KineticWeights())
    ke = train(_estimator(train_ds.stats), train_ds, val_ds, config,
               KineticWeights(path_length=0.5, intermediate_nll=0.1))
    # The kinetic and intermediate-NLL terms are positive here, so the KE loss is larger.
    assert ke.history[0].train_loss > plain.history[0].train_loss
    assert math.isfinite(ke.best_val_nll)


def test_learning_rate_schedules():
    cosine = TrainConfig(iterations=100, schedule="cosine", warmup_fraction=0.1,
                         final_lr_fraction=0.01)
    assert lr_factor(cosine, 0) == pytest.approx(0.1)
    assert lr_factor(cosine, 9) == pytest.approx(1.0)
    assert lr_factor(cosine, 10) == pytest.approx(1.0)
    assert lr_factor(cosine, 55) == pytest.approx(0.01 + 0.99 * 0.5)  # half-way down
    assert lr_factor(cosine, 100) == pytest.approx(0.01)
    onecycle = dataclasses.replace(cosine, schedule="onecycle")
    assert lr_factor(onecycle, 0) == pytest.approx(1 / 25)
    assert lr_factor(onecycle, 10) == pytest.approx(1.0)
    assert lr_factor(TrainConfig(), 1234) == 1.0
    # A time budget compresses the decay: half the budget gone = half-way down, whatever the
    # iteration; the budget never slows the iteration schedule down.
    budget = dataclasses.replace(cosine, time_budget_s=60.0)
    assert lr_factor(budget, 10, elapsed_s=30.0) == pytest.approx(0.01 + 0.99 * 0.5)
    assert lr_factor(budget, 10, elapsed_s=90.0) == pytest.approx(0.01)
    assert lr_factor(budget, 55, elapsed_s=0.0) == pytest.approx(lr_factor(cosine, 55))
    assert lr_factor(cosine, 10, elapsed_s=1e9) == pytest.approx(1.0)  # no budget: clock unread


def test_history_round_trip_and_plot(tmp_path):
    history = [EvalRecord(100 * i, 0.5 * i, 2.0 / i, 1.5 / i, 1.5 / i - 0.25, 1e-3)
               for i in range(1, 6)]
    assert history_from_csv(history_to_csv(history)) == history
    save_history(history, tmp_path / "h.csv", tmp_path / "h.json")
    assert history_from_csv((tmp_path / "h.csv").read_text()) == history
    plot_loss_curves(history, tmp_path / "loss.png")
    assert (tmp_path / "loss.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_train_and_save_writes_checkpoint_history_and_plot(toy, tmp_path):
    from pipeline.training.checkpoints import load_checkpoint

    train_ds, val_ds = toy
    estimator = _estimator(train_ds.stats)
    config = TrainConfig(num_threads=1, iterations=20, batch_size=64, eval_every=10, seed=0)
    result = train_and_save(estimator, train_ds, val_ds, config, KineticWeights(), tmp_path,
                            estimator_config=_estimator_config())
    assert {p.name for p in tmp_path.iterdir()} == {"model.pt", "history.csv", "history.json",
                                                   "loss.png"}
    loaded = load_checkpoint(tmp_path / "model.pt", expected_config=_estimator_config())
    assert loaded.meta.data_sha256 == "toy-1"
    assert loaded.meta.extra["best_val_nll"] == result.best_val_nll
    assert [h["iteration"] for h in loaded.meta.history] == [10, 20]
