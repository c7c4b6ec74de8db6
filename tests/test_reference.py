"""Reference posteriors against closed-form Gaussian posteriors, ESS, and the time bookkeeping."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.errors import ConfigError
from pipeline.inference.reference import (SIRCandidates, SIRReferenceConfig, VehicleCandidates, kish_ess,
                                simulate_sir_candidates, sir_reference, vehicle_reference,
                                weighted_reference)
from pipeline.systems.sir import SIR_PRIORS, get_prior
from pipeline.systems.vehicle import get_vehicle_config, simulate_nominal


def test_linear_gaussian_reference_matches_exact_posterior() -> None:
    """x ~ N(0, 1); o_r = x + N(0, s²), r = 1..3; target y = x + N(0, q²).

    Exact: x | o ~ N(Σo / (R + s²), s² / (R + s²)), so y | o has that mean and variance + q².
    """
    m, s, q, n_draws = 400_000, 0.8, 0.3, 20_000
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(m, generator=gen, dtype=torch.float64)
    y = x + q * torch.randn(m, generator=gen, dtype=torch.float64)
    observed = torch.tensor([[[0.9], [1.4], [0.7]], [[-0.5], [-1.0], [0.2]]], dtype=torch.float64)
    predicted = x[:, None, None, None].expand(m, 2, 3, 1)
    ref = weighted_reference(predicted, y[:, None, None].expand(m, 2, 1), observed, s, n_draws, 1)
    assert ref.samples.shape == (2, n_draws, 1)
    for b in range(2):
        total = float(observed[b].sum())
        mean = total / (3 + s * s)
        var = s * s / (3 + s * s) + q * q
        got = ref.samples[b, :, 0]
        # Errors: draw noise sd sqrt(var/n) plus importance-sampling noise (ESS ~ 1e5): 5 sd.
        tol = 5 * math.sqrt(var / n_draws + var / float(ref.ess[b]))
        assert abs(float(got.mean()) - mean) < tol
        assert abs(float(got.var()) / var - 1) < 5 * math.sqrt(2 / n_draws) + 0.02
    # ESS of likelihood weights: compare with the direct formula on the same weights.
    log_w = -0.5 * ((observed[0, :, 0][None] - x[:, None]) ** 2).sum(-1) / s ** 2
    w = torch.softmax(log_w, 0)
    assert float(ref.ess[0]) == pytest.approx(float(1 / (w * w).sum()), rel=1e-9)


def test_kish_ess_known_values() -> None:
    assert float(kish_ess(torch.zeros(10))) == pytest.approx(10.0)
    assert float(kish_ess(torch.tensor([0.0, -math.inf, -math.inf]))) == pytest.approx(1.0)
    # weights 1/2, 1/4, 1/4 -> 1 / (1/4 + 1/16 + 1/16) = 8/3
    assert float(kish_ess(torch.log(torch.tensor([2.0, 1.0, 1.0])))) == pytest.approx(8 / 3)
    with pytest.raises(ConfigError, match="zero likelihood"):
        kish_ess(torch.full((3,), -math.inf))


def _ramp_candidates(slope: float, n_days: int = 200, substeps: int = 4) -> SIRCandidates:
    """One 'trajectory' whose three components rise linearly in time: x(t) = slope·t (all comps)."""
    prior = get_prior("sir-single")
    step = 1.0 / substeps
    t = torch.arange(n_days * substeps + 1, dtype=torch.float64) * step
    states = (slope * t)[None, :, None].expand(1, -1, 3).contiguous()
    return SIRCandidates(states=states, parameters=torch.tensor([[0.03, 0.01]]), step=step,
                         prior=prior)


@pytest.mark.parametrize("direction", ["forward", "backward"])
def test_sir_reference_recovers_time_position_in_both_directions(direction: str) -> None:
    """Linear ramp x(t) = v·t: with R rows at offsets d_r and all 3 components observed,
    τ | o ~ N(mean_r mean_c (o/v) − mean(d), σ² / (3 R v²)) exactly (flat prior on τ), and the
    target x(τ) = v τ. The window's offsets are negative forward, positive backward."""
    slope, tau_true = 0.01, 80.0
    candidates = _ramp_candidates(slope)
    sigma = candidates.prior.obs_sigma
    offsets = torch.tensor([[-5.0, -4, -3, -2, -1]]) if direction == "forward" \
        else torch.tensor([[1.0, 2, 3, 4, 5]])
    gen = torch.Generator().manual_seed(3)
    observed = slope * (tau_true + offsets)[..., None].expand(1, 5, 3) \
        + sigma * torch.randn((1, 5, 3), generator=gen, dtype=torch.float64)
    ref = sir_reference(candidates, offsets, observed, n_draws=20_000, seed=4)
    tau_mean = float(observed.mean() / slope - offsets.double().mean())
    tau_sd = sigma / (slope * math.sqrt(15))
    got = ref.samples[0, :, 0].numpy() / slope
    assert abs(got.mean() - tau_mean) < 0.05 * tau_sd + 5 * tau_sd / math.sqrt(20_000)
    # grid h = 0.25 with uniform spreading inside each cell adds h²/12 to the variance
    assert got.std() == pytest.approx(math.sqrt(tau_sd ** 2 + 0.25 ** 2 / 12), rel=0.05)
    assert len(np.unique(got)) > 19_000, "draws must be continuous (no grid duplicates)"


def test_sir_reference_single_prior_concentrates_on_the_true_trajectory() -> None:
    prior = SIR_PRIORS["sir-single"]
    candidates = simulate_sir_candidates(prior, SIRReferenceConfig(substeps=2), seed=0)
    truth = candidates.states[0, ::2]                  # daily states (2 substeps per day)
    tau = 150
    offsets = torch.arange(-5.0, 0.0)[None]
    gen = torch.Generator().manual_seed(1)
    observed = truth[tau - 5:tau][None] + prior.obs_sigma * torch.randn((1, 5, 3), generator=gen,
                                                                         dtype=torch.float64)
    ref = sir_reference(candidates, offsets, observed, n_draws=1000, seed=2)
    assert ref.samples.shape == (1, 1000, 3)
    assert torch.allclose(ref.samples[0].sum(-1), torch.ones(1000, dtype=torch.float64), atol=1e-9)
    # the posterior mean state lies within a few posterior sds of the true state at tau
    err = (ref.samples[0].mean(0) - truth[tau]).abs()
    assert bool((err < 4 * ref.samples[0].std(0) + 1e-3).all()), (err, ref.samples[0].std(0))
    assert 1.0 < float(ref.ess[0]) < candidates.states.shape[1]


def test_sir_reference_rejects_offsets_off_grid() -> None:
    candidates = _ramp_candidates(0.01)
    with pytest.raises(ConfigError, match="multiples"):
        sir_reference(candidates, torch.tensor([[-0.1, -1.0]]), torch.zeros((1, 2, 3)), 10, 0)


def test_vehicle_reference_weights_use_the_context_times() -> None:
    """Two hand-made candidates that differ only at t = 3 and t = 8: a window observing t = 3
    (forward, target 4) must select by t = 3, one observing t = 8 (backward, target 7) by t = 8."""
    config = get_vehicle_config("vehicle-full")
    t = torch.arange(config.n_steps + 1, dtype=torch.float64)
    base = torch.stack([t, 0 * t], -1)
    a, b = base.clone(), base.clone()
    a[3, 1], b[3, 1] = 10.0, -10.0                       # differ at t = 3
    a[8, 1], b[8, 1] = -10.0, 10.0                       # and the other way round at t = 8
    a[[4, 7], 0] += 100.0                                # targets tell the candidates apart
    positions = torch.stack([a, b] * 500)                # M = 1000, alternating a, b
    candidates = VehicleCandidates(positions=positions, config=config)
    forward = vehicle_reference(candidates, torch.tensor([[2.0, 3.0]]),
                                torch.tensor([[[2.0, 0.0], [3.0, 10.0]]]), torch.tensor([4.0]),
                                n_draws=200, seed=0)
    backward = vehicle_reference(candidates, torch.tensor([[8.0, 9.0]]),
                                 torch.tensor([[[8.0, 10.0], [9.0, 0.0]]]), torch.tensor([7.0]),
                                 n_draws=200, seed=0)
    assert bool((forward.samples[0, :, 0] == 104.0).all())     # candidate a at t = 4
    assert bool((backward.samples[0, :, 0] == 7.0).all())      # candidate b at t = 7
    assert float(forward.ess[0]) == pytest.approx(500.0, rel=1e-6)


def test_vehicle_reference_from_simulator_before_switch_is_unimodal() -> None:
    config = get_vehicle_config("vehicle-full")
    from pipeline.inference.reference import simulate_vehicle_candidates

    candidates = simulate_vehicle_candidates(config, 4000, seed=0)
    truth = candidates.positions[0]
    times = torch.arange(0.0, 5.0)[None]
    ref = vehicle_reference(candidates, times, truth[:5][None], torch.tensor([5.0]), 1000, seed=1)
    # before the switch (t = 5.5) every vehicle follows the same nominal path up to process noise
    nominal = simulate_nominal(config, 1.0)[5, :2]
    assert torch.allclose(ref.samples[0].mean(0), nominal, atol=0.1)
    assert float((ref.samples[0] - nominal).norm(dim=-1).max()) < 1.0
    assert float(ref.ess[0]) > 3000


def test_reference_refuses_a_prior_whose_beta_drifts():
    from pipeline.errors import ConfigError
    from pipeline.inference.reference import SIRReferenceConfig, simulate_sir_candidates
    from pipeline.systems.sir import SIR_PRIORS

    with pytest.raises(ConfigError, match="constant beta"):
        simulate_sir_candidates(SIR_PRIORS["sir-sf"], SIRReferenceConfig(), seed=0)
