"""Presets: the paper's numbers, every preset × encoder × recipe builds, CLI end to end."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from pipeline.training.datasets import ABSOLUTE_TIME_FEATURE, build_dataset, save_dataset
from pipeline.errors import ConfigError
from pipeline.models.estimator import build_estimator
from pipeline.names import TRAINING_SETUPS
from pipeline.training.presets import ENCODER_CHOICES, RECIPES, get_preset



def _unit_stats(channels: int, features: int, target_transform: str = "identity"):
    from pipeline.models.standardization import Standardization

    return Standardization(torch.zeros(channels), torch.ones(channels), torch.zeros(features),
                           torch.ones(features), target_transform=target_transform)


@pytest.mark.parametrize("recipe", RECIPES)
@pytest.mark.parametrize("encoder", ENCODER_CHOICES)
@pytest.mark.parametrize("name", TRAINING_SETUPS)
def test_every_preset_builds_a_working_estimator(name, encoder, recipe):
    preset = get_preset(name, encoder, recipe=recipe)
    config = preset.estimator
    estimator = build_estimator(config, _unit_stats(config.context_channels,
                                                    config.flow.features, config.target_transform))
    context = torch.randn(4, config.window, config.context_channels)
    mask = torch.ones(4, config.window, dtype=torch.bool)
    # Targets inside the support of the preset's target transform (all of R^D for the identity).
    target = estimator.transform.inverse(torch.randn(4, config.flow.features))
    assert target.shape == (4, config.features)
    log_prob = estimator.log_prob(target, context, mask)
    assert log_prob.shape == (4,) and bool(torch.isfinite(log_prob).all())
    assert preset.train.batch_size <= get_preset(name, encoder, recipe="paper").train.batch_size
    assert preset.kinetic.is_plain_likelihood == (encoder != "transformer-ke")


def test_paper_numbers():
    vehicle = get_preset("vehicle", "transformer", recipe="paper")
    flow, train = vehicle.estimator.flow, vehicle.train
    assert (flow.layers, flow.hidden_features, flow.context_features, flow.features) == (
        10, 4, 4, 2)
    assert (train.iterations, train.batch_size, train.lr, train.schedule) == (10_000, 2048, 1e-3,
                                                                             "constant")
    assert vehicle.estimator.window == 5 and vehicle.dataset.name == "vehicle-dropout"
    sparse = get_preset("vehicle-sparse", "mamba", recipe="paper")
    assert (sparse.estimator.flow.layers, sparse.train.iterations, sparse.train.batch_size) == (
        4, 5_000, 128)
    for name in ("sir-single", "sir-multi", "sir-joint"):
        sir = get_preset(name, "mlp", recipe="paper")
        assert (sir.estimator.flow.hidden_features, sir.estimator.flow.context_features) == (6, 6)
        assert sir.train.context_noise_sigma == 0.01
    joint = get_preset("sir-joint", "mamba")
    assert joint.estimator.features == 5 and joint.dataset.target == "state+params"
    sf = get_preset("sir-sf-joint", "transformer", recipe="paper")
    # The product's model: the paper's joint architecture over the SIR log-ratio coordinates.
    paper_joint = get_preset("sir-joint", "transformer", recipe="paper").estimator
    assert paper_joint.target_transform == "identity"
    assert sf.estimator.target_transform == "sir-log-ratio" and sf.estimator.flow.features == 4
    assert sf.estimator == dataclasses.replace(
        paper_joint, target_transform="sir-log-ratio",
        flow=dataclasses.replace(paper_joint.flow, features=4))
    assert all(get_preset(name, "mlp").estimator.target_transform == "identity"
               for name in TRAINING_SETUPS if name not in ("sir-sf-joint", "sf-waves-joint"))
    # The product's joint model: (S, I, R, beta) on the multi-wave prior, two weeks of S/I/R
    # read with I on a log scale; the paper's presets read their windows as they are.
    waves = get_preset("sf-waves-joint", "mlp").estimator
    assert (waves.features, waves.window, waves.flow.features) == (4, 14, 3)
    assert (waves.target_transform, waves.context_transform) == ("sir-log-ratio",
                                                                 "sir-log-infectious")
    assert all(get_preset(name, "mlp").estimator.context_transform == "identity"
               for name in TRAINING_SETUPS if name != "sf-waves-joint")
    assert sf.dataset.name == "sir-sf" and sf.train.context_noise_sigma == 0.0
    ke = get_preset("sir-multi", "transformer-ke").kinetic
    assert ke.path_length > 0 and ke.intermediate_nll > 0 and ke.nll == 1.0


def test_backend_and_direction_are_passed_through():
    preset = get_preset("sir-multi", "mlp", backend="nflows", direction="backward")
    assert preset.estimator.flow.backend == "nflows" and preset.dataset.direction == "backward"
    assert preset.run_name == "sir-multi-backward-mlp-nflows-fast"
    tuned = preset.with_overrides(iterations=7, batch_size=3, lr=0.5, seed=9)
    assert (tuned.train.iterations, tuned.train.batch_size, tuned.train.lr, tuned.train.seed) == (
        7, 3, 0.5, 9)


@pytest.mark.parametrize("kwargs,match", [
    (dict(name="sir-double"), "unknown preset 'sir-double'"),
    (dict(name="sir-multi", encoder="lstm"), "unknown encoder 'lstm'"),
    (dict(name="sir-multi", recipe="slow"), "unknown recipe 'slow'"),
    (dict(name="sir-multi", backend="pyro"), "backend"),
])
def test_bad_names_are_rejected(kwargs, match):
    name = kwargs.pop("name")
    with pytest.raises(ConfigError, match=match):
        get_preset(name, **kwargs)


@pytest.mark.parametrize("name,dataset", [("sir-joint", "sir-multi"), ("sir-sf-joint", "sir-sf"),
                                          ("sf-waves-joint", "sf-waves"),
                                          ("vehicle-sparse", "vehicle-sparse"),
                                          ("vehicle", "vehicle-dropout")])
def test_preset_shapes_match_the_datasets(name, dataset):
    preset = get_preset(name, "mlp")
    ds = build_dataset(dataset, target=preset.dataset.target, window=preset.dataset.window,
                       n_trajectories=3)
    assert ds.context.shape[1:] == (preset.estimator.window, preset.estimator.context_channels)
    assert ds.target.shape[1] == preset.estimator.features
    # The model's context layout is the dataset's: t_obs channel for vehicles only.
    assert preset.estimator.absolute_time == (ABSOLUTE_TIME_FEATURE in ds.meta.context_features)
    assert preset.estimator.absolute_time == name.startswith("vehicle")


def test_cli_trains_and_writes_a_loadable_checkpoint(tmp_path):
    from typer.testing import CliRunner

    from pipeline.training.checkpoints import load_checkpoint
    from pipeline.cli import _register, app

    data_file = tmp_path / "sir.pt"
    save_dataset(build_dataset("sir-multi", n_trajectories=4, seed=1), data_file)
    _register()
    result = CliRunner().invoke(app, ["train", "sir-multi", "--encoder", "mlp", "--iterations",
                                      "20", "--batch-size", "64", "--dataset", str(data_file),
                                      "--threads", "1", "--out", str(tmp_path / "runs")])
    assert result.exit_code == 0, result.output
    assert "best validation NLL" in result.output
    run = tmp_path / "runs" / "sir-multi-forward-mlp-zuko-fast"
    assert {"model.pt", "history.csv", "history.json", "loss.png", "preset.json"} <= {
        p.name for p in run.iterdir()}
    expected = get_preset("sir-multi", "mlp").estimator
    loaded = load_checkpoint(run / "model.pt", expected_config=expected)
    assert loaded.meta.extra["train_config"]["iterations"] == 20
    help_text = CliRunner().invoke(app, ["train", "--help"])
    assert help_text.exit_code == 0 and "--encoder" in help_text.output
