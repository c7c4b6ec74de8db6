"""The SIR epidemic model on population proportions, integrated with classical RK4.

Equations (paper, section "Epidemiological Population Dynamics")::

    dS/dt = -beta * I * S
    dI/dt =  beta * I * S - gamma * I
    dR/dt =  gamma * I

Readings of the paper (see docs/systems.md):

* Initial state S0 = 0.99, I0 = 0.01, R0 = 0. The paper prints I0 = 0.00 and R0 = 0.01, under
  which I stays exactly 0 and no epidemic starts (I = 0 is a fixed point of the equations); we
  read the two values as swapped.
* Horizon 1000 days with step dt = 1 day, i.e. 1001 states per trajectory (t = 0 … 1000).
* Observations are the state plus independent N(0, sigma^2) noise on every compartment,
  sigma = 0.027; observations are not clipped to [0, 1] nor renormalised (the paper adds
  Gaussian noise "to observations", nothing more).
* ``sir-single`` is one (beta, gamma) = (0.03, 0.01) trajectory observed through many independent
  noise realisations; ``sir-multi`` draws beta ~ U[0.02, 0.04], gamma ~ U[0.005, 0.025] per
  trajectory. Both hold N * 1001 * 3 >= 1.5 million observed values, like the paper's data.

``sir-sf`` is not the paper's: it is the prior the San Francisco forecast trains on, fitted to
what the SF series (``pipeline.data.sf.sir_transform``) looks like. The paper's ``sir-multi`` puts
every epidemic at I0 = 0.01 with infectious periods of 40-200 days and observation noise 0.027;
the SF series has I <= 0.026 (median 0.0008, so the paper's noise alone is 30x the signal), an
infectious period fixed by the conversion (L = 7 days now, gamma near 0.14; the prior was fitted
when it was 10 days, gamma near 0.1), S >= 0.86 and several waves. ``sir-sf`` therefore draws
gamma ~ U[0.07, 0.14] (L = 7-14 days, both conversions inside), beta ~ U[0.03, 0.3]
(daily growth rates -0.11 to +0.23, the 1st-95th percentile range of the series), a log-uniform
I0 in [1e-5, 5e-3] and an already-removed share R0 ~ U[1e-6, 0.15] (later waves start from a
partly immune population; the floor, about one person of SF's 874,000, keeps every state strictly
inside the simplex, so the forecast model's log-ratio coordinates log(R/S) of a backward window's
first-day target are finite; with R0 = 0 exactly they would be -inf), over 150 days (one
wave); observation noise 5e-4 is about the day-to-day scatter of SF's I around its weekly mean
(2.9e-4 measured) with room for the reporting artefacts of S and R. docs/systems.md has the
measured coverage of SF by this prior.

Everything is vectorized over the ensemble (no Python loop over trajectories; the only loop is
over time steps) and computed in float64, the project's simulation precision.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.names import COMPARTMENTS, PARAMETERS
from pipeline.progress import ProgressReporter, SilentProgress

DTYPE = torch.float64
# Advance the progress reporter every this many RK4 steps: per-step updates of a rich bar would
# cost more than the arithmetic of a 500-trajectory step.
_PROGRESS_BLOCK = 50


@dataclass(frozen=True)
class SIRPrior:
    """A named SIR ensemble: parameter ranges (uniform), initial state, time grid, noise, size.

    ``beta`` and ``gamma`` are closed intervals ``(low, high)``; ``low == high`` fixes the
    parameter. ``n_trajectories`` is the default ensemble size (500 gives 500 x 1001 x 3 =
    1,501,500 observed values, the paper's "over 1.5 million data points").
    """

    name: str
    beta: tuple[float, float]
    gamma: tuple[float, float]
    s0: float = 0.99
    i0: float = 0.01
    r0: float = 0.0
    # Ranged initial states (None: the fixed s0, i0, r0 above). I0 is log-uniform (epidemics of
    # every size), R0 uniform; S0 = 1 - I0 - R0.
    i0_range: tuple[float, float] | None = None
    r0_range: tuple[float, float] | None = None
    # Time-varying transmission: log beta follows a Gaussian random walk with this standard
    # deviation per sqrt(day) (0: beta constant, the paper's model); beta stays in BETA_BOUNDS.
    beta_walk_sigma: float = 0.0
    horizon_days: int = 1000
    dt: float = 1.0
    obs_sigma: float = 0.027
    n_trajectories: int = 500

    def __post_init__(self) -> None:
        for field_name in ("beta", "gamma"):
            low, high = getattr(self, field_name)
            if not (0.0 <= low <= high):
                raise ConfigError(f"SIR prior {self.name!r}: {field_name} range ({low}, {high}) "
                                  "must satisfy 0 <= low <= high")
        if self.i0_range is not None and not 0.0 < self.i0_range[0] <= self.i0_range[1] < 1.0:
            raise ConfigError(f"SIR prior {self.name!r}: i0_range {self.i0_range} must satisfy "
                              "0 < low <= high < 1 (log-uniform)")
        if self.r0_range is not None and not 0.0 <= self.r0_range[0] <= self.r0_range[1] < 1.0:
            raise ConfigError(f"SIR prior {self.name!r}: r0_range {self.r0_range} must satisfy "
                              "0 <= low <= high < 1")
        if (self.i0_range or (0, 0))[1] + (self.r0_range or (0, 0))[1] >= 1.0:
            raise ConfigError(f"SIR prior {self.name!r}: i0_range and r0_range leave no "
                              "susceptibles (their upper ends sum to >= 1)")
        if abs(self.s0 + self.i0 + self.r0 - 1.0) > 1e-12:
            raise ConfigError(f"SIR prior {self.name!r}: s0 + i0 + r0 = "
                              f"{self.s0 + self.i0 + self.r0} must be 1 (proportions)")
        if self.dt <= 0 or self.horizon_days <= 0:
            raise ConfigError(f"SIR prior {self.name!r}: dt={self.dt} and "
                              f"horizon_days={self.horizon_days} must be positive")
        if abs(self.horizon_days / self.dt - round(self.horizon_days / self.dt)) > 1e-9:
            raise ConfigError(f"SIR prior {self.name!r}: horizon_days={self.horizon_days} is not "
                              f"a whole number of steps dt={self.dt}")
        if self.beta_walk_sigma < 0:
            raise ConfigError(f"SIR prior {self.name!r}: beta_walk_sigma="
                              f"{self.beta_walk_sigma} < 0")
        if self.obs_sigma < 0:
            raise ConfigError(f"SIR prior {self.name!r}: obs_sigma={self.obs_sigma} < 0")
        if self.n_trajectories < 1:
            raise ConfigError(f"SIR prior {self.name!r}: n_trajectories={self.n_trajectories} < 1")

    @property
    def n_steps(self) -> int:
        return round(self.horizon_days / self.dt)

    @property
    def parameters_fixed(self) -> bool:
        return self.beta[0] == self.beta[1] and self.gamma[0] == self.gamma[1]

    @property
    def beta_varies_in_time(self) -> bool:
        return self.beta_walk_sigma > 0.0

    @property
    def initial_state_fixed(self) -> bool:
        return self.i0_range is None and self.r0_range is None

    def initial_state(self) -> Tensor:
        """The fixed (S0, I0, R0); a prior with ranged initial states has none."""
        if not self.initial_state_fixed:
            raise ConfigError(f"SIR prior {self.name!r} draws its initial states; use "
                              "sample_initial_states")
        return torch.tensor([self.s0, self.i0, self.r0], dtype=DTYPE)

    def times(self) -> Tensor:
        return torch.arange(self.n_steps + 1, dtype=DTYPE) * self.dt


SIR_PRIORS: dict[str, SIRPrior] = {
    "sir-single": SIRPrior(name="sir-single", beta=(0.03, 0.03), gamma=(0.01, 0.01)),
    "sir-multi": SIRPrior(name="sir-multi", beta=(0.02, 0.04), gamma=(0.005, 0.025)),
    "sir-sf": SIRPrior(name="sir-sf", beta=(0.03, 0.3), gamma=(0.07, 0.14),
                       i0_range=(1e-5, 5e-3), r0_range=(1e-6, 0.15), horizon_days=150,
                       obs_sigma=5e-4, n_trajectories=2000, beta_walk_sigma=0.08),
}


def get_prior(name: str) -> SIRPrior:
    try:
        return SIR_PRIORS[name]
    except KeyError:
        raise ConfigError(f"unknown SIR prior {name!r}; known: {sorted(SIR_PRIORS)}") from None


@dataclass(frozen=True)
class SIREnsemble:
    """Simulated trajectories and their noisy observations (float64).

    ``times (T,)``, ``states (N, T, 3)`` = (S, I, R), ``observations (N, T, 3)``,
    ``beta (N,)``, ``gamma (N,)``. Every state is observed (no dropout for SIR).
    """

    times: Tensor
    states: Tensor
    observations: Tensor
    beta: Tensor
    gamma: Tensor
    prior: SIRPrior
    seed: int
    beta_path: Tensor | None = None  # (N, T): beta in effect from each time on (walk priors)

    @property
    def n_trajectories(self) -> int:
        return int(self.states.shape[0])

    @property
    def n_observed_values(self) -> int:
        return int(self.observations.numel())

    @property
    def parameters(self) -> Tensor:
        """``(N, 2)`` = (beta, gamma) per trajectory (beta at t = 0 when it varies)."""
        return torch.stack([self.beta, self.gamma], dim=-1)

    @property
    def parameter_paths(self) -> Tensor:
        """``(N, T, 2)`` = (beta, gamma) in effect at every time."""
        n_times = self.times.shape[0]
        beta = (self.beta_path if self.beta_path is not None
                else self.beta[:, None].expand(-1, n_times))
        return torch.stack([beta, self.gamma[:, None].expand(-1, n_times)], dim=-1)


def sir_rhs(x: Tensor, beta: Tensor | float, gamma: Tensor | float) -> Tensor:
    """Time derivative of ``x (..., 3)`` = (S, I, R); ``beta, gamma`` broadcast against ``(...)``."""
    beta_t = torch.as_tensor(beta, dtype=x.dtype, device=x.device)
    gamma_t = torch.as_tensor(gamma, dtype=x.dtype, device=x.device)
    s, i = x[..., 0], x[..., 1]
    infection = beta_t * i * s
    recovery = gamma_t * i
    return torch.stack([-infection, infection - recovery, recovery], dim=-1)


def rk4_step(x: Tensor, beta: Tensor | float, gamma: Tensor | float, dt: float) -> Tensor:
    """One classical fourth-order Runge-Kutta step of the SIR equations (autonomous system).

    The increments of the three stages sum to zero component-wise, so S + I + R is conserved
    to rounding error.
    """
    k1 = sir_rhs(x, beta, gamma)
    k2 = sir_rhs(x + 0.5 * dt * k1, beta, gamma)
    k3 = sir_rhs(x + 0.5 * dt * k2, beta, gamma)
    k4 = sir_rhs(x + dt * k3, beta, gamma)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def simulate_sir(x0: Tensor, beta: Tensor, gamma: Tensor, n_steps: int, dt: float,
                 progress: ProgressReporter | None = None) -> Tensor:
    """Integrate ``n_steps`` RK4 steps from ``x0 (N, 3)`` -> trajectories ``(N, n_steps + 1, 3)``.

    ``beta, gamma: (N,)`` (or scalars); ``beta`` may also be ``(N, n_steps)``, one value per
    step (time-varying transmission). The output includes the initial state at index 0 and has
    the dtype of ``x0`` (use float64). ``progress`` advances once per step (in blocks).
    """
    if x0.shape[-1] != 3:
        raise ConfigError("simulate_sir: x0 must have 3 components (S, I, R), "
                          f"got shape {tuple(x0.shape)}")
    if n_steps < 0:
        raise ConfigError(f"simulate_sir: n_steps={n_steps} < 0")
    reporter = progress or SilentProgress()
    out = torch.empty((*x0.shape[:-1], n_steps + 1, 3), dtype=x0.dtype, device=x0.device)
    out[..., 0, :] = x0
    x = x0
    pending = 0
    per_step = isinstance(beta, Tensor) and beta.dim() == 2
    for step in range(1, n_steps + 1):
        x = rk4_step(x, beta[:, step - 1] if per_step else beta, gamma, dt)
        out[..., step, :] = x
        pending += 1
        if pending == _PROGRESS_BLOCK:
            reporter.advance(pending)
            pending = 0
    if pending:
        reporter.advance(pending)
    return out


def sample_parameters(prior: SIRPrior, n: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Draw ``(beta (n,), gamma (n,))`` uniformly from the prior's ranges (float64).

    Both uniforms are always drawn (beta first, then gamma) so the stream of ``generator`` is
    consumed the same way for fixed and ranged priors.
    """
    u = torch.rand((2, n), generator=generator, dtype=DTYPE)
    beta = prior.beta[0] + (prior.beta[1] - prior.beta[0]) * u[0]
    gamma = prior.gamma[0] + (prior.gamma[1] - prior.gamma[0]) * u[1]
    return beta, gamma


def sample_initial_states(prior: SIRPrior, n: int, generator: torch.Generator) -> Tensor:
    """``(n, 3)`` initial states (float64). A fixed prior draws nothing from ``generator`` (its
    ensembles stay bit-identical); a ranged one draws I0 (log-uniform), then R0 (uniform)."""
    if prior.initial_state_fixed:
        return prior.initial_state().expand(n, 3).clone()
    u = torch.rand((2, n), generator=generator, dtype=DTYPE)
    i_low, i_high = prior.i0_range or (prior.i0, prior.i0)
    r_low, r_high = prior.r0_range or (prior.r0, prior.r0)
    i0 = torch.exp(math.log(i_low) + (math.log(i_high) - math.log(i_low)) * u[0])
    r0 = r_low + (r_high - r_low) * u[1]
    return torch.stack([(1.0 - i0) - r0, i0, r0], dim=-1)


BETA_BOUNDS = (0.005, 1.0)


def sample_beta_paths(prior: SIRPrior, beta0: Tensor, generator: torch.Generator) -> Tensor:
    """``(n, T)`` beta per time from ``beta0 (n,)``: log beta is a random walk with step
    N(0, beta_walk_sigma^2 dt), clipped to BETA_BOUNDS; column k is the beta of the step from
    time k (the last column, one walk step further, drives no step). Draws ``n x n_steps``
    normals from ``generator``."""
    n, steps = beta0.shape[0], prior.n_steps
    increments = torch.randn((n, steps), generator=generator, dtype=DTYPE)
    increments.mul_(prior.beta_walk_sigma * math.sqrt(prior.dt))
    log_walk = torch.cat([torch.zeros((n, 1), dtype=DTYPE), increments.cumsum(dim=1)], dim=1)
    return (beta0[:, None] * log_walk.exp()).clamp_(*BETA_BOUNDS)


def observe(states: Tensor, sigma: float, generator: torch.Generator) -> Tensor:
    """``states + N(0, sigma^2)`` independently per entry; any shape, same dtype as ``states``."""
    noise = torch.randn(states.shape, generator=generator, dtype=states.dtype,
                        device=states.device)
    return states + sigma * noise


def observation_log_likelihood(obs: Tensor, states: Tensor, sigma: float | Tensor) -> Tensor:
    """log p(obs | states) under independent N(0, sigma^2) noise on each component.

    ``obs`` and ``states`` broadcast against each other with shape ``(..., C)``; the result sums
    over the last (component) axis and has the broadcast leading shape ``(...)``. ``sigma`` is a
    scalar or broadcasts against ``(..., C)``.
    """
    sigma_t = torch.as_tensor(sigma, dtype=states.dtype, device=states.device)
    z = (obs - states) / sigma_t
    per_component = -0.5 * z.square() - torch.log(sigma_t) - 0.5 * math.log(2.0 * math.pi)
    return per_component.sum(dim=-1)


def simulate_ensemble(prior: SIRPrior | str, n_trajectories: int | None = None, seed: int = 0,
                      progress: ProgressReporter | None = None) -> SIREnsemble:
    """Simulate an ensemble from a prior and observe it with Gaussian noise.

    Draw order from ``torch.Generator().manual_seed(seed)``: parameters (beta, gamma), the initial
    states (ranged priors only), the beta walk (walk priors only), then the observation noise of all
    (N, T, 3) entries; the same seed reproduces the ensemble bit for bit.
    ``progress`` advances once per RK4 step (``prior.n_steps`` in total).
    """
    if isinstance(prior, str):
        prior = get_prior(prior)
    n = prior.n_trajectories if n_trajectories is None else int(n_trajectories)
    if n < 1:
        raise ConfigError(f"simulate_ensemble: n_trajectories={n} must be >= 1")
    generator = torch.Generator().manual_seed(seed)
    beta, gamma = sample_parameters(prior, n, generator)
    x0 = sample_initial_states(prior, n, generator)
    beta_path = sample_beta_paths(prior, beta, generator) if prior.beta_varies_in_time else None
    states = simulate_sir(x0, beta if beta_path is None else beta_path[:, :-1], gamma,
                          prior.n_steps, prior.dt, progress)
    observations = observe(states, prior.obs_sigma, generator)
    return SIREnsemble(times=prior.times(), states=states, observations=observations,
                       beta=beta, gamma=gamma, prior=prior, seed=seed, beta_path=beta_path)
