"""Reference ("true") posteriors for the paper's KL tables, by likelihood-weighting simulator draws.

The paper compares 1,000 samples of each estimate with "the true distribution" of the target
without saying how that distribution was obtained. Our protocol: the true distribution of the
target given a context window is the simulator's own posterior,

    p(x_target | o_context) ∝ ∫ p(o_context | trajectory) p(trajectory) [x_target of trajectory],

computed by importance sampling with the prior as proposal:

1. simulate many candidate trajectories from the prior the training data came from;
2. give each candidate the log-likelihood of the window's observed values under the dataset's
   Gaussian observation noise, evaluated at the context times (log-weights, normalised with
   ``logsumexp``; vectorized over candidates and windows);
3. the reference is the weighted distribution of the candidates' target value, resampled
   (multinomially, i.i.d.) to ``n_draws`` = 1,000 draws; its Kish effective sample size
   ``ESS = 1 / Σ w²`` says how many candidates really carry it.

What the candidates are:

* **SIR.** The context carries only *relative* time (t_obs − t_target), so the position of the
  window along the epidemic is unknown to the model: candidates are (β, γ) from the prior (one
  fixed pair for ``sir-single``) × every time position τ of the target along the trajectory such
  that all context times lie inside the simulated horizon. τ is treated as *continuous*: the
  ODE is solved on a grid ``substeps`` times finer than a day, candidates sit on that grid, and
  a drawn candidate's τ is spread uniformly over its grid cell (target by linear interpolation).
  Without this, ``sir-single`` would have a handful of support points near the peak (a discrete
  "truth" against which any density has infinite KL), and the KL would measure grid artefacts.
* **Vehicle.** The dynamics are stochastic (ψ ∈ {−1, +1}, process noise on v and φ) and
  time-inhomogeneous, and the absolute times of the window are known to the evaluator:
  candidates are M simulated vehicles; the weights use their positions at the window's context
  times; the target is the candidate's position at the target time.

The KL floor: two references built from *independent* candidate sets, compared with the same
k-NN estimator (:func:`pipeline.evaluation.metrics.knn_kl_divergence`). It shows what "0" looks like for
this estimator at this sample size (finite samples, duplicates from resampling, the reference's
own Monte-Carlo error); an estimate cannot be told apart from the truth below it.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.systems.sir import DTYPE, SIRPrior, observation_log_likelihood, \
    sample_initial_states, sample_parameters, simulate_sir
from pipeline.systems.vehicle import VehicleConfig, simulate_vehicle
from pipeline.names import COMPARTMENTS

DEFAULT_DRAWS = 1000
_CHUNK = 16


@dataclass(frozen=True, eq=False)
class ReferencePosterior:
    """``samples (B, n_draws, D)`` float64 for B windows; ``ess (B,)`` Kish ESS of the weights;
    ``n_candidates`` = number of weighted candidates per window."""

    samples: Tensor
    ess: Tensor
    n_candidates: int
    names: tuple[str, ...]


def normalize_log_weights(log_weights: Tensor) -> Tensor:
    """Subtract the ``logsumexp`` over the last axis (weights sum to 1); raises if all are -inf."""
    total = torch.logsumexp(log_weights, dim=-1, keepdim=True)
    if not bool(torch.isfinite(total).all()):
        raise ConfigError("every candidate has zero likelihood for some window: the observations "
                          "are impossible under the simulator's prior")
    return log_weights - total


def kish_ess(log_weights: Tensor) -> Tensor:
    """Kish effective sample size 1 / Σ w² of (unnormalised) log-weights over the last axis."""
    w = normalize_log_weights(log_weights).exp()
    return 1.0 / (w * w).sum(dim=-1)


def draw_indices(log_weights: Tensor, n_draws: int, generator: torch.Generator) -> Tensor:
    """``(B, n_draws)`` i.i.d. multinomial draws of candidate indices from log-weights (B, M)."""
    probabilities = normalize_log_weights(log_weights).exp()
    return torch.multinomial(probabilities, n_draws, replacement=True, generator=generator)


def weighted_reference(predicted_observations: Tensor, candidate_targets: Tensor,
                       observed: Tensor, obs_sigma: float, n_draws: int, seed: int,
                       names: tuple[str, ...] = ()) -> ReferencePosterior:
    """The generic step: weight M candidates by B windows' observations, resample the targets.

    ``predicted_observations (M, B, R, C)`` (noise-free observed values of each candidate at each
    window's context times), ``candidate_targets (M, B, D)``, ``observed (B, R, C)``; Gaussian
    N(0, obs_sigma²) noise on every observed value. Returns draws ``(B, n_draws, D)``.
    """
    observed = torch.as_tensor(observed, dtype=torch.float64)
    if predicted_observations.shape[1:] != observed.shape or \
            candidate_targets.shape[:2] != predicted_observations.shape[:2]:
        raise ConfigError(f"weighted_reference: shapes predicted {tuple(predicted_observations.shape)}, "
                          f"targets {tuple(candidate_targets.shape)}, observed "
                          f"{tuple(observed.shape)} do not match (M, B, R, C) / (M, B, D) / (B, R, C)")
    log_w = observation_log_likelihood(observed[None], predicted_observations.double(),
                                       obs_sigma).sum(-1).T                          # (B, M)
    index = draw_indices(log_w, n_draws, torch.Generator().manual_seed(seed))       # (B, n)
    window = torch.arange(observed.shape[0])[:, None]
    samples = candidate_targets.double()[index, window]                              # (B, n, D)
    return ReferencePosterior(samples=samples, ess=kish_ess(log_w),
                              n_candidates=int(candidate_targets.shape[0]), names=names)


# --------------------------------------------------------------------------------------- SIR


@dataclass(frozen=True)
class SIRReferenceConfig:
    """``n_parameter_draws`` (β, γ) from the prior (1 if the prior fixes them); ``substeps`` per
    ``prior.dt`` of the τ grid; ``n_draws`` reference draws per window."""

    n_parameter_draws: int = 1000
    substeps: int = 4
    n_draws: int = DEFAULT_DRAWS

    def __post_init__(self) -> None:
        if self.n_parameter_draws < 1 or self.substeps < 1 or self.n_draws < 2:
            raise ConfigError(f"SIRReferenceConfig: n_parameter_draws={self.n_parameter_draws}, "
                              f"substeps={self.substeps} must be >= 1 and n_draws={self.n_draws} "
                              ">= 2")


@dataclass(frozen=True, eq=False)
class SIRCandidates:
    """Trajectories on the fine grid: ``states (K, G, 3)`` at times ``k·h``, params ``(K, 2)``."""

    states: Tensor
    parameters: Tensor
    step: float
    prior: SIRPrior


def simulate_sir_candidates(prior: SIRPrior, config: SIRReferenceConfig, seed: int) -> SIRCandidates:
    """Candidate trajectories from the prior on a grid ``substeps`` times finer than ``prior.dt``."""
    if prior.beta_varies_in_time:
        raise ConfigError(f"reference posteriors assume a constant beta; prior {prior.name!r} "
                          "lets it drift (beta_walk_sigma > 0)")
    generator = torch.Generator().manual_seed(seed)
    k = 1 if prior.parameters_fixed and prior.initial_state_fixed else config.n_parameter_draws
    beta, gamma = sample_parameters(prior, k, generator)
    step = prior.dt / config.substeps
    x0 = sample_initial_states(prior, k, generator)
    states = simulate_sir(x0, beta, gamma, prior.n_steps * config.substeps, step)
    return SIRCandidates(states=states, parameters=torch.stack([beta, gamma], -1), step=step,
                         prior=prior)


def sir_reference(candidates: SIRCandidates, offsets: Tensor, observed: Tensor, n_draws: int,
                  seed: int) -> ReferencePosterior:
    """Reference posteriors of the state (S, I, R) for B SIR windows.

    ``offsets (B, R)``: context times relative to the target (t_obs − t_target, the dataset's time
    channel; multiples of the fine step); ``observed (B, R, 3)``: the window's observed values.
    Prior over candidates: uniform over parameter draws × target positions τ on the fine grid
    whose context times all fall inside [0, horizon]. Returns draws with τ continuous (module doc).
    """
    offsets = torch.as_tensor(offsets, dtype=DTYPE)
    observed = torch.as_tensor(observed, dtype=DTYPE)
    if offsets.ndim != 2 or observed.shape != (*offsets.shape, 3):
        raise ConfigError(f"sir_reference: offsets (B, R) and observed (B, R, 3) expected, got "
                          f"{tuple(offsets.shape)} and {tuple(observed.shape)}")
    fine = offsets / candidates.step
    lag = torch.round(fine).long()                                                   # (B, R)
    if not bool(torch.allclose(fine, lag.to(DTYPE), atol=1e-6)):
        raise ConfigError(f"sir_reference: context offsets {offsets[0].tolist()} are not multiples "
                          f"of the reference grid step {candidates.step}")
    states = candidates.states                                                       # (K, G, 3)
    n_grid = states.shape[1]
    sigma = candidates.prior.obs_sigma
    generator = torch.Generator().manual_seed(seed)
    samples, ess = [], []
    for b in range(offsets.shape[0]):  # windows differ in valid τ range; candidates vectorized
        lo = max(0, -int(lag[b].min()))
        hi = n_grid - max(0, int(lag[b].max()))                                      # τ in [lo, hi)
        if hi <= lo:
            raise ConfigError(f"sir_reference: window {b} spans more than the simulated horizon")
        tau = torch.arange(lo, hi)
        log_w = torch.zeros((states.shape[0], len(tau)), dtype=DTYPE)
        for r in range(lag.shape[1]):
            log_w += observation_log_likelihood(observed[b, r], states[:, tau + lag[b, r]], sigma)
        flat = log_w.reshape(1, -1)
        ess.append(kish_ess(flat)[0])
        index = draw_indices(flat, n_draws, generator)[0]
        traj, cell = index // len(tau), tau[index % len(tau)]
        # τ uniform within its grid cell [cell - 1/2, cell + 1/2] (clamped to the grid).
        position = (cell.to(DTYPE) + torch.rand(n_draws, generator=generator, dtype=DTYPE) - 0.5
                    ).clamp(0, n_grid - 1)
        left = position.floor().long().clamp(max=n_grid - 2)
        frac = (position - left.to(DTYPE))[:, None]
        samples.append((1 - frac) * states[traj, left] + frac * states[traj, left + 1])
    return ReferencePosterior(samples=torch.stack(samples), ess=torch.stack(ess),
                              n_candidates=int(states.shape[0] * n_grid), names=COMPARTMENTS)


# ----------------------------------------------------------------------------------- vehicle


@dataclass(frozen=True, eq=False)
class VehicleCandidates:
    """``positions (M, T, 2)`` float64 on ``config``'s time grid."""

    positions: Tensor
    config: VehicleConfig


def simulate_vehicle_candidates(config: VehicleConfig, n_trajectories: int,
                                seed: int) -> VehicleCandidates:
    """M vehicles from the system's own simulator (ψ ∈ {−1, +1}, process noise)."""
    ensemble = simulate_vehicle(config, n=n_trajectories, seed=seed, dtype=torch.float64)
    return VehicleCandidates(positions=ensemble.states[..., :2].contiguous(), config=config)


def grid_indices(times: Tensor, config: VehicleConfig) -> Tensor:
    """Indices of absolute ``times`` on the config's grid; raises if a time is off the grid."""
    times = torch.as_tensor(times, dtype=torch.float64)
    exact = times / config.dt
    index = torch.round(exact).long()
    if not bool(torch.allclose(exact, index.to(torch.float64), atol=1e-6)) or \
            bool((index < 0).any()) or bool((index > config.n_steps).any()):
        raise ConfigError(f"vehicle reference: times {times.flatten()[:8].tolist()} are not on "
                          f"the grid 0, {config.dt}, …, {config.t_end}")
    return index


def vehicle_reference(candidates: VehicleCandidates, context_times: Tensor, observed: Tensor,
                      target_times: Tensor, n_draws: int, seed: int) -> ReferencePosterior:
    """Reference posteriors of the position at ``target_times (B,)`` for B vehicle windows.

    ``context_times (B, R)`` absolute times; ``observed (B, R, 2)`` the window's noisy positions.
    All windows are weighted in one batched computation over the M candidates.
    """
    context_idx = grid_indices(context_times, candidates.config)                     # (B, R)
    target_idx = grid_indices(target_times, candidates.config)                       # (B,)
    observed = torch.as_tensor(observed, dtype=torch.float64)
    if observed.shape != (*context_idx.shape, 2):
        raise ConfigError(f"vehicle_reference: observed must be (B, R, 2) = "
                          f"{(*context_idx.shape, 2)}, got {tuple(observed.shape)}")
    positions = candidates.positions                                                  # (M, T, 2)
    # Windows in chunks: (M, chunk, R, 2) gathers stay ~50 MB at M = 20,000.
    parts = [weighted_reference(positions[:, context_idx[s:s + _CHUNK]],
                                positions[:, target_idx[s:s + _CHUNK]], observed[s:s + _CHUNK],
                                candidates.config.obs_sigma, n_draws, seed + s,
                                names=("p_x", "p_y"))
             for s in range(0, len(target_idx), _CHUNK)]
    return ReferencePosterior(samples=torch.cat([p.samples for p in parts]),
                              ess=torch.cat([p.ess for p in parts]),
                              n_candidates=parts[0].n_candidates, names=("p_x", "p_y"))
