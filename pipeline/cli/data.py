"""`flowcast data …`: import DataSF and CDPH exports, fetch live, show the cache, list California
counties, convert to S/I/R, plot."""
from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import typer

from pipeline.cli import app
from pipeline.cli.output_paths import output_dir, output_file
from pipeline.data.datasf import SF_POPULATION_2020_CENSUS
from pipeline.errors import FlowcastError

if TYPE_CHECKING:
    from datetime import datetime

    from pipeline.data.cache import DatasetCache
    from pipeline.data.series import SFDataConfig
    from pipeline.data.sir_transform import SIRConversionConfig

data_app = typer.Typer(no_args_is_help=True,
                       help="COVID-19 data: San Francisco from DataSF, California counties from "
                            "CDPH (data.chhs.ca.gov).")
app.add_typer(data_app, name="data")

TrailingDays = typer.Option(14, "--trailing-days", min=0,
                            help="Days dropped at the end of each dataset (DataSF revises them).")
Offline = typer.Option(False, "--offline", help="Use the cache only; never contact DataSF.")


def _fail(exc: Exception) -> NoReturn:
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(code=1)


def _config(trailing_days: int, *, base_url: str | None = None, app_token: str | None = None,
            accept_revisions: bool = False, offline: bool = False) -> SFDataConfig:
    from pipeline.data.datasf import DEFAULT_BASE_URL, ClientConfig
    from pipeline.data.series import SFDataConfig
    if offline:
        # Never contacted: a bad $FLOWCAST_DATASF_BASE_URL must not stop a cache-only command.
        base_url = base_url or DEFAULT_BASE_URL
    client = ClientConfig(base_url=base_url) if base_url else ClientConfig()
    if app_token:
        client = replace(client, app_token=app_token)
    return SFDataConfig(trailing_days=trailing_days, client=client,
                        accept_revisions=accept_revisions)


AcceptRevisions = typer.Option(
    False, "--accept-revisions",
    help="Take a payload even if it ends earlier, is an older vintage or revises settled days "
         "beyond the revision policy (docs/data.md); for a payload you have reviewed.")


@data_app.command("import")
def import_command(
    files: list[Path] = typer.Argument(..., exists=True, dir_okay=False,
                                       help="DataSF CSV exports (rows.csv?accessType=DOWNLOAD) "
                                            "and/or CDPH covid19cases_test.csv downloads "
                                            "(told apart by their columns)."),
    if_empty: bool = typer.Option(False, "--if-empty",
                                  help="Import only datasets the cache does not hold yet or "
                                       "holds damaged (those are repaired)."),
    accept_revisions: bool = AcceptRevisions,
) -> None:
    """Validate DataSF CSV exports and CDPH county files and put them into the cache
    ($FLOWCAST_DATA_DIR or ./data). CDPH files are vintages: each is kept, the newest is live."""
    from pipeline.data.cache import data_dir
    from pipeline.data.cdph_source import (is_cdph_export, peek_columns, store_cdph_exports,
                                           validate_cdph_exports)
    from pipeline.data.csv_import import import_csv_exports
    cdph = [f for f in files if is_cdph_export(peek_columns(f))]
    datasf = [f for f in files if f not in cdph]
    try:
        checked = validate_cdph_exports(cdph)  # every file is checked before any is stored
        summaries = import_csv_exports(datasf, if_empty=if_empty,
                                       accept_revisions=accept_revisions) if datasf else []
        cdph_summaries = store_cdph_exports(checked, if_empty=if_empty,
                                            accept_revisions=accept_revisions)
    except FlowcastError as exc:
        _fail(exc)
    for c in cdph_summaries:
        typer.echo(f"{c.action} {c.path.name}: CDPH counties vintage of {c.as_of}, "
                   f"{c.first_date} … {c.as_of}, {c.counties} counties, {c.row_count} rows"
                   + (f" — {c.note}" if c.note else ""))
    for s in summaries:
        total = f"{s.final_cumulative:,}" if s.final_cumulative is not None else "n/a"
        action = "imported" if s.imported else "skipped"
        typer.echo(f"{action} {s.path.name}: {s.dataset_key} ({s.dataset_id}), "
                   f"{s.first_date} … {s.last_date}, {s.row_count} rows, "
                   f"final cumulative {total}, data as of {s.data_as_of or 'unknown'}"
                   + (f" — {s.note}" if s.note else ""))
        for warning in s.warnings:
            typer.echo(f"  warning: {warning}")
    for folder, used in (("datasf", datasf), ("chhs", cdph)):
        if used:
            typer.echo(f"cache: {data_dir().resolve() / folder}")


@data_app.command("fetch")
def fetch_command(
    trailing_days: int = TrailingDays,
    base_url: str | None = typer.Option(
        None, "--base-url", envvar="FLOWCAST_DATASF_BASE_URL", metavar="URL",
        help="DataSF or a mirror/proxy of it (default https://data.sfgov.org)."),
    app_token: str | None = typer.Option(
        None, "--app-token", envvar="FLOWCAST_DATASF_APP_TOKEN", metavar="TOKEN",
        show_envvar=True, show_default=False,
        help="Socrata app token (sent as X-App-Token, only to the base URL's https host). "
             "Prefer the environment variable: a command line is visible to other users."),
    accept_revisions: bool = AcceptRevisions,
    source: str = typer.Option("datasf", "--source", metavar="datasf|chhs",
                               help="datasf: San Francisco (cases, deaths, tests); chhs: CDPH's "
                                    "California county file from data.chhs.ca.gov."),
    chhs_base_url: str | None = typer.Option(
        None, "--chhs-base-url", metavar="URL",
        help="The CHHS portal or a mirror of it (default $FLOWCAST_CHHS_BASE_URL, else "
             "https://data.chhs.ca.gov); --source chhs only."),
) -> None:
    """Fetch cases, deaths and tests from DataSF, or (--source chhs) the CDPH county file
    (falls back to the cache when offline)."""
    if source not in ("datasf", "chhs"):
        _fail(ValueError(f"--source must be datasf or chhs, got {source!r}"))
    if source == "chhs":
        _fetch_chhs(chhs_base_url, accept_revisions)
        return
    from pipeline.data.series import load_sf_series
    try:
        series = load_sf_series(_config(trailing_days, base_url=base_url, app_token=app_token,
                                        accept_revisions=accept_revisions))
    except FlowcastError as exc:
        _fail(exc)
    for p in series.provenance.datasets:
        where = f"cache (fetched {p.stale_days:.0f} days ago)" if p.from_cache else "DataSF"
        typer.echo(f"{p.dataset_key} ({p.dataset_id}) from {where}: {p.row_count} rows, "
                   f"{p.first_date} … {p.last_date}, data as of {p.data_as_of}")
        for note in p.notes:
            typer.echo(f"  note: {note}")
    typer.echo(series.vintage.describe())


def _fetch_chhs(base_url: str | None, accept_revisions: bool) -> None:
    from pipeline.data.cdph_source import CDPHConfig, load_cdph
    from pipeline.data.chhs import CHHSClientConfig
    try:
        loaded = load_cdph(CDPHConfig(client=CHHSClientConfig(base_url=base_url),
                                      accept_revisions=accept_revisions))
    except FlowcastError as exc:
        _fail(exc)
    p, v = loaded.provenance, loaded.vintage
    where = f"cache (fetched {p.stale_days:.0f} days ago)" if p.from_cache else "CHHS portal"
    typer.echo(f"{p.dataset_key} ({p.dataset_id}) from {where}: vintage of {v.as_of.date()}, "
               f"{len(v.counties)} counties, {p.first_date} … {p.last_date}, {p.row_count} rows")
    for note in p.notes:
        typer.echo(f"  note: {note}")


@data_app.command("status")
def status_command() -> None:
    """What the cache holds and how old it is."""
    from pipeline.data.cache import DatasetCache, utc_now
    from pipeline.data.datasf import DATASETS
    cache = DatasetCache.default()
    typer.echo(f"cache: {cache.root.resolve() / 'datasf'}")
    now = utc_now()
    for spec in DATASETS.values():
        try:
            manifest = cache.read_manifest(spec)
        except FlowcastError as exc:
            typer.echo(f"{spec.key} ({spec.dataset_id}): {exc}")
            continue
        if manifest is None:
            typer.echo(f"{spec.key} ({spec.dataset_id}): not cached — `flowcast data fetch` or "
                       f"`flowcast data import FILE`")
            continue
        typer.echo(f"{spec.key} ({spec.dataset_id}): {manifest.source_kind} {manifest.source}"
                   + (f" (answered by {manifest.final_url})"
                      if manifest.final_url and manifest.final_url != manifest.source else "")
                   + f"; {manifest.row_count} rows {manifest.first_date} … {manifest.last_date}; "
                   f"data as of {manifest.data_as_of}; fetched {manifest.fetched_at} "
                   f"({manifest.age_days(now):.1f} days ago)")
        held = sorted((cache.directory(spec) / "held").glob("payload-*.reason.json"))
        if held:
            typer.echo(f"  {len(held)} payload(s) held for review in "
                       f"{cache.directory(spec) / 'held'}")
    _status_chhs(cache, now)


def _status_chhs(cache: DatasetCache, now: datetime) -> None:
    from pipeline.data.cdph_source import SPEC, vintages_dir
    label = f"{SPEC.key} ({SPEC.dataset_id})"
    typer.echo(f"cache: {cache.root.resolve() / SPEC.cache_folder}")
    try:
        manifest = cache.read_manifest(SPEC)
    except FlowcastError as exc:
        typer.echo(f"{label}: {exc}")
        return
    if manifest is None:
        typer.echo(f"{label}: not cached — `flowcast data fetch --source chhs` or "
                   f"`flowcast data import covid19cases_test.csv`")
        return
    vintages = sorted(p.name[:10] for p in vintages_dir(cache).glob("*.csv"))
    typer.echo(f"{label}: {manifest.source_kind} {manifest.source}"
               + (f" (answered by {manifest.final_url})" if manifest.final_url else "")
               + f"; vintage of {manifest.last_date}, {manifest.row_count} county-day rows "
               f"{manifest.first_date} … {manifest.last_date}; fetched {manifest.fetched_at} "
               f"({manifest.age_days(now):.1f} days ago); {len(vintages)} vintage(s) kept"
               + (f" ({vintages[0]} … {vintages[-1]})" if vintages else ""))
    held = sorted((cache.directory(SPEC) / "held").glob("payload-*.reason.json"))
    if held:
        typer.echo(f"  {len(held)} payload(s) held for review in "
                   f"{cache.directory(SPEC) / 'held'}")


@data_app.command("counties")
def counties_command(
    min_population: int = typer.Option(0, "--min-population", min=0,
                                       help="Only counties with at least this many people."),
) -> None:
    """The California counties of the cached CDPH vintage, with CDPH's population (no network)."""
    from pipeline.data.cdph_source import load_cdph
    try:
        loaded = load_cdph(offline=True)
    except FlowcastError as exc:
        _fail(exc)
    vintage = loaded.vintage
    populations = vintage.populations()
    shown = [(a, p) for a, p in populations.items() if p >= min_population]
    typer.echo(f"CDPH vintage of {vintage.as_of.date()} ({loaded.provenance.source}): "
               f"{len(shown)} of {len(populations)} counties"
               + (f" with at least {min_population:,} people" if min_population else ""))
    for area, population in shown:
        typer.echo(f"{area:<20} {population:>12,}")


def _sir_config(population: int, infectious_days: int,
                ascertainment: bool) -> SIRConversionConfig:
    from pipeline.data.sir_transform import AscertainmentConfig, SIRConversionConfig
    return SIRConversionConfig(population=population, infectious_period_days=infectious_days,
                               ascertainment=AscertainmentConfig() if ascertainment else None)


Population = typer.Option(SF_POPULATION_2020_CENSUS, "--population", min=1, help="Population N (2020 Census).")
InfectiousDays = typer.Option(10, "--infectious-days", min=1, help="Infectious period L (days).")
Ascertainment = typer.Option(False, "--ascertainment/--no-ascertainment",
                             help="Correct cases for under-ascertainment from test positivity.")


@data_app.command("sir")
def sir_command(out: Path = typer.Option(..., "--out", help="CSV to write (date,S,I,R)."),
                trailing_days: int = TrailingDays, offline: bool = Offline,
                population: int = Population, infectious_days: int = InfectiousDays,
                ascertainment: bool = Ascertainment) -> None:
    """Write the S/I/R proportions of San Francisco, plus <out>.provenance.json (vintage)."""
    from pipeline.data.series import load_sf_series
    from pipeline.data.sir_transform import to_sir
    from pipeline.io import atomic_write_json, atomic_write_text
    try:
        output_file(out, example="sf_sir.csv")
        sir = to_sir(load_sf_series(_config(trailing_days, offline=offline), offline=offline),
                     _sir_config(population, infectious_days, ascertainment))
    except FlowcastError as exc:
        _fail(exc)
    frame = sir.frame.assign(date=sir.frame["date"].dt.strftime("%Y-%m-%d"))
    atomic_write_text(out, frame.to_csv(index=False))
    atomic_write_json(out.with_name(out.name + ".provenance.json"), sir.provenance.to_dict())
    typer.echo(f"wrote {out} ({len(frame)} days); {sir.provenance.series.vintage.describe()}")


@data_app.command("plot")
def plot_command(out: Path = typer.Option(Path("figures"), "--out", help="Output directory."),
                 trailing_days: int = TrailingDays, offline: bool = Offline,
                 population: int = Population, infectious_days: int = InfectiousDays,
                 ascertainment: bool = Ascertainment,
                 n_trajectories: int = typer.Option(500, "--n-trajectories", min=10),
                 i0: float = typer.Option(0.01, "--i0", min=1e-9, max=0.5,
                                          help="Prior initial infected share (S0 = 1 - I0); "
                                               "sir-multi uses 0.01."),
                 seed: int = typer.Option(0, "--seed")) -> None:
    """Figures: the SF S/I/R series, and SF beside the sir-multi prior (+ measured overlap)."""
    from pipeline.data.plots import (PriorEnsembleConfig, compare_with_prior, plot_sir_series,
                                     plot_sir_vs_prior)
    from pipeline.data.series import load_sf_series
    from pipeline.data.sir_transform import to_sir
    from pipeline.io import atomic_write_json
    try:
        output_dir(out)
        sir = to_sir(load_sf_series(_config(trailing_days, offline=offline), offline=offline),
                     _sir_config(population, infectious_days, ascertainment))
    except FlowcastError as exc:
        _fail(exc)
    prior = PriorEnsembleConfig(n_trajectories=n_trajectories, seed=seed, i0=i0, s0=1.0 - i0)
    comparison = compare_with_prior(sir, prior)
    paths = [plot_sir_series(sir, out / "sf_sir.png"),
             plot_sir_vs_prior(sir, prior, out / "sf_sir_vs_prior.png", comparison)]
    atomic_write_json(out / "sf_prior_comparison.json",
                      {"comparison": asdict(comparison), "provenance": sir.provenance.to_dict()})
    for path in paths:
        typer.echo(f"wrote {path}")
    inside = comparison.states_aligned.inside
    typer.echo("SF days inside the prior's 1–99 % state band (offset 0): "
               + ", ".join(f"{k} {v:.0%}" for k, v in inside.items()))
    typer.echo(json.dumps({"best_offset": comparison.states_best.offset,
                           "inside_at_best_offset": comparison.states_best.inside}))
