"""A multi-wave epidemic prior for forecasting reported cases: SIRS with a fixed reporting window.

The SF series is a sequence of waves (five by 2022), each started by a change of transmission
(variants, seasons, behaviour) rather than by a fresh epidemic in a naive population. A
single-wave SIR prior teaches a flow that "low I late in an epidemic means decline"; this prior
gives every level of I every direction, so a model trained on it has to read the trend.

Daily discrete-time dynamics per trajectory (population fractions, N = the SF population):

* infectious pressure P_t = n_{t-1} + … + n_{t-L}: an infection is infectious for exactly L days,
  the same fixed window the S/I/R conversion (:mod:`pipeline.data.sf.sir_transform`) applies to
  reported cases;
* new infections n_t = S_t (1 − exp(−β_t P_t − ι)), with an importation hazard ι;
* waning S_{t+1} = S_t − n_t + ω (1 − S_t − P_t) (SIRS: immunity lost at rate ω);
* transmission log β_t is mean-reverting (Ornstein–Uhlenbeck towards log(R̄/L)) with daily
  volatility σ and rare jumps (new variants, interventions): log β_{t+1} = log β_t
  + θ (μ − log β_t) + σ ε_t + J_t, J_t ≠ 0 with probability ``jump_rate`` per day;
* reported cases c_t ~ Poisson(N n_t w_{dow(t)} G_t), G_t ~ Gamma(k, 1/k) (negative binomial
  reporting noise) with weekday factors w (mean 1).

Each trajectory draws its own ranges' values (``WavePrior``), so the ensemble spans slow and fast
epidemics, calm and volatile transmission, clean and noisy reporting. Simulation is vectorized
over trajectories (one loop over days).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from pipeline.data.sf.sir_transform import SF_POPULATION_2020_CENSUS
from pipeline.errors import ConfigError

REPORTING_WINDOW_DAYS = 7


@dataclass(frozen=True)
class WavePrior:
    """Ranges each trajectory's settings are drawn from (uniform unless named log-uniform)."""

    population: int = SF_POPULATION_2020_CENSUS
    window_days: int = REPORTING_WINDOW_DAYS
    days: int = 200
    burn_in_days: int = 30
    reproduction_mean: tuple[float, float] = (0.8, 1.3)    # R̄ = β̄ L, the level log β reverts to
    reproduction_start: tuple[float, float] = (0.6, 1.8)   # R at day 0
    reversion_per_day: tuple[float, float] = (0.005, 0.08)  # θ
    volatility_per_day: tuple[float, float] = (0.005, 0.06)  # σ of log β per day
    jump_rate_per_day: float = 1.0 / 120.0
    jump_sd: float = 0.5
    initial_incidence: tuple[float, float] = (5e-6, 2e-3)  # n per day, log-uniform
    initial_susceptible: tuple[float, float] = (0.75, 1.0)
    importation: tuple[float, float] = (3e-7, 1e-5)        # ι per day, log-uniform
    waning_per_day: tuple[float, float] = (0.0, 1.0 / 180.0)
    weekday_sd: tuple[float, float] = (0.0, 0.3)
    dispersion: tuple[float, float] = (10.0, 1000.0)       # k, log-uniform

    @property
    def beta_range(self) -> tuple[float, float]:
        """The transmission rate's starting range, R at day 0 over L (per susceptible)."""
        return (self.reproduction_start[0] / self.window_days,
                self.reproduction_start[1] / self.window_days)

    def __post_init__(self) -> None:
        if self.days <= self.burn_in_days:
            raise ConfigError(f"WavePrior.days={self.days} must exceed burn_in_days="
                              f"{self.burn_in_days}")
        if self.window_days < 1 or self.population < 1:
            raise ConfigError("WavePrior: window_days and population must be >= 1")
        for name in ("reproduction_mean", "reproduction_start", "reversion_per_day",
                     "volatility_per_day", "initial_incidence", "initial_susceptible",
                     "importation", "waning_per_day", "weekday_sd", "dispersion"):
            low, high = getattr(self, name)
            if not 0 <= low <= high:
                raise ConfigError(f"WavePrior.{name}={getattr(self, name)}: need 0 <= low <= high")


@dataclass(frozen=True, eq=False)
class WaveEnsemble:
    """``cases (M, T)`` reported daily counts after burn-in; ``infections (M, T)`` true daily
    infections and ``susceptible (M, T)`` the susceptible share at the start of each day
    (fractions); ``log_beta (M, T)``; the prior that made them."""

    cases: NDArray[np.int64]
    infections: NDArray[np.float64]
    susceptible: NDArray[np.float64]
    log_beta: NDArray[np.float64]
    prior: WavePrior


def _uniform(rng: np.random.Generator, bounds: tuple[float, float], n: int) -> NDArray[np.float64]:
    return rng.uniform(bounds[0], bounds[1], size=n)


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float],
                 n: int) -> NDArray[np.float64]:
    return np.exp(rng.uniform(math.log(bounds[0]), math.log(bounds[1]), size=n))


def _weekday_factors(rng: np.random.Generator, sd: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, 7) multiplicative weekday effects with mean 1 per trajectory."""
    raw = np.exp(sd[:, None] * rng.standard_normal((sd.size, 7)))
    return raw / raw.mean(axis=1, keepdims=True)


def simulate_waves(prior: WavePrior, n_trajectories: int, seed: int) -> WaveEnsemble:
    """Simulate ``n_trajectories`` epidemics of ``prior.days`` days (burn-in dropped)."""
    if n_trajectories < 1:
        raise ConfigError(f"n_trajectories={n_trajectories} must be >= 1")
    rng = np.random.default_rng(seed)
    m, window = n_trajectories, prior.window_days
    mean_log_beta = np.log(_uniform(rng, prior.reproduction_mean, m) / window)
    log_beta = np.log(_uniform(rng, prior.reproduction_start, m) / window)
    theta = _uniform(rng, prior.reversion_per_day, m)
    sigma = _uniform(rng, prior.volatility_per_day, m)
    importation = _log_uniform(rng, prior.importation, m)
    waning = _uniform(rng, prior.waning_per_day, m)
    weekday = _weekday_factors(rng, _uniform(rng, prior.weekday_sd, m))
    dispersion = _log_uniform(rng, prior.dispersion, m)
    susceptible = _uniform(rng, prior.initial_susceptible, m)
    recent = np.repeat(_log_uniform(rng, prior.initial_incidence, m)[:, None], window, axis=1)

    days = prior.days
    infections = np.empty((m, days))
    susceptibles = np.empty((m, days))
    log_betas = np.empty((m, days))
    for t in range(days):
        pressure = recent.sum(axis=1)
        hazard = np.exp(log_beta) * pressure + importation
        new = susceptible * -np.expm1(-hazard)
        infections[:, t], susceptibles[:, t], log_betas[:, t] = new, susceptible, log_beta
        susceptible = susceptible - new + waning * np.clip(1.0 - susceptible - pressure, 0.0, 1.0)
        recent = np.concatenate([recent[:, 1:], new[:, None]], axis=1)
        jumps = (rng.random(m) < prior.jump_rate_per_day) * prior.jump_sd * rng.standard_normal(m)
        log_beta = (log_beta + theta * (mean_log_beta - log_beta)
                    + sigma * rng.standard_normal(m) + jumps)

    dow = weekday[:, np.arange(days) % 7]
    noise = rng.gamma(dispersion[:, None], 1.0 / dispersion[:, None], size=(m, days))
    cases = rng.poisson(prior.population * infections * dow * noise)
    keep = slice(prior.burn_in_days, days)
    return WaveEnsemble(cases=cases[:, keep].astype(np.int64), infections=infections[:, keep],
                        susceptible=susceptibles[:, keep], log_beta=log_betas[:, keep], prior=prior)


# ----------------------------------------------------------------------------- S/I/R view
#
# The joint state/parameter flows and the NF-seeded SMC see this prior through the S/I/R
# conversion of :mod:`pipeline.data.sf.sir_transform` applied to its reported cases, so they model
# the same quantities the SF series holds: I_t = the cases reported in the last L days over N,
# R_t = the cases reported before that (plus the cases reported before the series started) over
# N, S_t = 1 − I_t − R_t. The recovery rate is γ = 1/L by construction (the window removes every
# case after exactly L days), so it is stated, not estimated. The transmission rate reported
# with it is the one these coordinates imply: R_t = β_t S_t^true L is the reproduction number
# of the simulated epidemic, and β^obs_t = R_t / (L S_t) the rate per *observed* susceptible,
# so that R_t = β^obs S / γ holds in the coordinates every report shows.

REMOVED_BEFORE_RANGE = (1e-6, 0.15)   # cases reported before the first day, as a share of N


def recovery_rate(prior: WavePrior) -> float:
    """γ = 1/L per day: the conversion's fixed infectious window, not a free parameter."""
    return 1.0 / prior.window_days


def observed_sir(cases: NDArray[np.integer] | NDArray[np.floating], population: int,
                 window_days: int, removed_before: NDArray[np.float64] | float = 0.0
                 ) -> NDArray[np.float64]:
    """``(..., T − L + 1, 3)`` S, I, R of daily reported ``cases (..., T)`` as the conversion
    computes them, from day L − 1 on (the first day with a whole window). ``removed_before``:
    the share of N reported before day 0 (scalar or ``(...,)``)."""
    c = np.asarray(cases, dtype=np.float64)
    cumulative = np.concatenate([np.zeros(c.shape[:-1] + (1,)), np.cumsum(c, axis=-1)], axis=-1)
    infectious = (cumulative[..., window_days:] - cumulative[..., :-window_days]) / population
    before = np.asarray(removed_before, dtype=np.float64)[..., None]
    removed = before + cumulative[..., :-window_days] / population
    susceptible = (1.0 - infectious) - removed
    return np.stack([susceptible, infectious, removed], axis=-1)


@dataclass(frozen=True, eq=False)
class WaveSIRView:
    """A wave ensemble in S/I/R coordinates (module section above): ``sir (M, T', 3)`` the
    conversion's S/I/R of the reported cases, ``reproduction (M, T')`` R_t = β_t S_t^true L,
    ``beta (M, T')`` = β^obs_t = R_t / (L S_t), on days ``L − 1 …`` of the ensemble."""

    sir: NDArray[np.float64]
    reproduction: NDArray[np.float64]
    beta: NDArray[np.float64]
    gamma: float


def sir_view(ensemble: WaveEnsemble, seed: int) -> WaveSIRView:
    """The ensemble through the S/I/R conversion; each trajectory draws the share of N reported
    before its first day (uniform in :data:`REMOVED_BEFORE_RANGE`, from ``seed``): later waves
    start from a population with earlier cases on record, as SF's do."""
    prior = ensemble.prior
    rng = np.random.default_rng(seed)
    before = rng.uniform(*REMOVED_BEFORE_RANGE, size=ensemble.cases.shape[0])
    sir = observed_sir(ensemble.cases, prior.population, prior.window_days, before)
    keep = slice(prior.window_days - 1, None)
    reproduction = np.exp(ensemble.log_beta[:, keep]) * ensemble.susceptible[:, keep] \
        * prior.window_days
    beta = reproduction / (prior.window_days * sir[..., 0])
    return WaveSIRView(sir=sir, reproduction=reproduction, beta=beta,
                       gamma=recovery_rate(prior))
