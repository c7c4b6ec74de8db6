"""NF-seeded SMC (the paper's hybrid, section "Predicting Disease System Parameters").

"We predict the mean underlying system state and parameters, β and γ, using NF with
five-observation context … Then, we use those predictions as inputs to SMC considering SIR model
dynamics, and using real COVID-19 data as observations." The figure shows a 3σ filter.

Our reading: instead of seeding with the *mean* only, we seed the particle filter with N draws
from the joint flow's estimate p(S, I, R, β, γ | o_{n-5..n-1}) at the target time n — the mean
is then the particle mean, and the flow's uncertainty about β, γ becomes the filter's prior
(the paper's "mean" seeding is the special case of a point mass). The filter then runs
forward over the observations from n on (:func:`pipeline.inference.smc.seeded_filter`, SIR dynamics with
parameters as static state, :class:`pipeline.inference.smc_models.SIRParamsModel`).

Invalid flow draws (``HybridConfig.invalid_draws``): a flow in raw (S, I, R, β, γ) coordinates
has unbounded support while the SIR dynamics accept no negative proportions or rates, so by
default (``project``) the draws are mapped to valid particles: (S, I, R) projected onto the simplex
(clamped at 0, renormalised), β, γ clamped at 0, and the fraction that needed a clamp reported. A
model whose coordinates guarantee validity (the forecast's ``sir-log-ratio`` target transform)
runs with ``refuse``: an invalid draw then means a wrong model, and is an error, not a clamp.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.inference.estimate import Estimator, ObservationWindow, sample_conditional, target_dim, \
    window_context, context_window_length
from pipeline.progress import ProgressReporter
from pipeline.inference.smc import (DEFAULT_QUANTILES, SMCConfig, SMCResult, owned_planar,
                                    seeded_filter)
from pipeline.inference.smc_models import DEFAULT_OBS_SIGMA, DEFAULT_PROCESS_SIGMA, SIRParamsModel, \
    WaveRenewalModel, project_to_simplex, reporting_pattern
from pipeline.systems.waves import WavePrior



@dataclass(frozen=True)
class HybridConfig:
    """Particle count, seed, and the filter's SIR model noise (see :mod:`pipeline.inference.smc_models`)."""

    n_particles: int = 1000
    seed: int = 0
    obs_sigma: float = DEFAULT_OBS_SIGMA
    process_sigma: float = DEFAULT_PROCESS_SIGMA
    param_jitter: float = 0.0
    ess_threshold: float = 0.5
    quantiles: tuple[float, ...] = DEFAULT_QUANTILES  # weighted quantiles recorded per step
    invalid_draws: Literal["project", "refuse"] = "project"

    def __post_init__(self) -> None:
        if self.n_particles < 2:
            raise ConfigError(f"HybridConfig.n_particles={self.n_particles} must be >= 2")
        if self.obs_sigma <= 0:
            raise ConfigError(f"HybridConfig.obs_sigma={self.obs_sigma} must be > 0")
        if self.invalid_draws not in ("project", "refuse"):
            raise ConfigError(f"HybridConfig.invalid_draws must be 'project' or 'refuse', got "
                              f"{self.invalid_draws!r}")


@dataclass(frozen=True, eq=False)
class HybridResult:
    """``seed_particles (N, 5)`` (after projection), the full :class:`SMCResult` of the single
    filter, and the 3σ band / ESS per step at ``times (T,)``."""

    times: np.ndarray
    seed_particles: Tensor
    clamped_fraction: float
    smc: SMCResult

    @property
    def mean(self) -> Tensor:
        return self.smc.mean[0]

    @property
    def ess(self) -> Tensor:
        return self.smc.ess[0]

    def band(self, n_sigma: float = 3.0) -> tuple[Tensor, Tensor]:
        lower, upper = self.smc.sigma_band(n_sigma)
        return lower[0], upper[0]


def to_valid_particles(draws: Tensor) -> tuple[Tensor, float]:
    """(S, I, R) onto the simplex, (β, γ) >= 0; returns the particles and the clamped fraction."""
    if draws.shape[-1] != 5:
        raise ConfigError(f"NF-seeded SMC needs a joint model with target (S, I, R, beta, gamma); "
                          f"the estimator's target has {draws.shape[-1]} components")
    draws = draws.double()
    clamped = (draws < 0).any(dim=-1)
    state = project_to_simplex(draws[..., :3])
    params = draws[..., 3:].clamp(min=0.0)
    return torch.cat([state, params], dim=-1), float(clamped.double().mean())


def check_valid_draws(draws: Tensor) -> None:
    """Refuse joint draws that are not S/I/R states on the simplex with positive rates."""
    state, rates = draws[..., :3], draws[..., 3:]
    bad = ((state < 0).any(-1) | ((state.sum(-1) - 1).abs() > 1e-6)
           | (rates <= 0).any(-1) | ~torch.isfinite(draws).all(-1))
    if bool(bad.any()):
        raise ConfigError(f"{int(bad.sum())} of {bad.numel()} flow draws seeding the multi-wave model "
                          "are not valid S/I/R states with positive rates; the joint model must "
                          "use target_transform='sir-log-ratio' (retrain it)")


def nf_seeded_smc(estimator: Estimator, window: ObservationWindow, times: np.ndarray,
                  observations: np.ndarray, config: HybridConfig = HybridConfig(), *,
                  progress: ProgressReporter | None = None) -> HybridResult:
    """Seed particles from the joint flow at ``window.target_time``, then filter forward.

    ``window``: the forward context (observations before the target time). ``times (T,)``: the
    filter's times, ``times[0] == window.target_time``; ``observations (T, 3)``: observed
    (S, I, R) at those times (NaN rows = no observation, pure propagation).
    """
    times = np.asarray(times, dtype=np.float64)
    observations = np.asarray(observations, dtype=np.float64)
    if observations.shape != (len(times), 3):
        raise ConfigError(f"nf_seeded_smc: observations must be (T, 3) with T = {len(times)}, got "
                          f"{observations.shape}")
    if len(times) == 0 or abs(times[0] - window.target_time) > 1e-9:
        raise ConfigError(f"nf_seeded_smc: times[0] must be the window's target time "
                          f"{window.target_time}, got {times[:1].tolist()}")
    if target_dim(estimator) != 5:
        raise ConfigError("NF-seeded SMC needs a joint (state + beta, gamma) model: the "
                          f"estimator predicts {target_dim(estimator)} components, not 5")
    context, mask = window_context(window, "forward",
                                   context_window_length(estimator, window.n_rows))
    draws = sample_conditional(estimator, context, mask, config.n_particles, config.seed)[0]
    if config.invalid_draws == "refuse":
        check_valid_draws(draws.double())
        particles, clamped = draws.double(), 0.0
    else:
        if not bool(torch.isfinite(draws).all()):
            raise ConfigError("the joint flow produced non-finite draws for the seeding window")
        particles, clamped = to_valid_particles(draws)
    model = SIRParamsModel.create(prior_mean=particles[:, :3].mean(0),
                                  obs_sigma=config.obs_sigma, process_sigma=config.process_sigma,
                                  param_jitter=config.param_jitter)
    smc_config = SMCConfig(num_particles=config.n_particles, ess_threshold=config.ess_threshold,
                           seed=config.seed, quantiles=config.quantiles)
    result = seeded_filter(particles[None], torch.as_tensor(observations)[None], model, smc_config,
                           times=torch.as_tensor(times), progress=progress)
    return HybridResult(times=times, seed_particles=particles, clamped_fraction=clamped,
                        smc=result)


# -- NF-seeded SMC on the multi-wave model (the weekly forecast's) -----------------------------

@dataclass(frozen=True)
class WaveSMCConfig:
    """Particles, seed, resampling threshold, recorded quantiles, and how many recent days the
    reporting dispersion is estimated from."""

    n_particles: int = 1000
    seed: int = 0
    ess_threshold: float = 0.5
    quantiles: tuple[float, ...] = DEFAULT_QUANTILES
    pattern_days: int = 56

    def __post_init__(self) -> None:
        if self.n_particles < 2:
            raise ConfigError(f"WaveSMCConfig.n_particles={self.n_particles} must be >= 2")
        if self.pattern_days < 14:
            raise ConfigError(f"WaveSMCConfig.pattern_days={self.pattern_days} must be >= 14")


@dataclass(frozen=True, eq=False)
class WaveSMCRun:
    """F filters over the last T days: the result, the model, and the seed draws ``(F, N, 4)``
    of (S, I, R, β)."""

    smc: SMCResult
    model: WaveRenewalModel
    seed_draws: Tensor


def _static_prior_draws(prior: WavePrior, shape: tuple[int, int],
                        generator: torch.Generator) -> Tensor:
    """(F, N, 4) = μ, θ, σ, ι per particle from the prior's ranges (as ``simulate_waves``)."""
    u = torch.rand((4, *shape), generator=generator, dtype=torch.float64)

    def uniform(bounds: tuple[float, float], k: int) -> Tensor:
        return bounds[0] + (bounds[1] - bounds[0]) * u[k]

    log_import = (math.log(prior.importation[0])
                  + (math.log(prior.importation[1]) - math.log(prior.importation[0])) * u[3])
    mu = torch.log(uniform(prior.reproduction_mean, 0) / prior.window_days)
    return torch.stack([mu, uniform(prior.reversion_per_day, 1),
                        uniform(prior.volatility_per_day, 2), log_import.exp()], dim=-1)


def wave_particles(draws: Tensor, lag_shape: Tensor, prior: WavePrior,
                   generator: torch.Generator) -> Tensor:
    """(F, N, D) particles of :class:`WaveRenewalModel` from the joint flow's (S, I, R, β) draws
    ``(F, N, 4)``: the last L days' new cases are each draw's I spread over its window in
    ``lag_shape (F, L)`` (rows summing to 1, oldest day first); μ, θ, σ, ι from ``prior``."""
    check_valid_draws(draws)
    return torch.cat([draws, draws[..., 1:2] * lag_shape[:, None, :],
                      _static_prior_draws(prior, (draws.shape[0], draws.shape[1]), generator),
                      draws.new_zeros((*draws.shape[:2], 1))], dim=-1)


def wave_model(prior: WavePrior, population: Tensor | np.ndarray | float, dispersion: Tensor,
               *, forecasting: bool) -> WaveRenewalModel:
    """The prior as a state-space model for F places (``dispersion (F,)``); ``forecasting``
    proposes jumps at the prior's own rate (no importance correction), filtering more often."""
    num_filters = dispersion.shape[0]
    people = torch.as_tensor(population, dtype=torch.float64).reshape(-1, 1)
    model = WaveRenewalModel(population=people.expand(num_filters, 1),
                             dispersion=dispersion.reshape(-1, 1).double(),
                             window_days=prior.window_days, jump_rate=prior.jump_rate_per_day,
                             jump_sd=prior.jump_sd)
    return (dataclasses.replace(model, proposal_jump_rate=model.jump_rate) if forecasting
            else model)


def nf_seeded_wave_smc(estimator: Estimator, context: Tensor, mask: Tensor,
                       daily_cases: Tensor, population: Tensor, filter_days: int,
                       prior: WavePrior, config: WaveSMCConfig = WaveSMCConfig(), *,
                       progress: ProgressReporter | None = None) -> WaveSMCRun:
    """F independent NF-seeded filters on :class:`WaveRenewalModel`.

    ``daily_cases (F, T)``: each history's reported cases; the filter runs over the last
    ``filter_days`` days (T ≥ ``filter_days`` + 2L), observing each day's L-day sum (N·I);
    ``context``/``mask``: the forward joint flow's raw windows for the first filtered day (the
    days before it), one per filter; ``population (F,)``. The flow's (S, I, R, β) draws seed
    the particles; the last L days' new cases are the particle's I spread over its window in
    the shape the reports of the L days before had (weekday pattern divided out); μ, θ, σ, ι
    are drawn from ``prior``. The reporting dispersion comes from the last
    ``config.pattern_days`` days of ``daily_cases``.
    """
    cases = torch.as_tensor(daily_cases, dtype=torch.float64)
    num_filters, length = cases.shape
    lag = prior.window_days
    if length < filter_days + 2 * lag:
        raise ConfigError(f"NF-seeded SMC: {length} days of cases, need filter_days "
                          f"{filter_days} + {2 * lag}")
    if target_dim(estimator) != 4:
        raise ConfigError("the multi-wave NF-seeded SMC needs the joint (S, I, R, beta) flow; the "
                          f"estimator predicts {target_dim(estimator)} components")
    factors, dispersion = reporting_pattern(cases, min(config.pattern_days, length))
    draws = sample_conditional(estimator, context, mask, config.n_particles,
                               config.seed).double()                          # (F, N, 4)
    generator = torch.Generator().manual_seed(config.seed + 1)
    start = length - filter_days
    position = (torch.arange(start - lag, start) - length) % 7
    before = (cases[:, start - lag:start] + 0.5) / factors[:, position]
    particles = wave_particles(draws, before / before.sum(1, keepdim=True), prior, generator)
    model = wave_model(prior, population, dispersion, forecasting=False)
    cumulative = torch.cat([cases.new_zeros((num_filters, 1)), cases.cumsum(1)], dim=1)
    window_sums = cumulative[:, lag:] - cumulative[:, :-lag]                 # days L-1 … T-1
    observations = window_sums[:, -filter_days:, None]
    smc_config = SMCConfig(num_particles=config.n_particles, ess_threshold=config.ess_threshold,
                           seed=config.seed + 2, quantiles=config.quantiles)
    result = seeded_filter(particles, observations, model, smc_config,
                           times=torch.arange(filter_days, dtype=torch.float64),
                           progress=progress)
    return WaveSMCRun(smc=result, model=model, seed_draws=draws)


def forecast_weekly_reports(run: WaveSMCRun, weeks: int, seed: int) -> Tensor:
    """``(F, N, weeks)`` cases reported in each of the next ``weeks`` L-day weeks after the
    filters' last day (N·I at each week's end): the filtered particles, resampled by weight,
    simulated forward with the model's own dynamics (jumps at the prior's rate) and reporting."""
    generator = torch.Generator().manual_seed(seed)
    result = run.smc
    model = dataclasses.replace(run.model, proposal_jump_rate=run.model.jump_rate)
    weights = result.log_weights.exp()
    ancestors = torch.multinomial(weights, weights.shape[1], replacement=True,
                                  generator=generator)                       # (F, N)
    x = owned_planar(torch.gather(result.particles, 1,
                                  ancestors[..., None].expand(-1, -1, result.particles.shape[-1])),
                     torch.float64)
    totals = []
    for day in range(1, weeks * model.window_days + 1):
        x = model.transition(x, float(day), 1.0, generator)
        if day % model.window_days == 0:
            totals.append(model.sample_window_reports(x, generator))
    return torch.stack(totals, dim=-1)
