"""The hubverse submission of the published weekly forecast (no Prefect, no torch).

For a hub of California's counties whose config is ``hub-config/`` (the 2024+ COVID-19 Forecast
Hub conventions; ``location`` is the county's FIPS code, San Francisco ``06075`` by default,
:mod:`pipeline.data.california.counties`):
``model-output/<team>-<model>/<reference_date>-<team>-<model>.csv`` with the columns
``reference_date, target, horizon, location, target_end_date, output_type, output_type_id,
value``, validated by :func:`validate_model_output` against ``hub-config/tasks.json``.

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

A round of a hub of many locations, such as the CDC COVID-19 Forecast Hub (53 locations, the
targets ``wk inc covid hosp`` and ``wk inc covid prop ed visits``, horizons −1..3, 23 quantiles,
200 samples per compound task {location, target}): :func:`write_hub_round` writes a long frame
in hubverse format, and its ``model-metadata/<model_id>.yml``, after validating the text it
writes against the hub's own ``tasks.json``; :func:`compound_sample_ids` numbers sample ids as
that hub requires (one id per trajectory of one location and target, shared by its horizons).

The validator (:func:`validate_model_output`) is generic over a hubverse v5 ``tasks.json`` of one
round definition and one model task: allowed task-id values (targets, horizons, locations, dates),
output types, quantile levels and sample-id text, finite values within the declared bounds,
``target_end_date = reference_date + 7·horizon``, complete non-decreasing quantile sets, sample
counts per compound task, sample ids owned by one compound task, no duplicated row. It works
column by column (each distinct task-id value checked once, values vectorized), so a round of
118,000 rows validates in well under a second.
"""
from __future__ import annotations

import datetime as dt
import io
import json
import logging
import os
import re
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.data.california.counties import COUNTY_FIPS, SAN_FRANCISCO
from pipeline.errors import FlowcastError
from pipeline.backtest.result import QuantileForecast
from pipeline.panels.targets import HUB_QUANTILE_LEVELS, format_level
from pipeline.io import atomic_write_text, sha256_bytes

SF_COUNTY_FIPS = COUNTY_FIPS[SAN_FRANCISCO]
_QUANTILE_TOL = 1e-12

log = logging.getLogger(__name__)


class HubFormatError(FlowcastError):
    """A forecast or a hub file that does not meet the hub format (levels, NaN, dates...)."""


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
_MODEL_ID = re.compile(r"^[A-Za-z0-9_+]+-[A-Za-z0-9_+]+$")


class HubValidationError(HubFormatError):
    """A model-output file that breaks the hub's ``tasks.json`` rules (names file, row, rule)."""


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
        validate_model_output_frame(_frame_from_text(text, path), tasks, source=path)
    atomic_write_text(path, text)
    return Submission(path=path, frame=frame, reference_date=reference_date,
                      horizons=tuple(sorted(set(frame["horizon"].astype(int)))),
                      omitted=omitted, sha256=sha256_bytes(text.encode("utf-8")))


# -------------------------------------------------------------------- tasks.json and checks


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


def load_tasks_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise HubValidationError(f"cannot read the hub tasks config {path}: {exc}") from exc


def _frame_from_text(text: str, source: object) -> pd.DataFrame:
    try:
        return pd.read_csv(io.StringIO(text), dtype=str, keep_default_na=False)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise HubValidationError(f"{source}: not a readable CSV ({exc})") from exc


def _round_for(tasks: Mapping[str, Any], source: object) -> Mapping[str, Any]:
    rounds = tasks.get("rounds") or []
    if len(rounds) != 1 or len(rounds[0].get("model_tasks", [])) != 1:
        raise HubValidationError(f"{source}: this validator handles hubs with one round "
                                 "definition holding one model task")
    return rounds[0]["model_tasks"][0]


def _task_values(spec: Mapping[str, Any]) -> list[Any]:
    return list(spec.get("required") or []) + list(spec.get("optional") or [])


def _row_schema(model_task: Mapping[str, Any], output_type: str) -> dict[str, Any]:
    """A JSON Schema (draft 2020-12) for one model-output row of ``output_type``."""
    spec = model_task["output_type"][output_type]
    properties: dict[str, Any] = {
        name: {"enum": _task_values(values)} for name, values in model_task["task_ids"].items()}
    properties["output_type"] = {"const": output_type}
    if "output_type_id" in spec:
        properties["output_type_id"] = {"enum": _task_values(spec["output_type_id"])}
    else:
        params = spec["output_type_id_params"]
        properties["output_type_id"] = {"type": "string", "minLength": 1,
                                        "maxLength": int(params.get("max_length", 15))}
    value: dict[str, Any] = {"type": "integer" if spec["value"]["type"] == "integer"
                             else "number"}
    for bound in ("minimum", "maximum"):
        if bound in spec["value"]:
            value[bound] = spec["value"][bound]
    properties["value"] = value
    return {"type": "object", "properties": properties, "required": sorted(properties),
            "additionalProperties": False}


def _int_task_ids(model_task: Mapping[str, Any]) -> set[str]:
    return {name for name, spec in model_task["task_ids"].items()
            if _task_values(spec) and all(isinstance(v, int) and not isinstance(v, bool)
                                          for v in _task_values(spec))}


def _numbers(cells: pd.Series, column: str, kind: str, source: object) -> np.ndarray:
    """Text cells as float64 (``nan``/``inf`` parse and are judged later); the first cell that
    is no number is an error naming its row."""
    try:
        return cells.to_numpy(dtype=object).astype(np.float64)
    except (TypeError, ValueError):
        parsed = pd.to_numeric(cells, errors="coerce")
        literal = cells.astype(str).str.strip().str.lower().isin(
            ["nan", "inf", "+inf", "-inf", "infinity", "-infinity"])
        row = int(np.flatnonzero((parsed.isna() & ~literal).to_numpy())[0])
        raise HubValidationError(f"{source} row {row + 2}: column {column!r} must be {kind}, "
                                 f"got {cells.iloc[row]!r}") from None


def _typed_columns(frame: pd.DataFrame, model_task: Mapping[str, Any],
                   source: object) -> pd.DataFrame:
    """The CSV's text cells in the types the tasks config declares, column by column: integer
    task ids as int64, ``value`` as float64, a quantile's ``output_type_id`` as its level (text
    that is no number stays text, for the level check to name it), a sample's as text."""
    int_ids = _int_task_ids(model_task)
    typed = frame.reset_index(drop=True).copy()
    for column in int_ids & set(frame.columns):
        numbers = _numbers(typed[column], column, "an integer", source)
        fractional = ~np.isfinite(numbers) | (numbers != np.round(numbers))
        if fractional.any():
            row = int(np.flatnonzero(fractional)[0])
            raise HubValidationError(f"{source} row {row + 2}: column {column!r} must be an "
                                     f"integer, got {typed[column].iloc[row]!r}")
        typed[column] = numbers.astype(np.int64)
    typed["value"] = _numbers(typed["value"], "value", "a number", source)
    ids = typed["output_type_id"].to_numpy(dtype=object).copy()
    levels = pd.to_numeric(typed["output_type_id"], errors="coerce").to_numpy(dtype=np.float64)
    sample = (typed["output_type"] == "sample").to_numpy()
    as_level = ~sample & ~np.isnan(levels)
    ids[as_level] = levels[as_level].tolist()
    ids[sample] = pd.Series(ids[sample], dtype=object).map(frame_id_text).to_numpy(dtype=object)
    typed["output_type_id"] = ids
    return typed


def _cell_errors(typed: pd.DataFrame, schemas: Mapping[str, Mapping[str, Any]],
                 source: object) -> None:
    """Every cell against its output type's row schema, column by column: a task-id column's
    distinct values are checked once (its enums of every location and date are slow to scan),
    values vectorized. Raises for the first row with an error (its alphabetically first)."""
    from jsonschema import Draft202012Validator

    kinds = typed["output_type"].to_numpy(dtype=object)
    found: list[tuple[int, str]] = []
    unknown = ~np.isin(kinds, list(schemas))
    if unknown.any():
        row = int(np.flatnonzero(unknown)[0])
        found.append((row, f"output_type {kinds[row]!r} is not one of {sorted(schemas)}"))
    for kind, schema in schemas.items():
        rows = np.flatnonzero(kinds == kind)
        if rows.size == 0:
            continue
        part = typed.iloc[rows]
        for column, spec in schema["properties"].items():
            if column == "value":
                found += _value_errors(part["value"].to_numpy(), rows, spec)
                continue
            validator = Draft202012Validator(spec)
            cells = part[column].to_numpy(dtype=object)
            distinct = pd.unique(cells)
            bad = {}
            for cell in distinct:
                plain = cell.item() if isinstance(cell, np.generic) else cell
                errors = list(validator.iter_errors(plain))
                if errors:
                    bad[cell] = min(errors, key=lambda e: str(e)).message
            if bad:
                hit = np.flatnonzero(pd.Series(cells).isin(list(bad)).to_numpy())[0]
                found.append((int(rows[hit]), f"column {column!r}: {bad[cells[hit]]}"))
    if found:
        row = min(r for r, _ in found)
        message = min(m for r, m in found if r == row)
        raise HubValidationError(f"{source} row {row + 2}: {message}")


def _value_errors(values: np.ndarray, rows: np.ndarray,
                  spec: Mapping[str, Any]) -> list[tuple[int, str]]:
    """Non-finite values (a JSON Schema number would let NaN pass its bounds), then the
    spec's type and bounds, each with jsonschema's own message for its first offender."""
    from jsonschema import Draft202012Validator

    found: list[tuple[int, str]] = []
    finite = np.isfinite(values)
    if not finite.all():
        k = int(np.flatnonzero(~finite)[0])
        found.append((int(rows[k]), f"column 'value': {values[k]} is not a finite number"))
    offending = np.zeros(values.size, dtype=bool)
    if spec.get("type") == "integer":
        offending |= finite & (values != np.round(values))
    if "minimum" in spec:
        offending |= finite & (values < spec["minimum"])
    if "maximum" in spec:
        offending |= finite & (values > spec["maximum"])
    if offending.any():
        k = int(np.flatnonzero(offending)[0])
        value = float(values[k])
        cell: float | int = int(value) if spec.get("type") == "integer" and value.is_integer() \
            else value
        errors = list(Draft202012Validator(spec).iter_errors(cell))
        found.append((int(rows[k]), f"column 'value': {min(errors, key=str).message}"))
    return found


def frame_id_text(value: Any) -> str:
    """A sample id as hubverse text: ``3.0`` read as a number goes back to ``"3"``."""
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def validate_model_output(path: str | os.PathLike[str], tasks: Mapping[str, Any]) -> pd.DataFrame:
    """Validate a model-output CSV against a hub's ``tasks.json``; return it typed.

    Row rules (JSON Schema, ``jsonschema``): the exact columns, allowed task id values (targets,
    horizons, locations, dates), output types, quantile levels, sample id text, value types and
    bounds (non-negative). File rules: the file name is ``<reference_date>-<model_id>.csv`` in
    ``model-output/<model_id>/``; ``target_end_date = reference_date + 7·horizon``; every
    quantile task has the complete level set and non-decreasing values; sample counts per compound
    task within the config's bounds, no duplicated rows. Raises ``HubValidationError`` naming the
    file, the row or task, and the rule.
    """
    target = Path(path)
    try:
        text = target.read_text(encoding="utf-8")
    except OSError as exc:
        raise HubValidationError(f"cannot read model-output file {target}: {exc}") from exc
    frame = _frame_from_text(text, target)
    _check_file_name(target, frame)
    return validate_model_output_frame(frame, tasks, source=target)


def _check_file_name(path: Path, frame: pd.DataFrame) -> None:
    match = re.fullmatch(r"(\d{4}-\d{2}-\d{2})-(.+)\.(csv|parquet)", path.name)
    if match is None:
        raise HubValidationError(f"{path}: file name must be <reference_date>-<team>-<model>.csv")
    if path.parent.name != match.group(2):
        raise HubValidationError(f"{path}: model id {match.group(2)!r} in the file name differs "
                                 f"from its folder {path.parent.name!r}")
    if "reference_date" in frame.columns and set(frame["reference_date"]) - {match.group(1)}:
        raise HubValidationError(f"{path}: reference_date values "
                                 f"{sorted(set(frame['reference_date']))} differ from the file "
                                 f"name's {match.group(1)}")


def validate_model_output_frame(frame: pd.DataFrame, tasks: Mapping[str, Any], *,
                                source: object = "model output") -> pd.DataFrame:
    """:func:`validate_model_output` on a frame of text cells (as read with ``dtype=str``)."""
    model_task = _round_for(tasks, source)
    expected = [*model_task["task_ids"], "output_type", "output_type_id", "value"]
    if sorted(frame.columns) != sorted(expected):
        missing = sorted(set(expected) - set(frame.columns))
        extra = sorted(set(frame.columns) - set(expected))
        raise HubValidationError(f"{source}: columns must be {expected}; missing {missing}, "
                                 f"unexpected {extra}")
    if frame.empty:
        raise HubValidationError(f"{source}: no rows")
    typed = _typed_columns(frame, model_task, source)
    _cell_errors(typed, {name: _row_schema(model_task, name)
                         for name in model_task["output_type"]}, source)
    _check_dates(typed, source)
    _check_duplicates(typed, source)
    if "quantile" in model_task["output_type"]:
        _check_quantile_sets(typed, model_task, source)
    if "sample" in model_task["output_type"]:
        _check_sample_counts(typed, model_task, source)
    return typed


def _check_dates(frame: pd.DataFrame, source: object) -> None:
    if not {"reference_date", "target_end_date", "horizon"} <= set(frame.columns):
        return
    ref = pd.to_datetime(frame["reference_date"])
    end = pd.to_datetime(frame["target_end_date"])
    bad = ((end - ref).dt.days != 7 * frame["horizon"].astype(int)).to_numpy()
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise HubValidationError(f"{source} row {row + 2}: target_end_date "
                                 f"{frame['target_end_date'].iloc[row]} is not reference_date "
                                 f"{frame['reference_date'].iloc[row]} + 7·horizon "
                                 f"({frame['horizon'].iloc[row]})")


def _task_id_columns(frame: pd.DataFrame) -> list[str]:
    return [c for c in frame.columns if c not in ("output_type", "output_type_id", "value")]


def _check_duplicates(frame: pd.DataFrame, source: object) -> None:
    keys = [*_task_id_columns(frame), "output_type", "output_type_id"]
    dup = frame.duplicated(subset=keys, keep=False).to_numpy()
    if dup.any():
        row = int(np.flatnonzero(dup)[0])
        raise HubValidationError(f"{source} row {row + 2}: duplicated row "
                                 f"{frame.iloc[row][keys].to_dict()}")


def _task_codes(frame: pd.DataFrame) -> np.ndarray:
    """One integer per distinct task (the task-id columns' values)."""
    return frame.groupby(_task_id_columns(frame), sort=False, dropna=False).ngroup() \
        .to_numpy(dtype=np.int64)


def _check_quantile_sets(frame: pd.DataFrame, model_task: Mapping[str, Any],
                         source: object) -> None:
    levels = sorted(float(v) for v in
                    _task_values(model_task["output_type"]["quantile"]["output_type_id"]))
    required = sorted(float(v) for v in
                      model_task["output_type"]["quantile"]["output_type_id"].get("required")
                      or [])
    q = frame[(frame["output_type"] == "quantile").to_numpy()]
    if q.empty:
        return
    task = _task_codes(q)
    level = q["output_type_id"].astype(np.float64).to_numpy()
    # rows are unique by now (duplicates were refused): counting required levels per task finds
    # an incomplete set, and values sorted by level within each task find a crossing
    n_required = np.bincount(task, weights=np.isin(level, required), minlength=task.max() + 1)
    short = np.flatnonzero(n_required < len(required))
    if short.size:
        rows = task == short[0]
        found = sorted(level[rows].tolist())
        absent = [lv for lv in required if lv not in found]
        label = _task_label(frame, tuple(q[rows].iloc[0][_task_id_columns(frame)]))
        raise HubValidationError(f"{source}: quantile task {label} lacks the levels {absent} "
                                 f"(incomplete quantile set: {len(found)} of {len(levels)})")
    order = np.lexsort((level, task))
    values = q["value"].to_numpy(dtype=np.float64)[order]
    same_task = task[order][1:] == task[order][:-1]
    falling = same_task & (np.diff(values) < -_QUANTILE_TOL)
    if falling.any():
        first = q.iloc[order[int(np.flatnonzero(falling)[0])]]
        label = _task_label(frame, tuple(first[_task_id_columns(frame)]))
        raise HubValidationError(f"{source}: quantile task {label} has values that decrease as "
                                 "the level rises (crossing quantiles)")


def _check_sample_counts(frame: pd.DataFrame, model_task: Mapping[str, Any],
                         source: object) -> None:
    params = model_task["output_type"]["sample"]["output_type_id_params"]
    samples = frame[(frame["output_type"] == "sample").to_numpy()]
    if samples.empty:
        return
    compound = list(params.get("compound_taskid_set") or _task_id_columns(frame))
    low = int(params.get("min_samples_per_task", 1))
    high = int(params.get("max_samples_per_task", 10**9))
    ids = samples["output_type_id"].astype(str)
    per_compound = samples.assign(_id=ids).groupby(compound, sort=True)["_id"].nunique()
    outside = per_compound[(per_compound < low) | (per_compound > high)]
    if not outside.empty:
        key, count = outside.index[0], int(outside.iloc[0])
        raise HubValidationError(f"{source}: {count} samples for compound task "
                                 f"{dict(zip(compound, _as_tuple(key), strict=True))}; "
                                 f"the hub asks for {low}..{high}")
    # one id is one joint draw of one compound task: the same id in two compound tasks
    # would join draws the hub declares independent
    owner = samples.groupby(compound, sort=True, dropna=False).ngroup().to_numpy()
    spread = pd.Series(owner).groupby(ids.to_numpy(), sort=True).nunique()
    if (spread > 1).any():
        first = spread.index[(spread > 1).to_numpy()][0]
        keys = samples[(ids == first).to_numpy()][compound].drop_duplicates()
        pair = [tuple(k) for k in keys.itertuples(index=False)][:2]
        raise HubValidationError(f"{source}: sample id {first!r} is used in two compound "
                                 f"tasks ({pair[0]} and {pair[1]})")
    per_task = samples.assign(_id=ids).groupby(_task_id_columns(frame), sort=True)["_id"] \
        .nunique().rename("_count").reset_index()
    expected = per_compound.rename("_want").reset_index()
    check = per_task.merge(expected, on=compound, how="left")
    wrong = check[check["_count"] != check["_want"]]
    if not wrong.empty:
        row = wrong.iloc[0]
        label = _task_label(frame, tuple(row[_task_id_columns(frame)]))
        raise HubValidationError(f"{source}: sample task {label} has {int(row['_count'])} "
                                 f"samples, its compound task has {int(row['_want'])}: each "
                                 "sample must cover every target and horizon")


def _as_tuple(key: Hashable) -> tuple[Hashable, ...]:
    """A groupby key as a tuple (pandas gives a scalar when grouping by one column)."""
    return key if isinstance(key, tuple) else (key,)


def _task_label(frame: pd.DataFrame, task: Hashable) -> str:
    names = _task_id_columns(frame)
    return ", ".join(f"{n}={v}" for n, v in zip(names, _as_tuple(task), strict=True))


# ------------------------------------------------------ a round of a many-location hub (CDC's)

CDC_HUB_MODEL_ID = "flowcast-nfhub"   # team flowcast; the model's name is to be settled


@dataclass(frozen=True)
class RoundFile:
    """What :func:`write_hub_round` wrote: the model-output file and its metadata file."""

    path: Path
    metadata_path: Path
    frame: pd.DataFrame
    reference_date: dt.date
    sha256: str


def compound_sample_ids(frame: pd.DataFrame,
                        compound: Sequence[str] = ("location", "target")) -> pd.DataFrame:
    """``frame`` with its sample ids renumbered ``"0"``, ``"1"``, … so that each (compound task
    × given id) pair has its own id: ids that repeat from one location or target to the next
    (e.g. ``1..200`` everywhere) become unique per compound task, as hubverse requires, while
    one id still joins the horizons of one trajectory."""
    sample = (frame["output_type"] == "sample").to_numpy()
    if not sample.any():
        return frame
    part = frame.loc[sample, [*compound, "output_type_id"]].astype(str)
    ids = part.groupby([*compound, "output_type_id"], sort=False).ngroup()
    renumbered = frame.copy()
    column = renumbered["output_type_id"].astype(object).to_numpy(copy=True)
    column[sample] = ids.astype(str).to_numpy(dtype=object)
    renumbered["output_type_id"] = column
    return renumbered


def _round_text_frame(frame: pd.DataFrame, source: object) -> pd.DataFrame:
    """A round's long frame as the text cells of its CSV: ISO dates, integer horizons, quantile
    levels as ``0.025``, sample ids as text; quantiles first, then samples, each by target,
    location and horizon. Non-finite and negative values are refused here, before any file."""
    missing = [c for c in MODEL_OUTPUT_COLUMNS if c not in frame.columns]
    extra = [c for c in frame.columns if c not in MODEL_OUTPUT_COLUMNS]
    if missing or extra:
        raise HubValidationError(f"{source}: columns must be {list(MODEL_OUTPUT_COLUMNS)}; "
                                 f"missing {missing}, unexpected {extra}")
    if frame.empty:
        raise HubValidationError(f"{source}: no rows")
    values = frame["value"].to_numpy(dtype=np.float64)
    bad = ~np.isfinite(values) | (values < 0)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise HubValidationError(f"{source}: row {row} "
                                 f"({frame.iloc[row][list(HUBVERSE_TASK_IDS)].to_dict()}, "
                                 f"{frame['output_type'].iloc[row]} "
                                 f"{frame['output_type_id'].iloc[row]}) has the value "
                                 f"{values[row]}: hub values must be finite and >= 0")
    kind = frame["output_type"].astype(str).to_numpy()
    ids = frame["output_type_id"]
    quantile = kind == "quantile"
    levels = pd.to_numeric(ids.where(quantile), errors="coerce").to_numpy(dtype=np.float64)
    text = ids.astype(object).to_numpy(copy=True)
    # a few distinct levels and ids repeat down the rows: each is formatted once
    text[quantile] = pd.Series(levels[quantile]).map(
        {lv: format_level(lv) for lv in pd.unique(levels[quantile]) if np.isfinite(lv)}) \
        .fillna(pd.Series(text[quantile], dtype=object).astype(str)).to_numpy(dtype=object)
    others = pd.Series(text[~quantile], dtype=object)
    text[~quantile] = others.map({cell: frame_id_text(cell) for cell in pd.unique(others)}) \
        .to_numpy(dtype=object)
    dates = {c: pd.to_datetime(frame[c]).dt.strftime("%Y-%m-%d")
             for c in ("reference_date", "target_end_date")}
    out = pd.DataFrame({
        "reference_date": dates["reference_date"].to_numpy(),
        "target": frame["target"].astype(str).to_numpy(),
        "horizon": frame["horizon"].astype(np.int64).to_numpy(),
        "location": frame["location"].astype(str).to_numpy(),
        "target_end_date": dates["target_end_date"].to_numpy(),
        "output_type": kind, "output_type_id": text, "value": values})
    out["_kind"] = np.where(quantile, 0, 1)
    out["_level"] = np.where(quantile, levels, 0.0)
    out = out.sort_values(["_kind", "target", "location", "horizon", "_level"], kind="stable")
    return out.drop(columns=["_kind", "_level"]).reset_index(drop=True)


def load_model_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A hubverse model-metadata YAML file as a dict."""
    import yaml

    try:
        metadata = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise HubValidationError(f"cannot read model metadata {path}: {exc}") from exc
    if not isinstance(metadata, dict):
        raise HubValidationError(f"{path}: model metadata must be a mapping of fields")
    return metadata


def validate_model_metadata(metadata: Mapping[str, Any], model_id: str,
                            schema: Mapping[str, Any] | None = None) -> None:
    """The metadata belongs to ``model_id`` (``team_abbr-model_abbr``) and, with a hub's
    ``model-metadata-schema.json``, meets it (required fields, 200-character ``methods``, …)."""
    own = f"{metadata.get('team_abbr')}-{metadata.get('model_abbr')}"
    if own != model_id:
        raise HubValidationError(f"model metadata is for {own!r}, the round for {model_id!r}")
    if schema is not None:
        from jsonschema import Draft202012Validator

        errors = sorted(Draft202012Validator(schema).iter_errors(dict(metadata)), key=str)
        if errors:
            where = "/".join(str(p) for p in errors[0].absolute_path) or "(top level)"
            raise HubValidationError(f"model metadata of {model_id}: {where}: "
                                     f"{errors[0].message}")


def write_hub_round(frame: pd.DataFrame, *, hub_dir: str | os.PathLike[str], model_id: str,
                    tasks: Mapping[str, Any], metadata: Mapping[str, Any],
                    metadata_schema: Mapping[str, Any] | None = None) -> RoundFile:
    """Write one round of a hub: ``<hub_dir>/model-output/<model_id>/<reference_date>-
    <model_id>.csv`` from ``frame`` (long hubverse format, :data:`MODEL_OUTPUT_COLUMNS`, one
    reference date; sample ids unique per compound task, see :func:`compound_sample_ids`) and
    ``<hub_dir>/model-metadata/<model_id>.yml`` from ``metadata``.

    The file's text is validated against the hub's ``tasks`` (and the metadata against
    ``metadata_schema``) before anything is written; both files are then replaced atomically,
    so a refused round leaves the last good files as they were."""
    import yaml

    if not _MODEL_ID.match(model_id):
        raise HubFormatError(f"model id {model_id!r} must be <team_abbr>-<model_abbr> of "
                             "letters, digits, '_' and '+'")
    rounds = sorted(set(pd.to_datetime(frame["reference_date"]).dt.date)) \
        if "reference_date" in frame.columns else []
    if len(rounds) != 1:
        raise HubValidationError(f"a round file holds one reference_date, got {rounds}")
    reference_date = rounds[0]
    path = model_output_path(hub_dir, reference_date, model_id)
    text = hub_csv_text(_round_text_frame(frame, path))
    typed = validate_model_output_frame(_frame_from_text(text, path), tasks, source=path)
    validate_model_metadata(metadata, model_id, metadata_schema)
    metadata_path = Path(hub_dir) / "model-metadata" / f"{model_id}.yml"
    atomic_write_text(path, text)
    atomic_write_text(metadata_path, yaml.safe_dump(dict(metadata), sort_keys=False,
                                                    allow_unicode=True, width=100))
    return RoundFile(path=path, metadata_path=metadata_path, frame=typed,
                    reference_date=reference_date, sha256=sha256_bytes(text.encode("utf-8")))
