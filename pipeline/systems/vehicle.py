"""Autonomous vehicle with a random switch (Delecki et al. 2023; paper section "Autonomous Vehicle
Dynamics with Random Switching"), plus a kinematic ``bicycle`` variant.

State ``x = (p_x, p_y, theta, phi, v)``; one explicit (Euler-type) difference step of size dt at
time t (all right-hand sides use the values *before* the step)::

    p_x   += dt * v * cos(theta)
    p_y   += dt * v * sin(theta)
    theta += dt * v * phi                 (model "paper")
    theta += dt * v * tan(phi) / L        (model "bicycle", wheel base L = 2.8)
    phi   += dt * s(t) * c1 * cos(c2 * t) + eps_phi,   eps_phi ~ N(0, sigma_phi^2)
    v     +=                                 eps_v,     eps_v   ~ N(0, sigma_v^2)

with c1 = 0.1, c2 = 0.5, sigma_v = 0.01, sigma_phi = 0.001, s(t) = 1 for t < 5.5 and s(t) = psi
for t >= 5.5. Start at the origin with theta = phi = 0, v = 6, t in [0, 15].

Readings of the paper (see docs/systems.md):

* psi: the paper says psi ~ U([-1, 1]) drawn at t = 5.5. A continuous psi does not give the two
  separated modes the paper shows and discusses ("bimodal trajectory"), so we draw psi from
  {-1, +1} with probability 1/2 each. psi only acts from t = 5.5 on, so drawing it at t = 0 (as
  done here, one per trajectory) gives the same distribution of trajectories.
* Noise: "Gaussian noise is added to v and phi at each time step": one independent draw per step
  on the state variables v and phi (process noise; it is per step, not per unit time, so it does
  not scale with dt). Positions are observed with N(0, 1) noise on p_x and p_y (paper, section
  "Training": "adding Gaussian noise with sigma = 1.0").
* Datasets: (a) ``vehicle-full``: step dt = 1.0 (16 states, all observed); (b) ``vehicle-dropout``:
  base step dt = 0.1 (151 states), each state kept independently with probability 0.1, 100,000
  trajectories -> about 1.51 million kept points; (c) ``vehicle-sparse``: the same with 100
  trajectories -> about 1,510 kept points ("approximately 1,500 data points").

The dynamics are integrated in float64; the stored ensemble defaults to float32, which keeps the
100,000 x 151 x 5 dropout ensemble at 302 MB instead of 604 MB. Positions stay below ~100 in
magnitude, so float32 storage rounds them by < 1e-5, five orders below the observation noise.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.progress import ProgressReporter, SilentProgress

SIM_DTYPE = torch.float64
STATE_NAMES = ("p_x", "p_y", "theta", "phi", "v")
OBSERVED_NAMES = ("p_x", "p_y")
MODELS = ("paper", "bicycle")
# Times are k * dt in floating point (e.g. 55 * 0.1); compare with the switch time with a margin
# far below any step size so t = 5.5 counts as "switched" whatever the rounding.
_SWITCH_TOLERANCE = 1e-9


@dataclass(frozen=True)
class VehicleConfig:
    """One vehicle dataset: dynamics, time grid, noise, dropout and default ensemble size."""

    name: str
    model: str = "paper"
    dt: float = 0.1
    t_end: float = 15.0
    switch_time: float = 5.5
    c1: float = 0.1
    c2: float = 0.5
    v0: float = 6.0
    sigma_v: float = 0.01
    sigma_phi: float = 0.001
    obs_sigma: float = 1.0
    wheelbase: float = 2.8
    keep_probability: float = 1.0
    n_trajectories: int = 100_000

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ConfigError(f"vehicle config {self.name!r}: model={self.model!r}, "
                              f"expected one of {MODELS}")
        if self.dt <= 0 or self.t_end <= 0:
            raise ConfigError(f"vehicle config {self.name!r}: dt={self.dt} and "
                              f"t_end={self.t_end} must be positive")
        if abs(self.t_end / self.dt - round(self.t_end / self.dt)) > 1e-9:
            raise ConfigError(f"vehicle config {self.name!r}: t_end={self.t_end} is not a whole "
                              f"number of steps dt={self.dt}")
        if not 0.0 < self.keep_probability <= 1.0:
            raise ConfigError(f"vehicle config {self.name!r}: keep_probability="
                              f"{self.keep_probability} must be in (0, 1]")
        for field_name in ("sigma_v", "sigma_phi", "obs_sigma"):
            if getattr(self, field_name) < 0:
                raise ConfigError(f"vehicle config {self.name!r}: {field_name}="
                                  f"{getattr(self, field_name)} < 0")
        if self.wheelbase <= 0:
            raise ConfigError(f"vehicle config {self.name!r}: wheelbase={self.wheelbase} <= 0")
        if self.n_trajectories < 1:
            raise ConfigError(f"vehicle config {self.name!r}: n_trajectories="
                              f"{self.n_trajectories} < 1")

    @property
    def n_steps(self) -> int:
        return round(self.t_end / self.dt)

    def times(self) -> Tensor:
        return torch.arange(self.n_steps + 1, dtype=SIM_DTYPE) * self.dt

    def initial_state(self) -> Tensor:
        return torch.tensor([0.0, 0.0, 0.0, 0.0, self.v0], dtype=SIM_DTYPE)


VEHICLE_CONFIGS: dict[str, VehicleConfig] = {
    # (a) fixed step 1.0 -> 16 states; 100,000 trajectories -> 1.6 million points.
    "vehicle-full": VehicleConfig(name="vehicle-full", dt=1.0, keep_probability=1.0,
                                  n_trajectories=100_000),
    # (b) base step 0.1 -> 151 states, 10 % kept -> 100,000 x 151 x 0.1 ~ 1.51 million points.
    "vehicle-dropout": VehicleConfig(name="vehicle-dropout", dt=0.1, keep_probability=0.1,
                                     n_trajectories=100_000),
    # (c) as (b) with 100 trajectories -> 100 x 151 x 0.1 ~ 1,510 points (sd ~ 37).
    "vehicle-sparse": VehicleConfig(name="vehicle-sparse", dt=0.1, keep_probability=0.1,
                                    n_trajectories=100),
}


def get_vehicle_config(name: str, model: str = "paper") -> VehicleConfig:
    """The named dataset config with the chosen dynamics model (``paper`` or ``bicycle``)."""
    try:
        config = VEHICLE_CONFIGS[name]
    except KeyError:
        raise ConfigError(f"unknown vehicle config {name!r}; "
                          f"known: {sorted(VEHICLE_CONFIGS)}") from None
    return dataclasses.replace(config, model=model)


@dataclass(frozen=True)
class VehicleEnsemble:
    """Simulated vehicles: ``times (T,)`` float64, ``states (N, T, 5)`` = (p_x, p_y, theta, phi, v),
    ``psi (N,)`` in {-1, +1}, ``observations (N, T, 2)`` (noisy positions at *every* state),
    ``kept (N, T)`` bool (True = the observation survives dropout)."""

    times: Tensor
    states: Tensor
    psi: Tensor
    observations: Tensor
    kept: Tensor
    config: VehicleConfig
    seed: int

    @property
    def n_trajectories(self) -> int:
        return int(self.states.shape[0])

    @property
    def n_points(self) -> int:
        """Number of kept (observed) positions."""
        return int(self.kept.sum())


def switch_factor(t: float | Tensor, psi: Tensor, config: VehicleConfig) -> Tensor:
    """s(t) = 1 before ``config.switch_time`` and ``psi`` from then on (broadcast over ``psi``)."""
    t_tensor = torch.as_tensor(t, dtype=psi.dtype, device=psi.device)
    switched = t_tensor >= config.switch_time - _SWITCH_TOLERANCE
    return torch.where(switched, psi, torch.ones_like(psi))


def vehicle_step(state: Tensor, t: float | Tensor, dt: float, psi: Tensor, noise_v: Tensor | float,
                 noise_phi: Tensor | float, config: VehicleConfig) -> Tensor:
    """One transition x(t) -> x(t + dt) for ``state (..., 5)``.

    ``psi (...)`` is the switch value (+-1); ``t`` is the time at the start of the step (float or a
    tensor broadcasting against ``(...)``). ``noise_v`` and ``noise_phi`` are the *additive* process
    noise increments of this step in state units (already multiplied by sigma; pass 0 to switch
    noise off); :func:`draw_process_noise` draws them with the config's sigmas.
    """
    p_x, p_y, theta, phi, v = state.unbind(dim=-1)
    t_tensor = torch.as_tensor(t, dtype=state.dtype, device=state.device)
    if config.model == "paper":
        heading_rate = v * phi
    else:  # bicycle: kinematic single-track model, steering angle phi, wheel base L
        heading_rate = v * torch.tan(phi) / config.wheelbase
    steering = switch_factor(t_tensor, psi, config) * config.c1 * torch.cos(config.c2 * t_tensor)
    return torch.stack([
        p_x + dt * v * torch.cos(theta),
        p_y + dt * v * torch.sin(theta),
        theta + dt * heading_rate,
        phi + dt * steering + noise_phi,
        v + noise_v,
    ], dim=-1)


def standard_normal(shape: tuple[int, ...], generator: torch.Generator,
                    dtype: torch.dtype = SIM_DTYPE) -> Tensor:
    """Standard normal deviates drawn in float32 and returned in ``dtype``.

    torch's CPU sampler is ~6x faster in float32 than in float64 (measured 1.5 vs 9.6 ms for
    200,000 draws), and a float32 deviate is exact to ~1e-7 relative, far below anything the
    noise levels here (sigma = 0.001 ... 1) can resolve. Drawing in one precision also keeps the
    random stream independent of the storage dtype.
    """
    return torch.randn(shape, generator=generator, dtype=torch.float32).to(dtype)


def draw_process_noise(shape: tuple[int, ...], config: VehicleConfig, generator: torch.Generator,
                       dtype: torch.dtype = SIM_DTYPE) -> tuple[Tensor, Tensor]:
    """``(noise_v, noise_phi)`` of ``shape``: N(0, sigma_v^2) and N(0, sigma_phi^2) increments.

    One standard-normal draw of shape ``(2, *shape)`` (v first, then phi) per call.
    """
    eps = standard_normal((2, *shape), generator, dtype)
    return config.sigma_v * eps[0], config.sigma_phi * eps[1]


def draw_psi(n: int, generator: torch.Generator, dtype: torch.dtype = SIM_DTYPE) -> Tensor:
    """``n`` independent switches, -1 or +1 with probability 1/2 each."""
    return (2 * torch.randint(0, 2, (n,), generator=generator) - 1).to(dtype)


def simulate_nominal(config: VehicleConfig, psi: float) -> Tensor:
    """The noiseless trajectory ``(T, 5)`` (float64) for a given switch value (plots' black line)."""
    psi_t = torch.tensor(psi, dtype=SIM_DTYPE)
    state = config.initial_state()
    out = [state]
    for k in range(config.n_steps):
        state = vehicle_step(state, k * config.dt, config.dt, psi_t, 0.0, 0.0, config)
        out.append(state)
    return torch.stack(out)


def simulate_vehicle(config: VehicleConfig | str, n: int | None = None, seed: int = 0,
                     progress: ProgressReporter | None = None,
                     dtype: torch.dtype = torch.float32) -> VehicleEnsemble:
    """Simulate ``n`` vehicles (default ``config.n_trajectories``), observe them, apply dropout.

    Draw order from ``torch.Generator().manual_seed(seed)``: psi (N,); then for
    each time index k = 0 … T-1: the process noise (2, N) of the step into k (k >= 1), the
    observation noise (N, 2) of state k, the dropout uniforms (N,) of state k (only when
    ``keep_probability < 1``). Normal deviates and uniforms are drawn in float32 (see
    :func:`standard_normal`), the dynamics run in float64 whatever ``dtype`` is, so the
    storage precision (``states``, ``psi``, ``observations``; float32 by default, see the module
    docstring) changes values by rounding only. ``progress`` advances once per step.
    """
    if isinstance(config, str):
        config = get_vehicle_config(config)
    n = config.n_trajectories if n is None else int(n)
    if n < 1:
        raise ConfigError(f"simulate_vehicle: n={n} must be >= 1")
    reporter = progress or SilentProgress()
    generator = torch.Generator().manual_seed(seed)
    psi = draw_psi(n, generator)
    n_times = config.n_steps + 1
    states = torch.empty((n, n_times, 5), dtype=dtype)
    observations = torch.empty((n, n_times, 2), dtype=dtype)
    kept = torch.ones((n, n_times), dtype=torch.bool)
    state = config.initial_state().expand(n, 5).clone()
    # One time index at a time: the float64 working set stays (N, 5), and only the stored
    # result is (N, T, .) in the storage dtype.
    for k in range(n_times):
        if k > 0:
            noise_v, noise_phi = draw_process_noise((n,), config, generator)
            state = vehicle_step(state, (k - 1) * config.dt, config.dt, psi, noise_v, noise_phi,
                                 config)
        states[:, k] = state
        noise_obs = standard_normal((n, 2), generator)
        observations[:, k] = state[:, :2] + config.obs_sigma * noise_obs
        if config.keep_probability < 1.0:
            kept[:, k] = torch.rand(n, generator=generator) < config.keep_probability
        if k > 0:
            reporter.advance(1)
    return VehicleEnsemble(times=config.times(), states=states, psi=psi.to(dtype),
                           observations=observations, kept=kept, config=config, seed=seed)
