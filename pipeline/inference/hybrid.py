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

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.inference.estimate import Estimator, ObservationWindow, sample_conditional, target_dim, \
    window_context, context_window_length
from pipeline.progress import ProgressReporter
from pipeline.inference.smc import DEFAULT_QUANTILES, SMCConfig, SMCResult, seeded_filter
from pipeline.inference.smc_models import DEFAULT_OBS_SIGMA, DEFAULT_PROCESS_SIGMA, SIRParamsModel, \
    project_to_simplex



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
        raise ConfigError(f"{int(bad.sum())} of {bad.numel()} flow draws seeding the SMC filter "
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
