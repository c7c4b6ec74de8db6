"""Cross-check against pyro's SMCFilter (the paper's implementation) on the same SIR model."""
from __future__ import annotations

import math

import torch

from pipeline.inference.smc import SMCConfig, run_filter
from pipeline.inference.smc_models import SIRStateModel, run_pyro_sir_filter
from pipeline.systems.sir import simulate_ensemble

NAN = float("nan")
REPLICATES = 12
PARTICLES = 300


def test_filtered_means_agree_with_pyro_within_monte_carlo_error():
    """Same dynamics (RK4 + process noise + simplex projection), prior N(o_n, σ²), likelihood and
    particle budget; the paper's protocol on 3 windows (prior at n, updates n+1..n+4, propagation
    to n+5). Each filter is run REPLICATES times with independent seeds by both implementations;
    the replicate spreads give the Monte-Carlo standard errors of both averages, and the
    averages must agree within 4 combined standard errors at every step and compartment."""
    ensemble = simulate_ensemble("sir-single", n_trajectories=1, seed=21)
    starts = torch.tensor([40, 150, 420])
    index = starts[:, None] + torch.arange(6)
    obs = ensemble.observations[0, index].clone()
    prior = obs[:, 0].clone()
    obs[:, 0] = NAN
    obs[:, 5] = NAN
    # A larger process noise than the default makes resampling and noise matter in 5 steps.
    model = SIRStateModel.create(0.03, 0.01, prior, process_sigma=0.005)

    windows = len(starts)
    # Ours: all windows × replicates as one batch of independent filters.
    batch_model = SIRStateModel.create(0.03, 0.01, prior.repeat_interleave(REPLICATES, 0),
                                       process_sigma=0.005)
    ours = run_filter(batch_model, obs.repeat_interleave(REPLICATES, 0),
                      SMCConfig(num_particles=PARTICLES, seed=0, quantiles=()))
    ours_means = ours.mean.reshape(windows, REPLICATES, 6, 3)

    pyro_means = torch.stack([
        torch.stack([run_pyro_sir_filter(model.select(w), obs[w], PARTICLES, seed=100 * w + r)[0]
                     for r in range(REPLICATES)])
        for w in range(windows)])                                       # (W, R, 6, 3)

    standard_error = torch.sqrt(ours_means.var(1) / REPLICATES + pyro_means.var(1) / REPLICATES)
    difference = (ours_means.mean(1) - pyro_means.mean(1)).abs()
    assert bool((difference < 4 * standard_error + 1e-6).all()), (difference / standard_error)
    # The comparison has power: the Monte-Carlo error is far below the posterior spread.
    assert float(standard_error.max()) < 0.2 * float(ours.std[:, 1:].min())
    # Both land near the truth at n+4 (posterior sd ~ 0.01).
    truth = ensemble.states[0, index[:, 4]]
    assert float((pyro_means.mean(1)[:, 4] - truth).abs().max()) < 0.05
    assert math.isfinite(float(ours.log_evidence.sum()))
