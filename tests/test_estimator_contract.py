"""One contract over every encoder x flow backend: shapes, units, gradients, checkpoint round
trip, determinism from a seed."""
from __future__ import annotations

import dataclasses
import io

import pytest
import torch

from pipeline.training.checkpoints import dataclass_from_dict
from pipeline.models.standardization import Standardization
from pipeline.errors import ConfigError
from pipeline.training.kinetic import KineticWeights, kinetic_loss
from pipeline.models import (EncoderConfig, EstimatorConfig,
                             add_context_noise, build_estimator, make_estimator_config)
from pipeline.models.encoders import ENCODER_KINDS
from pipeline.models.maf import BACKENDS

D, C, R, E = 2, 3, 5, 4
COMBINATIONS = [(kind, backend) for kind in ENCODER_KINDS for backend in BACKENDS]
STATS = Standardization(context_mean=torch.tensor([1.0, -2.0, -3.0]),
                        context_std=torch.tensor([0.5, 2.0, 1.5]),
                        target_mean=torch.tensor([10.0, -1.0]),
                        target_std=torch.tensor([2.0, 0.1]))



def config_for(kind: str, backend: str) -> EstimatorConfig:
    return make_estimator_config(D, C, R, EncoderConfig(kind=kind, embedding_features=E),
                                 layers=2, hidden_features=6, backend=backend)


def batch(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    context = STATS.context_mean + STATS.context_std * torch.randn(6, R, C, generator=g)
    mask = torch.ones(6, R, dtype=torch.bool)
    mask[2, 3:] = False
    context[~mask] = 0.0
    target = STATS.target_mean + STATS.target_std * torch.randn(6, D, generator=g)
    return target, context, mask


@pytest.mark.parametrize(("kind", "backend"), COMBINATIONS)
def test_estimator_contract(kind, backend):
    config = config_for(kind, backend)
    estimator = build_estimator(config, STATS, seed=3)
    target, context, mask = batch()

    # shapes and original units
    log_prob = estimator.log_prob(target, context, mask)
    assert log_prob.shape == (6,) and bool(torch.isfinite(log_prob).all())
    standardized = estimator.standardized_log_prob(
        STATS.standardize_target(target), STATS.standardize_context(context, mask), mask)
    assert torch.allclose(log_prob, standardized - torch.log(STATS.target_std).sum(), atol=1e-5)
    generator = torch.Generator().manual_seed(0)
    samples = estimator.sample(5, context, mask, generator)
    assert samples.shape == (6, 5, D) and bool(torch.isfinite(samples).all())
    eps = torch.randn((6, 5, D), generator=torch.Generator().manual_seed(0))
    assert torch.equal(estimator.noise_to_data(eps, context, mask), samples)
    outputs = estimator.layer_outputs(STATS.standardize_target(target),
                                      STATS.standardize_context(context, mask), mask)
    assert len(outputs) == config.flow.layers + 1

    # gradients reach every parameter and are finite
    loss = kinetic_loss(estimator, STATS.standardize_target(target),
                        STATS.standardize_context(context, mask), mask,
                        KineticWeights(1.0, 0.5, 0.5))
    loss.backward()
    for name, parameter in estimator.named_parameters():
        assert parameter.grad is not None, name
        assert bool(torch.isfinite(parameter.grad).all()), name
    assert sum(float(p.grad.abs().sum()) for p in estimator.encoder.parameters()) > 0

    # checkpoint round trip: config through a plain dict, weights through torch.save
    rebuilt_config = dataclass_from_dict(EstimatorConfig, dataclasses.asdict(config))
    assert rebuilt_config == config
    buffer = io.BytesIO()
    torch.save(estimator.state_dict(), buffer)
    buffer.seek(0)
    other = build_estimator(rebuilt_config, STATS, seed=99)
    assert not torch.equal(other.log_prob(target, context, mask), log_prob)
    other.load_state_dict(torch.load(buffer, weights_only=True))
    assert torch.equal(other.log_prob(target, context, mask), log_prob)
    assert torch.equal(other.sample(5, context, mask, torch.Generator().manual_seed(0)), samples)

    # determinism from a seed, without touching the global RNG
    state = torch.random.get_rng_state()
    again = build_estimator(config, STATS, seed=3)
    assert torch.equal(torch.random.get_rng_state(), state)
    assert torch.equal(again.log_prob(target, context, mask), log_prob)


def test_standardization_travels_in_the_state_dict():
    estimator = build_estimator(config_for("mlp", "zuko"), STATS)
    state = estimator.state_dict()
    for name in ("context_mean", "context_std", "target_mean", "target_std"):
        assert torch.equal(state[name], getattr(STATS, name))
    assert torch.equal(estimator.stats.target_std, STATS.target_std)
    assert estimator.window == R


def test_context_noise_touches_only_observed_values_of_real_rows():
    _, context, mask = batch()
    noisy = add_context_noise(context, mask, 0.5, torch.Generator().manual_seed(0))
    difference = noisy - context
    assert torch.equal(difference[..., -1], torch.zeros_like(difference[..., -1]))  # time channel
    assert torch.equal(difference[~mask], torch.zeros_like(difference[~mask]))        # padding
    observed = difference[..., :-1][mask]
    assert observed.numel() == 2 * int(mask.sum())
    assert 0.3 < float(observed.std()) < 0.7
    scaled = add_context_noise(context, mask, 0.5, torch.Generator().manual_seed(0),
                               channel_std=torch.tensor([0.5, 2.0, 1.0]))
    assert torch.allclose((scaled - context)[..., 1], difference[..., 1] / 2.0)


def test_context_noise_leaves_both_time_channels_of_vehicle_rows_exact():
    context = torch.randn(6, R, 4)
    mask = torch.ones(6, R, dtype=torch.bool)
    difference = add_context_noise(context, mask, 0.5, torch.Generator().manual_seed(0),
                                   time_channels=2) - context
    assert torch.equal(difference[..., 2:], torch.zeros_like(difference[..., 2:]))
    assert bool((difference[..., :2] != 0).all())
    with pytest.raises(ConfigError, match="time_channels=4"):
        add_context_noise(context, mask, 0.5, torch.Generator().manual_seed(0), time_channels=4)


def test_inconsistent_configs_and_stats_are_rejected():
    with pytest.raises(ConfigError, match="context_features"):
        EstimatorConfig(D, C, R, EncoderConfig(embedding_features=4),
                        make_estimator_config(D, C, R, EncoderConfig(embedding_features=3)).flow)
    bad = dataclasses.replace(STATS, target_mean=torch.zeros(3), target_std=torch.ones(3))
    with pytest.raises(ConfigError, match="target_mean"):
        build_estimator(config_for("mlp", "zuko"), bad)
