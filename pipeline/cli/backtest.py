"""`flowcast backtest --from DATE --to DATE --out DIR`: the real-time backtest of the weekly forecast.

``--county NAME|all`` backtests California counties instead of San Francisco's DataSF series:
every county with at least 100,000 people on the latest cached CDPH vintage is forecast (the
pooled members learn from all of them); ``all`` reports every one of them, a name that county
(the panel still pools the others). It writes ``summary.json`` (geometric-mean relative WIS per
target × horizon, share of counties beating the baseline, coverage, per-county ratios),
``scores.csv`` and ``weights.csv`` (:mod:`pipeline.backtest.writers`).

For every weekly origin in the range it writes the hub-format forecast a user would have published
that day (``forecasts/<origin>-published.csv``), plus ``scores.csv`` (WIS and its parts, 50 %/90 %
coverage and PIT per forecaster × target × horizon × origin) and ``summary.json`` (relative WIS
vs the hub baseline and coverage per target × horizon). See
:mod:`pipeline.backtest.backtest`.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from pipeline.cli import app
from pipeline.cli.output_paths import output_dir
from pipeline.cli.choices import DataSource, value
from pipeline.errors import ConfigError, FlowcastError

if TYPE_CHECKING:
    from pipeline.backtest.track_record import TrackRecordConfig
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
    from pipeline.backtest.track_record import track_record
    from pipeline.backtest.writers import write_backtest
    from pipeline.forecast.sources import SF_COUNTY, load_sf_history, reference_panel
    from pipeline.progress import rich_progress
    from pipeline.training.model_store import default_store_root

    try:
        output_dir(out)
        history = load_sf_history(fc.DataSourceConfig(
            kind=_source_kind(source), import_paths=tuple(str(p) for p in import_from or [])))
        record = _without_flows(fc.resolve_config("default", seed=seed).track_record_config(),
                                nf)
        panel = reference_panel(SF_COUNTY, history)
        with rich_progress("backtest") as progress:
            made = track_record(panel, SF_COUNTY, record, default_store_root(), progress,
                                scored_only=not all_origins, first=_date(first, "--from"),
                                last=_date(last, "--to"))
        written = write_backtest(made.result, out)
    except FlowcastError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from None
    summary = made.summary()
    _print_summary(summary, "relative_wis_vs_baseline")
    typer.echo(f"{summary['n_origins']} origins, invalid values {summary['invalid_values']}; "
               f"{len(written)} files under {out}")


def _without_flows(record: TrackRecordConfig, nf: bool) -> TrackRecordConfig:
    """The published members, without the flow members with ``--no-nf``."""
    return dataclasses.replace(record, members=dataclasses.replace(record.members,
                                                                   include_nf=nf))


def _county_backtest(county: str, out: Path, nf: bool, seed: int) -> None:
    """``--county``: the cross-county backtest on the latest cached CDPH vintage."""
    from pipeline.backtest.writers import write_backtest
    from pipeline.data.california.cdph_source import load_cdph_vintage
    from pipeline.forecast import resolve_config
    from pipeline.forecast.county_skill import county_backtest
    from pipeline.panels.california import select_counties
    from pipeline.progress import rich_progress
    from pipeline.training.model_store import default_store_root

    try:
        output_dir(out)
        vintage = load_cdph_vintage(offline=True)
        pool = select_counties(vintage)
        chosen = pool if county.lower() == "all" else select_counties(vintage, counties=[county])
        config = resolve_config("default", seed=seed)
        config = dataclasses.replace(config, track_record=_without_flows(config.track_record, nf))
        with rich_progress("cross-county backtest") as progress:
            result, _ = county_backtest(vintage, config, default_store_root(),
                                        counties=sorted({*pool, *chosen}), progress=progress)
        result = result.for_places(chosen)
        written = write_backtest(result, out, {"vintage": str(vintage.as_of.date()),
                                               "pooled_places": len({*pool, *chosen})})
    except FlowcastError as exc:
        typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from None
    summary = result.summary()
    _print_summary(summary, "gmean_relative_wis")
    typer.echo(f"{len(chosen)} of {len({*pool, *chosen})} counties, {summary['n_origins']} "
               f"origins, vintage {vintage.as_of.date()}; {len(written)} files under {out}")


def _print_summary(summary: dict[str, Any], key: str) -> None:
    """One line per target × forecaster: relative WIS by horizon, share beating the baseline
    (panels), coverage."""
    for target, by_forecaster in summary["by_target"].items():
        for name, s in by_forecaster.items():
            beat = (f"  beat {s['share_beating_baseline']['all']:.2f}"
                    if summary["n_places"] > 1 else "")
            typer.echo(f"{target:5s} {name:22s} relative WIS {_horizon_cells(s[key])}{beat}  "
                       f"coverage {s['coverage50']:.2f}/{s['coverage90']:.2f}")


def _horizon_cells(by_horizon: dict[str, float | None]) -> str:
    """``h1=0.812 h2=… all=…`` (``n/a`` where a horizon has no score)."""
    return " ".join(f"{k}={v:.3f}" if v is not None else f"{k}=n/a"
                    for k, v in by_horizon.items())
