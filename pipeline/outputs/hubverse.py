"""The hubverse submission of the published weekly forecast (no Prefect, no torch).

For a hub of California's counties whose config is ``hub-config/`` (the 2024+ COVID-19 Forecast
Hub conventions; ``location`` is the county's FIPS code, San Francisco ``06075`` by default,
:mod:`pipeline.data.california.counties`):
``model-output/<team>-<model>/<reference_date>-<team>-<model>.csv`` with the columns
``reference_date, target, horizon, location, target_end_date, output_type, output_type_id,
value``, validated by
:func:`~pipeline.outputs.hubverse_validation.validate_model_output` against ``hub-config/tasks.json``.

* ``reference_date``: the Saturday ending the CDC epiweek (Sunday–Saturday, ``epiweeks``) of the
  run's date; ``target_end_date = reference_date + 7·horizon`` days, a Saturday; ``horizon`` in
  -1..3 (-1 is the week just past, a nowcast).
* ``wk inc case``: reported cases in the epiweek ending on ``target_end_date``; ``I prop``: the
  infectious share of the population on that day. The published forecast
  (:mod:`pipeline.backtest.track_record`) forecasts weeks ending on Saturdays 1–4 weeks after its
  origin (the last Saturday of data); a hub horizon is filled when its target week is one of them.
* quantiles: the published forecast's own 23 quantiles, unchanged (the report's headline shows
  the same numbers); samples: its weekly sample paths, ``output_type_id`` ``"1"``..``"n"``, one id
  = one joint path across targets and horizons (compound task id set =
  {reference_date, location}); a path's week of cases is N·I at the week's end (the conversion's
  infectious window is one week).
* values are non-negative by construction; a forecast holding a negative or non-finite value is
  refused, never clipped.
* a hub week that lies wholly in the data (horizon −1, and 0 when the data end on a Saturday)
  is filled from the nowcast of its final count (:class:`NowcastWeek`: the days still being
  reported, ``pipeline.nowcast.completions``), its samples aligned with the forecast's paths;
* hub horizons whose target week is observed with no nowcast given, or is not one of the
  forecast's weeks, are left out with a logged reason (:attr:`Submission.omitted`).

``output_type_id`` is written as text (quantile levels as ``0.025``, sample ids as ``17``) as
hubverse does for mixed output types.

The validator: :mod:`pipeline.outputs.hubverse_validation`; a round of a many-location hub:
:mod:`pipeline.outputs.hubverse_round`.
"""
from __future__ import annotations

import datetime as dt
import io
import logging
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.backtest.result import QuantileForecast
from pipeline.data.california.counties import COUNTY_FIPS, SAN_FRANCISCO
from pipeline.io import atomic_write_text, sha256_bytes
from pipeline.outputs.hubverse_validation import (HubFormatError, frame_from_text,
                                                  validate_model_output_frame)
from pipeline.panels.targets import HUB_QUANTILE_LEVELS, format_level

SF_COUNTY_FIPS = COUNTY_FIPS[SAN_FRANCISCO]

log = logging.getLogger(__name__)


def hub_csv_text(frame: pd.DataFrame) -> str:
    buffer = io.StringIO()
    frame.to_csv(buffer, index=False, float_format="%.8g", lineterminator="\n")
    return buffer.getvalue()


# ---------------------------------------------------------------------- hubverse submission

TEAM_ABBR = "flowcast"
MODEL_ABBR = "nfens"
TARGET_WEEKLY_CASES = "wk inc case"
TARGET_I_PROP = "I prop"
HUBVERSE_TARGETS: tuple[str, ...] = (TARGET_WEEKLY_CASES, TARGET_I_PROP)
HUBVERSE_HORIZONS: tuple[int, ...] = (-1, 0, 1, 2, 3)
HUBVERSE_TASK_IDS: tuple[str, ...] = ("reference_date", "target", "horizon", "location",
                                      "target_end_date")
MODEL_OUTPUT_COLUMNS: tuple[str, ...] = (*HUBVERSE_TASK_IDS, "output_type", "output_type_id",
                                         "value")
TASKS_SCHEMA_URL = ("https://raw.githubusercontent.com/hubverse-org/schemas/main/v5.0.0/"
                    "tasks-schema.json")
_MODEL_ID_PART = re.compile(r"^[A-Za-z0-9_+]+$")


@dataclass(frozen=True)
class SubmissionConfig:
    """Who submits (team, model: hubverse ``team_abbr``/``model_abbr``) and what."""

    team_abbr: str = TEAM_ABBR
    model_abbr: str = MODEL_ABBR
    horizons: tuple[int, ...] = HUBVERSE_HORIZONS
    quantile_levels: tuple[float, ...] = HUB_QUANTILE_LEVELS
    n_samples: int = 200
    location: str = SF_COUNTY_FIPS

    def __post_init__(self) -> None:
        for name in ("team_abbr", "model_abbr"):
            if not _MODEL_ID_PART.match(getattr(self, name)):
                raise HubFormatError(f"SubmissionConfig.{name}={getattr(self, name)!r}: hubverse "
                                     "allows letters, digits, '_' and '+' only")
        if self.n_samples < 1:
            raise HubFormatError(f"SubmissionConfig.n_samples={self.n_samples} must be >= 1")

    @property
    def model_id(self) -> str:
        return f"{self.team_abbr}-{self.model_abbr}"


@dataclass(frozen=True, eq=False)
class NowcastWeek:
    """A hub week that lies wholly in the data but is still being reported: the nowcast of its
    final weekly cases — quantiles at the hub levels and samples aligned with the forecast's
    sample paths (sample i belongs to path i)."""

    end: dt.date
    quantiles: np.ndarray
    samples: np.ndarray


@dataclass(frozen=True)
class Submission:
    """What :func:`write_model_output` wrote, and which horizons it left out and why."""

    path: Path
    frame: pd.DataFrame
    reference_date: dt.date
    horizons: tuple[int, ...]
    omitted: dict[int, str] = field(default_factory=dict)
    sha256: str = ""


def reference_date_for(run_date: dt.date) -> dt.date:
    """The Saturday ending the CDC epiweek (Sunday–Saturday) that contains ``run_date``."""
    from epiweeks import Week

    return Week.fromdate(run_date, system="cdc").enddate()


def model_output_path(hub_dir: str | os.PathLike[str], reference_date: dt.date,
                      model_id: str) -> Path:
    """``<hub_dir>/model-output/<model_id>/<reference_date>-<model_id>.csv``."""
    return (Path(hub_dir) / "model-output" / model_id /
            f"{reference_date.isoformat()}-{model_id}.csv")


def _horizon_index(forecast: QuantileForecast, end: dt.date) -> tuple[int | None, str]:
    """The forecast's horizon index whose target week ends on ``end``, or (None, why not)."""
    origin = forecast.origin.date()
    if end <= origin:
        return None, (f"target week ending {end} is observed (the forecast's origin is {origin}); "
                      "nothing to forecast")
    weeks, rest = divmod((end - origin).days, 7)
    if rest or weeks not in forecast.horizons:
        return None, (f"target week ending {end} is not one of the forecast's weeks (origin "
                      f"{origin}, horizons {forecast.horizons} weeks)")
    return forecast.horizons.index(weeks), ""


def _check_nowcast(week: NowcastWeek, config: SubmissionConfig) -> None:
    if week.quantiles.shape != (len(config.quantile_levels),) or \
            week.samples.shape[0] < config.n_samples:
        raise HubFormatError(f"the nowcast of the week ending {week.end} needs "
                             f"{len(config.quantile_levels)} quantiles and {config.n_samples} "
                             f"samples, got {week.quantiles.shape} and {week.samples.shape}")
    for values in (week.quantiles, week.samples):
        if not np.all(np.isfinite(values)) or (values < 0).any():
            raise HubFormatError(f"the nowcast of the week ending {week.end} holds NaN, inf or "
                                 "negative values; refusing to write a submission")


def _check_forecast(forecast: QuantileForecast, population: float,
                    config: SubmissionConfig) -> None:
    if not np.allclose(forecast.levels, config.quantile_levels, rtol=0, atol=1e-12):
        raise HubFormatError(f"the forecast's quantile levels {forecast.levels.tolist()} are not "
                             "the hub's 23")
    if population <= 0 or not np.isfinite(population):
        raise HubFormatError(f"population must be a positive number, got {population}")
    if forecast.paths is None or forecast.paths.shape[0] < config.n_samples:
        have = 0 if forecast.paths is None else forecast.paths.shape[0]
        raise HubFormatError(f"{config.n_samples} sample paths required, got {have}")
    for name, values in (("quantiles", np.concatenate([forecast.values["cases"].ravel(),
                                                       forecast.values["I"].ravel()])),
                         ("sample paths", forecast.paths)):
        if not np.all(np.isfinite(values)) or (values < 0).any():
            raise HubFormatError(f"the forecast's {name} hold NaN, inf or negative values; "
                                 "refusing to write a submission")


def submission_frame(forecast: QuantileForecast, *, population: float, reference_date: dt.date,
                     config: SubmissionConfig = SubmissionConfig(),
                     nowcasts: Sequence[NowcastWeek] = ()
                     ) -> tuple[pd.DataFrame, dict[int, str]]:
    """The model-output rows of the published weekly forecast (its quantiles exactly, and its
    sample paths: I at the week's end and the week's cases N·I, the conversion's 7-day window),
    the ``nowcasts`` of weeks already in the data, and the hub horizons left out with reasons.
    Raises ``HubFormatError`` if none is left."""
    _check_forecast(forecast, population, config)
    by_end = {w.end: w for w in nowcasts}
    for week in nowcasts:
        _check_nowcast(week, config)
    assert forecast.paths is not None
    level_ids = [format_level(lv) for lv in config.quantile_levels]
    sample_ids = [str(k + 1) for k in range(config.n_samples)]
    rows: list[pd.DataFrame] = []
    omitted: dict[int, str] = {}
    for horizon in config.horizons:
        end = reference_date + dt.timedelta(weeks=horizon)
        index, reason = _horizon_index(forecast, end)
        if end in by_end:
            cases = by_end[end].samples[: config.n_samples]
            draws = {TARGET_WEEKLY_CASES: cases, TARGET_I_PROP: cases / population}
            quantiles = {TARGET_WEEKLY_CASES: by_end[end].quantiles,
                         TARGET_I_PROP: by_end[end].quantiles / population}
        elif index is None:
            omitted[horizon] = reason
            continue
        else:
            infectious = forecast.paths[: config.n_samples, index, 1]
            draws = {TARGET_WEEKLY_CASES: infectious * population, TARGET_I_PROP: infectious}
            quantiles = {TARGET_WEEKLY_CASES: forecast.values["cases"][index],
                         TARGET_I_PROP: forecast.values["I"][index]}
        for target in HUBVERSE_TARGETS:
            task = {"reference_date": reference_date.isoformat(), "target": target,
                    "horizon": horizon, "location": config.location,
                    "target_end_date": end.isoformat()}
            rows.append(pd.DataFrame({**task, "output_type": "quantile",
                                      "output_type_id": level_ids, "value": quantiles[target]}))
            rows.append(pd.DataFrame({**task, "output_type": "sample",
                                      "output_type_id": sample_ids, "value": draws[target]}))
    if not rows:
        raise HubFormatError("no horizon of the submission is covered by the forecast: "
                             + "; ".join(f"horizon {h}: {r}" for h, r in omitted.items()))
    frame = pd.concat(rows, ignore_index=True)[list(MODEL_OUTPUT_COLUMNS)]
    order = {"quantile": 0, "sample": 1}
    frame = frame.sort_values(["output_type", "target", "horizon"], kind="stable",
                              key=lambda c: c.map(order) if c.name == "output_type" else c)
    return frame.reset_index(drop=True), omitted


def write_model_output(forecast: QuantileForecast, *, population: float, run_date: dt.date,
                       hub_dir: str | os.PathLike[str],
                       config: SubmissionConfig = SubmissionConfig(),
                       tasks: Mapping[str, Any] | None = None,
                       nowcasts: Sequence[NowcastWeek] = ()) -> Submission:
    """Write the hubverse model-output CSV of the published weekly ``forecast`` (and the
    ``nowcasts`` of weeks in the data) for the round of ``run_date`` (the Saturday ending its
    epiweek; the run date is the last day in the data). With ``tasks`` (a parsed
    ``tasks.json``) the file is validated against it before it replaces anything."""
    reference_date = reference_date_for(run_date)
    frame, omitted = submission_frame(forecast, population=population,
                                      reference_date=reference_date, config=config,
                                      nowcasts=nowcasts)
    for horizon, reason in omitted.items():
        log.info("hub submission %s: horizon %d left out: %s", reference_date, horizon, reason)
    path = model_output_path(hub_dir, reference_date, config.model_id)
    text = hub_csv_text(frame)
    if tasks is not None:
        validate_model_output_frame(frame_from_text(text, path), tasks, source=path)
    atomic_write_text(path, text)
    return Submission(path=path, frame=frame, reference_date=reference_date,
                      horizons=tuple(sorted(set(frame["horizon"].astype(int)))),
                      omitted=omitted, sha256=sha256_bytes(text.encode("utf-8")))


# ---------------------------------------------------------------------------- tasks.json


def hub_tasks_config(first_reference: dt.date, last_reference: dt.date) -> dict[str, Any]:
    """The California county hub's ``tasks.json`` (hubverse schema v5) for the rounds between
    the two dates: every county's FIPS code a location."""
    saturdays = [reference_date_for(first_reference)]
    while saturdays[-1] + dt.timedelta(weeks=1) <= last_reference:
        saturdays.append(saturdays[-1] + dt.timedelta(weeks=1))
    ends = [saturdays[0] + dt.timedelta(weeks=k)
            for k in range(min(HUBVERSE_HORIZONS), len(saturdays) + max(HUBVERSE_HORIZONS))]
    value = {"type": "double", "minimum": 0}
    week = ("in the epiweek (Sunday-Saturday) ending on target_end_date, [horizon] weeks after "
            "the reference_date")
    return {
        "schema_version": TASKS_SCHEMA_URL,
        "rounds": [{
            "round_id_from_variable": True,
            "round_id": "reference_date",
            "model_tasks": [{
                "task_ids": {
                    "reference_date": {"required": None,
                                       "optional": [d.isoformat() for d in saturdays]},
                    "target": {"required": None, "optional": list(HUBVERSE_TARGETS)},
                    "horizon": {"required": None, "optional": list(HUBVERSE_HORIZONS)},
                    "location": {"required": None, "optional": sorted(COUNTY_FIPS.values())},
                    "target_end_date": {"required": None,
                                        "optional": [d.isoformat() for d in ends]},
                },
                "output_type": {
                    "quantile": {"output_type_id": {"required": list(HUB_QUANTILE_LEVELS)},
                                 "is_required": False, "value": value},
                    "sample": {"output_type_id_params": {
                        "type": "character", "max_length": 15, "min_samples_per_task": 100,
                        "max_samples_per_task": 200,
                        "compound_taskid_set": ["reference_date", "location"]},
                        "is_required": False, "value": value},
                },
                "target_metadata": [
                    {"target_id": TARGET_WEEKLY_CASES, "target_name": "weekly reported cases",
                     "target_units": "count", "target_keys": {"target": TARGET_WEEKLY_CASES},
                     "target_type": "continuous", "is_step_ahead": True, "time_unit": "week",
                     "description": f"Reported COVID-19 cases in the county {week}."},
                    {"target_id": TARGET_I_PROP, "target_name": "infectious share",
                     "target_units": "proportion", "target_keys": {"target": TARGET_I_PROP},
                     "target_type": "continuous", "is_step_ahead": True, "time_unit": "week",
                     "description": ("Share of the county's population infectious (reported "
                                     "in the last 7 days) on target_end_date, [horizon] weeks "
                                     "after the reference_date.")},
                ],
            }],
            "submissions_due": {"relative_to": "reference_date", "start": -6, "end": 0},
        }],
    }

