"""`flowcast smc filter`: run the bootstrap particle filter over a CSV of observations.

CSV input: a ``time`` column (numbers) or a ``date`` column (ISO dates; time = days since the first
date), plus the system's observed columns (SIR: S, I, R; vehicle: p_x, p_y); empty cells are
missing observations (the filter propagates without an update there). Output CSV: one row per
input row with, for every state component, the weighted mean, std, the ±3σ band (mean ∓ 3 std)
and the 0.135 % / 99.865 % weighted quantiles, plus ESS and whether the filter resampled (the
total log-evidence is printed).
"""
from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
import pandas as pd
import torch
import typer

from pipeline.cli import app
from pipeline.cli.csv_input import read_timed_csv
from pipeline.errors import ConfigError, FlowcastError
from pipeline.io import atomic_write_text
from pipeline.progress import rich_progress
from pipeline.smc import SMCConfig, run_filter
from pipeline.smc_models import (DEFAULT_OBS_SIGMA, DEFAULT_PROCESS_SIGMA, SIRParamsModel,
                                 SIRStateModel, VehicleModel)
from pipeline.systems.vehicle import get_vehicle_config

smc_app = typer.Typer(no_args_is_help=True, help="Particle filter (bootstrap SMC) baselines.")
app.add_typer(smc_app, name="smc")

SYSTEMS = ("sir", "sir-params", "vehicle")
_OBSERVED = {"sir": ("S", "I", "R"), "sir-params": ("S", "I", "R"), "vehicle": ("p_x", "p_y")}


def read_observations(path: Path, columns: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(times (T,), values (T, C) with NaN for empty cells: the filter skips those updates)."""
    times, values, _ = read_timed_csv(path, columns)
    return times, values


def build_model(system: str, first: np.ndarray, beta: float, gamma: float, obs_sigma: float,
                process_sigma: float, param_jitter: float):
    """The filter's model; the prior is centred on the first observation (the paper's p(o_n))."""
    first = np.array(first, dtype=np.float64)  # a writable copy (pandas hands out read-only views)
    if np.isnan(first).any():
        raise ConfigError("the first observation row must be complete: it centres the prior")
    if system == "sir":
        return SIRStateModel.create(beta, gamma, first, prior_std=obs_sigma, obs_sigma=obs_sigma,
                                    process_sigma=process_sigma)
    if system == "sir-params":
        return SIRParamsModel.create(first, prior_std=obs_sigma, obs_sigma=obs_sigma,
                                     process_sigma=process_sigma, param_jitter=param_jitter)
    config = get_vehicle_config("vehicle-full")
    mean = config.initial_state().clone()
    mean[:2] = torch.as_tensor(first)
    return VehicleModel.create(config, initial_mean=mean)


def result_frame(result, times: np.ndarray, observations: np.ndarray,
                 observed: tuple[str, ...]) -> pd.DataFrame:
    lower, upper = result.sigma_band(3.0)
    q_low, q_high = result.quantile_band(0.9973002039367398)
    columns: dict[str, np.ndarray] = {"time": times}
    for c, name in enumerate(observed):
        columns[f"obs_{name}"] = observations[:, c]
    for d, name in enumerate(result.state_names):
        columns[f"{name}_mean"] = result.mean[0, :, d].numpy()
        columns[f"{name}_std"] = result.std[0, :, d].numpy()
        columns[f"{name}_lower_3sigma"] = lower[0, :, d].numpy()
        columns[f"{name}_upper_3sigma"] = upper[0, :, d].numpy()
        columns[f"{name}_q00135"] = q_low[0, :, d].numpy()
        columns[f"{name}_q99865"] = q_high[0, :, d].numpy()
    columns["ess"] = result.ess[0].numpy()
    columns["resampled"] = result.resampled[0].numpy()
    return pd.DataFrame(columns)


@smc_app.command("filter")
def filter_command(
    observations: Annotated[Path, typer.Option("--observations", help="CSV: time|date + observed "
                                               "columns (SIR: S,I,R; vehicle: p_x,p_y)")],
    out: Annotated[Path, typer.Option("--out", help="output CSV (means, bands, ESS per step)")],
    system: Annotated[str, typer.Option(help=f"one of {', '.join(SYSTEMS)}")] = "sir",
    particles: Annotated[int, typer.Option(help="number of particles")] = 1000,
    seed: Annotated[int, typer.Option(help="random seed")] = 0,
    beta: Annotated[float, typer.Option(help="SIR infection rate (system sir)")] = 0.03,
    gamma: Annotated[float, typer.Option(help="SIR recovery rate (system sir)")] = 0.01,
    obs_sigma: Annotated[float, typer.Option(help="SIR observation noise")] = DEFAULT_OBS_SIGMA,
    process_sigma: Annotated[float, typer.Option(help="SIR process noise per sqrt(day)")]
    = DEFAULT_PROCESS_SIGMA,
    param_jitter: Annotated[float, typer.Option(help="log-normal jitter of beta, gamma per "
                                                "sqrt(day) (sir-params)")] = 0.0,
) -> None:
    """Filter one observed series with the bootstrap particle filter and write the summaries."""
    try:
        if system not in SYSTEMS:
            raise ConfigError(f"--system {system!r}: expected one of {list(SYSTEMS)}")
        observed = _OBSERVED[system]
        times, values = read_observations(observations, observed)
        model = build_model(system, values[0], beta, gamma, obs_sigma, process_sigma,
                            param_jitter)
        obs = torch.tensor(values)[None]  # a copy: pandas hands out read-only arrays
        obs[0, 0] = float("nan")  # the first row centres the prior; using it again would count it twice
        config = SMCConfig(num_particles=particles, seed=seed)
        with rich_progress(f"SMC {system}", total=len(times)) as progress:
            result = run_filter(model, obs, config, times=torch.tensor(times),
                                progress=progress)
        frame = result_frame(result, times, values, observed)
        atomic_write_text(out, frame.to_csv(index=False))
        typer.echo(f"wrote {out} ({len(frame)} steps, log-evidence "
                   f"{float(result.log_evidence[0]):.3f}, min ESS {float(result.ess.min()):.0f})")
    except FlowcastError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(code=2) from None
