"""Valid by construction: the SIR log-ratio target transform of the SF forecast's joint model.

The transform's round trip and log-det (against torch.autograd's Jacobian), a density that
integrates to 1 over the simplex in original units, a briefly trained ``sir-sf-joint`` model whose
samples and 28-day rollouts stay on the simplex with positive rates, checkpoints that keep the
transform, and old checkpoints (no field) that load as identity.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from pipeline.training.checkpoints import load_checkpoint, save_checkpoint
from pipeline.models.standardization import Standardization, compute_standardization
from pipeline.training.datasets import train_validation_split, windows_from_sir
from pipeline.errors import ConfigError, DatasetError
from pipeline.inference.estimate import ObservationWindow, sample_conditional
from pipeline.models.encoders import EncoderConfig
from pipeline.models.estimator import build_estimator, make_estimator_config
from pipeline.models.target_transforms import get_target_transform
from pipeline.training.presets import get_preset
from pipeline.inference.rollout import RolloutConfig, rollout
from pipeline.systems.sir import SIR_PRIORS, sample_initial_states, simulate_ensemble
from pipeline.training.trainer import TrainConfig, train, train_and_save

F64 = torch.float64
LOG_RATIO = get_target_transform("sir-log-ratio")


def _valid_targets(n: int, seed: int, rates: int = 2) -> torch.Tensor:
    """(n, 3 + rates) float64 points strictly inside the simplex with positive rates."""
    g = torch.Generator().manual_seed(seed)
    # Normalized exponentials are uniform on the simplex (Dirichlet(1, 1, 1)); seeded, unlike
    # torch.distributions.Dirichlet, which takes no generator.
    raw = -torch.log(torch.rand((n, 3), generator=g, dtype=F64))
    simplex = raw / raw.sum(-1, keepdim=True)
    positive = torch.exp(torch.randn((n, rates), generator=g, dtype=F64) - 2.0)
    return torch.cat([simplex, positive], dim=-1)


def _assert_valid(samples: torch.Tensor, atol: float = 1e-5) -> None:
    """S, I, R in (0, 1] summing to 1, every rate > 0, all finite."""
    assert bool(torch.isfinite(samples).all())
    sir = samples[..., :3].double()
    assert bool((sir > 0).all()) and bool((sir <= 1).all())
    assert (sir.sum(-1) - 1).abs().max().item() <= atol
    assert bool((samples[..., 3:] > 0).all())


# ----------------------------------------------------------------------------- the transform


@pytest.mark.parametrize("rates", [0, 2])
def test_round_trip_both_ways(rates: int) -> None:
    y = _valid_targets(500, seed=1, rates=rates)
    u = LOG_RATIO.forward(y)
    assert u.shape == (500, 2 + rates)
    torch.testing.assert_close(LOG_RATIO.inverse(u), y, atol=1e-14, rtol=1e-12)
    u_any = 8.0 * torch.randn((500, 2 + rates), generator=torch.Generator().manual_seed(2),
                              dtype=F64)
    torch.testing.assert_close(LOG_RATIO.forward(LOG_RATIO.inverse(u_any)), u_any, atol=1e-10,
                               rtol=0)
    # The identity's formulas are u = (log(I/S), log(R/S), log beta, log gamma).
    expected = torch.stack([torch.log(y[:, 1] / y[:, 0]), torch.log(y[:, 2] / y[:, 0])]
                           + [torch.log(y[:, 3 + k]) for k in range(rates)], dim=-1)
    torch.testing.assert_close(u, expected)


def test_inverse_is_valid_for_any_flow_output() -> None:
    """Even far in the tails (|u| up to 60, float32 as the flow emits) the image is valid."""
    u = 60.0 * (2 * torch.rand((20_000, 4), generator=torch.Generator().manual_seed(3)) - 1)
    y = LOG_RATIO.inverse(u)
    assert y.dtype == torch.float32
    _assert_valid(y[(u[:, :2].abs() < 40).all(-1)])       # I, R representable in float32
    assert bool((y >= 0).all()) and bool(torch.isfinite(y).all())
    assert ((y[:, :3].double().sum(-1) - 1).abs() < 1e-6).all()


@pytest.mark.parametrize("rates", [0, 2])
def test_log_abs_det_matches_autograd_jacobian(rates: int) -> None:
    """log|det du/d(I, R, rates)| with S = 1 - I - R, against torch.autograd's Jacobian."""
    y = _valid_targets(25, seed=4, rates=rates)

    def u_of_free(free: torch.Tensor) -> torch.Tensor:
        s = 1.0 - free[0] - free[1]
        full = torch.cat([s[None], free])
        return LOG_RATIO.forward(full[None])[0]

    for point in y:
        free = point[1:].clone()
        jacobian = torch.autograd.functional.jacobian(u_of_free, free)
        expected = torch.linalg.slogdet(jacobian).logabsdet
        assert LOG_RATIO.log_abs_det(point[None])[0].item() == pytest.approx(expected.item(),
                                                                             abs=1e-10)
        closed_form = -torch.log(point[:3]).sum() - torch.log(point[3:]).sum()
        assert expected.item() == pytest.approx(closed_form.item(), abs=1e-10)


def test_support_and_names() -> None:
    good = _valid_targets(3, seed=5)
    bad = good.clone()
    bad[0, 1] = -1e-4                      # negative I
    bad[1, 0] += 1e-3                      # S + I + R = 1.001
    bad[2, 3] = 0.0                        # beta = 0
    assert LOG_RATIO.in_support(good).all() and not LOG_RATIO.in_support(bad).any()
    with pytest.raises(ConfigError, match="unknown target transform 'logit'"):
        get_target_transform("logit")
    with pytest.raises(ConfigError, match="first 3 target components"):
        make_estimator_config(2, 3, 5, target_transform="sir-log-ratio")
    assert make_estimator_config(5, 4, 5, target_transform="sir-log-ratio").flow.features == 4


# ----------------------------------------------------------------------------- the estimator


def _untrained(features: int, mean_u: list[float], std_u: float, seed: int = 0):
    config = make_estimator_config(features, 4, 5, EncoderConfig(kind="mlp", embedding_features=4),
                                   target_transform="sir-log-ratio", layers=2, hidden_features=8)
    stats = Standardization(torch.zeros(4), torch.ones(4), torch.tensor(mean_u),
                            torch.full((len(mean_u),), std_u), target_transform="sir-log-ratio")
    return build_estimator(config, stats, seed=seed)


def test_log_prob_is_the_change_of_variables_of_the_flow_density() -> None:
    """log p(y) = flow log-density of z(y) + log|det dz/d(I, R, beta, gamma)| (autograd)."""
    estimator = _untrained(5, [-3.0, -1.0, -2.0, -2.3], 0.7)
    context = torch.randn(1, 5, 4, generator=torch.Generator().manual_seed(6))
    y = _valid_targets(6, seed=7).float()
    log_prob = estimator.log_prob(y, context.expand(6, -1, -1))
    embedding = estimator._embed_raw(context, None)
    for k, point in enumerate(y.double()):
        def z_of_free(free: torch.Tensor) -> torch.Tensor:
            full = torch.cat([(1.0 - free[0] - free[1])[None], free])
            u = LOG_RATIO.forward(full[None])[0]
            return (u - estimator.target_mean.double()) / estimator.target_std.double()

        free = point[1:].clone()
        log_det = torch.linalg.slogdet(torch.autograd.functional.jacobian(z_of_free, free))[1]
        z = z_of_free(free).float()[None]
        expected = estimator.flow.log_prob(z, embedding)[0].double() + log_det
        assert log_prob[k].item() == pytest.approx(expected.item(), abs=2e-4)
    outside = y.clone()
    outside[0, 1] = -0.01
    scored = estimator.log_prob(outside, context.expand(6, -1, -1))
    assert scored[0].item() == -math.inf and bool(torch.isfinite(scored[1:]).all())


def test_density_in_original_units_integrates_to_one_over_the_simplex() -> None:
    """State-only model (S, I, R): Riemann sum of p(I, R) over the triangle I, R > 0, I + R < 1.
    The mass sits well inside (S, I, R near 0.5, 0.25, 0.25), so the grid sees all of it; a
    missing or wrong log-det term (e.g. dropping log S) moves the sum far from 1."""
    estimator = _untrained(3, [-0.7, -0.7], 0.25, seed=1)
    context = torch.zeros(1, 5, 4)
    h = 0.0025
    grid = torch.arange(h / 2, 1.0, h, dtype=F64)
    i, r = torch.meshgrid(grid, grid, indexing="ij")
    inside = (i + r) < 1.0 - 1e-9
    points = torch.stack([1.0 - i[inside] - r[inside], i[inside], r[inside]], dim=-1).float()
    with torch.no_grad():
        log_p = torch.cat([estimator.log_prob(chunk, context.expand(len(chunk), -1, -1))
                           for chunk in points.split(50_000)])
    total = float(log_p.double().exp().sum() * h * h)
    assert total == pytest.approx(1.0, abs=1e-4)   # measured: 1 - 3e-8
    # Dropping the -log S part of the log-det would not integrate to 1.
    wrong = float((log_p.double() + torch.log(points[:, 0].double())).exp().sum() * h * h)
    assert abs(wrong - 1.0) > 0.2


# ----------------------------------------------------------------------------- a trained model


@pytest.fixture(scope="module")
def sf_joint(tmp_path_factory):
    """A tiny sir-sf-joint model (MLP encoder), trained briefly, and its checkpoint."""
    preset = get_preset("sir-sf-joint", "mlp", n_trajectories=24)
    prior = dataclasses.replace(SIR_PRIORS["sir-sf"], horizon_days=60, n_trajectories=24)
    ensemble = simulate_ensemble(prior, seed=0)
    ds = windows_from_sir(ensemble, "forward", "state+params", window=5, val_fraction=0.25)
    train_ds, val_ds = train_validation_split(ds, preset.estimator.target_transform)
    estimator = build_estimator(preset.estimator, train_ds.stats, seed=0)
    config = TrainConfig(iterations=40, batch_size=256, lr=3e-3, eval_every=20, seed=0)
    out = tmp_path_factory.mktemp("sf-joint")
    result = train_and_save(estimator, train_ds, val_ds, config, None, out,
                            estimator_config=preset.estimator,
                            extra={"preset": preset.to_dict()})
    return preset, estimator, train_ds, val_ds, result, out / "model.pt", ensemble


def test_standardization_is_fitted_on_transformed_training_targets(sf_joint) -> None:
    _, _, train_ds, val_ds, _, _, _ = sf_joint
    stats = train_ds.stats
    assert stats.target_transform == "sir-log-ratio" and stats.target_mean.shape == (4,)
    u = LOG_RATIO.forward(train_ds.target.double())
    torch.testing.assert_close(stats.target_mean.double(), u.mean(0), atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(stats.target_std.double(), u.std(0, correction=0), atol=1e-5,
                               rtol=1e-5)
    assert torch.equal(val_ds.stats.target_mean, stats.target_mean)   # train split only
    z = stats.standardize_target(train_ds.target)
    torch.testing.assert_close(stats.unstandardize_target(z), train_ds.target, atol=1e-6,
                               rtol=1e-4)


def test_targets_outside_the_support_are_refused_with_a_named_error() -> None:
    target = _valid_targets(4, seed=8).float()
    target[2, 2] = 0.0                                   # R = 0 exactly
    with pytest.raises(DatasetError, match="outside the support of target transform"):
        compute_standardization(torch.zeros(4, 5, 4), torch.ones(4, 5, dtype=torch.bool),
                                target, "sir-log-ratio")


def test_sf_prior_keeps_every_target_inside_the_simplex() -> None:
    """R0 is drawn >= 1e-6 (the backward windows' first-day targets) and I0 >= 1e-5, so both
    directions' log-ratio coordinates are finite."""
    x0 = sample_initial_states(SIR_PRIORS["sir-sf"], 50_000, torch.Generator().manual_seed(9))
    assert x0[:, 2].min().item() >= 1e-6 and x0[:, 1].min().item() >= 1e-5
    prior = dataclasses.replace(SIR_PRIORS["sir-sf"], horizon_days=30, n_trajectories=40)
    ensemble = simulate_ensemble(prior, seed=1)
    backward = windows_from_sir(ensemble, "backward", "state+params", window=5)
    train_ds, _ = train_validation_split(backward, "sir-log-ratio")
    assert bool(torch.isfinite(train_ds.stats.standardize_target(backward.target)).all())


def test_trained_samples_are_on_the_simplex_with_positive_rates(sf_joint) -> None:
    _, estimator, _, val_ds, _, _, _ = sf_joint
    assert estimator.features == 4 and estimator.target_features == 5
    samples = sample_conditional(estimator, val_ds.context[:64], val_ds.mask[:64], 300, seed=0)
    assert samples.shape == (64, 300, 5)
    _assert_valid(samples)


def test_validation_nll_in_original_units_is_the_log_prob_of_the_targets(sf_joint) -> None:
    """The training history's original-unit NLL includes the transform's log-det."""
    _, estimator, _, val_ds, result, _, _ = sf_joint
    assert len(val_ds) <= 8192        # the validation subset is the whole split
    with torch.no_grad():
        nll = -estimator.log_prob(val_ds.target, val_ds.context, val_ds.mask).double().mean()
    assert result.best_val_nll_original == pytest.approx(float(nll), abs=2e-3)


def test_checkpoint_keeps_the_transform(sf_joint) -> None:
    preset, estimator, _, val_ds, _, path, _ = sf_joint
    loaded = load_checkpoint(path, expected_config=preset.estimator)
    assert loaded.config.target_transform == "sir-log-ratio"
    assert loaded.estimator.target_transform == "sir-log-ratio"
    assert loaded.estimator.stats.target_transform == "sir-log-ratio"
    context, mask = val_ds.context[:8], val_ds.mask[:8]
    a = sample_conditional(estimator, context, mask, 50, seed=3)
    b = sample_conditional(loaded.estimator, context, mask, 50, seed=3)
    assert torch.equal(a, b)
    with torch.no_grad():
        torch.testing.assert_close(loaded.estimator.log_prob(val_ds.target[:8], context, mask),
                                   estimator.log_prob(val_ds.target[:8], context, mask))


def test_an_old_checkpoint_without_the_field_loads_as_identity(tmp_path) -> None:
    config = make_estimator_config(3, 4, 5, EncoderConfig(kind="mlp", embedding_features=4),
                                   layers=2, hidden_features=8)
    stats = Standardization(torch.zeros(4), torch.ones(4), torch.full((3,), 0.3),
                            torch.full((3,), 0.1))
    estimator = build_estimator(config, stats, seed=2)
    path = save_checkpoint(tmp_path / "model.pt", estimator, config=config, stats=stats)
    payload = torch.load(path, weights_only=True)
    del payload["config"]["target_transform"], payload["stats"]["target_transform"]
    torch.save(payload, path)
    loaded = load_checkpoint(path, expected_config=config)
    assert loaded.config.target_transform == "identity"
    assert loaded.estimator.target_transform == "identity"
    target = torch.tensor([[0.2, -0.1, 0.5]])            # identity: any real target is scored
    context = torch.zeros(1, 5, 4)
    with torch.no_grad():
        assert torch.equal(loaded.estimator.log_prob(target, context),
                           estimator.log_prob(target, context))


def test_a_28_day_rollout_stays_valid(sf_joint) -> None:
    """Every state of every path on the simplex with beta, gamma > 0, with feedback noise at the
    prior's observation noise (the fed-back rows are noisy observations, as in training)."""
    _, estimator, _, _, _, _, ensemble = sf_joint
    times = ensemble.times[20:25].numpy()
    values = ensemble.observations[3, 20:25].numpy()
    window = ObservationWindow(times=times, values=values, target_time=float(times[-1]) + 1.0)
    config = RolloutConfig(n_paths=100, feedback_noise_sigma=SIR_PRIORS["sir-sf"].obs_sigma,
                           seed=0)
    result = rollout(estimator, window, 28, 1.0, "forward", config,
                     names=("S", "I", "R", "beta", "gamma"), window_length=5)
    assert result.samples.shape == (100, 28, 5)
    _assert_valid(result.samples)
    assert np.all(np.diff(result.times) == 1.0)


def test_smc_seed_refuses_invalid_draws_instead_of_clipping_them() -> None:
    from pipeline.errors import ConfigError
    from pipeline.inference.hybrid import check_valid_draws

    good = torch.tensor([[[0.9, 0.05, 0.05, 0.2, 0.1], [0.8, 0.1, 0.1, 0.3, 0.1]]],
                        dtype=torch.float64)
    check_valid_draws(good)
    bad = good.clone()
    bad[0, 1, 1] = -0.01                       # negative I
    bad[0, 0, 3] = -0.2                        # negative beta
    with pytest.raises(ConfigError, match="2 of 2 flow draws seeding the multi-wave model"):
        check_valid_draws(bad)
