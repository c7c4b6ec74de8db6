"""SIR model: RK4 against scipy's DOP853, conservation laws, convergence order, priors, noise."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy import stats
from scipy.integrate import solve_ivp

from pipeline.errors import ConfigError
from pipeline.systems.sir import (SIR_PRIORS, SIRPrior, observation_log_likelihood, observe,
                                  rk4_step, sample_beta_paths, sample_initial_states,
                                  sample_parameters, simulate_ensemble, simulate_sir, sir_rhs)

F64 = torch.float64


X0 = (0.99, 0.01, 0.0)
# The four corners of the sir-multi prior, its centre and the sir-single parameters.
PARAMETER_SETS = [(0.02, 0.005), (0.02, 0.025), (0.04, 0.005), (0.04, 0.025), (0.03, 0.015),
                  (0.03, 0.01)]


def scipy_reference(beta: float, gamma: float, times: np.ndarray, rtol: float = 1e-12,
                    atol: float = 1e-12) -> np.ndarray:
    def rhs(_t: float, x: np.ndarray) -> list[float]:
        infection = beta * x[0] * x[1]
        return [-infection, infection - gamma * x[1], gamma * x[1]]

    sol = solve_ivp(rhs, (0.0, float(times[-1])), list(X0), method="DOP853", rtol=rtol,
                    atol=atol, t_eval=times)
    assert sol.success
    return sol.y.T


def simulate_parameter_sets(dt: float, horizon: float = 1000.0) -> torch.Tensor:
    n = len(PARAMETER_SETS)
    beta = torch.tensor([p[0] for p in PARAMETER_SETS], dtype=F64)
    gamma = torch.tensor([p[1] for p in PARAMETER_SETS], dtype=F64)
    x0 = torch.tensor([X0] * n, dtype=F64)
    return simulate_sir(x0, beta, gamma, round(horizon / dt), dt)


def test_rk4_matches_dop853_over_the_horizon() -> None:
    trajectories = simulate_parameter_sets(dt=1.0)
    times = np.arange(1001, dtype=float)
    for k, (beta, gamma) in enumerate(PARAMETER_SETS):
        reference = scipy_reference(beta, gamma, times)
        error = np.abs(trajectories[k].numpy() - reference).max()
        assert error <= 1e-6, (beta, gamma, error)


def test_rk4_global_error_is_fourth_order() -> None:
    # Errors at dt = 4, 2, 1 against a tight DOP853 reference (measured ~1.6e-6 -> 1e-7 -> 6.6e-9
    # for beta=0.04, gamma=0.005): halving dt must divide the error by ~2^4.
    errors = []
    for dt in (4.0, 2.0, 1.0):
        trajectories = simulate_parameter_sets(dt)
        times = np.arange(round(1000 / dt) + 1) * dt
        per_set = [np.abs(trajectories[k].numpy() - scipy_reference(b, g, times, 1e-13, 1e-13)).max()
                   for k, (b, g) in enumerate(PARAMETER_SETS) if (b, g) in {(0.04, 0.005), (0.03, 0.01)}]
        errors.append(per_set)
    errors = np.array(errors)
    orders = np.log2(errors[:-1] / errors[1:])
    assert np.all((orders > 3.8) & (orders < 4.2)), orders


def test_population_is_conserved_and_stays_nonnegative() -> None:
    ensemble = simulate_ensemble("sir-multi", n_trajectories=64, seed=1)
    total = ensemble.states.sum(dim=-1)
    assert ensemble.states.dtype == F64
    assert (total - 1.0).abs().max().item() <= 1e-9
    assert ensemble.states.min().item() >= 0.0


def test_sir_first_integral_is_conserved() -> None:
    # dI/dS = -1 + gamma / (beta S)  =>  S + I - (gamma / beta) ln S is constant along solutions.
    trajectories = simulate_parameter_sets(dt=1.0)
    for k, (beta, gamma) in enumerate(PARAMETER_SETS):
        s, i = trajectories[k, :, 0], trajectories[k, :, 1]
        invariant = s + i - (gamma / beta) * torch.log(s)
        assert (invariant - invariant[0]).abs().max().item() < 1e-7, (beta, gamma)


def test_rhs_and_one_step_by_hand() -> None:
    x = torch.tensor([0.99, 0.01, 0.0], dtype=F64)
    derivative = sir_rhs(x, 0.03, 0.01)
    expected = torch.tensor([-0.03 * 0.99 * 0.01, 0.03 * 0.99 * 0.01 - 0.01 * 0.01, 0.01 * 0.01],
                            dtype=F64)
    assert torch.allclose(derivative, expected, rtol=0, atol=1e-18)
    # With S = 0 there is no infection and dI/dt = -gamma I is linear: one RK4 step multiplies I
    # by the degree-4 Taylor polynomial of exp(-gamma dt).
    x = torch.tensor([0.0, 0.5, 0.5], dtype=F64)
    gamma, dt = 0.3, 0.7
    z = -gamma * dt
    growth = 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24
    stepped = rk4_step(x, 0.05, gamma, dt)
    assert stepped[1].item() == pytest.approx(0.5 * growth, abs=1e-15)
    assert stepped.sum().item() == pytest.approx(1.0, abs=1e-15)


def test_paper_initial_state_has_no_epidemic_and_ours_does() -> None:
    printed = dataclasses.replace(SIR_PRIORS["sir-single"], i0=0.0, r0=0.01)
    flat = simulate_ensemble(printed, n_trajectories=1, seed=0)
    assert flat.states[..., 1].abs().max().item() == 0.0  # I = 0 is a fixed point
    ours = simulate_ensemble("sir-single", n_trajectories=1, seed=0)
    assert ours.states[0, :, 1].max().item() > 0.2  # R0 = beta/gamma = 3: a large outbreak
    assert ours.states[0, 0].tolist() == [0.99, 0.01, 0.0]


def test_priors_match_the_paper() -> None:
    single, multi = SIR_PRIORS["sir-single"], SIR_PRIORS["sir-multi"]
    assert (single.beta, single.gamma) == ((0.03, 0.03), (0.01, 0.01))
    assert (multi.beta, multi.gamma) == ((0.02, 0.04), (0.005, 0.025))
    for prior in (single, multi):
        assert (prior.horizon_days, prior.dt, prior.obs_sigma) == (1000, 1.0, 0.027)
        assert prior.n_trajectories * (prior.n_steps + 1) * 3 >= 1_500_000


def test_default_multi_ensemble_holds_1_5_million_observed_values() -> None:
    ensemble = simulate_ensemble("sir-multi", seed=0)
    assert ensemble.n_observed_values == 500 * 1001 * 3 == 1_501_500
    assert ensemble.times.tolist() == list(map(float, range(1001)))


def test_sir_single_is_one_trajectory_seen_through_independent_noise() -> None:
    ensemble = simulate_ensemble("sir-single", n_trajectories=8, seed=2)
    assert torch.equal(ensemble.states, ensemble.states[:1].expand_as(ensemble.states))
    assert torch.all(ensemble.beta == 0.03) and torch.all(ensemble.gamma == 0.01)
    assert not torch.equal(ensemble.observations[0], ensemble.observations[1])


def test_parameters_are_uniform_on_the_prior_box() -> None:
    prior = SIR_PRIORS["sir-multi"]
    beta, gamma = sample_parameters(prior, 20_000, torch.Generator().manual_seed(5))
    for values, (low, high) in ((beta, prior.beta), (gamma, prior.gamma)):
        assert low <= values.min().item() and values.max().item() <= high
        ks = stats.kstest(values.numpy(), stats.uniform(loc=low, scale=high - low).cdf)
        assert ks.pvalue > 1e-3


def test_observation_noise_has_the_configured_statistics() -> None:
    ensemble = simulate_ensemble("sir-multi", n_trajectories=50, seed=3)
    residual = (ensemble.observations - ensemble.states).reshape(-1, 3)
    n = residual.shape[0]  # 50 * 1001 = 50,050 per compartment
    sigma = 0.027
    # 4 standard errors: SE(mean) = sigma / sqrt(n) = 1.2e-4, SE(std) ~ sigma / sqrt(2n) = 8.5e-5
    # (Gaussian); a false alarm has probability ~6e-5 per check, and the seed is fixed anyway.
    assert residual.mean(dim=0).abs().max().item() < 4 * sigma / math.sqrt(n)
    assert (residual.std(dim=0) - sigma).abs().max().item() < 4 * sigma / math.sqrt(2 * n)
    # independent across compartments and in time: correlations within 4 / sqrt(n)
    correlation = torch.corrcoef(residual.T)
    assert (correlation - torch.eye(3, dtype=F64)).abs().max().item() < 4 / math.sqrt(n)
    lagged = (ensemble.observations - ensemble.states)[:, :, 0]
    lag1 = torch.corrcoef(torch.stack([lagged[:, 1:].reshape(-1), lagged[:, :-1].reshape(-1)]))
    assert abs(lag1[0, 1].item()) < 4 / math.sqrt(n)


def test_observe_and_log_likelihood_agree_with_scipy_and_broadcast() -> None:
    generator = torch.Generator().manual_seed(0)
    states = torch.rand((7, 3), generator=generator, dtype=F64)
    obs = observe(states, 0.027, generator)
    expected = stats.norm.logpdf(obs.numpy(), loc=states.numpy(), scale=0.027).sum(axis=-1)
    got = observation_log_likelihood(obs, states, 0.027)
    assert got.shape == (7,)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12)
    # particles (P, 1, 3) against a series of observations (1, T, 3) -> (P, T)
    particles = states[:4].unsqueeze(1)
    series = obs.unsqueeze(0)
    table = observation_log_likelihood(series, particles, 0.027)
    assert table.shape == (4, 7)
    np.testing.assert_allclose(table[2, 5].item(),
                               stats.norm.logpdf(obs[5].numpy(), states[2].numpy(), 0.027).sum(),
                               rtol=1e-12)


def test_ensembles_are_reproducible_from_the_seed() -> None:
    a = simulate_ensemble("sir-multi", n_trajectories=10, seed=11)
    b = simulate_ensemble("sir-multi", n_trajectories=10, seed=11)
    c = simulate_ensemble("sir-multi", n_trajectories=10, seed=12)
    for field in ("states", "observations", "beta", "gamma"):
        assert torch.equal(getattr(a, field), getattr(b, field))
        assert not torch.equal(getattr(a, field), getattr(c, field))


def test_progress_counts_every_step() -> None:
    class Counter:
        total = 0

        def advance(self, steps: int = 1, **fields: float | str) -> None:
            self.total += steps

    counter = Counter()
    simulate_ensemble("sir-single", n_trajectories=2, seed=0, progress=counter)
    assert counter.total == 1000


@pytest.mark.parametrize("kwargs, field", [
    ({"beta": (0.04, 0.02)}, "beta"),
    ({"gamma": (-0.1, 0.1)}, "gamma"),
    ({"i0": 0.5}, "s0 + i0 + r0"),
    ({"dt": 0.3}, "horizon_days"),
    ({"obs_sigma": -1.0}, "obs_sigma"),
    ({"i0_range": (0.0, 0.01)}, "i0_range"),
    ({"r0_range": (0.2, 0.1)}, "r0_range"),
    ({"i0_range": (0.1, 0.6), "r0_range": (0.0, 0.5)}, "no susceptibles"),
])
def test_invalid_priors_are_rejected_with_the_field_named(kwargs: dict, field: str) -> None:
    base = {"name": "bad", "beta": (0.02, 0.04), "gamma": (0.005, 0.025)}
    with pytest.raises(ConfigError, match=field.replace("+", r"\+")):
        SIRPrior(**{**base, **kwargs})


def test_unknown_prior_name_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="sir-triple"):
        simulate_ensemble("sir-triple", n_trajectories=1)


# ------------------------------------------------------------------ the SF prior (ranged x0)


def test_fixed_priors_draw_no_initial_state_so_their_ensembles_are_unchanged() -> None:
    """Adding ranged initial states must not shift the paper priors' random streams."""
    prior = SIR_PRIORS["sir-multi"]
    ensemble = simulate_ensemble(prior, n_trajectories=6, seed=4)
    generator = torch.Generator().manual_seed(4)
    beta, gamma = sample_parameters(prior, 6, generator)
    x0 = torch.tensor([X0] * 6, dtype=F64)
    states = simulate_sir(x0, beta, gamma, prior.n_steps, prior.dt)
    assert torch.equal(ensemble.states, states)
    assert torch.equal(ensemble.observations, observe(states, prior.obs_sigma, generator))


def test_sf_prior_initial_states_are_log_uniform_i0_uniform_r0_on_the_simplex() -> None:
    prior = SIR_PRIORS["sir-sf"]
    x0 = sample_initial_states(prior, 20_000, torch.Generator().manual_seed(6))
    s0, i0, r0 = x0.unbind(-1)
    assert (s0 + i0 + r0 - 1.0).abs().max().item() <= 2.0 ** -52
    (i_low, i_high), (r_low, r_high) = prior.i0_range, prior.r0_range
    assert i_low <= i0.min().item() and i0.max().item() <= i_high
    assert r_low <= r0.min().item() and r0.max().item() <= r_high
    log_i0 = torch.log(i0).numpy()
    ks = stats.kstest(log_i0, stats.uniform(loc=math.log(i_low),
                                            scale=math.log(i_high) - math.log(i_low)).cdf)
    assert ks.pvalue > 1e-3
    assert stats.kstest(r0.numpy(), stats.uniform(loc=r_low, scale=r_high - r_low).cdf).pvalue \
        > 1e-3
    with pytest.raises(ConfigError, match="sample_initial_states"):
        prior.initial_state()


def test_sf_prior_ensemble_covers_the_sf_scale_and_conserves_population() -> None:
    """SF's I never exceeds 0.026 and its scatter is ~3e-4 (docs/systems.md); the prior the
    forecast trains on must put most of its windows there, unlike the paper's sir-multi."""
    sf = simulate_ensemble("sir-sf", n_trajectories=400, seed=0)
    multi = simulate_ensemble("sir-multi", n_trajectories=400, seed=0)
    assert (sf.states.sum(-1) - 1.0).abs().max().item() < 1e-12
    assert sf.states.shape == (400, 151, 3)
    share_sf_scale = (sf.states[..., 1] <= 0.03).double().mean().item()
    share_multi = (multi.states[..., 1] <= 0.03).double().mean().item()
    assert share_sf_scale > 0.6 > share_multi
    residual = sf.observations - sf.states
    assert abs(residual.std().item() - 5e-4) < 1e-5
    assert sf.states[:, 0, 1].min().item() >= 1e-5 and sf.states[:, 0, 1].max().item() <= 5e-3


def test_sf_beta_walk_has_the_configured_log_increments_and_drives_the_dynamics():
    prior = SIR_PRIORS["sir-sf"]
    beta0 = torch.full((4000,), 0.1, dtype=F64)  # mid-range: the bounds never bind here
    paths = sample_beta_paths(dataclasses.replace(prior, horizon_days=20), beta0,
                              torch.Generator().manual_seed(8))
    assert paths.shape == (4000, 21) and torch.equal(paths[:, 0], beta0)
    steps = torch.diff(torch.log(paths), dim=1).reshape(-1)
    n = steps.numel()  # 80,000 increments ~ N(0, 0.08^2)
    assert abs(steps.mean().item()) < 4 * 0.08 / math.sqrt(n)
    assert abs(steps.std().item() - 0.08) < 4 * 0.08 / math.sqrt(2 * n)
    # The ensemble's states follow its own beta path (RK4 step by step), and conserve S+I+R.
    ensemble = simulate_ensemble("sir-sf", n_trajectories=3, seed=5)
    x = ensemble.states[:, 0]
    for k in range(10):
        x = rk4_step(x, ensemble.beta_path[:, k], ensemble.gamma, 1.0)
        assert torch.allclose(x, ensemble.states[:, k + 1], rtol=0, atol=1e-15)
    assert (ensemble.states.sum(-1) - 1).abs().max().item() < 1e-12
    assert ensemble.parameter_paths.shape == (3, 151, 2)
    assert torch.equal(ensemble.parameter_paths[:, :, 0], ensemble.beta_path)


def test_joint_windows_of_a_walk_prior_target_the_beta_at_the_target_time():
    from pipeline.training.datasets import windows_from_sir

    ensemble = simulate_ensemble("sir-sf", n_trajectories=4, seed=2)
    for direction in ("forward", "backward"):
        ds = windows_from_sir(ensemble, direction=direction, target="state+params")
        index = ds.target_time.round().long()
        expected = ensemble.beta_path[ds.trajectory, index].to(torch.float32)
        assert torch.equal(ds.target[:, 3], expected)
        assert torch.equal(ds.target[:, 4], ensemble.gamma[ds.trajectory].to(torch.float32))
