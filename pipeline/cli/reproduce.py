"""`flowcast reproduce tables`: the paper's Tables 1–4 (runs bench/paper_tables.py).

The benchmark lives in the repository's ``bench/`` folder (not in the installed package), so the
command must be run from a checkout (it looks for ``bench/paper_tables.py`` under the working
directory).
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Annotated

import typer

from pipeline.cli import app

reproduce_app = typer.Typer(no_args_is_help=True, help="Reproduce the paper's results.")
app.add_typer(reproduce_app, name="reproduce")


@reproduce_app.command("tables")
def tables_command(
    quick: Annotated[bool, typer.Option(help="tiny sizes: checks the pipeline in minutes; "
                                             "writes paper_tables_quick.{json,md}")] = False,
    train_budget_s: Annotated[float | None, typer.Option(
        help="wall-clock cap per trained SIR model in seconds (default 200; quick 10)")] = None,
    vehicle_train_budget_s: Annotated[float | None, typer.Option(
        help="wall-clock cap per vehicle model in seconds (default 360)")] = None,
    jobs: Annotated[int, typer.Option(min=1, help="train missing models this many at a time "
                                                  "first, one thread each")] = 2,
) -> None:
    """Train/load the models and write bench/results/paper_tables.{json,md} + figures."""
    root = Path.cwd()
    if not (root / "bench" / "paper_tables.py").is_file():
        typer.secho(f"error: bench/paper_tables.py not found under {root}; run this from the "
                    "flowcast repository root", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1)
    sys.path.insert(0, str(root))
    from bench.paper_tables import BenchConfig, pretrain, run

    cfg = BenchConfig.quick_config() if quick else BenchConfig()
    if train_budget_s is not None:
        cfg = dataclasses.replace(cfg, train_budget_s=train_budget_s)
    if vehicle_train_budget_s is not None:
        cfg = dataclasses.replace(cfg, vehicle_train_budget_s=vehicle_train_budget_s)
    if jobs > 1:
        pretrain(cfg, jobs)
    result = run(cfg)
    typer.echo(f"{len(result['cells'])} cells, {result['cells_at_or_below_paper']} at or below "
               f"the paper's value; {result['seconds']:.0f} s")
