"""Step 1: the forecast's series — San Francisco from DataSF, or a California county from CDPH
(each live with cache fallback, cache only, or imported exports) — every day up to the last one
in the data (the run nowcasts the days still being reported:
:mod:`pipeline.forecast.nowcasting`), and its S/I/R proportions on the place's own population."""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import requests

from pipeline.data.core.cache import utc_now
from pipeline.data.california.counties import SAN_FRANCISCO
from pipeline.data.california.cdph import CountySeries, find_vintage_files
from pipeline.data.california.chhs import CHHSClientConfig
from pipeline.data.sf.csv_import import ImportSummary, detect_dataset, import_csv_exports
from pipeline.data.sf.datasf import ClientConfig
from pipeline.data.sf.payloads import read_csv_bytes
from pipeline.data.sf.series import (DatasetProvenance, DataVintage, SeriesProvenance,
                                     SFDataConfig, SFSeries, load_sf_series, require_sf_cached,
                                     trim_trailing_days)
from pipeline.data.sf.sir_transform import SIRConversionConfig, SIRSeries, to_sir
from pipeline.data.california.cdph_source import (CDPHConfig, CDPHProvenance,
                                                  import_cdph_exports, load_cdph,
                                                  load_cdph_vintage, require_cdph_cached)
from pipeline.panels.california import place_panel, test_positivity
from pipeline.panels.history import (EpiHistory, History, history_from_county,
                                     history_from_frames)
from pipeline.panels.panel import Panel
from pipeline.errors import ConfigError, FlowcastError, OfflineError
from pipeline.forecast.config import DataSourceConfig, DataSourceKind
from pipeline.forecast.results import SIRArrays
from pipeline.names import COMPARTMENTS

log = logging.getLogger(__name__)
SF_COUNTY = SAN_FRANCISCO
REFERENCE_MIN_POPULATION = 100_000


def import_exports(paths: Sequence[str], *, if_empty: bool = False,
                   folder: Path | None = None) -> list[ImportSummary]:
    """``flowcast data import`` as a function: validate and cache DataSF CSV exports (into the
    data ``folder``; None: $FLOWCAST_DATA_DIR or ./data)."""
    return import_csv_exports(_expand_import_paths(paths), folder, if_empty=if_empty)


def _expand_import_paths(paths: Sequence[str]) -> list[Path]:
    """Files as given; a directory contributes its cases/deaths/tests exports (by column match)."""
    out: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if path.is_file():
            out.append(path)
        elif path.is_dir():
            out.extend(_exports_in(path))
        else:
            raise ConfigError(f"import path {path} does not exist")
    if not out:
        raise ConfigError(f"no DataSF CSV exports found in {list(paths)}")
    return out


def _exports_in(folder: Path) -> list[Path]:
    found: dict[str, Path] = {}
    for candidate in sorted(folder.rglob("*.csv")):
        try:
            head = read_csv_bytes(candidate.read_bytes()[:4096].rsplit(b"\n", 1)[0],
                                  source=str(candidate))
            key = detect_dataset(list(head.columns), source=str(candidate)).key
        except (FlowcastError, ValueError, UnicodeDecodeError):  # not an export we know: skip
            continue
        found.setdefault(key, candidate)
    return list(found.values())


def load_series(source: DataSourceConfig, *,
                session: requests.Session | None = None) -> SFSeries:
    """The forecast's series per ``source`` (San Francisco from DataSF, or ``source.county``
    from CDPH); see :class:`DataSourceConfig`."""
    if source.county is not None:
        return load_county_series(source, session=session)
    client = ClientConfig(max_retries=source.http_retries, backoff_base_s=source.http_backoff_s,
                          fetch_deadline_s=source.fetch_deadline_s)
    if source.base_url:
        client = dataclasses.replace(client, base_url=source.base_url)
    data_config = SFDataConfig(trailing_days=source.trailing_days, client=client,
                               data_dir=source.folder)
    if source.kind == "import":
        summaries = import_exports(source.import_paths, folder=source.folder)
        log.info("imported %s", ", ".join(f"{s.dataset_key} ({s.row_count} rows)"
                                          for s in summaries))
    try:
        return load_sf_series(data_config, offline=source.kind != "live", session=session)
    except OfflineError as exc:
        raise no_usable_data(exc, source) from exc


def no_usable_data(error: OfflineError, source: DataSourceConfig) -> OfflineError:
    """The run's error when the cache holds nothing to forecast from: what, and the fix."""
    if source.county is None:
        return OfflineError(f"{error} No usable DataSF data, so no forecast was made; the last "
                            "good report is unchanged. Import the exports with `flowcast data "
                            "import FILE...` (or run with data source 'import').")
    return OfflineError(f"{error} No usable CDPH data, so no forecast for {source.county} was "
                        "made; the last good report is unchanged.")


def require_offline_data(source: DataSourceConfig) -> None:
    """A cache-only run (``source.kind`` "cache"): the error it would end in when the cache
    holds nothing to forecast from, raised before any work (the flow would meet it only after
    starting Prefect and its tasks)."""
    if source.kind != "cache":
        return
    try:
        if source.county is None:
            require_sf_cached(SFDataConfig(data_dir=source.folder))
        else:
            require_cdph_cached(CDPHConfig(data_dir=source.folder))
    except OfflineError as exc:
        raise no_usable_data(exc, source) from exc


def load_county_series(source: DataSourceConfig, *,
                       session: requests.Session | None = None) -> SFSeries:
    """``source.county`` from CDPH's county file (live from the CHHS portal with cache
    fallback, cache only, or imported downloads first), as the series the run reads: episode-date
    cases and deaths on CDPH's population for the county, its vintage's last day as its "data
    as of" (the nowcast's lags count from it)."""
    if source.county is None:
        raise ConfigError("a county series needs DataSourceConfig.county")
    if source.kind == "import":
        summaries = import_cdph_exports(_cdph_files(source.import_paths), source.folder)
        log.info("imported %s", ", ".join(f"{s.path.name} ({s.action}, CDPH vintage of "
                                          f"{s.as_of})" for s in summaries))
    client = CHHSClientConfig(max_retries=source.http_retries,
                              backoff_base_s=source.http_backoff_s,
                              fetch_deadline_s=source.fetch_deadline_s)
    try:
        loaded = load_cdph(CDPHConfig(client=client, data_dir=source.folder),
                           offline=source.kind != "live",
                           session=session)
    except OfflineError as exc:
        raise no_usable_data(exc, source) from exc
    return county_series(loaded.vintage.county(source.county), loaded.provenance,
                         trailing_days=source.trailing_days)


def _cdph_files(paths: Sequence[str]) -> list[Path]:
    """Files as given; a directory contributes every ``covid19cases_test.csv`` under it."""
    files = [f for p in map(Path, paths)
             for f in (find_vintage_files(p) if p.is_dir() else [p])]
    if not files:
        raise ConfigError(f"no CDPH covid19cases_test.csv files found in {list(paths)}")
    return files


def county_series(county: CountySeries, provenance: CDPHProvenance, *,
                  trailing_days: int = 0) -> SFSeries:
    """A CDPH county's cases (by episode date) and deaths as the run's daily series, less its
    last ``trailing_days`` days."""
    cases, deaths = county.cases.astype(np.int64), county.deaths.astype(np.int64)
    frame = trim_trailing_days(pd.DataFrame({
        "date": county.dates.astype("datetime64[us]"), "new_cases": cases,
        "cumulative_cases": np.cumsum(cases), "new_deaths": deaths,
        "cumulative_deaths": np.cumsum(deaths)}), trailing_days)
    vintage = DataVintage(
        data_as_of=provenance.last_date[:10], loaded_at=utc_now().isoformat(timespec="seconds"),
        first_date=str(frame["date"].iloc[0].date()),
        last_date_kept=str(frame["date"].iloc[-1].date()), trimmed_days=trailing_days,
        publisher="CDPH")
    # CDPH's provenance has the DataSF one's fields but its "data as of" stamp
    dataset = DatasetProvenance(**dataclasses.asdict(provenance),
                                data_as_of=provenance.last_date[:10])
    return SFSeries(frame, SeriesProvenance(vintage, (dataset,)), place=county.area,
                    population=county.population)


def data_is_stale(series: SFSeries, source: DataSourceKind) -> bool:
    """True when a live fetch was asked for but the cache had to be used."""
    return source == "live" and any(p.from_cache for p in series.provenance.datasets)


def staleness_notes(series: SFSeries) -> list[str]:
    return [f"{p.dataset_key}: {note}" for p in series.provenance.datasets for note in p.notes]


def series_to_sir(series: SFSeries) -> SIRSeries:
    """S, I, R proportions with the default conversion (see :mod:`pipeline.data.sf.sir_transform`)
    on the place's own population."""
    return to_sir(series, SIRConversionConfig(population=series.population))


def sir_arrays(sir_frame: pd.DataFrame) -> SIRArrays:
    dates = pd.DatetimeIndex(pd.to_datetime(sir_frame["date"]))
    times = ((dates - dates[0]) / pd.Timedelta(days=1)).to_numpy(dtype=np.float64, copy=True)
    values = sir_frame[list(COMPARTMENTS)].to_numpy(dtype=np.float64, copy=True)  # writable
    return SIRArrays(times=times, values=values, dates=dates)


def sf_history(series: SFSeries, sir: SIRSeries) -> EpiHistory:
    """The weekly forecast's :class:`EpiHistory`: the daily counts the S/I/R conversion used
    (ascertainment-adjusted, rounded, when it was on: ``sir.counts.multiplier``)."""
    raw = series.frame["new_cases"].to_numpy(dtype=np.float64)
    multiplier = sir.counts["multiplier"].to_numpy(dtype=np.float64)
    cases = np.rint(raw * multiplier).astype(np.int64)
    return history_from_frames(sir.frame, cases, int(sir.provenance.conversion.population))


SETTLED_DAYS = 14


@dataclass(frozen=True)
class ReferencePlaces:
    """The counties the pooled members learn from (by name), and those the validation gate
    left out of the vintage, with why."""

    histories: dict[str, EpiHistory]
    skipped: dict[str, str]
    signal: Panel | None = None     # their test positivity (pipeline.panels.california)


def load_reference_places(min_population: int = REFERENCE_MIN_POPULATION,
                          drop_days: int = SETTLED_DAYS, *,
                          folder: Path | None = None) -> ReferencePlaces:
    """California's counties with at least ``min_population`` people, by name, from the latest
    cached CDPH vintage without its last ``drop_days`` days, still being reported (the
    cross-county backtest cuts the same days): the places the published forecast's pooled
    members learn from. Empty, with a warning, when the cache holds no CDPH data (the members
    then learn from the forecast's own series alone). A county the gate skipped is left out and
    named (the run's log and report say so). ``folder``: the data folder (None:
    $FLOWCAST_DATA_DIR or ./data)."""
    try:
        vintage = load_cdph_vintage(CDPHConfig(data_dir=folder), offline=True)
    except OfflineError as exc:
        log.warning("no CDPH county data in the cache (%s): the pooled members learn from the "
                    "San Francisco series alone; `flowcast data import` the CDPH files", exc)
        return ReferencePlaces({}, {})
    last = vintage.as_of - pd.Timedelta(days=drop_days)
    if vintage.skipped:  # failed the gate or held for review: not in vintage.counties
        log.warning("the pooled members leave out %d county(ies) (each with why): %s",
                    len(vintage.skipped), "; ".join(vintage.skipped.values()))
    counties = vintage.counties_with_population(min_population)
    return ReferencePlaces({c: history_from_county(vintage.county(c)).up_to(last)
                            for c in counties},
                           dict(vintage.skipped), test_positivity(vintage, counties, last))


def reference_panel(place: str, history: History, folder: Path | None = None) -> Panel:
    """``place``'s series pooled with :func:`load_reference_places`' counties, their test
    positivity its panel's other signal (:func:`~pipeline.panels.california.place_panel`)."""
    references = load_reference_places(folder=folder)
    return place_panel(place, history, references.histories, references.skipped,
                       references.signal)


def load_reference_histories(min_population: int = REFERENCE_MIN_POPULATION,
                             drop_days: int = SETTLED_DAYS) -> dict[str, EpiHistory]:
    """:func:`load_reference_places`' histories."""
    return load_reference_places(min_population, drop_days).histories


def load_sf_history(source: DataSourceConfig, drop_days: int = SETTLED_DAYS) -> EpiHistory:
    """The SF history of the real-time backtest, from ``source`` (live, cache or import): it
    scores forecasts against this vintage, whose last ``drop_days`` are still being reported,
    so they are dropped (the weekly run nowcasts them instead)."""
    series = load_series(dataclasses.replace(source, trailing_days=max(source.trailing_days,
                                                                       drop_days)))
    return sf_history(series, series_to_sir(series))
