"""`flowcast backtest --from DATE --to DATE --out DIR`: the real-time backtest of the weekly forecast.

For every weekly origin in the range it writes the hub-format forecast a user would have published
that day (``forecasts/<origin>-published.csv``), plus ``scores.csv`` (WIS and its parts, 50 %/90 %
coverage and PIT per forecaster × target × horizon × origin) and ``summary.json`` (relative WIS
vs the hub baseline and coverage per target × horizon). See
:mod:`pipeline.ensemble.backtest`.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from pipeline.cli import app
from pipeline.cli.output_paths import output_dir
from pipeline.cli.choices import DataSource, value
from pipeline.errors import ConfigError, FlowcastError

if TYPE_CHECKING:
    from pipeline.forecast.config import DataSourceKind


def _source_kind(source: Enum) -> DataSourceKind:
    kind = value(source)
    if kind == "live" or kind == "cache" or kind == "import":
        return kind
    raise ConfigError(f"unknown data source {kind!r}")  # typer only passes DataSource's values


def _date(value: str | None, option: str) -> dt.date | None:
    if value is None:
        return None
    try:
        return dt.date.fromisoformat(value)
    except ValueError:
        typer.secho(f"error: {option} {value!r} is not a date (YYYY-MM-DD)", fg=typer.colors.RED,
                    err=True)
        raise typer.Exit(code=2) from None


@app.command("backtest")
def backtest_command(
    out: Annotated[Path, typer.Option("--out", help="output directory")],
    first: Annotated[str | None, typer.Option(
        "--from", help="first origin (YYYY-MM-DD; default: 8 weeks into the data)")] = None,
    last: Annotated[str | None, typer.Option(
        "--to", help="last origin (YYYY-MM-DD; default: the last with 4 weeks of truth)")] = None,
    all_origins: Annotated[bool, typer.Option(
        "--all-origins", help="also origins whose 4-week truth is not observed yet")] = False,
    nf: Annotated[bool, typer.Option("--nf/--no-nf", help="include the NF member")] = True,
    source: Annotated[DataSource, typer.Option(
        help="where the SF series comes from")] = DataSource("cache"),
    import_from: Annotated[list[Path] | None, typer.Option(
        "--import", help="DataSF CSV exports to import first (with --source import)")] = None,
    seed: Annotated[int, typer.Option(help="seed of the members' draws")] = 0,
) -> None:
    """Real-time backtest over weekly origins: published forecasts, scores and a summary."""
    from pipeline import forecast as fc
    from pipeline.forecast.sources import import_exports, load_sf_history
    from pipeline.training.model_store import default_store_root
    from pipeline.ensemble.backtest import (backtest_origins,
                                               run_realtime_backtest, summarize, write_backtest)
    from pipeline.ensemble.weekly import build_weekly_members
    from pipeline.progress import rich_progress

    try:
        output_dir(out)
        history = load_sf_history(fc.DataSourceConfig(
            kind=_source_kind(source), import_paths=tuple(str(p) for p in import_from or [])))
        weekly = dataclasses.replace(fc.resolve_config("default", seed=seed).weekly_config(),
                                     include_nf=nf)
        config = weekly.backtest_config(scored_only=not all_origins,
                                        first_origin=_date(first, "--from"),
                                        last_origin=_date(last, "--to"))
        n_origins = len(backtest_origins(history, config))
        members, _, _ = build_weekly_members(weekly, default_store_root())
        with rich_progress("backtest", n_origins) as progress:
            result = run_realtime_backtest(history, members, config, progress)
        written = write_backtest(result, out)
    except FlowcastError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from None
    summary = summarize(result)
    for target, by_forecaster in summary["by_target"].items():
        for name, s in by_forecaster.items():
            rel = s["relative_wis_vs_baseline"]
            cells = " ".join(f"{k}={v:.3f}" if v is not None else f"{k}=n/a"
                             for k, v in rel.items())
            typer.echo(f"{target:5s} {name:22s} relative WIS {cells}  coverage "
                       f"{s['coverage50']:.2f}/{s['coverage90']:.2f}")
    typer.echo(f"{len(result.origins)} origins, invalid values {summary['invalid_values']}, "
               f"{result.seconds:.1f} s; {len(written)} files under {out}")
