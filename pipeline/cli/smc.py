"""`flowcast smc filter`: run the bootstrap particle filter over a CSV of observations.

CSV input: a ``time`` column (numbers) or a ``date`` column (ISO dates; time = days since the first
date), plus the system's observed columns (SIR: S, I, R; vehicle: p_x, p_y); empty cells are
missing observations (the filter propagates without an update there); any other cell that is
not a number is refused (file, row, column named). ``--prior`` names the SIR settings
(``sir-sf`` for San Francisco data; the default ``sir-single`` is the paper's synthetic set-up)
and every setting used is printed. Output CSV: one row per input row (with the input's ``date``
column when it has one) with, for every state component, the weighted mean, std, the ±3σ band
(mean ∓ 3 std) and the 0.135 % / 99.865 % weighted quantiles, plus ESS and whether the filter
resampled (the total log-evidence is printed).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import pandas as pd
import typer

from pipeline.cli import app
from pipeline.cli.choices import SIRPriorName, SMCSystem, finite, value
from pipeline.cli.csv_input import read_timed_csv
from pipeline.cli.output_paths import output_file
from pipeline.errors import ConfigError, FlowcastError
from pipeline.io import atomic_write_text
from pipeline.progress import rich_progress

# The filter's modules (torch) load when the command runs, not when the command line is listed.

smc_app = typer.Typer(no_args_is_help=True, help="Particle filter (bootstrap SMC) baselines.")
app.add_typer(smc_app, name="smc")

SYSTEMS = ("sir", "sir-params", "vehicle")
# Process noise per prior: the paper's 1e-3 was sized for sir-multi's I of ~0.1; SF's I (median
# 8e-4) needs a fifth of sir-sf's observation noise (as the weekly forecast's seeded filter).
PRIOR_PROCESS_SIGMA = {"sir-sf": 1e-4}
_OBSERVED = {"sir": ("S", "I", "R"), "sir-params": ("S", "I", "R"), "vehicle": ("p_x", "p_y")}


def build_model(system: str, first: np.ndarray, settings: FilterSettings):  # noqa: ANN201
    """The filter's model; the prior is centred on the first observation (the paper's p(o_n))."""
    import torch

    from pipeline.inference.smc_models import SIRParamsModel, SIRStateModel, VehicleModel
    from pipeline.systems.vehicle import get_vehicle_config

    first = np.array(first, dtype=np.float64)  # a writable copy (pandas hands out read-only views)
    if np.isnan(first).any():
        raise ConfigError("the first observation row must be complete: it centres the prior")
    if system == "sir":
        return SIRStateModel.create(settings.beta, settings.gamma, first,
                                    prior_std=settings.obs_sigma, obs_sigma=settings.obs_sigma,
                                    process_sigma=settings.process_sigma)
    if system == "sir-params":
        return SIRParamsModel.create(first, prior_std=settings.obs_sigma,
                                     beta_range=settings.beta_range,
                                     gamma_range=settings.gamma_range,
                                     obs_sigma=settings.obs_sigma,
                                     process_sigma=settings.process_sigma,
                                     param_jitter=settings.param_jitter)
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


@dataclass(frozen=True)
class FilterSettings:
    """The filter's SIR settings: the named prior's, with any option given on the command line
    in its place."""

    prior: str
    beta: float
    gamma: float
    beta_range: tuple[float, float]
    gamma_range: tuple[float, float]
    obs_sigma: float
    process_sigma: float
    param_jitter: float

    def describe(self, system: str) -> str:
        rates = (f"beta {self.beta:.3g}, gamma {self.gamma:.3g}" if system == "sir" else
                 f"beta in {self.beta_range}, gamma in {self.gamma_range}, jitter "
                 f"{self.param_jitter:g}")
        return (f"prior {self.prior}: {rates}, observation noise {self.obs_sigma:g}, process "
                f"noise {self.process_sigma:g}")


def filter_settings(prior_name: str, *, beta: float | None = None, gamma: float | None = None,
                    obs_sigma: float | None = None, process_sigma: float | None = None,
                    param_jitter: float | None = None) -> FilterSettings:
    """Settings from the prior ``prior_name`` (``pipeline.systems.sir.SIR_PRIORS``): its β, γ
    ranges (fixed rates: their geometric middle), observation noise, β random-walk jitter; the
    process noise is :data:`PRIOR_PROCESS_SIGMA`'s."""
    from pipeline.inference.smc_models import DEFAULT_PROCESS_SIGMA
    from pipeline.systems.sir import SIR_PRIORS

    prior = SIR_PRIORS[prior_name]
    return FilterSettings(
        prior=prior_name,
        beta=beta if beta is not None else math.sqrt(prior.beta[0] * prior.beta[1]),
        gamma=gamma if gamma is not None else math.sqrt(prior.gamma[0] * prior.gamma[1]),
        beta_range=prior.beta, gamma_range=prior.gamma,
        obs_sigma=obs_sigma if obs_sigma is not None else prior.obs_sigma,
        process_sigma=(process_sigma if process_sigma is not None
                       else PRIOR_PROCESS_SIGMA.get(prior_name, DEFAULT_PROCESS_SIGMA)),
        param_jitter=param_jitter if param_jitter is not None else prior.beta_walk_sigma)


@smc_app.command("filter")
def filter_command(
    observations: Annotated[Path, typer.Option("--observations", help="CSV: time|date + observed "
                                               "columns (SIR: S,I,R; vehicle: p_x,p_y)")],
    out: Annotated[Path, typer.Option("--out", help="output CSV (means, bands, ESS per step; "
                                                    "the input's dates when it has them)")],
    system: Annotated[SMCSystem, typer.Option(
        help="sir: fixed beta, gamma; sir-params: beta, gamma estimated too; vehicle")]
    = SMCSystem("sir"),
    prior: Annotated[SIRPriorName, typer.Option(
        help="SIR settings by name: sir-sf for San Francisco data (fitted to it), sir-single / "
             "sir-multi for the paper's synthetic set-ups; the options below override it")]
    = SIRPriorName("sir-single"),
    particles: Annotated[int, typer.Option(min=1, help="number of particles")] = 1000,
    seed: Annotated[int, typer.Option(help="random seed")] = 0,
    beta: Annotated[float | None, typer.Option(
        callback=finite(0.0), help="SIR infection rate (system sir; default: the prior's)")]
    = None,
    gamma: Annotated[float | None, typer.Option(
        callback=finite(0.0), help="SIR recovery rate (system sir; default: the prior's)")]
    = None,
    obs_sigma: Annotated[float | None, typer.Option(
        callback=finite(0.0, strictly=True),
        help="SIR observation noise (default: the prior's)")] = None,
    process_sigma: Annotated[float | None, typer.Option(
        callback=finite(0.0), help="SIR process noise per sqrt(day) (default: the prior's)")]
    = None,
    param_jitter: Annotated[float | None, typer.Option(
        callback=finite(0.0), help="log-normal jitter of beta, gamma per sqrt(day) (sir-params; "
                                   "default: the prior's)")] = None,
) -> None:
    """Filter one observed series with the bootstrap particle filter and write the summaries."""
    import torch

    from pipeline.inference.smc import SMCConfig, run_filter

    try:
        output_file(out, example="filtered.csv")
        system_name = str(value(system))
        observed = _OBSERVED[system_name]
        times, values, dates = read_timed_csv(observations, observed)
        settings = filter_settings(str(value(prior)), beta=beta, gamma=gamma,
                                   obs_sigma=obs_sigma, process_sigma=process_sigma,
                                   param_jitter=param_jitter)
        if system_name != "vehicle":
            typer.echo(settings.describe(system_name), err=True)
        model = build_model(system_name, values[0], settings)
        obs = torch.tensor(values)[None]  # a copy: pandas hands out read-only arrays
        obs[0, 0] = float("nan")  # the first row centres the prior; using it again would count it twice
        config = SMCConfig(num_particles=particles, seed=seed)
        with rich_progress(f"SMC {system_name}", total=len(times)) as progress:
            result = run_filter(model, obs, config, times=torch.tensor(times),
                                progress=progress)
        frame = result_frame(result, times, values, observed)
        if dates is not None:
            frame.insert(0, "date", dates.dt.strftime("%Y-%m-%d").to_numpy())
        atomic_write_text(out, frame.to_csv(index=False))
        typer.echo(f"wrote {out} ({len(frame)} steps, log-evidence "
                   f"{float(result.log_evidence[0]):.3f}, min ESS {float(result.ess.min()):.0f})")
    except FlowcastError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(code=2) from None
