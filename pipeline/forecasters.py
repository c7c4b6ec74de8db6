"""Forecasters for the backtest (:mod:`pipeline.backtest`): NF rollout and plain SMC.

Both implement ``forecast(history, horizon_days, n_samples, seed) -> (n_samples, horizon, 3)``:
``history`` has columns date, S, I, R (daily, ascending); the paths cover the days after the last
date. Time inside the models is in days since the first date of the history (only differences
matter to the flow; the SIR dynamics are autonomous).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import torch
from numpy.typing import NDArray

from pipeline.errors import ConfigError
from pipeline.estimate import Estimator, ObservationWindow, context_window_length
from pipeline.rollout import RolloutConfig, rollout
from pipeline.smc import SMCConfig, run_filter
from pipeline.smc_models import DEFAULT_OBS_SIGMA, DEFAULT_PROCESS_SIGMA, SIRParamsModel
from pipeline.systems.sir import SIR_PRIORS

COMPARTMENTS = ("S", "I", "R")


def history_days(history: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """(days since the first date (T,), values (T, 3)) of a date, S, I, R frame."""
    missing = [c for c in ("date", *COMPARTMENTS) if c not in history.columns]
    if missing:
        raise ConfigError(f"history lacks columns {missing}; expected date, S, I, R")
    dates = pd.to_datetime(history["date"])
    days = np.array(((dates - dates.iloc[0]) / pd.Timedelta(days=1)).to_numpy(dtype=np.float64))
    values = np.array(history[list(COMPARTMENTS)].to_numpy(dtype=np.float64))  # writable copy
    if not np.isfinite(values).all():
        raise ConfigError("history has missing S/I/R values (NaN)")
    return days, values


@dataclass
class NFRolloutForecaster:
    """Forward rollout of a trained forward S/I/R flow from the last R days of history.

    ``feedback_noise_sigma``: noise added to fed-back predictions (see :mod:`pipeline.rollout`);
    the default is the SIR training data's observation noise.
    """

    estimator: Estimator
    name: str = "nf-rollout"
    feedback_noise_sigma: float = SIR_PRIORS["sir-multi"].obs_sigma

    def forecast(self, history: pd.DataFrame, horizon_days: int, n_samples: int,
                 seed: int) -> NDArray[np.float64]:
        days, values = history_days(history)
        length = context_window_length(self.estimator, 5)
        if len(days) < length:
            raise ConfigError(f"{self.name}: needs at least {length} days of history, got {len(days)}")
        window = ObservationWindow(times=days[-length:], values=values[-length:],
                                   target_time=days[-1] + 1.0)
        result = rollout(self.estimator, window, horizon_days, 1.0, "forward",
                         RolloutConfig(n_paths=n_samples, seed=seed,
                                       feedback_noise_sigma=self.feedback_noise_sigma))
        return result.samples[..., :3].double().numpy()


@dataclass
class SMCForecaster:
    """Plain bootstrap filter over the last ``history_days`` days, then sample paths forward.

    Particles (S, I, R, β, γ), prior β, γ ~ the ``sir-multi`` prior, state prior around the first
    observation of the filtered stretch; after filtering, ``n_samples`` particles are drawn by
    their final weights and propagated through the stochastic SIR transition for the horizon
    (one vectorized step per day for all paths).
    """

    name: str = "smc"
    history_days: int = 56
    n_particles: int = 2000
    obs_sigma: float = DEFAULT_OBS_SIGMA
    process_sigma: float = DEFAULT_PROCESS_SIGMA
    param_jitter: float = 0.01
    beta_range: tuple[float, float] = field(default=SIR_PRIORS["sir-multi"].beta)
    gamma_range: tuple[float, float] = field(default=SIR_PRIORS["sir-multi"].gamma)

    def forecast(self, history: pd.DataFrame, horizon_days: int, n_samples: int,
                 seed: int) -> NDArray[np.float64]:
        days, values = history_days(history)
        days, values = days[-self.history_days:], values[-self.history_days:]
        model = SIRParamsModel.create(prior_mean=values[0], prior_std=self.obs_sigma,
                                      beta_range=self.beta_range, gamma_range=self.gamma_range,
                                      obs_sigma=self.obs_sigma, process_sigma=self.process_sigma,
                                      param_jitter=self.param_jitter)
        result = run_filter(model, torch.as_tensor(values)[None],
                            SMCConfig(num_particles=self.n_particles, seed=seed, quantiles=()),
                            times=torch.as_tensor(days))
        generator = torch.Generator().manual_seed(seed + 1)
        weights = result.log_weights[0].exp()
        index = torch.multinomial(weights, n_samples, replacement=True, generator=generator)
        x = result.particles[0, index][None]                                   # (1, n, 5)
        paths = torch.empty((n_samples, horizon_days, 3), dtype=torch.float64)
        for step in range(horizon_days):
            x = model.transition(x, float(days[-1] + step), 1.0, generator)
            paths[:, step] = x[0, :, :3]
        if not bool(torch.isfinite(paths).all()):
            raise ConfigError(f"{self.name}: non-finite forecast paths")
        return paths.numpy()
