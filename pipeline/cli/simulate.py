"""`flowcast simulate`: simulate a named system and write its windowed dataset."""
from __future__ import annotations

import time
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console

from pipeline.cli import app
from pipeline.cli.output_paths import output_file
from pipeline.errors import FlowcastError
from pipeline.names import DEFAULT_VAL_FRACTION, DEFAULT_WINDOW
from pipeline.progress import rich_progress

if TYPE_CHECKING:
    from pipeline.training.datasets import DatasetConfig


class DatasetName(str, Enum):
    sir_single = "sir-single"
    sir_multi = "sir-multi"
    sir_sf = "sir-sf"
    vehicle_full = "vehicle-full"
    vehicle_dropout = "vehicle-dropout"
    vehicle_sparse = "vehicle-sparse"


class Direction(str, Enum):
    forward = "forward"
    backward = "backward"


class TargetKind(str, Enum):
    state = "state"
    state_params = "state+params"


class VehicleModel(str, Enum):
    paper = "paper"
    bicycle = "bicycle"


def default_output(config: DatasetConfig) -> Path:
    """data/datasets/<config>-<direction>-<target>.pt (relative to the working directory);
    ``-bicycle`` is appended for the bicycle vehicle model so it never overwrites the paper's."""
    suffix = "-bicycle" if config.system == "vehicle" and config.vehicle_model == "bicycle" else ""
    stem = f"{config.name}-{config.direction}-{config.target}{suffix}"
    return Path("data") / "datasets" / f"{stem}.pt"


@app.command("simulate")
def simulate(
    config: DatasetName = typer.Argument(..., help="Named dataset config to simulate."),
    out: Path | None = typer.Option(
        None, "--out",
        help="Output file (default: data/datasets/<config>-<direction>-<target>.pt)."),
    direction: Direction = typer.Option(Direction.forward, help="forward: context before the "
                                        "target; backward: context after it."),
    target: TargetKind = typer.Option(TargetKind.state, help="state, or state+params "
                                      "(S, I, R, beta, gamma; sir-multi and sir-sf)."),
    window: int = typer.Option(DEFAULT_WINDOW, min=1, help="Context length R."),
    seed: int = typer.Option(0, help="Seed of the simulation and of the train/validation split."),
    vehicle_model: VehicleModel = typer.Option(VehicleModel.paper, help="Vehicle dynamics: the "
                                               "paper's equations or the kinematic bicycle."),
    n_trajectories: int | None = typer.Option(
        None, min=1, help="Override the preset's ensemble size (for quick experiments)."),
    val_fraction: float = typer.Option(DEFAULT_VAL_FRACTION, min=0.0, max=0.99,
                                       help="Fraction of trajectories held out for validation."),
) -> None:
    """Simulate a system (SIR or vehicle) and write its windowed (context, target) dataset."""
    # the engine (torch) loads when a command runs, not when the command line is listed
    from pipeline.training.datasets import (DatasetConfig, build_dataset_from_config, describe,
                                            progress_total, save_dataset)

    console = Console()
    try:
        dataset_config = DatasetConfig(
            name=config.value, direction=direction.value, target=target.value, window=window,
            seed=seed, vehicle_model=vehicle_model.value, val_fraction=val_fraction,
            n_trajectories=n_trajectories)
        path = output_file(out if out is not None else default_output(dataset_config),
                           example=default_output(dataset_config).name)
        started = time.perf_counter()
        with rich_progress(f"simulate {dataset_config.name}",
                           progress_total(dataset_config)) as reporter:
            ds = build_dataset_from_config(dataset_config, reporter)
        file_sha256 = save_dataset(ds, path)
        seconds = time.perf_counter() - started
    except FlowcastError as exc:
        console.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(code=1) from exc
    summary = describe(ds)
    rows = [("windows", f"{summary['windows']:,} ({summary['validation_windows']:,} validation)"),
            ("trajectories", f"{summary['trajectories']:,}"),
            ("observed points", f"{summary['observed_points']:,}"),
            ("observed values", f"{summary['observed_values']:,}"),
            ("context / target", f"{summary['context_shape']} / {summary['target_shape']}"),
            ("seconds", f"{seconds:.2f}"), ("file", str(path)), ("sha256", file_sha256),
            ("data sha256", summary["data_sha256"])]
    # Plain lines with soft wrap: hashes and paths stay whole and copyable at any terminal width.
    for key, value in rows:
        console.print(f"[bold]{key:<17}[/bold] {value}", soft_wrap=True, highlight=False)
