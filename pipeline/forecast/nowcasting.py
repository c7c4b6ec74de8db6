"""The weekly run's nowcast: the delay model from the CDPH vintages (fitted once per set of
vintages, cached), the nowcast of the series' last days, and the completions the published
forecast is mixed over.

San Francisco's DataSF series has no report-date column and the project holds one DataSF
vintage, so its delays cannot be fitted from DataSF itself. CDPH's episode-date cases for San
Francisco match DataSF's weekly sums (median ratio 0.99), so the CDPH delay model is SF's prior:
SF is nowcast as a *new county* of it (the pooled curve with the between-county spread), with
reports arriving around the data date (the latest era, extrapolated by the random walk). Lags
count from DataSF's own "data as of" stamp when it gives one (DataSF publishes a day only some
days after it: the export of 2022-03-21 ends on 2022-03-16), else from the last day in the data.

A California county forecast from CDPH data (``DataSourceConfig.county``) is one of the delay
model's own places: it is nowcast with its own (partially pooled) county effect when the model
has one, else as a new county, with lags counted from the CDPH vintage's last day.
"""
from __future__ import annotations

import json
import logging
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import pandas as pd

from pipeline.data.core.cache import data_dir
from pipeline.data.california.cdph import CDPHVintage, find_vintage_files
from pipeline.data.california.cdph_source import cached_vintages, validate_cdph_exports
from pipeline.data.california.delays import (DelayModel, DelayModelError, fit_delay_model,
                                             load_delay_model, save_delay_model)
from pipeline.data.sf.series import DataVintage, SFSeries
from pipeline.data.sf.sir_transform import SIRSeries
from pipeline.data.california.vintage_pairs import revision_pairs
from pipeline.nowcast.completions import NowcastConfig, complete_histories, nowcast_history
from pipeline.nowcast.hub_weeks import hub_weeks, last_saturday
from pipeline.nowcast.mixture import RunNowcast, median_history
from pipeline.panels.history import EpiHistory
from pipeline.panels.targets import DAYS_PER_WEEK
from pipeline.forecast.settings import NowcastSettings
from pipeline.forecast.sources import SF_COUNTY, sf_history
from pipeline.io import sha256_bytes

ARCHIVE_ENV = "FLOWCAST_CDPH_ARCHIVE"
MODELS_DIR = "delay-models"

log = logging.getLogger(__name__)


def archive_from_environment() -> tuple[str, ...]:
    """The CDPH archive folders ``$FLOWCAST_CDPH_ARCHIVE`` names (colon-separated): read once,
    at the edge (the flow's config), onto :attr:`NowcastSettings.archive`; the nowcast itself
    reads only its settings."""
    return tuple(p for p in os.environ.get(ARCHIVE_ENV, "").split(os.pathsep) if p)


def delay_vintages(settings: NowcastSettings, folder: Path | None = None) -> list[CDPHVintage]:
    """Every CDPH vintage the cache (in the data ``folder``) holds, plus the validated
    downloads in the archive folders (one per date; the cache's copy first)."""
    chosen: dict[pd.Timestamp, CDPHVintage] = {v.as_of: v for v in cached_vintages(folder)}
    for archive in settings.archive:
        files = find_vintage_files(archive) if Path(archive).is_dir() else []
        for checked in validate_cdph_exports(files):
            chosen.setdefault(checked.vintage.as_of, checked.vintage)
    return [chosen[d] for d in sorted(chosen)]


def _model_key(vintages: Sequence[CDPHVintage], settings: NowcastSettings) -> str:
    identity = {"config": asdict(settings.delay),
                "vintages": [[str(v.as_of.date()), len(v.frame), int(v.frame["cases"].sum())]
                             for v in vintages]}
    return sha256_bytes(json.dumps(identity, sort_keys=True, default=str).encode())[:16]


def delay_model_for_run(settings: NowcastSettings, folder: Path | None = None
                        ) -> DelayModel | None:
    """The delay model of the CDPH vintages at hand (fitted once per set, then read from
    ``<data dir>/delay-models/``); None with fewer than two vintages."""
    vintages = delay_vintages(settings, folder)
    if len(vintages) < 2:
        log.warning("nowcast: %d CDPH vintage(s) in the cache and archive, two are needed for "
                    "the delay model; import CDPH downloads with `flowcast data import` or set "
                    "%s", len(vintages), ARCHIVE_ENV)
        return None
    path = data_dir(folder) / MODELS_DIR / f"delay-{_model_key(vintages, settings)}.npz"
    if path.is_file():
        try:
            return load_delay_model(path, settings.delay)
        except DelayModelError as exc:
            log.warning("refitting the delay model: %s", exc)
    pairs = revision_pairs(vintages, max_lag=settings.delay.max_lag, consecutive=True)
    model = fit_delay_model(pairs, settings.delay,
                            sources=tuple(str(v.as_of.date()) for v in vintages))
    save_delay_model(model, path)
    return model


def data_date(vintage: DataVintage, history: EpiHistory) -> pd.Timestamp:
    """When the data were published: DataSF's "data as of" day, else the last day in them."""
    if vintage.data_as_of:
        stamp = pd.Timestamp(vintage.data_as_of[:10])
        if stamp >= history.origin:
            return stamp
    return history.origin


def run_nowcast(history: EpiHistory, vintage: DataVintage, settings: NowcastSettings,
                seed: int, county: str | None = None, folder: Path | None = None
                ) -> tuple[EpiHistory, RunNowcast | None]:
    """(the history the weekly step forecasts from, the nowcast): with a delay model, every day
    with its last ones nowcast (the history is their per-day median; the completions are in
    the nowcast); without one, the history less ``fallback_trailing_days``. ``county``: the
    CDPH county the history is (None: San Francisco from DataSF, a new county to the model);
    ``folder``: the data folder (its CDPH vintages and delay models)."""
    model = delay_model_for_run(settings, folder) if settings.enabled else None
    if model is None:
        cut = history.origin - pd.Timedelta(days=settings.fallback_trailing_days)
        return history.up_to(cut), None
    published = data_date(vintage, history)
    nowcast = nowcast_history(history, model, as_of=published, county=county,
                              config=NowcastConfig(n_completions=settings.nowcast_samples),
                              seed=seed)
    completed = complete_histories(history, nowcast)
    weeks = hub_weeks(history.origin)
    note = (f"CDPH delay model of {len(model.sources)} vintages "
            f"({', '.join(model.sources)}), {_delay_place(model, county)}; lags from "
            f"{published.date()}")
    median = median_history(history, nowcast)
    return median, RunNowcast(nowcast, completed, median, weeks, note)


def _delay_place(model: DelayModel, county: str | None) -> str:
    if county is not None and county in model.counties:
        return f"{county} with its own county effect"
    return f"{county or SF_COUNTY} as a new county"


@dataclass(frozen=True, eq=False)
class RecentDays:
    """Step ``nowcast-recent-days``: the history the weekly step forecasts from, the S/I/R
    frame the joint models read (recent days at the nowcast's per-day median), the nowcast
    (None: no delay model, ``fallback_trailing_days`` dropped instead)."""

    history: EpiHistory
    sir_frame: pd.DataFrame
    nowcast: RunNowcast | None


def nowcast_recent_days(series: SFSeries, sir: SIRSeries, settings: NowcastSettings,
                        seed: int, county: str | None = None, folder: Path | None = None
                        ) -> RecentDays:
    """The series' last days nowcast (:func:`run_nowcast`; ``county``: the CDPH county it is,
    None for San Francisco from DataSF), as the run's later steps use it."""
    history, nowcast = run_nowcast(sf_history(series, sir), series.vintage, settings, seed,
                                   county, folder)
    frame = sir.frame.iloc[:len(history)].copy()
    for name in ("S", "I", "R"):
        frame[name] = getattr(history, name)
    return RecentDays(history, frame, nowcast)


def mixture_start(nowcast: RunNowcast, weeks: int) -> pd.Timestamp:
    """The first origin whose forecast is mixed over the completions."""
    return last_saturday(nowcast.weeks.data_date) - pd.Timedelta(days=DAYS_PER_WEEK * (weeks - 1))
