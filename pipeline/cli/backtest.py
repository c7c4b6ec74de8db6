"""`flowcast backtest --from DATE --to DATE --out DIR`: the real-time backtest of the weekly forecast.

``--county NAME|all`` backtests California counties instead of San Francisco's DataSF series:
every county with at least 100,000 people on the latest cached CDPH vintage is forecast (the
pooled members learn from all of them); ``all`` reports every one of them, a name that county
(the panel still pools the others). It writes ``summary.json`` (geometric-mean relative WIS per
target × horizon, share of counties beating the baseline, coverage, per-county ratios),
``scores.csv`` and ``weights.csv`` (:mod:`pipeline.ensemble.county_backtest`).

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
    county: Annotated[str | None, typer.Option(
        "--county", help="a California county (CDPH data), or 'all' for every county with "
                         "at least 100,000 people; default: San Francisco from DataSF")] = None,
) -> None:
    """Real-time backtest over weekly origins: published forecasts, scores and a summary."""
    if county is not None:
        _county_backtest(county, out, nf, seed)
        return
    from pipeline import forecast as fc
    from pipeline.forecast.sources import (SF_COUNTY, import_exports,
                                           load_reference_histories, load_sf_history)
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
        members = build_weekly_members(weekly, default_store_root(),
                                       load_reference_histories(),
                                       history, SF_COUNTY).members
        with rich_progress("backtest", n_origins) as progress:
            result = run_realtime_backtest(history, members, config, progress)
        written = write_backtest(result, out)
    except FlowcastError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from None
    summary = summarize(result)
    for target, by_forecaster in summary["by_target"].items():
        for name, s in by_forecaster.items():
            typer.echo(f"{target:5s} {name:22s} relative WIS "
                       f"{_horizon_cells(s['relative_wis_vs_baseline'])}  coverage "
                       f"{s['coverage50']:.2f}/{s['coverage90']:.2f}")
    typer.echo(f"{len(result.origins)} origins, invalid values {summary['invalid_values']}, "
               f"{result.seconds:.1f} s; {len(written)} files under {out}")


def _county_backtest(county: str, out: Path, nf: bool, seed: int) -> None:
    """``--county``: the cross-county backtest on the latest cached CDPH vintage."""
    from pipeline.data.cdph_source import load_cdph_vintage
    from pipeline.ensemble.county_backtest import (CountyBacktestConfig, county_panel,
                                                   for_places, run_panel_backtest,
                                                   select_counties, summarize_panel,
                                                   write_panel_backtest)
    from pipeline.ensemble.panel import weekly_origins
    from pipeline.ensemble.weekly import build_panel_members
    from pipeline.forecast import resolve_config
    from pipeline.progress import rich_progress
    from pipeline.training.model_store import default_store_root

    try:
        output_dir(out)
        vintage = load_cdph_vintage(offline=True)
        config = CountyBacktestConfig(seed=seed)
        pool = select_counties(vintage, config)
        chosen = pool if county.lower() == "all" else select_counties(vintage, config, [county])
        panel = county_panel(vintage, sorted({*pool, *chosen}), config.trailing_days)
        origins = weekly_origins(panel.dates, min_history_weeks=config.min_history_weeks,
                                 horizon_weeks=max(config.horizons))
        weekly = dataclasses.replace(resolve_config("default", seed=seed).weekly_config(),
                                     include_nf=nf)
        with rich_progress("members' models", 1) as progress:
            members = build_panel_members(list(panel.histories.values()), origins, weekly,
                                          default_store_root(), progress).members
        cells = len(panel.places) * len(origins) * (len(members) + 1)
        with rich_progress("cross-county backtest", cells) as progress:
            result = for_places(run_panel_backtest(panel, members, config, progress=progress),
                                chosen)
        written = write_panel_backtest(result, out, {"vintage": str(vintage.as_of.date()),
                                                     "pooled_places": len(panel.places)})
    except FlowcastError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from None
    summary = summarize_panel(result)
    for target, by_forecaster in summary["by_target"].items():
        for name, s in by_forecaster.items():
            typer.echo(f"{target:5s} {name:22s} relative WIS "
                       f"{_horizon_cells(s['gmean_relative_wis'])}  beat "
                       f"{s['share_beating_baseline']['all']:.2f}  coverage "
                       f"{s['coverage50']:.2f}/{s['coverage90']:.2f}")
    typer.echo(f"{len(chosen)} of {len(panel.places)} counties, {len(origins)} origins, "
               f"vintage {vintage.as_of.date()}; {len(written)} files under {out}")


def _horizon_cells(by_horizon: dict[str, float | None]) -> str:
    """``h1=0.812 h2=… all=…`` (``n/a`` where a horizon has no score)."""
    return " ".join(f"{k}={v:.3f}" if v is not None else f"{k}=n/a"
                    for k, v in by_horizon.items())
