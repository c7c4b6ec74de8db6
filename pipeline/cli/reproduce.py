"""`flowcast reproduce tables`: the paper's Tables 1–4 (:mod:`pipeline.paper`).

Writes ``paper_tables.{json,md}`` and the figures to ``--out`` (default ``bench/results`` under
the working directory) and caches the trained models under ``--work`` (default ``bench/work``),
the layout of ``python -m bench.paper_tables`` in a checkout.
"""
from __future__ import annotations

import dataclasses
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
    out: Annotated[Path, typer.Option(help="results directory (paper_tables.{json,md}, "
                                           "figures/)")] = Path("bench/results"),
    work: Annotated[Path, typer.Option(help="trained-model cache (reused by later runs with "
                                            "the same budgets)")] = Path("bench/work"),
) -> None:
    """Train/load the models and write paper_tables.{json,md} + figures (to bench/results)."""
    from pipeline.paper import BenchConfig, Locations, pretrain, run

    cfg = BenchConfig.quick_config() if quick else BenchConfig()
    if train_budget_s is not None:
        cfg = dataclasses.replace(cfg, train_budget_s=train_budget_s)
    if vehicle_train_budget_s is not None:
        cfg = dataclasses.replace(cfg, vehicle_train_budget_s=vehicle_train_budget_s)
    locations = Locations(results=out.resolve(), work=work.resolve(), root=Path.cwd().resolve())
    if jobs > 1:
        pretrain(cfg, locations, jobs)
    result = run(cfg, locations)
    typer.echo(f"{len(result['cells'])} cells, {result['cells_at_or_below_paper']} at or below "
               f"the paper's value; {result['seconds']:.0f} s")
