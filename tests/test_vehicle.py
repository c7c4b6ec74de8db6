"""Vehicle with random switch: exact dynamics against a scalar integration, noise placement,
switch modes, dropout rates and dataset sizes."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from scipy import stats

from pipeline.errors import ConfigError
from pipeline.systems.vehicle import (VEHICLE_CONFIGS, VehicleConfig, draw_process_noise,
                                      get_vehicle_config, simulate_nominal, simulate_vehicle,
                                      switch_factor, vehicle_step)

F64 = torch.float64




def scalar_trajectory(psi: float, steps_per_unit: int, t_end: int, model: str) -> list[list[float]]:
    """Independent step-by-step integration of the noiseless equations with Python floats."""
    dt = 1.0 / steps_per_unit
    p_x = p_y = theta = phi = 0.0
    v = 6.0
    rows = [[p_x, p_y, theta, phi, v]]
    for k in range(t_end * steps_per_unit):
        t = k / steps_per_unit  # exact for t = 5.5
        factor = psi if t >= 5.5 else 1.0
        turn = v * phi if model == "paper" else v * math.tan(phi) / 2.8
        p_x, p_y, theta, phi = (p_x + dt * v * math.cos(theta), p_y + dt * v * math.sin(theta),
                                theta + dt * turn, phi + dt * factor * 0.1 * math.cos(0.5 * t))
        rows.append([p_x, p_y, theta, phi, v])
    return rows


@pytest.mark.parametrize("model", ["paper", "bicycle"])
@pytest.mark.parametrize("name, steps_per_unit", [("vehicle-dropout", 10), ("vehicle-full", 1)])
def test_noiseless_simulation_matches_scalar_integration(model: str, name: str,
                                                         steps_per_unit: int) -> None:
    config = dataclasses.replace(get_vehicle_config(name, model), sigma_v=0.0, sigma_phi=0.0)
    ensemble = simulate_vehicle(config, n=8, seed=4, dtype=F64)
    assert set(ensemble.psi.tolist()) == {-1.0, 1.0}
    for k in range(8):
        expected = torch.tensor(scalar_trajectory(ensemble.psi[k].item(), steps_per_unit, 15,
                                                  model), dtype=F64)
        assert ensemble.states[k].shape == expected.shape == (15 * steps_per_unit + 1, 5)
        assert torch.allclose(ensemble.states[k], expected, rtol=0, atol=1e-10), (model, name, k)


def test_noise_enters_only_velocity_and_steering_once_per_step() -> None:
    config = VEHICLE_CONFIGS["vehicle-dropout"]
    ensemble = simulate_vehicle(config, n=2000, seed=7, dtype=F64)
    x, dt = ensemble.states, config.dt
    before, after = x[:, :-1], x[:, 1:]
    p_x, p_y, theta, phi, v = before.unbind(-1)
    # positions and heading follow deterministically from the previous state
    assert torch.allclose(after[..., 0], p_x + dt * v * torch.cos(theta), rtol=0, atol=1e-12)
    assert torch.allclose(after[..., 1], p_y + dt * v * torch.sin(theta), rtol=0, atol=1e-12)
    assert torch.allclose(after[..., 2], theta + dt * v * phi, rtol=0, atol=1e-12)
    t = ensemble.times[:-1]
    drift = dt * switch_factor(t.unsqueeze(0), ensemble.psi.unsqueeze(1), config) * 0.1 * torch.cos(0.5 * t)
    noise_v = (after[..., 4] - v).reshape(-1)
    noise_phi = (after[..., 3] - phi - drift).reshape(-1)
    n = noise_v.numel()  # 300,000 draws: SE(std)/sigma = 1/sqrt(2n) = 0.13 %; allow 4 SE
    for noise, sigma in ((noise_v, 0.01), (noise_phi, 0.001)):
        assert abs(noise.mean().item()) < 4 * sigma / math.sqrt(n)
        assert abs(noise.std().item() / sigma - 1) < 4 / math.sqrt(2 * n)
    assert abs(torch.corrcoef(torch.stack([noise_v, noise_phi]))[0, 1].item()) < 4 / math.sqrt(n)


def test_observations_are_positions_plus_unit_gaussian_noise() -> None:
    ensemble = simulate_vehicle("vehicle-dropout", n=1000, seed=8)
    residual = (ensemble.observations - ensemble.states[..., :2]).double().reshape(-1, 2)
    n = residual.shape[0]  # 151,000 per coordinate
    assert residual.mean(0).abs().max().item() < 4 / math.sqrt(n)
    assert (residual.std(0) - 1).abs().max().item() < 4 / math.sqrt(2 * n)


def test_switch_acts_only_from_t_5_5() -> None:
    for name, first_changed in (("vehicle-dropout", 56), ("vehicle-full", 7)):
        config = VEHICLE_CONFIGS[name]
        up, down = simulate_nominal(config, 1.0), simulate_nominal(config, -1.0)
        assert torch.equal(up[:first_changed], down[:first_changed])
        assert up[first_changed, 3] != down[first_changed, 3]  # steering first
        assert up[first_changed + 2, 1] != down[first_changed + 2, 1]  # then position


def test_two_modes_in_equal_shares_and_separated_in_p_y() -> None:
    ensemble = simulate_vehicle("vehicle-dropout", n=2000, seed=9)
    up = ensemble.psi > 0
    assert set(ensemble.psi.tolist()) == {-1.0, 1.0}
    assert stats.binomtest(int(up.sum()), up.numel(), 0.5).pvalue > 1e-3
    final_y = ensemble.states[:, -1, 1].double()
    separation = (final_y[up].mean() - final_y[~up].mean()) / torch.sqrt(
        0.5 * (final_y[up].var() + final_y[~up].var()))
    assert separation.item() > 3.0  # measured ~3.6: two distinct modes, ~+7.5 and ~-7.6
    assert ((final_y > 0) == up).double().mean().item() > 0.9
    # before the switch acts the two groups are the same population (Welch t-test at t = 5.5)
    at_switch = ensemble.states[:, 55, 1].double()
    assert stats.ttest_ind(at_switch[up], at_switch[~up], equal_var=False).pvalue > 1e-3


def test_dropout_keeps_each_state_independently_with_probability_0_1() -> None:
    ensemble = simulate_vehicle("vehicle-dropout", n=2000, seed=10)
    kept = ensemble.kept
    assert kept.shape == (2000, 151) and kept.dtype == torch.bool
    assert stats.binomtest(int(kept.sum()), kept.numel(), 0.1).pvalue > 1e-3
    per_time = kept.sum(0).double().numpy()  # no time index favoured
    assert stats.chisquare(per_time).pvalue > 1e-3


def test_dataset_sizes_match_the_paper() -> None:
    full, dropout, sparse = (VEHICLE_CONFIGS[n] for n in
                             ("vehicle-full", "vehicle-dropout", "vehicle-sparse"))
    assert full.n_steps + 1 == 16 and full.keep_probability == 1.0
    assert dropout.n_steps + 1 == 151
    assert dropout.n_trajectories * 151 * dropout.keep_probability == pytest.approx(1_510_000)
    ensemble = simulate_vehicle(sparse, seed=0)
    # ~1,500 points: Binomial(15,100, 0.1) has mean 1,510 and sd 36.9
    assert abs(ensemble.n_points - 1510) < 4 * math.sqrt(15_100 * 0.1 * 0.9)
    full_ensemble = simulate_vehicle(full, n=3, seed=0)
    assert bool(full_ensemble.kept.all()) and full_ensemble.times.tolist() == list(map(float, range(16)))


def test_vehicle_step_accepts_per_particle_times_and_given_noise() -> None:
    config = VEHICLE_CONFIGS["vehicle-dropout"]
    generator = torch.Generator().manual_seed(0)
    state = torch.randn((6, 5), generator=generator, dtype=F64)
    psi = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0, -1.0], dtype=F64)
    times = torch.tensor([0.0, 5.0, 5.5, 5.5, 9.0, 14.9], dtype=F64)
    noise_v, noise_phi = draw_process_noise((6,), config, generator)
    batched = vehicle_step(state, times, 0.1, psi, noise_v, noise_phi, config)
    for k in range(6):
        single = vehicle_step(state[k], times[k].item(), 0.1, psi[k], noise_v[k], noise_phi[k], config)
        assert torch.equal(batched[k], single)
    assert torch.equal(batched[:, 4], state[:, 4] + noise_v)
    expected_phi = state[1, 3] + 0.1 * 1.0 * 0.1 * math.cos(0.5 * 5.0) + noise_phi[1]  # psi ignored
    assert batched[1, 3].item() == pytest.approx(expected_phi.item(), abs=1e-15)


def test_ensembles_are_reproducible_from_the_seed() -> None:
    a = simulate_vehicle("vehicle-sparse", seed=1)
    b = simulate_vehicle("vehicle-sparse", seed=1)
    c = simulate_vehicle("vehicle-sparse", seed=2)
    for field in ("states", "observations", "kept", "psi"):
        assert torch.equal(getattr(a, field), getattr(b, field))
        assert not torch.equal(getattr(a, field), getattr(c, field))


def test_float32_storage_matches_float64_simulation() -> None:
    low = simulate_vehicle("vehicle-sparse", seed=3)
    high = simulate_vehicle("vehicle-sparse", seed=3, dtype=F64)
    assert low.states.dtype == torch.float32
    # same random draws (all made in float64), so only storage rounding differs
    assert torch.equal(low.kept, high.kept) and torch.equal(low.psi.double(), high.psi)
    assert (low.states.double() - high.states).abs().max().item() < 1e-5
    assert (low.observations.double() - high.observations).abs().max().item() < 1e-5


@pytest.mark.parametrize("kwargs, field", [
    ({"model": "unicycle"}, "model"), ({"dt": 0.0}, "dt"), ({"dt": 0.7}, "t_end"),
    ({"keep_probability": 0.0}, "keep_probability"), ({"sigma_v": -0.1}, "sigma_v"),
])
def test_invalid_configs_name_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        VehicleConfig(name="bad", **kwargs)


def test_unknown_config_name_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="vehicle-tiny"):
        get_vehicle_config("vehicle-tiny")
