"""State-space models the particle filter (:mod:`pipeline.inference.smc`) runs on.

Each model has ``state_names``, ``observation_names`` and three vectorized methods over
F filters × N particles: ``initial(F, N, generator) -> (F, N, D)``,
``transition(x, t, dt, generator) -> x'`` (one draw from p(x_{t+dt} | x_t)) and
``observation_log_prob(x, obs (F, O)) -> (F, N)`` (NaN observation components are ignored).
The deterministic dynamics come from :mod:`pipeline.systems` so they are defined once.

SIR process noise
-----------------
The SIR equations are deterministic. A bootstrap filter on a deterministic model never creates
new particle values: after a few resampling steps the population is copies of a handful of
ancestors (degeneracy). We therefore add process noise — our choice, the paper does not state one:
after each RK4 step every compartment gets additive N(0, τ²·dt) noise, then the state is projected
back onto the simplex (negative parts clamped to 0, then divided by S + I + R) so particles stay
valid proportions. Default τ = 1e-3 per √day: 1/27 of the observation noise σ = 0.027, far below
it (the likelihood still decides the weights) yet larger than the spacing of resampled copies after
one step. ``process_sigma = 0`` gives the noiseless model. Configurable per model.

Parameters as state (``SIRParamsModel``)
----------------------------------------
Particles carry (S, I, R, β, γ). β and γ are static by default (``param_jitter = 0``), which is
exact Bayesian filtering of static parameters but, with resampling, their particle diversity can
only shrink. ``param_jitter = ρ > 0`` multiplies both by exp(ρ·√dt·ε) each step (a log-normal
random walk, "artificial dynamics" à la Liu & West) to keep diversity over long horizons, at the
price of slightly widening their posterior.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, overload

import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.systems.sir import SIR_PRIORS, rk4_step
from pipeline.systems.vehicle import (OBSERVED_NAMES, STATE_NAMES, VehicleConfig,
                                      get_vehicle_config, vehicle_step)
from pipeline.names import COMPARTMENTS

DEFAULT_OBS_SIGMA = 0.027          # the paper's SIR observation noise
DEFAULT_PROCESS_SIGMA = 1e-3       # SIR process noise τ per √day (see the module docstring)
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def gaussian_log_likelihood(predicted: Tensor, observation: Tensor, sigma: float) -> Tensor:
    """Σ_c log N(o_c | h_c(x), σ²) over observed components; NaN components contribute 0.

    ``predicted`` (F, N, O) = h(x) per particle; ``observation`` (F, O). A row that is entirely NaN
    gives 0 for every particle (no update). Computed component by component (O ≤ 3 columns,
    each an (F, N) slice that is contiguous in the filter's planar particle layout): three
    elementwise ops per component and no (F, N, O) temporaries; a missing component gets
    precision 0 (its filled-in 0 then contributes nothing).
    """
    dtype = predicted.dtype
    observed = ~torch.isnan(observation)                                   # (F, O)
    filled = torch.where(observed, observation, torch.zeros_like(observation)).to(dtype)
    precision = observed.to(dtype) * (-0.5 / sigma ** 2)                   # (F, O)
    constant = observed.sum(-1).to(dtype) * (math.log(sigma) + _LOG_SQRT_2PI)  # (F,)
    total = None
    for c in range(predicted.shape[-1]):
        diff = torch.sub(predicted[..., c], filled[:, c, None]).square_()
        if total is None:
            total = diff.mul_(precision[:, c, None])
        else:
            total.addcmul_(diff, precision[:, c, None])
    assert total is not None
    return total.sub_(constant[:, None])


def planar_empty(num_filters: int, num_particles: int, dim: int, dtype: torch.dtype) -> Tensor:
    """An uninitialized (F, N, D) particle tensor in *planar* layout (memory order (F, D, N)).

    Each component ``x[..., d]`` is then a contiguous (F, N) block, so the columnwise model code
    (RK4 on S and I, likelihood per observed component) runs on contiguous memory, and
    ``x.transpose(1, 2)`` is a contiguous (F, D, N) tensor for batched weighted moments.
    """
    return torch.empty((num_filters, dim, num_particles), dtype=dtype).transpose(1, 2)


def is_planar(x: Tensor) -> bool:
    """Whether (F, N, D) particles have the planar layout of :func:`planar_empty`."""
    return x.ndim == 3 and x.transpose(1, 2).is_contiguous()


def standard_normal(shape: tuple[int, ...], generator: torch.Generator, dtype: torch.dtype) -> Tensor:
    """N(0, 1) draws of ``shape`` in ``dtype``, generated in float32 and cast.

    torch's CPU normal sampler is vectorized for float32 only; float64 draws were ~6x slower here
    and dominated an SIR filter step. A float32 draw has 24 bits of resolution, immaterial for
    process noise (the states themselves stay in ``dtype``).
    """
    draws = torch.randn(shape, generator=generator, dtype=torch.float32)
    return draws if dtype == torch.float32 else draws.to(dtype)


def project_to_simplex(x: Tensor) -> Tensor:
    """Clamp compartments at 0 and renormalize so S + I + R = 1 (last axis, size 3)."""
    clamped = x.clamp(min=0.0)
    # Matrix-vector product instead of .sum(-1): torch reduces a size-3 last axis slowly.
    total = (clamped @ clamped.new_ones(3)).clamp_(min=1e-12)
    return clamped.div_(total[..., None])


def sir_rk4_columns(s: Tensor, i: Tensor, r: Tensor, beta: float | Tensor, gamma: float | Tensor,
                    dt: float, out: tuple[Tensor, Tensor, Tensor] | None = None
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """One RK4 step of dS = −βSI, dI = βSI − γI, dR = γI on separate compartment columns.

    Same scheme as :func:`pipeline.systems.sir.rk4_step` (equal to rounding error), written for
    speed on (F, N) columns: no ``stack``/``cat`` per stage, only the infection flux βSI and dI
    are evaluated per stage (dS = −βSI), and R is advanced by the RK4 combination of the stage
    increments of S and I with the sign flipped (the increments sum to zero), so S + I + R is
    conserved without integrating dR. ``beta``/``gamma``: floats or tensors broadcasting against
    the columns ((F, 1) per filter, (F, N) per particle). ``out``: optional columns to write the
    result into (e.g. the planes of a :func:`planar_empty` tensor).
    """
    half = 0.5 * dt
    acc_flux: Tensor | None = None     # Σ_k w_k βS_kI_k   (w = 1, 2, 2, 1)
    acc_di: Tensor | None = None       # Σ_k w_k dI_k
    s_k, i_k = s, i
    for weight, advance in ((1.0, half), (2.0, half), (2.0, dt), (1.0, None)):
        flux = torch.mul(s_k, i_k)
        flux = flux.mul_(beta)
        if isinstance(gamma, Tensor):
            d_i = torch.addcmul(flux, i_k, gamma, value=-1.0)
        else:
            d_i = torch.add(flux, i_k, alpha=-gamma)
        if acc_flux is None or acc_di is None:
            acc_flux, acc_di = flux, d_i
        else:
            acc_flux.add_(flux, alpha=weight)
            acc_di.add_(d_i, alpha=weight)
        if advance is not None:
            s_k = torch.add(s, flux, alpha=-advance)
            i_k = torch.add(i, d_i, alpha=advance)
    assert acc_flux is not None and acc_di is not None
    sixth = dt / 6.0
    s_out, i_out, r_out = out if out is not None else (None, None, None)
    s_new = torch.add(s, acc_flux, alpha=-sixth, out=s_out)
    i_new = torch.add(i, acc_di, alpha=sixth, out=i_out)
    # ΔR = −(ΔS + ΔI) = (dt/6)·(acc_flux − acc_di): the recovery flux γI, never evaluated alone.
    r_new = torch.add(r, acc_flux.sub_(acc_di), alpha=sixth, out=r_out)
    return s_new, i_new, r_new


def _add_noise_and_project(planes: Tensor, scale: float, generator: torch.Generator) -> None:
    """In place on ``planes`` (F, 3, N): add N(0, scale²) to every compartment, clamp at 0 and
    renormalize so S + I + R = 1 (whole-block ops over the contiguous (F, 3, N) block)."""
    eps = standard_normal(tuple(planes.shape), generator, planes.dtype)
    planes.add_(eps, alpha=scale).clamp_(min=0.0)
    # S + I + R as two adds of contiguous planes (a reduction over the middle axis is slower).
    total = torch.add(planes[:, 0], planes[:, 1]).add_(planes[:, 2]).clamp_(min=1e-12)
    planes.div_(total[:, None])


def _planar_simplex_prior(location: Tensor, prior_std: float, num_particles: int,
                          generator: torch.Generator) -> Tensor:
    """Draws of the projection of N(location, prior_std²) onto the simplex, planar (F, N, 3);
    ``location`` (F, 3) or (1, 3). float64, from float32 standard normals (see
    :func:`standard_normal`)."""
    num_filters = location.shape[0]
    x = planar_empty(num_filters, num_particles, 3, torch.float64)
    planes = x.transpose(1, 2)                                           # (F, 3, N) contiguous
    planes.copy_(standard_normal(tuple(planes.shape), generator, torch.float64))
    planes.mul_(prior_std).add_(location.to(torch.float64)[:, :, None]).clamp_(min=0.0)
    planes.div_(planes.sum(1, keepdim=True).clamp_(min=1e-12))
    return x


@overload
def _per_filter(value: Tensor, name: str, trailing: tuple[int, ...]) -> Tensor: ...
@overload
def _per_filter(value: float | Tensor, name: str, trailing: tuple[int, ...]) -> float | Tensor: ...
def _per_filter(value: float | Tensor, name: str, trailing: tuple[int, ...]) -> float | Tensor:
    """A scalar stays a float; a tensor (F, *trailing) becomes (F, 1, *trailing) to broadcast
    against particles (F, N, ...)."""
    if isinstance(value, int | float):
        return float(value)
    tensor = torch.as_tensor(value, dtype=torch.float64)
    if tensor.ndim == len(trailing):  # shared by all filters
        return tensor
    if tensor.ndim != len(trailing) + 1 or tuple(tensor.shape[1:]) != trailing:
        raise ConfigError(f"{name}: expected a scalar/{trailing} or (F, *{trailing}) tensor, got "
                          f"shape {tuple(tensor.shape)}")
    return tensor.unsqueeze(1)


def _check_filters(value: float | Tensor, num_filters: int, name: str) -> None:
    if isinstance(value, Tensor) and value.ndim >= 2 and value.shape[0] not in (1, num_filters):
        raise ConfigError(f"{name} has {value.shape[0]} filters but {num_filters} were requested")


def _cast(value: float | Tensor, like: Tensor) -> float | Tensor:
    return value.to(like.dtype) if isinstance(value, Tensor) else value


def _column(value: float | Tensor, like: Tensor) -> float | Tensor:
    """A per-filter parameter as a float or an (F, 1) tensor in ``like``'s dtype, to broadcast
    against (F, N) columns ((F, 1, 1) tensors from :func:`_per_filter` lose the trailing axis)."""
    if isinstance(value, Tensor):
        return value.to(like.dtype).reshape(value.shape[0] if value.ndim else 1, 1)
    return value


@overload
def _select(value: Tensor, index: int) -> Tensor: ...
@overload
def _select(value: float | Tensor, index: int) -> float | Tensor: ...
def _select(value: float | Tensor, index: int) -> float | Tensor:
    if isinstance(value, Tensor) and value.ndim >= 2:
        return value[index: index + 1]
    return value


@dataclass(frozen=True, eq=False)
class SIRStateModel:
    """SIR state (S, I, R) with known β, γ; all three compartments observed with N(0, σ²) noise.

    ``beta``, ``gamma``: scalars or (F,) tensors (one per filter). Prior p(x_0): the projection of
    N(``prior_mean``, ``prior_std``²) onto the simplex, ``prior_mean`` (3,) or (F, 3), e.g. the
    observation o_n of the window (the paper's "p(o_n) as the prior", with ``prior_std`` = σ).
    Use :meth:`create` to build one from plain values. Filtered in float32 by default
    (``default_dtype``; see docs/smc.md for the measured float32/float64 difference).
    """

    default_dtype: ClassVar[torch.dtype] = torch.float32

    beta: float | Tensor
    gamma: float | Tensor
    prior_mean: Tensor
    prior_std: float = DEFAULT_OBS_SIGMA
    obs_sigma: float = DEFAULT_OBS_SIGMA
    process_sigma: float = DEFAULT_PROCESS_SIGMA
    state_names: tuple[str, ...] = COMPARTMENTS
    observation_names: tuple[str, ...] = COMPARTMENTS

    @classmethod
    def create(cls, beta: float | Tensor, gamma: float | Tensor, prior_mean: Any,
               prior_std: float = DEFAULT_OBS_SIGMA, obs_sigma: float = DEFAULT_OBS_SIGMA,
               process_sigma: float = DEFAULT_PROCESS_SIGMA) -> SIRStateModel:
        if obs_sigma <= 0 or prior_std < 0 or process_sigma < 0:
            raise ConfigError(f"SIRStateModel: obs_sigma={obs_sigma} must be > 0, prior_std="
                              f"{prior_std} and process_sigma={process_sigma} >= 0")
        return cls(beta=_per_filter(beta, "beta", ()), gamma=_per_filter(gamma, "gamma", ()),
                   prior_mean=_per_filter(torch.as_tensor(prior_mean, dtype=torch.float64),
                                          "prior_mean", (3,)),
                   prior_std=float(prior_std), obs_sigma=float(obs_sigma),
                   process_sigma=float(process_sigma))

    def select(self, index: int) -> SIRStateModel:
        """The model of filter ``index`` alone (F = 1), e.g. to run it through pyro."""
        return SIRStateModel(beta=_select(self.beta, index), gamma=_select(self.gamma, index),
                             prior_mean=_select(self.prior_mean, index), prior_std=self.prior_std,
                             obs_sigma=self.obs_sigma, process_sigma=self.process_sigma)

    # -- pieces shared with the pyro version of this model (tests, bench) ----------------------
    def prior_location(self, num_filters: int, num_particles: int, like: Tensor) -> Tensor:
        _check_filters(self.prior_mean, num_filters, "prior_mean")
        return self.prior_mean.to(like.dtype).expand(num_filters, num_particles, 3)

    def deterministic_step(self, x: Tensor, dt: float) -> Tensor:
        """The RK4 step of the SIR equations for every particle (F, N, 3)."""
        return rk4_step(x, _cast(self.beta, x), _cast(self.gamma, x), dt)

    # -- StateSpaceModel ------------------------------------------------------------------------
    def initial(self, num_filters: int, num_particles: int, generator: torch.Generator) -> Tensor:
        """Planar (F, N, 3) float64 draws of the projected N(prior_mean, prior_std²)."""
        _check_filters(self.prior_mean, num_filters, "prior_mean")
        location = self.prior_mean.reshape(-1, 3).expand(num_filters, 3)
        return _planar_simplex_prior(location, self.prior_std, num_particles, generator)

    def transition(self, x: Tensor, t: float, dt: float, generator: torch.Generator) -> Tensor:
        """RK4 (:func:`sir_rk4_columns`), then noise and projection; returns a new planar tensor
        (x is not modified). Equals ``deterministic_step`` to rounding when process_sigma = 0."""
        out = planar_empty(x.shape[0], x.shape[1], 3, x.dtype)
        planes = out.transpose(1, 2)                                     # (F, 3, N)
        s_plane, i_plane, r_plane = planes.unbind(1)
        sir_rk4_columns(x[..., 0], x[..., 1], x[..., 2], _column(self.beta, x),
                        _column(self.gamma, x), dt, out=(s_plane, i_plane, r_plane))
        if self.process_sigma > 0.0:
            _add_noise_and_project(planes, self.process_sigma * math.sqrt(dt), generator)
        return out

    def observation_log_prob(self, x: Tensor, observation: Tensor) -> Tensor:
        return gaussian_log_likelihood(x, observation, self.obs_sigma)


@dataclass(frozen=True, eq=False)
class SIRParamsModel:
    """SIR state and parameters (S, I, R, β, γ) as particles; (S, I, R) observed, N(0, σ²).

    Prior: (S, I, R) as in :class:`SIRStateModel`; β ~ U(``beta_range``), γ ~ U(``gamma_range``)
    (default: the ``sir-multi`` prior the joint flow is trained on). β, γ static unless
    ``param_jitter`` > 0 (see the module docstring). For NF-seeded SMC the initial particles come
    from the flow instead and the prior here is not used. Filtered in float32 by default.
    """

    default_dtype: ClassVar[torch.dtype] = torch.float32

    prior_mean: Tensor
    prior_std: float = DEFAULT_OBS_SIGMA
    beta_range: tuple[float, float] = SIR_PRIORS["sir-multi"].beta
    gamma_range: tuple[float, float] = SIR_PRIORS["sir-multi"].gamma
    obs_sigma: float = DEFAULT_OBS_SIGMA
    process_sigma: float = DEFAULT_PROCESS_SIGMA
    param_jitter: float = 0.0
    state_names: tuple[str, ...] = ("S", "I", "R", "beta", "gamma")
    observation_names: tuple[str, ...] = COMPARTMENTS

    @classmethod
    def create(cls, prior_mean: Any, prior_std: float = DEFAULT_OBS_SIGMA,
               beta_range: tuple[float, float] = SIR_PRIORS["sir-multi"].beta,
               gamma_range: tuple[float, float] = SIR_PRIORS["sir-multi"].gamma,
               obs_sigma: float = DEFAULT_OBS_SIGMA, process_sigma: float = DEFAULT_PROCESS_SIGMA,
               param_jitter: float = 0.0) -> SIRParamsModel:
        if obs_sigma <= 0 or prior_std < 0 or process_sigma < 0 or param_jitter < 0:
            raise ConfigError(f"SIRParamsModel: obs_sigma={obs_sigma} must be > 0; prior_std, "
                              f"process_sigma, param_jitter must be >= 0")
        for name, (low, high) in (("beta_range", beta_range), ("gamma_range", gamma_range)):
            if not 0.0 <= low <= high:
                raise ConfigError(f"SIRParamsModel: {name}=({low}, {high}) needs 0 <= low <= high")
        return cls(prior_mean=_per_filter(torch.as_tensor(prior_mean, dtype=torch.float64),
                                          "prior_mean", (3,)),
                   prior_std=float(prior_std), beta_range=(beta_range[0], beta_range[1]),
                   gamma_range=(gamma_range[0], gamma_range[1]), obs_sigma=float(obs_sigma),
                   process_sigma=float(process_sigma), param_jitter=float(param_jitter))

    def initial(self, num_filters: int, num_particles: int, generator: torch.Generator) -> Tensor:
        _check_filters(self.prior_mean, num_filters, "prior_mean")
        location = self.prior_mean.reshape(-1, 3).expand(num_filters, 3)
        state = _planar_simplex_prior(location, self.prior_std, num_particles, generator)
        x = planar_empty(num_filters, num_particles, 5, torch.float64)
        x[..., :3] = state
        u = torch.rand((2, num_filters, num_particles), generator=generator, dtype=torch.float64)
        x[..., 3] = self.beta_range[0] + (self.beta_range[1] - self.beta_range[0]) * u[0]
        x[..., 4] = self.gamma_range[0] + (self.gamma_range[1] - self.gamma_range[0]) * u[1]
        return x

    def transition(self, x: Tensor, t: float, dt: float, generator: torch.Generator) -> Tensor:
        """Columnwise RK4 with per-particle β, γ, noise and projection; β, γ copied or jittered.
        Returns a new planar tensor (x is not modified)."""
        out = planar_empty(x.shape[0], x.shape[1], 5, x.dtype)
        planes = out.transpose(1, 2)                                     # (F, 5, N)
        beta, gamma = x[..., 3], x[..., 4]
        s_plane, i_plane, r_plane = planes[:, :3].unbind(1)
        sir_rk4_columns(x[..., 0], x[..., 1], x[..., 2], beta, gamma, dt,
                        out=(s_plane, i_plane, r_plane))
        if self.process_sigma > 0.0:
            _add_noise_and_project(planes[:, :3], self.process_sigma * math.sqrt(dt), generator)
        params = x[..., 3:].transpose(1, 2)                              # (F, 2, N)
        if self.param_jitter > 0.0:
            eps = standard_normal(tuple(params.shape), generator, x.dtype)
            torch.mul(params, eps.mul_(self.param_jitter * math.sqrt(dt)).exp_(),
                      out=planes[:, 3:])
        else:
            planes[:, 3:] = params
        return out

    def observation_log_prob(self, x: Tensor, observation: Tensor) -> Tensor:
        return gaussian_log_likelihood(x[..., :3], observation, self.obs_sigma)


@dataclass(frozen=True, eq=False)
class VehicleModel:
    """Vehicle with random switch: particles (p_x, p_y, θ, φ, v, ψ); (p_x, p_y) observed.

    Dynamics: :func:`pipeline.systems.vehicle.vehicle_step` with process noise N(0, σ_v²) on v and
    N(0, σ_φ²) on φ per step (the system's reading of the paper). ψ is 0 ("not drawn yet") until
    the first transition whose start time reaches ``config.switch_time`` (5.5), where each
    particle draws ψ ∈ {−1, +1} with probability ½ — so resampling before the switch cannot
    collapse the ψ diversity. Seeded particles that already carry ψ = ±1 keep it.
    Prior: N(``initial_mean``, diag(``initial_std``²)) over the 5 physical components
    (default: the system's start state, positions spread by the observation noise).
    """

    config: VehicleConfig
    initial_mean: Tensor
    initial_std: Tensor
    state_names: tuple[str, ...] = (*STATE_NAMES, "psi")
    observation_names: tuple[str, ...] = OBSERVED_NAMES

    @classmethod
    def create(cls, config: VehicleConfig | str = "vehicle-full", initial_mean: Any = None,
               initial_std: Any = None) -> VehicleModel:
        if isinstance(config, str):
            config = get_vehicle_config(config)
        mean = config.initial_state() if initial_mean is None else torch.as_tensor(
            initial_mean, dtype=torch.float64)
        std = (torch.tensor([config.obs_sigma, config.obs_sigma, 0.0, 0.0, 0.0],
                            dtype=torch.float64)
               if initial_std is None else torch.as_tensor(initial_std, dtype=torch.float64))
        if std.shape != (5,) or bool((std < 0).any()):
            raise ConfigError(f"VehicleModel: initial_std must be 5 non-negative values, got {std}")
        return cls(config=config, initial_mean=_per_filter(mean, "initial_mean", (5,)),
                   initial_std=std)

    def initial(self, num_filters: int, num_particles: int, generator: torch.Generator) -> Tensor:
        _check_filters(self.initial_mean, num_filters, "initial_mean")
        eps = torch.randn((num_filters, num_particles, 5), generator=generator,
                          dtype=torch.float64)
        physical = self.initial_mean.expand(num_filters, num_particles, 5) + self.initial_std * eps
        return torch.cat([physical, physical.new_zeros((num_filters, num_particles, 1))], dim=-1)

    def transition(self, x: Tensor, t: float, dt: float, generator: torch.Generator) -> Tensor:
        psi = x[..., 5]
        if t >= self.config.switch_time - 1e-9:
            draws = (2 * torch.randint(0, 2, psi.shape, generator=generator) - 1).to(x.dtype)
            psi = torch.where(psi == 0, draws, psi)
        noise = standard_normal((2, *psi.shape), generator, x.dtype)
        moved = vehicle_step(x[..., :5], t, dt, psi, self.config.sigma_v * noise[0],
                             self.config.sigma_phi * noise[1], self.config)
        return torch.cat([moved, psi[..., None]], dim=-1)

    def observation_log_prob(self, x: Tensor, observation: Tensor) -> Tensor:
        return gaussian_log_likelihood(x[..., :2], observation, self.config.obs_sigma)


@dataclass(frozen=True)
class LinearGaussianModel:
    """x_{t+1} = a·x_t + N(0, q), o_t = x_t + N(0, r), x_0 ~ N(m0, p0); scalar state.

    The Kalman filter solves it exactly (:func:`kalman_filter`), which makes it the known-answer
    test of the particle filter (means, variances and the log-evidence).
    """

    a: float = 0.9
    q: float = 0.5
    r: float = 1.0
    m0: float = 0.0
    p0: float = 2.0
    state_names: tuple[str, ...] = ("x",)
    observation_names: tuple[str, ...] = ("x",)

    def initial(self, num_filters: int, num_particles: int, generator: torch.Generator) -> Tensor:
        eps = torch.randn((num_filters, num_particles, 1), generator=generator, dtype=torch.float64)
        return self.m0 + math.sqrt(self.p0) * eps

    def transition(self, x: Tensor, t: float, dt: float, generator: torch.Generator) -> Tensor:
        eps = torch.randn(x.shape, generator=generator, dtype=x.dtype)
        return self.a * x + math.sqrt(self.q) * eps

    def observation_log_prob(self, x: Tensor, observation: Tensor) -> Tensor:
        return gaussian_log_likelihood(x, observation, math.sqrt(self.r))


def kalman_filter(model: LinearGaussianModel, observations: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Exact filtering of :class:`LinearGaussianModel`: (means (F, T), variances (F, T),
    log-evidence (F,)) for observations (F, T) (NaN = no update), row 0 at the prior's time."""
    obs = torch.as_tensor(observations, dtype=torch.float64)
    mean = torch.full(obs.shape[:1], model.m0, dtype=torch.float64)
    var = torch.full_like(mean, model.p0)
    log_evidence = torch.zeros_like(mean)
    means, variances = [], []
    for step in range(obs.shape[1]):
        if step > 0:
            mean, var = model.a * mean, model.a ** 2 * var + model.q
        o = obs[:, step]
        seen = ~torch.isnan(o)
        innovation_var = var + model.r
        innovation = torch.where(seen, o - mean, torch.zeros_like(o))
        gain = torch.where(seen, var / innovation_var, torch.zeros_like(var))
        log_evidence += torch.where(
            seen, -0.5 * (innovation ** 2 / innovation_var + torch.log(2 * math.pi * innovation_var)),
            torch.zeros_like(o))
        mean, var = mean + gain * innovation, (1 - gain) * var
        means.append(mean)
        variances.append(var)
    return torch.stack(means, 1), torch.stack(variances, 1), log_evidence


# -- pyro's SMCFilter on the same SIR model (the paper's implementation; tests and bench) ------

class _PyroSIRModel:
    """pyro model for :class:`SIRStateModel` of one filter: same prior, RK4 step, noise, projection
    and likelihood, expressed as pyro sample sites (bootstrap: the guide proposes from the prior)."""

    def __init__(self, model: SIRStateModel) -> None:
        self.model = model

    def init(self, state: Any, observation: Tensor | None) -> None:
        import pyro
        import pyro.distributions as dist
        eps = pyro.sample("init_noise", dist.Normal(torch.zeros(3, dtype=torch.float64),
                                                    self.model.prior_std).to_event(1))
        location = self.model.prior_mean.reshape(3).to(torch.float64)
        state["x"] = project_to_simplex(location + eps)
        self._observe(state["x"], observation)

    def step(self, state: Any, dt: float, observation: Tensor | None) -> None:
        import pyro
        import pyro.distributions as dist
        scale = self.model.process_sigma * math.sqrt(dt)
        moved = self.model.deterministic_step(state["x"][None], dt)[0]
        if scale > 0:
            eps = pyro.sample("noise", dist.Normal(torch.zeros(3, dtype=torch.float64),
                                                   scale).to_event(1))
            moved = project_to_simplex(moved + eps)
        state["x"] = moved
        self._observe(moved, observation)

    def _observe(self, x: Tensor, observation: Tensor | None) -> None:
        import pyro
        import pyro.distributions as dist
        if observation is not None:
            pyro.sample("obs", dist.Normal(x, self.model.obs_sigma).to_event(1), obs=observation)


class _PyroSIRGuide:
    """Bootstrap proposal: the same noise distributions as the model."""

    def __init__(self, model: SIRStateModel) -> None:
        self.model = model

    def init(self, state: Any, observation: Tensor | None) -> None:
        import pyro
        import pyro.distributions as dist
        pyro.sample("init_noise", dist.Normal(torch.zeros(3, dtype=torch.float64),
                                              self.model.prior_std).to_event(1))

    def step(self, state: Any, dt: float, observation: Tensor | None) -> None:
        import pyro
        import pyro.distributions as dist
        scale = self.model.process_sigma * math.sqrt(dt)
        if scale > 0:
            pyro.sample("noise", dist.Normal(torch.zeros(3, dtype=torch.float64),
                                             scale).to_event(1))


def run_pyro_sir_filter(model: SIRStateModel, observations: Tensor, num_particles: int,
                        seed: int, times: Tensor | None = None,
                        ess_threshold: float = 0.5) -> tuple[Tensor, Tensor, Tensor]:
    """Filter one SIR window with pyro's ``SMCFilter`` (the paper's implementation).

    ``model``: a single-filter model (``model.select(f)``); ``observations`` (T, 3), NaN rows =
    no update, row 0 at the prior's time. Returns (weighted means (T, 3), final particles (N, 3),
    final normalized log-weights (N,)). pyro draws from torch's global RNG; it is seeded with
    ``seed`` inside ``torch.random.fork_rng`` so the caller's global RNG state is left untouched.
    """
    import pyro
    from pyro.infer import SMCFilter

    obs = torch.as_tensor(observations, dtype=torch.float64)
    steps = obs.shape[0]
    grid = torch.arange(steps, dtype=torch.float64) if times is None else torch.as_tensor(
        times, dtype=torch.float64)

    def row(step: int) -> Tensor | None:
        return None if bool(torch.isnan(obs[step]).all()) else obs[step]

    means = torch.empty((steps, 3), dtype=torch.float64)
    with torch.random.fork_rng(devices=[]):
        pyro.set_rng_seed(seed)
        smc = SMCFilter(_PyroSIRModel(model), _PyroSIRGuide(model), num_particles=num_particles,
                        max_plate_nesting=0, ess_threshold=ess_threshold)
        smc.init(observation=row(0))
        means[0] = _pyro_mean(smc)
        for step in range(1, steps):
            smc.step(dt=float(grid[step] - grid[step - 1]), observation=row(step))
            means[step] = _pyro_mean(smc)
        log_weights = smc.state._log_weights - torch.logsumexp(smc.state._log_weights, 0)
        return means, smc.state["x"].clone(), log_weights


def _pyro_mean(smc: Any) -> Tensor:
    # Weights as pyro holds them *after* its optional resampling (then uniform) — the same
    # estimator of the filtering mean as ours up to resampling noise.
    weights = torch.softmax(smc.state._log_weights, dim=0).to(torch.float64)
    return weights @ smc.state["x"]


# -- the multi-wave renewal model (the weekly forecast's epidemic model) -----------------------

_LOG_FLOOR = 1e-300


def negative_binomial_log_prob(count: Tensor, mean: Tensor, dispersion: Tensor) -> Tensor:
    """log NB(count | mean, dispersion k) (variance mean + mean²/k), broadcasting; mean > 0."""
    k = dispersion
    log_total = torch.log(k + mean)
    return (torch.lgamma(count + k) - torch.lgamma(k) - torch.lgamma(count + 1.0)
            + k * (torch.log(k) - log_total) + count * (torch.log(mean) - log_total))


@dataclass(frozen=True, eq=False)
class WaveRenewalModel:
    """The multi-wave prior (:mod:`pipeline.systems.waves`) as a state-space model, in the S/I/R
    conversion's coordinates — the model the joint flows and the flow member are trained on.

    Particles (F, N, D): ``S, I, R, beta`` (S/I/R as the conversion has them, β per observed
    susceptible, R_t = β S L), the last L days' new cases ``n_lag{L-1} … n_lag0`` (shares of N;
    I is their sum), each particle's static prior draws ``log_beta_mean`` (μ), ``reversion``
    (θ), ``volatility`` (σ), ``importation`` (ι), and ``proposal_log_weight`` (below). One day
    (dt = 1): log β ← log β + θ(μ − log β) + σε + J (J ~ N(0, jump_sd²) with probability
    ``jump_rate``), new = S(1 − exp(−β I − ι)), the window moves on by a day, S ← S − new,
    R = 1 − S − I: the prior's step with the window as the infectious period (γ = 1/L) and no
    waning (the conversion's S never rises).

    Observation (F, 1): the cases reported in the L days ending that day, N·I of the S/I/R
    series. The L-day sum of NB(k) daily reports is NB(N·I, L·k) (equal days; their weekday
    pattern sums out of a whole week). Each daily report enters L overlapping sums, so each sum's
    log-likelihood is counted at weight 1/L (a composite likelihood): every report informs the
    filter once, and no weekday factors are needed. (Daily counts with estimated weekday factors
    left 2 of 1,000 particles on SF's 2022-01-10, where the factor was off for that week.)

    Jumps are rare in the prior (``jump_rate``, 1 in 120 days) but they are how a wave turns; the
    filter proposes them more often (``proposal_jump_rate``) and corrects by the ratio of the two
    probabilities (importance weights, so the filter still targets the same posterior). The
    correction is the last state component, written by ``transition`` and added by
    ``observation_log_prob``; with ``proposal_jump_rate = jump_rate`` (forecasting) it is 0.
    """

    default_dtype: ClassVar[torch.dtype] = torch.float64

    population: Tensor            # (F, 1) people
    dispersion: Tensor            # (F, 1) k of the daily reports
    window_days: int = 7
    jump_rate: float = 1.0 / 120.0
    jump_sd: float = 0.5
    proposal_jump_rate: float = 0.1

    @property
    def state_names(self) -> tuple[str, ...]:
        lags = tuple(f"n_lag{k}" for k in range(self.window_days - 1, -1, -1))
        return ("S", "I", "R", "beta", *lags, "log_beta_mean", "reversion", "volatility",
                "importation", "proposal_log_weight")

    @property
    def observation_names(self) -> tuple[str, ...]:
        return ("window_cases",)

    @property
    def lag_slice(self) -> slice:
        return slice(4, 4 + self.window_days)

    def initial(self, num_filters: int, num_particles: int, generator: torch.Generator) -> Tensor:
        raise ConfigError("WaveRenewalModel has no prior of its own: the joint flow's draws seed "
                          "it (pipeline.inference.hybrid.nf_seeded_wave_smc)")

    def transition(self, x: Tensor, t: float, dt: float, generator: torch.Generator) -> Tensor:
        if abs(dt - 1.0) > 1e-9:
            raise ConfigError(f"WaveRenewalModel steps whole days; got dt={dt}")
        num_filters, num_particles, dim = x.shape
        planes = x.transpose(1, 2)                                       # (F, D, N)
        out = planar_empty(num_filters, num_particles, dim, x.dtype)
        new_planes = out.transpose(1, 2)
        lags = self.lag_slice
        static = slice(lags.stop, lags.stop + 4)
        mu, theta, sigma, iota = planes[:, static].unbind(1)
        noise = standard_normal((2, num_filters, num_particles), generator, x.dtype)
        jumped = torch.rand((num_filters, num_particles), generator=generator,
                            dtype=x.dtype) < self.proposal_jump_rate
        log_beta = torch.log(planes[:, 3])
        log_beta = (log_beta + theta * (mu - log_beta) + sigma * noise[0]
                    + jumped.to(x.dtype) * self.jump_sd * noise[1])
        beta = torch.exp(log_beta)
        susceptible, infectious = planes[:, 0], planes[:, 1]
        new = susceptible * -torch.expm1(-(beta * infectious + iota))
        new_planes[:, lags.start:lags.stop - 1] = planes[:, lags.start + 1:lags.stop]
        new_planes[:, lags.stop - 1] = new
        susceptible = susceptible - new
        infectious = new_planes[:, lags].sum(1)
        new_planes[:, 0], new_planes[:, 1] = susceptible, infectious
        new_planes[:, 2] = (1.0 - susceptible) - infectious
        new_planes[:, 3] = beta
        new_planes[:, static] = planes[:, static]
        if self.proposal_jump_rate == self.jump_rate:
            new_planes[:, -1] = 0.0
        else:
            new_planes[:, -1] = torch.where(
                jumped, math.log(self.jump_rate / self.proposal_jump_rate),
                math.log((1.0 - self.jump_rate) / (1.0 - self.proposal_jump_rate)))
        return out

    def window_dispersion(self, like: Tensor) -> Tensor:
        """(F, 1) dispersion of an L-day sum of reports: L·k."""
        return self.window_days * self.dispersion.to(like)

    def observation_log_prob(self, x: Tensor, observation: Tensor) -> Tensor:
        cases = observation[:, :1]
        seen = ~torch.isnan(cases)
        mean = (x[..., 1] * self.population.to(x)).clamp(min=1e-9)
        log_p = negative_binomial_log_prob(torch.where(seen, cases, torch.zeros_like(cases)),
                                           mean, self.window_dispersion(x))
        return torch.where(seen, log_p / self.window_days, torch.zeros_like(log_p)) + x[..., -1]

    def sample_window_reports(self, x: Tensor, generator: torch.Generator) -> Tensor:
        """(F, N) cases reported in the L days of particles ``x``'s window: NB(N·I, L·k) as a
        gamma–Poisson draw."""
        mean = (x[..., 1] * self.population.to(x)).clamp(min=1e-9)
        k = self.window_dispersion(x).expand_as(mean)
        return torch.poisson(_gamma(k, generator) * (mean / k), generator=generator)


def _gamma(shape: Tensor, generator: torch.Generator) -> Tensor:
    """Gamma(shape, 1) draws with an explicit generator (Marsaglia–Tsang, shape ≥ 1 via the
    boost Γ(a) = Γ(a + 1)·U^(1/a) for a < 1), vectorized; torch's own gamma sampler takes no
    generator."""
    boost = shape < 1.0
    a = torch.where(boost, shape + 1.0, shape)
    d = a - 1.0 / 3.0
    c = 1.0 / torch.sqrt(9.0 * d)
    out = torch.empty_like(a)
    pending = torch.ones_like(a, dtype=torch.bool)
    while bool(pending.any()):
        z = torch.randn(a.shape, generator=generator, dtype=a.dtype)
        u = torch.rand(a.shape, generator=generator, dtype=a.dtype)
        v = (1.0 + c * z) ** 3
        ok = (v > 0) & (torch.log(u.clamp(min=_LOG_FLOOR))
                        < 0.5 * z * z + d - d * v + d * torch.log(v.clamp(min=_LOG_FLOOR)))
        take = pending & ok
        out = torch.where(take, d * v, out)
        pending = pending & ~ok
    u = torch.rand(a.shape, generator=generator, dtype=a.dtype)
    return torch.where(boost, out * u.clamp(min=_LOG_FLOOR) ** (1.0 / shape), out)


def reporting_pattern(cases: Tensor, fit_days: int = 56) -> tuple[Tensor, Tensor]:
    """Weekday factors and the NB dispersion of daily reports, from ``cases (F, T)`` alone.

    Each day's count over its centred 7-day mean, over the last ``fit_days`` days with a whole
    centred week; per weekday the geometric mean, normalised to mean 1: factors ``(F, 7)``,
    entry j the factor of days T − 7 + j, T + j, … (the last day is j = 6). Dispersion k by
    moments of the residuals, var = m + m²/k, clipped to [5, 1000]: ``(F,)``.
    """
    c = cases.double()
    num_filters, length = c.shape
    if length < 14:
        raise ConfigError(f"reporting_pattern needs at least 14 days, got {length}")
    kernel = torch.ones((1, 1, 7), dtype=torch.float64) / 7.0
    centred = torch.nn.functional.conv1d(c[:, None], kernel)[:, 0]         # days 3 … T−4
    start = max(0, centred.shape[1] - fit_days)
    mean = centred[:, start:]
    observed = c[:, 3 + start: 3 + start + mean.shape[1]]
    log_ratio = torch.log((observed + 0.5) / (mean + 0.5))
    position = (torch.arange(3 + start, 3 + start + mean.shape[1]) - length) % 7
    factors = torch.stack([log_ratio[:, position == j].mean(1) for j in range(7)], dim=1).exp()
    factors = factors / factors.mean(1, keepdim=True)
    expected = mean * factors[:, position]
    excess = ((observed - expected) ** 2 - expected).mean(1)
    k = (expected ** 2).mean(1) / excess.clamp(min=1e-9)
    return factors, k.clamp(5.0, 1000.0)
