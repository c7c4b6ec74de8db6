"""Windowed datasets: window contents against the ensembles, dropout times, split and
standardization, save/load round trip and damaged files, determinism, the CLI."""
from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import pytest
import torch
import typer
from typer.testing import CliRunner

import pipeline
from pipeline.training.datasets import (ABSOLUTE_TIME_FEATURE, FORMAT, FORMAT_VERSION, TIME_FEATURE,
                               DatasetConfig, build_dataset,
                               build_dataset_from_config, dataset_sha256, load_dataset,
                               progress_total, save_dataset, split_by_trajectory,
                               train_validation_split, window_indices, windows_from_sir,
                               windows_from_vehicle)
from pipeline.errors import ConfigError, DatasetError
from pipeline.io import sha256_file
from pipeline.systems.sir import simulate_ensemble
from pipeline.systems.vehicle import simulate_vehicle

R = 5




@pytest.fixture(scope="module")
def sir_ensemble():
    return simulate_ensemble("sir-multi", n_trajectories=6, seed=21)


@pytest.fixture(scope="module")
def vehicle_ensemble():
    return simulate_vehicle("vehicle-dropout", n=300, seed=22)


def reference_windows(kept: torch.Tensor, window: int) -> list[tuple[int, list[int]]]:
    """Loop-based reference: for each trajectory, every run of window + 1 consecutive kept times."""
    runs = []
    for trajectory in range(kept.shape[0]):
        times = torch.nonzero(kept[trajectory]).flatten().tolist()
        for start in range(len(times) - window):
            runs.append((trajectory, times[start:start + window + 1]))
    return runs


@pytest.mark.parametrize("direction", ["forward", "backward"])
def test_sir_windows_hold_the_observations_and_the_state_at_the_target_time(sir_ensemble,
                                                                            direction: str) -> None:
    ds = windows_from_sir(sir_ensemble, direction, "state+params", window=R)
    assert len(ds) == 6 * (1001 - R)
    assert ds.context.shape[1:] == (R, 4) and ds.target.shape[1:] == (5,)
    assert ds.context.dtype == ds.target.dtype == torch.float32 and bool(ds.mask.all())
    offsets = torch.arange(-R, 0) if direction == "forward" else torch.arange(1, R + 1)
    for i in torch.randint(0, len(ds), (40,), generator=torch.Generator().manual_seed(0)).tolist():
        traj, t = int(ds.trajectory[i]), int(ds.target_time[i])
        rows = t + offsets
        assert torch.equal(ds.context[i, :, :3], sir_ensemble.observations[traj, rows].float())
        assert torch.equal(ds.context[i, :, 3], offsets.float())  # t_obs - t_target, days
        assert torch.equal(ds.target[i, :3], sir_ensemble.states[traj, t].float())
        assert torch.equal(ds.target[i, 3:], torch.stack([sir_ensemble.beta[traj],
                                                           sir_ensemble.gamma[traj]]).float())
    assert ds.meta.context_features == ("S_obs", "I_obs", "R_obs", "t_obs-t_target")
    assert ds.meta.target_features == ("S", "I", "R", "beta", "gamma")


@pytest.mark.parametrize("direction", ["forward", "backward"])
def test_dropout_windows_match_a_loop_reference_and_carry_true_time_gaps(vehicle_ensemble,
                                                                         direction: str) -> None:
    ens = vehicle_ensemble
    ds = windows_from_vehicle(ens, direction, window=R)
    reference = reference_windows(ens.kept, R)
    assert len(ds) == len(reference)
    # trajectories with fewer than R + 1 kept points give nothing, the others (count - R) windows
    counts = ens.kept.sum(1)
    assert len(ds) == int((counts - R).clamp(min=0).sum())
    for i, (traj, times) in enumerate(reference):
        context_times = times[:R] if direction == "forward" else times[1:]
        target_time = times[R] if direction == "forward" else times[0]
        assert int(ds.trajectory[i]) == traj
        assert torch.equal(ds.context[i, :, :2], ens.observations[traj, context_times])
        assert torch.equal(ds.target[i], ens.states[traj, target_time, :2])
        gaps = (ens.times[context_times] - ens.times[target_time]).float()
        assert torch.equal(ds.context[i, :, 2], gaps)
        assert ds.target_time[i].item() == ens.times[target_time].item()
    time_channel = ds.context[..., 2]
    if direction == "forward":
        assert bool((time_channel < 0).all()) and bool((time_channel[:, -1] >= -15.0).all())
    else:
        assert bool((time_channel > 0).all())
    assert bool((time_channel.diff(dim=1) > 0).all())  # chronological rows
    # irregular steps: gaps are whole multiples of the base step 0.1 but not all equal
    steps = torch.round(time_channel.double() / 0.1)
    assert torch.allclose(time_channel.double(), steps * 0.1, atol=1e-5)
    assert len(torch.unique(steps[:, -1] - steps[:, -2])) > 5


def test_window_indices_of_a_hand_made_mask() -> None:
    kept = torch.tensor([[1, 0, 1, 1, 0, 1, 1],   # 5 kept -> runs of 3: 3
                         [1, 1, 0, 0, 0, 0, 0],   # 2 kept -> none
                         [0, 1, 1, 1, 0, 0, 0]], dtype=torch.bool)  # 3 kept -> 1
    traj, times = window_indices(kept, 2)
    assert traj.tolist() == [0, 0, 0, 2]
    assert times.tolist() == [[0, 2, 3], [2, 3, 5], [3, 5, 6], [1, 2, 3]]


def test_split_by_trajectory_has_no_leak_and_is_seeded(sir_ensemble) -> None:
    ds = windows_from_sir(sir_ensemble, window=R, val_fraction=0.34)
    train, val = split_by_trajectory(ds, 0.34, seed=3)
    train_ids, val_ids = set(train.trajectory.tolist()), set(val.trajectory.tolist())
    assert not train_ids & val_ids and train_ids | val_ids == set(range(6))
    assert len(val_ids) == round(0.34 * 6) == 2
    assert len(train) + len(val) == len(ds)
    again, _ = split_by_trajectory(ds, 0.34, seed=3)
    assert torch.equal(again.trajectory, train.trajectory)
    other_val_sets = {frozenset(split_by_trajectory(ds, 0.34, seed=s)[1].trajectory.tolist())
                      for s in range(8)}
    assert len(other_val_sets) > 1
    assert (train.meta.split, val.meta.split) == ("train", "validation")
    assert train.meta.data_sha256 == dataset_sha256(train)


def test_standardization_is_fitted_on_training_trajectories_only(sir_ensemble) -> None:
    ds = windows_from_sir(sir_ensemble, "forward", "state+params", window=R, val_fraction=0.34)
    train, val = train_validation_split(ds)
    for name, value in ds.stats.as_dict().items():  # the stored stats are the training split's
        assert torch.equal(value, getattr(train.stats, name)), name
        assert torch.equal(value, getattr(val.stats, name)), name
    rows = train.context.reshape(-1, 4).double()
    assert torch.allclose(ds.stats.context_mean.double(), rows.mean(0), atol=1e-6)
    assert torch.allclose(ds.stats.context_std.double(), rows.std(0, correction=0), atol=1e-6)
    assert torch.allclose(ds.stats.target_mean.double(), train.target.double().mean(0), atol=1e-7)
    # validation data do not move the statistics at all ...
    is_val = torch.isin(ds.trajectory, val.trajectory)
    shifted = dataclasses.replace(ds, context=ds.context + 1000.0 * is_val[:, None, None],
                                  target=ds.target + 1000.0 * is_val[:, None])
    moved_train, _ = train_validation_split(shifted)
    assert torch.equal(moved_train.stats.context_mean, train.stats.context_mean)
    assert torch.equal(moved_train.stats.target_std, train.stats.target_std)
    # ... while they would if they were included (the parameters differ between trajectories)
    assert not torch.allclose(ds.stats.target_mean, ds.target.mean(0), atol=1e-6)


def test_standardization_transforms(sir_ensemble) -> None:
    ds = windows_from_sir(sir_ensemble, "backward", "state+params", window=R)
    train, _ = train_validation_split(ds)
    z = ds.stats.standardize_target(train.target).double()
    assert torch.allclose(z.mean(0), torch.zeros(5, dtype=torch.float64), atol=1e-4)
    assert torch.allclose(z.std(0, correction=0), torch.ones(5, dtype=torch.float64), atol=1e-4)
    back = ds.stats.unstandardize_target(ds.stats.standardize_target(ds.target))
    assert torch.allclose(back, ds.target, rtol=1e-6, atol=1e-7)
    expected_log_det = -torch.log(ds.stats.target_std.double()).sum()
    assert ds.stats.log_abs_det.item() == pytest.approx(expected_log_det.item(), rel=1e-6)
    # a jacobian check: log|det dz/dy| of the affine map computed by autograd
    y = ds.target[0].clone().requires_grad_(True)
    jacobian = torch.autograd.functional.jacobian(ds.stats.standardize_target, y)
    assert torch.logdet(jacobian.double()).item() == pytest.approx(expected_log_det.item(), rel=1e-6)
    mask = torch.tensor([[True, True, False, True, False]])
    padded = ds.context[:1] * mask[..., None]
    standardized = ds.stats.standardize_context(padded, mask)
    assert torch.equal(standardized[0, 2], torch.zeros(4)) and torch.equal(standardized[0, 4], torch.zeros(4))
    assert torch.allclose(standardized[0, 0], (padded[0, 0] - ds.stats.context_mean) / ds.stats.context_std)


def test_save_load_round_trip_is_bit_exact(tmp_path: Path, vehicle_ensemble) -> None:
    ds = windows_from_vehicle(vehicle_ensemble, "backward", window=R)
    path = tmp_path / "sub" / "vehicle.pt"
    file_hash = save_dataset(ds, path)
    assert file_hash == sha256_file(path)
    assert [p.name for p in path.parent.iterdir()] == ["vehicle.pt"]  # no temporary left behind
    loaded = load_dataset(path, system="vehicle", config_name="vehicle-dropout",
                          direction="backward", target="state", window=R, vehicle_model="paper")
    for field in ("context", "mask", "target", "trajectory", "target_time"):
        original, back = getattr(ds, field), getattr(loaded, field)
        assert original.dtype == back.dtype and torch.equal(original, back), field
    for name, value in ds.stats.as_dict().items():
        assert torch.equal(value, getattr(loaded.stats, name))
    assert loaded.meta == ds.meta
    assert loaded.meta.package_version == pipeline.__version__
    assert loaded.meta.config["keep_probability"] == 0.1 and loaded.meta.seed == 22


@pytest.fixture
def saved(tmp_path: Path, sir_ensemble) -> Path:
    path = tmp_path / "sir.pt"
    save_dataset(windows_from_sir(sir_ensemble, window=R), path)
    return path


def test_truncated_file_is_a_dataset_error(saved: Path) -> None:
    data = saved.read_bytes()
    saved.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=r"sir\.pt is damaged or truncated"):
        load_dataset(saved)


def test_flipped_bytes_are_detected(saved: Path) -> None:
    data = bytearray(saved.read_bytes())
    # corrupt the middle of the file, inside the context tensor's storage
    for k in range(len(data) // 3, len(data) // 3 + 64):
        data[k] ^= 0xFF
    saved.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"sir\.pt is damaged"):
        load_dataset(saved)


def test_a_consistently_rewritten_but_altered_tensor_fails_the_content_hash(saved: Path) -> None:
    payload = torch.load(saved, weights_only=True)
    payload["tensors"]["context"][0, 0, 0] += 0.5
    torch.save(payload, saved)
    with pytest.raises(DatasetError, match="content sha256"):
        load_dataset(saved)


def test_wrong_format_version_names_both_versions(saved: Path) -> None:
    payload = torch.load(saved, weights_only=True)
    payload["format_version"] = FORMAT_VERSION + 1
    torch.save(payload, saved)
    with pytest.raises(DatasetError, match=f"format version {FORMAT_VERSION + 1}.*reads version {FORMAT_VERSION}"):
        load_dataset(saved)


def test_other_files_are_rejected_clearly(tmp_path: Path, saved: Path) -> None:
    with pytest.raises(DatasetError, match="does not exist"):
        load_dataset(tmp_path / "missing.pt")
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(DatasetError, match="not a flowcast windowed dataset"):
        load_dataset(foreign)
    text = tmp_path / "text.pt"
    text.write_text("hello")
    with pytest.raises(DatasetError, match="damaged or truncated"):
        load_dataset(text)
    payload = torch.load(saved, weights_only=True)
    del payload["meta"]["seed"]
    torch.save(payload, saved)
    with pytest.raises(DatasetError, match="seed"):
        load_dataset(saved)
    assert payload["format"] == FORMAT


def test_shape_inconsistency_is_reported(saved: Path) -> None:
    payload = torch.load(saved, weights_only=True)
    payload["tensors"]["target"] = payload["tensors"]["target"][:-1]
    torch.save(payload, saved)
    with pytest.raises(DatasetError, match=r"target has shape"):
        load_dataset(saved)


def test_mismatch_with_the_request_is_a_dataset_error(saved: Path) -> None:
    with pytest.raises(DatasetError, match="direction='forward', but 'backward' was asked for"):
        load_dataset(saved, direction="backward")
    with pytest.raises(DatasetError, match="window=5, but 7"):
        load_dataset(saved, window=7)
    with pytest.raises(DatasetError, match="system='sir', but 'vehicle'"):
        load_dataset(saved, system="vehicle")


def test_build_dataset_is_deterministic_from_the_seed() -> None:
    a = build_dataset("vehicle-sparse", "forward", "state", R, seed=5)
    b = build_dataset("vehicle-sparse", "forward", "state", R, seed=5)
    c = build_dataset("vehicle-sparse", "forward", "state", R, seed=6)
    assert a.meta.data_sha256 == b.meta.data_sha256 != c.meta.data_sha256
    for field in ("context", "target", "trajectory", "target_time"):
        assert torch.equal(getattr(a, field), getattr(b, field))
    assert a.context.shape != c.context.shape or not torch.equal(a.context, c.context)


@pytest.mark.parametrize("name, n, per_trajectory, target_dim", [
    ("sir-single", 3, 1001 - R, 3), ("sir-multi", 3, 1001 - R, 3), ("vehicle-full", 20, 16 - R, 2),
])
def test_named_fixed_step_configs(name: str, n: int, per_trajectory: int, target_dim: int) -> None:
    ds = build_dataset(name, "forward", "state", R, seed=1, n_trajectories=n)
    assert len(ds) == n * per_trajectory and ds.target.shape[1] == target_dim
    step = 1.0
    relative = ds.meta.context_features.index(TIME_FEATURE)
    assert torch.equal(ds.context[0, :, relative], torch.arange(-R, 0) * step)
    assert ds.meta.config_name == name and ds.meta.n_trajectories == n


@pytest.mark.parametrize("direction", ["forward", "backward"])
def test_vehicle_windows_carry_the_absolute_observation_times(vehicle_ensemble,
                                                             direction: str) -> None:
    ds = windows_from_vehicle(vehicle_ensemble, direction, window=R, absolute_time=True)
    assert ds.meta.context_features == ("p_x_obs", "p_y_obs", TIME_FEATURE, ABSOLUTE_TIME_FEATURE)
    relative, absolute = ds.context[..., 2].double(), ds.context[..., 3].double()
    # t_obs - (t_obs - t_target) = t_target, for every row of every window.
    recovered = absolute - relative
    torch.testing.assert_close(recovered, ds.target_time[:, None].expand_as(recovered),
                               atol=1e-5, rtol=0)
    grid = vehicle_ensemble.times
    assert bool(torch.isin(torch.round(absolute * 10).long(), torch.round(grid * 10).long()).all())
    without = windows_from_vehicle(vehicle_ensemble, direction, window=R)
    assert torch.equal(without.context, ds.context[..., :3])


def test_absolute_time_defaults_on_for_vehicles_and_is_refused_for_sir() -> None:
    assert DatasetConfig(name="vehicle-dropout").absolute_time is True
    assert DatasetConfig(name="vehicle-full", absolute_time=False).absolute_time is False
    assert DatasetConfig(name="sir-multi").absolute_time is False
    with pytest.raises(ConfigError, match="epidemic's start is not observed"):
        DatasetConfig(name="sir-multi", absolute_time=True)


def test_loading_a_dataset_without_the_channel_a_model_needs_is_refused(tmp_path: Path) -> None:
    config = DatasetConfig(name="vehicle-full", n_trajectories=20, absolute_time=False)
    path = tmp_path / "old.pt"
    save_dataset(build_dataset_from_config(config), path)
    assert load_dataset(path, absolute_time=False).context.shape[-1] == 3
    with pytest.raises(DatasetError, match="absolute time channel 't_obs'"):
        load_dataset(path, absolute_time=True)


def test_sparse_dataset_has_about_1500_points_and_the_bicycle_model_is_recorded() -> None:
    ds = build_dataset("vehicle-sparse", "backward", seed=0, vehicle_model="bicycle")
    assert abs(ds.meta.n_observed_points - 1510) < 4 * math.sqrt(15_100 * 0.09)
    assert ds.meta.config["model"] == "bicycle" and ds.meta.config["n_trajectories"] == 100
    assert len(ds) < ds.meta.n_observed_points  # R points of each trajectory are context only


def test_progress_reports_exactly_the_announced_total() -> None:
    class Counter:
        total = 0

        def advance(self, steps: int = 1, **fields: float | str) -> None:
            self.total += steps

    config = DatasetConfig(name="vehicle-dropout", n_trajectories=10)
    counter = Counter()
    build_dataset_from_config(config, counter)
    assert counter.total == progress_total(config) == 151


@pytest.mark.parametrize("kwargs, message", [
    ({"name": "sir-triple"}, "sir-triple"),
    ({"name": "sir-multi", "direction": "sideways"}, "direction"),
    ({"name": "sir-single", "target": "state+params"}, "state\\+params"),
    ({"name": "vehicle-full", "target": "state+params"}, "state\\+params"),
    ({"name": "sir-multi", "window": 0}, "window"),
    ({"name": "sir-multi", "val_fraction": 1.0}, "val_fraction"),
    ({"name": "vehicle-full", "vehicle_model": "tank"}, "vehicle_model"),
])
def test_bad_configs_are_rejected(kwargs: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        DatasetConfig(**kwargs)


def test_too_few_kept_points_for_any_window_is_a_dataset_error() -> None:
    with pytest.raises(DatasetError, match="no trajectory has 151 kept times"):
        build_dataset("vehicle-sparse", window=150, n_trajectories=3)


def test_cli_writes_a_loadable_dataset_and_prints_its_hash(tmp_path: Path, monkeypatch) -> None:
    from pipeline.cli.simulate import simulate

    cli = typer.Typer()
    cli.callback()(lambda: None)  # keep "simulate" a sub-command, as in the full app
    cli.command("simulate")(simulate)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(cli, ["simulate", "sir-multi", "--n-trajectories", "4",
                                      "--direction", "backward", "--target", "state+params",
                                      "--seed", "2"])
    assert result.exit_code == 0, result.output
    path = tmp_path / "data" / "datasets" / "sir-multi-backward-state+params.pt"
    ds = load_dataset(path, direction="backward", target="state+params")
    assert len(ds) == 4 * (1001 - R) and ds.meta.seed == 2
    assert sha256_file(path) in result.output and f"{len(ds):,}" in result.output
    failed = CliRunner().invoke(cli, ["simulate", "vehicle-full", "--target", "state+params"])
    assert failed.exit_code == 1 and "state+params" in failed.output


def test_bench_quick_run_writes_the_required_keys(tmp_path: Path) -> None:
    import json

    from bench.simulate import main

    out = tmp_path / "simulate.json"
    record = main(["--quick", "--out", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(record))
    assert record["sir_multi_points"] == 10 * 1001 * 3
    # 1,000 x 151 states kept with p = 0.1: mean 15,100, sd 36.9
    assert abs(record["vehicle_dropout_points"] - 15_100) < 4 * math.sqrt(151_000 * 0.09)
    for key in ("sir_multi_seconds", "vehicle_dropout_seconds", "peak_rss_mb"):
        assert record[key] > 0
    assert record["machine"]["cpu_count"] == os.cpu_count()
