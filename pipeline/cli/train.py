"""`flowcast train <preset>`: build (or load) the dataset, train, write checkpoint and curves."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli import app
from pipeline.cli.choices import Backend, Direction, Encoder, Recipe, TrainPreset, finite, value

_PRESET_HELP = ("vehicle, vehicle-sparse, sir-single, sir-multi, sir-joint (paper set-ups), "
                "sir-sf-joint, sf-waves-joint (the SF forecast's); see docs/training.md")


@app.command("train")
def train_command(
    preset: Annotated[TrainPreset, typer.Argument(help=_PRESET_HELP)],
    encoder: Annotated[Encoder, typer.Option(help="context encoder")] = Encoder("transformer"),
    backend: Annotated[Backend | None, typer.Option(help="flow package (default: zuko)")] = None,
    direction: Annotated[Direction, typer.Option(
        help="forward: context before the target; backward: after it")] = Direction("forward"),
    recipe: Annotated[Recipe, typer.Option(
        help="paper (the paper's optimiser settings) or fast (ours)")] = Recipe("fast"),
    iterations: Annotated[int | None, typer.Option(min=1,
                                                   help="override the recipe's iterations")]
    = None,
    batch_size: Annotated[int | None, typer.Option(min=1,
                                                   help="override the recipe's batch size")]
    = None,
    lr: Annotated[float | None, typer.Option(callback=finite(0.0, strictly=True),
                                             help="override the recipe's (peak) learning rate")]
    = None,
    seed: Annotated[int, typer.Option(help="seed of initialisation, batches and noise")] = 0,
    dataset: Annotated[Path | None, typer.Option(help="windowed dataset file (from `flowcast "
                                                      "simulate`); default: simulate the "
                                                      "preset's data")] = None,
    threads: Annotated[int | None, typer.Option(min=1, help="torch threads while training")]
    = None,
    out: Annotated[Path, typer.Option(help="output directory (model.pt, history.csv/json, "
                                           "loss.png, preset.json)")] = Path("runs"),
) -> None:
    """Train a conditional flow for a paper preset and write its checkpoint and loss curves."""
    from pipeline.errors import FlowcastError

    try:
        result_line = run_train(value(preset), encoder=value(encoder), backend=value(backend),
                                direction=value(direction), recipe=value(recipe),
                                iterations=iterations, batch_size=batch_size,
                                lr=lr, seed=seed, dataset=dataset, threads=threads, out=out)
    except FlowcastError as error:
        typer.secho(f"error: {error}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from error
    typer.echo(result_line)


def run_train(preset_name: str, *, encoder: str = "transformer", backend: str | None = None,
              direction: str = "forward", recipe: str = "fast", iterations: int | None = None,
              batch_size: int | None = None, lr: float | None = None, seed: int = 0,
              dataset: Path | None = None, threads: int | None = None,
              out: Path = Path("runs"), show_progress: bool = True) -> str:
    """The command's work, callable from tests; returns the summary line."""
    from pipeline.io import atomic_write_text
    from pipeline.progress import rich_progress
    from pipeline.training.datasets import (build_dataset_from_config, load_dataset,
                                            train_validation_split)
    from pipeline.training.fit import fit_preset
    from pipeline.training.presets import get_preset

    # The seed seeds the initial weights too: fit_preset takes it from preset.train.seed.
    preset = get_preset(preset_name, encoder, recipe=recipe, backend=backend,
                        direction=direction, seed=seed)
    preset = preset.with_overrides(iterations=iterations, batch_size=batch_size, lr=lr,
                                   num_threads=threads)
    if dataset is not None:
        data = load_dataset(dataset, config_name=preset.dataset.name, direction=direction,
                            target=preset.dataset.target, window=preset.dataset.window,
                            absolute_time=preset.dataset.absolute_time)
    else:
        typer.echo(f"simulating {preset.dataset.name} ({direction}) ...", err=True)
        data = build_dataset_from_config(preset.dataset)
    train_ds, val_ds = train_validation_split(data, preset.estimator.target_transform)
    run_dir = out / preset.run_name
    typer.echo(f"training {preset.run_name}: {len(train_ds)} training / {len(val_ds)} "
               f"validation windows -> {run_dir}", err=True)
    extra = {"dataset_file": str(dataset) if dataset else None}
    if show_progress:
        with rich_progress(preset.run_name, preset.train.iterations) as progress:
            result = fit_preset(preset, train_ds, val_ds, run_dir, progress=progress, extra=extra)
    else:
        result = fit_preset(preset, train_ds, val_ds, run_dir, extra=extra)
    atomic_write_text(run_dir / "preset.json",
                      json.dumps(dataclasses.asdict(preset), indent=2, default=str) + "\n")
    return (f"best validation NLL {result.best_val_nll_original:.4f} nats (original units; "
            f"{result.best_val_nll:.4f} standardized) at iteration {result.best_iteration} of "
            f"{result.iterations_run} ({result.stop_reason}, {result.wall_s:.1f} s); "
            f"checkpoint {run_dir / 'model.pt'}")
