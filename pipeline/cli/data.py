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
from pipeline.data.sf.datasf import SF_POPULATION_2020_CENSUS
from pipeline.errors import ConfigError, FlowcastError

if TYPE_CHECKING:
    from datetime import datetime

    from pipeline.data.core.cache import CacheManifest, CacheSpec, DatasetCache
    from pipeline.data.hub.target_import import HubImportSummary
    from pipeline.data.sf.series import SFDataConfig
    from pipeline.data.sf.sir_transform import SIRConversionConfig

data_app = typer.Typer(no_args_is_help=True,
                       help="COVID-19 data: San Francisco from DataSF, California counties from "
                            "CDPH (data.chhs.ca.gov), hospital admissions and ED visits of the "
                            "US and every state from NHSN/NSSP (data.cdc.gov, or a forecast "
                            "hub's target data).")
app.add_typer(data_app, name="data")

TrailingDays = typer.Option(14, "--trailing-days", min=0,
                            help="Days dropped at the end of each dataset (DataSF revises them).")
Offline = typer.Option(False, "--offline", help="Use the cache only; never contact DataSF.")


def _fail(exc: Exception) -> NoReturn:
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(code=1)


def _config(trailing_days: int, *, base_url: str | None = None, app_token: str | None = None,
            accept_revisions: bool = False, offline: bool = False) -> SFDataConfig:
    from pipeline.data.sf.datasf import DEFAULT_BASE_URL, ClientConfig
    from pipeline.data.sf.series import SFDataConfig
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
    files: list[Path] = typer.Argument(..., exists=True,
                                       help="DataSF CSV exports (rows.csv?accessType=DOWNLOAD), "
                                            "CDPH covid19cases_test.csv downloads, a forecast "
                                            "hub's time-series.parquet or hub folder, or a hub "
                                            "target CSV (with --target and --as-of); told "
                                            "apart by their columns."),
    if_empty: bool = typer.Option(False, "--if-empty",
                                  help="Import only datasets the cache does not hold yet or "
                                       "holds damaged (those are repaired)."),
    accept_revisions: bool = AcceptRevisions,
    target: str | None = typer.Option(None, "--target", metavar="TARGET",
                                      help="The hub target of a plain target CSV, e.g. "
                                           "'wk inc covid hosp'."),
    as_of: str | None = typer.Option(None, "--as-of", metavar="YYYY-MM-DD",
                                     help="The vintage date of a target CSV (or of a time "
                                          "series without an as_of column)."),
) -> None:
    """Validate downloaded data and put it into the cache ($FLOWCAST_DATA_DIR or ./data). CDPH
    files and hub target data are vintages: each is kept, the newest is live."""
    from pipeline.data.core.cache import data_dir
    from pipeline.data.california.cdph_source import (is_cdph_export, peek_columns,
                                                      store_cdph_exports, validate_cdph_exports)
    from pipeline.data.sf.csv_import import import_csv_exports
    from pipeline.data.hub.release import release_date
    from pipeline.data.hub.target_import import is_hub_time_series, is_target_csv
    if as_of is not None:     # a bad date is one named error before any file is read
        try:
            release_date(as_of, where="--as-of")
        except FlowcastError as exc:
            _fail(exc)
    hub = [f for f in files if is_hub_time_series(f)]
    dirs = [f for f in files if f.is_dir() and f not in hub]
    if dirs:
        _fail(ValueError(f"{dirs[0]} is a folder without a hub time-series.parquet (give the "
                         f"files themselves)"))
    targets = [f for f in files if f not in hub and is_target_csv(peek_columns(f))]
    cdph = [f for f in files if f not in hub and is_cdph_export(peek_columns(f))]
    datasf = [f for f in files if f not in (*hub, *targets, *cdph)]
    try:
        checked = validate_cdph_exports(cdph)  # every file is checked before any is stored
        hub_summaries = _import_nhsn(hub, targets, target, as_of, if_empty, accept_revisions)
        summaries = import_csv_exports(datasf, if_empty=if_empty,
                                       accept_revisions=accept_revisions) if datasf else []
        cdph_summaries = store_cdph_exports(checked, if_empty=if_empty,
                                            accept_revisions=accept_revisions)
    except FlowcastError as exc:
        _fail(exc)
    for line in (line for h in hub_summaries for line in h.lines()):
        typer.echo(line)
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
    for folder, used in (("datasf", datasf), ("chhs", cdph), ("nhsn", [*hub, *targets])):
        if used:
            typer.echo(f"cache: {data_dir().resolve() / folder}")


def _import_nhsn(hub: list[Path], targets: list[Path], target: str | None, as_of: str | None,
                 if_empty: bool, accept_revisions: bool) -> list[HubImportSummary]:
    from pipeline.data.hub.target_import import import_hub_time_series, import_target_csv
    if targets and (target is None or as_of is None):
        raise ConfigError(f"{targets[0]} is a hub target CSV: give its target and vintage date "
                          f"(--target 'wk inc covid hosp' --as-of YYYY-MM-DD)")
    done = [import_hub_time_series(f, as_of=as_of, if_empty=if_empty,
                                   accept_revisions=accept_revisions) for f in hub]
    if targets and target is not None and as_of is not None:
        done += [import_target_csv(f, target=target, as_of=as_of,
                                   accept_revisions=accept_revisions) for f in targets]
    return done


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
    source: str = typer.Option("datasf", "--source", metavar="datasf|chhs|nhsn",
                               help="datasf: San Francisco (cases, deaths, tests); chhs: CDPH's "
                                    "California county file from data.chhs.ca.gov; nhsn: weekly "
                                    "hospital admissions (NHSN) and ED-visit shares (NSSP) of "
                                    "the US and every state from data.cdc.gov."),
    disease: str = typer.Option("covid", "--disease", metavar="covid|flu|rsv",
                                help="--source nhsn: which disease's admissions and ED share."),
    release: str = typer.Option("official", "--release", metavar="official|preliminary",
                                help="--source nhsn: NHSN's official (Friday) or preliminary "
                                     "(Wednesday) release."),
    nhsn_base_url: str | None = typer.Option(
        None, "--nhsn-base-url", metavar="URL",
        help="data.cdc.gov or a mirror (default $FLOWCAST_NHSN_BASE_URL, else "
             "https://data.cdc.gov); --source nhsn only."),
    chhs_base_url: str | None = typer.Option(
        None, "--chhs-base-url", metavar="URL",
        help="The CHHS portal or a mirror of it (default $FLOWCAST_CHHS_BASE_URL, else "
             "https://data.chhs.ca.gov); --source chhs only."),
) -> None:
    """Fetch cases, deaths and tests from DataSF, (--source chhs) the CDPH county file, or
    (--source nhsn) NHSN admissions and the NSSP ED share (falls back to the cache when
    offline)."""
    if source not in ("datasf", "chhs", "nhsn"):
        _fail(ValueError(f"--source must be datasf, chhs or nhsn, got {source!r}"))
    if source == "chhs":
        _fetch_chhs(chhs_base_url, accept_revisions)
        return
    if source == "nhsn":
        _fetch_nhsn(disease, release, nhsn_base_url, accept_revisions)
        return
    from pipeline.data.sf.series import load_sf_series
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
    from pipeline.data.california.cdph_source import CDPHConfig, load_cdph
    from pipeline.data.california.chhs import CHHSClientConfig
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


def _fetch_nhsn(disease: str, release: str, base_url: str | None,
                accept_revisions: bool) -> None:
    from pipeline.data.hub.nhsn import NHSNClientConfig, NHSNConfig, load_nhsn
    try:
        loaded = load_nhsn(NHSNConfig(disease=disease, release=release,  # type: ignore[arg-type]
                                      client=NHSNClientConfig(base_url=base_url),
                                      accept_revisions=accept_revisions))
    except FlowcastError as exc:
        _fail(exc)
    for target, p in loaded.provenance.items():
        where = f"cache (fetched {p.stale_days:.0f} days ago)" if p.from_cache else "data.cdc.gov"
        v = loaded[target]
        typer.echo(f"{target} from {where}: vintage of {p.as_of}, {len(v.locations)} locations, "
                   f"weeks {p.first_week} … {p.last_week}")
        for note in p.notes:
            typer.echo(f"  note: {note}")


@data_app.command("status")
def status_command() -> None:
    """What the cache holds and how old it is."""
    from pipeline.data.core.cache import DatasetCache, utc_now
    from pipeline.data.sf.datasf import DATASETS
    cache = DatasetCache.default()
    typer.echo(f"cache: {cache.root.resolve() / 'datasf'}")
    now = utc_now()
    for spec in DATASETS.values():
        readable, manifest = _manifest(cache, spec, f"{spec.key} ({spec.dataset_id})")
        if not readable:
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
    _status_nhsn(cache, now)


def _manifest(cache: DatasetCache, spec: CacheSpec, label: str
              ) -> tuple[bool, CacheManifest | None]:
    """(readable, the manifest or None when nothing is cached); a damaged one is said."""
    try:
        return True, cache.read_manifest(spec)
    except FlowcastError as exc:
        typer.echo(f"{label}: {exc}")
        return False, None


def _status_chhs(cache: DatasetCache, now: datetime) -> None:
    from pipeline.data.california.cdph_source import SPEC, counties_waiting, vintages_dir
    label = f"{SPEC.key} ({SPEC.dataset_id})"
    typer.echo(f"cache: {cache.root.resolve() / SPEC.cache_folder}")
    readable, manifest = _manifest(cache, SPEC, label)
    if not readable:
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
    for county, hold in counties_waiting(cache.root).items():
        typer.echo(f"  {county}: revision waiting since the vintage of {hold.since} "
                   f"(`flowcast data accept-revisions --cdph '{county}'`): {hold.reason}")


def _status_nhsn(cache: DatasetCache, now: datetime) -> None:
    from pipeline.data.hub.nhsn_vintages import (CACHE_FOLDER, TARGETS, held_count,
                                                 revisions_waiting, vintages_folder)
    from pipeline.data.core.vintages import VintageArchive
    typer.echo(f"cache: {cache.root.resolve() / CACHE_FOLDER}")
    if not any(cache.has(spec) for spec in TARGETS.values()):
        typer.echo("NHSN: not cached — `flowcast data fetch --source nhsn` or `flowcast data "
                   "import <hub folder or time-series.parquet>`")
    for target, spec in TARGETS.items():
        readable, manifest = _manifest(cache, spec, target)
        if manifest is None:
            continue
        dates = [str(d) for d, _ in VintageArchive(cache, spec).listing()]
        typer.echo(f"{target}: {manifest.source_kind} {manifest.source}; live vintage of "
                   f"{manifest.data_as_of}, weeks {manifest.first_date} … {manifest.last_date}; "
                   f"fetched {manifest.fetched_at} ({manifest.age_days(now):.1f} days ago); "
                   f"{len(dates)} vintage(s) kept"
                   + (f" ({dates[0]} … {dates[-1]})" if dates else "")
                   + f" in {vintages_folder(target, cache.root)}")
        held = held_count(target, cache.root)
        if held:
            typer.echo(f"  {held} payload(s) held for review in "
                       f"{cache.directory(spec) / 'held'}")
        for location, hold in revisions_waiting(target, cache.root).items():
            what = "missing" if hold.kind == "missing" else "revision waiting"
            typer.echo(f"  {location}: {what} since the release of {hold.since} "
                       f"(`flowcast data accept-revisions --target '{target}' {location}`): "
                       f"{hold.reason}")


@data_app.command("accept-revisions")
def accept_revisions_command(
    locations: list[str] = typer.Argument(..., help="Hub locations (codes such as 22, or "
                                                    "postal abbreviations such as LA), or with "
                                                    "--cdph California counties (Los Angeles), "
                                                    "whose waiting revision you have reviewed."),
    target: str | None = typer.Option(None, "--target", metavar="TARGET",
                                      help="The hub target, e.g. 'wk inc flu hosp'."),
    cdph: bool = typer.Option(False, "--cdph", help="The locations are CDPH counties."),
) -> None:
    """Accept the revised history of these locations alone (held by the revision policy while
    the rest of each release went live): from the live vintage on, they are read again."""
    from pipeline.data.california.cdph_source import accept_county_revisions
    from pipeline.data.hub.nhsn_vintages import accept_location_revisions
    if (target is None) == (not cdph):
        _fail(ConfigError("give either --target TARGET (hub locations) or --cdph (counties)"))
    try:
        ended = (accept_county_revisions(locations) if cdph else
                 accept_location_revisions(str(target), locations))
    except FlowcastError as exc:
        _fail(exc)
    for location, hold in ended.items():
        typer.echo(f"accepted {'CDPH' if cdph else target} {location}: its revision held since "
                   f"the release of {hold.since} is live from the current vintage on")


@data_app.command("counties")
def counties_command(
    min_population: int = typer.Option(0, "--min-population", min=0,
                                       help="Only counties with at least this many people."),
) -> None:
    """The California counties of the cached CDPH vintage, with CDPH's population (no network)."""
    from pipeline.data.california.cdph_source import load_cdph
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
    from pipeline.data.sf.sir_transform import AscertainmentConfig, SIRConversionConfig
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
    from pipeline.data.sf.series import load_sf_series
    from pipeline.data.sf.sir_transform import to_sir
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
    from pipeline.report.data_figures import (PriorEnsembleConfig, compare_with_prior,
                                              plot_sir_series, plot_sir_vs_prior)
    from pipeline.data.sf.series import load_sf_series
    from pipeline.data.sf.sir_transform import to_sir
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
