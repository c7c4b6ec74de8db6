"""A hubverse model-output file checked against its hub's ``tasks.json`` (no Prefect, no torch).

Real hubs (the CDC COVID-19 Forecast Hub, FluSight) have several round definitions and several
model tasks in a round, each with its own output types and rules. The validator
(:func:`validate_model_output`) finds the file's round from its round-id column
(``reference_date``: a date outside every round is refused, naming the hub's rounds), gives
each row to the model task whose task-id values it holds (a row that fits none is refused by
the closest task's first broken rule), and checks each model task by its own rules:

* the exact columns of the hub (``hubdata.create_hub_schema``, the hubverse's own reader);
* every cell against its output type's row schema (JSON Schema via ``jsonschema``): allowed
  task-id values (targets, horizons, locations, reference and target end dates; a task id the
  task declares no value for must be ``NA``), output types, output-type ids, the value's type
  (``integer`` or ``double``) and bounds;
* required task-id values present for required output types;
* ``target_end_date = reference_date + 7·horizon`` for step-ahead tasks;
* complete, non-decreasing quantile sets; complete pmfs summing to 1;
* ``min``/``max_samples_per_task`` per ``compound_taskid_set``, a sample id owned by one
  compound task and covering every task of it; no duplicated row.

It works column by column (each distinct task-id value checked once, values vectorized), so a
round of 118,000 rows validates in about a second. The writers (:mod:`pipeline.outputs.hubverse`,
:mod:`pipeline.outputs.hubverse_round`) validate the text they are about to write here, so a
refused file never replaces a good one. :mod:`pipeline.outputs.hub_tasks` reads what a round
must follow from the same config (sample counts, value types, bounds, the hub's rounds).
"""
from __future__ import annotations

import io
import json
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.io import JSONBoundError, read_bounded_json
from pipeline.outputs.hub_tasks import (MAX_TASKS_BYTES, MAX_TASKS_DEPTH, NA_TEXT,
                                        HubFormatError, HubValidationError, describe_rounds,
                                        find_round, hub_round_ids, round_id_column, task_values)
from pipeline.outputs.hubverse_task_checks import (check_dates, check_duplicates, check_pmfs,
                                                   check_quantile_sets, check_required_values,
                                                   check_sample_counts, file_row,
                                                   task_id_columns)

__all__ = ["HubFormatError", "HubValidationError", "frame_from_text", "frame_id_text",
           "hub_columns", "load_tasks_config", "validate_model_output",
           "validate_model_output_frame"]



def load_tasks_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The hub's ``tasks.json``, its size and nesting bounded before it is parsed."""
    try:
        return read_bounded_json(path, max_bytes=MAX_TASKS_BYTES, max_depth=MAX_TASKS_DEPTH)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, JSONBoundError) as exc:
        raise HubValidationError(f"cannot read the hub tasks config {path}: {exc}") from exc


def frame_from_text(text: str, source: object) -> pd.DataFrame:
    try:
        return pd.read_csv(io.StringIO(text), dtype=str, keep_default_na=False)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise HubValidationError(f"{source}: not a readable CSV ({exc})") from exc


def _task_values(spec: Mapping[str, Any] | None) -> list[Any]:
    return task_values(spec)


def _row_schema(model_task: Mapping[str, Any], output_type: str) -> dict[str, Any]:
    """A JSON Schema (draft 2020-12) for one model-output row of ``output_type``."""
    spec = model_task["output_type"][output_type]
    # a task id the model task gives no value (a peak target's horizon) must be NA
    properties: dict[str, Any] = {
        name: {"enum": _task_values(values)} if _task_values(values) else {"type": "null"}
        for name, values in model_task["task_ids"].items()}
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
        raise HubValidationError(f"{source} row {file_row(cells.to_frame(), row)}: column "
                                 f"{column!r} must be {kind}, got {cells.iloc[row]!r}") from None


def _typed_columns(frame: pd.DataFrame, model_task: Mapping[str, Any],
                   source: object) -> pd.DataFrame:
    """The CSV's text cells in the types the tasks config declares, column by column: integer
    task ids as int64, a task id the task gives no value as None (its ``NA``), ``value`` as
    float64, a quantile's ``output_type_id`` as its level (text that is no number stays text,
    for the level check to name it), a sample's as text. The frame's row labels are kept (they
    are the file's rows, for the messages)."""
    int_ids = _int_task_ids(model_task)
    typed = frame.copy()
    for column, spec in model_task["task_ids"].items():
        if column in typed.columns and not _task_values(spec):
            cells = typed[column].astype(object)
            typed[column] = cells.where(~cells.isin(NA_TEXT), None)
    for column in int_ids & set(frame.columns):
        numbers = _numbers(typed[column], column, "an integer", source)
        fractional = ~np.isfinite(numbers) | (numbers != np.round(numbers))
        if fractional.any():
            k = int(np.flatnonzero(fractional)[0])
            raise HubValidationError(f"{source} row {file_row(typed, k)}: column {column!r} must "
                                     f"be an integer, got {typed[column].iloc[k]!r}")
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
        raise HubValidationError(f"{source} row {file_row(typed, row)}: {message}")


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
    frame = frame_from_text(text, target)
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


def hub_columns(tasks: Mapping[str, Any]) -> list[str]:
    """A model-output file's columns, as the hubverse's own reader (``hubdata``) builds its
    schema from the config: every task id of every round, then the output columns."""
    from hubdata import create_hub_schema

    return list(create_hub_schema(dict(tasks), partitions=None).names)


def validate_model_output_frame(frame: pd.DataFrame, tasks: Mapping[str, Any], *,
                                source: object = "model output") -> pd.DataFrame:
    """:func:`validate_model_output` on a frame of text cells (as read with ``dtype=str``)."""
    expected = hub_columns(tasks)
    if sorted(frame.columns) != sorted(expected):
        missing = sorted(set(expected) - set(frame.columns))
        extra = sorted(set(frame.columns) - set(expected))
        raise HubValidationError(f"{source}: columns must be {expected}; missing {missing}, "
                                 f"unexpected {extra}")
    if frame.empty:
        raise HubValidationError(f"{source}: no rows")
    frame = frame.reset_index(drop=True)
    round_def = _round_of(frame, tasks, source)
    model_tasks = list(round_def["model_tasks"])
    owner = _model_task_of_rows(frame, model_tasks, source)
    typed_parts = []
    for k, model_task in enumerate(model_tasks):
        part = frame[owner == k]
        if part.empty:
            continue
        typed = _typed_columns(part, model_task, source)
        _cell_errors(typed, {name: _row_schema(model_task, name)
                             for name in model_task["output_type"]}, source)
        check_required_values(typed, model_task, source)
        check_dates(typed, source)
        check_duplicates(typed, source)
        kinds = model_task["output_type"]
        if "quantile" in kinds:
            check_quantile_sets(typed, model_task, source)
        if "pmf" in kinds:
            check_pmfs(typed, model_task, source)
        if "sample" in kinds:
            check_sample_counts(typed, model_task, source)
        typed_parts.append(typed)
    return _typed_frame(typed_parts, model_tasks)


def _round_of(frame: pd.DataFrame, tasks: Mapping[str, Any],
              source: object) -> Mapping[str, Any]:
    """The round definition of the file's round: the one whose round-id column (``reference_
    date``) holds the file's value. A hub without rounds from a variable has one definition."""
    rounds = list(tasks.get("rounds") or [])
    if not rounds:
        raise HubValidationError(f"{source}: the hub's tasks config has no round")
    column = round_id_column(rounds[0])
    if column is None:
        if len(rounds) != 1:
            raise HubValidationError(f"{source}: the hub names its rounds by id, not by a "
                                     "column of the file; give a hub with rounds from a variable")
        return rounds[0]
    values = pd.unique(frame[column].astype(str))
    round_def = find_round(tasks, str(values[0]))
    if round_def is None:
        raise HubValidationError(
            f"{source} row 2: column {column!r}: {values[0]!r} is not a round of the hub "
            f"({describe_rounds(hub_round_ids(tasks))})")
    return round_def


def _canonical_text(cells: pd.Series) -> np.ndarray:
    """An integer task id's text as the config's values print: ``1.0`` reads ``1``."""
    # a column holds a few distinct values (the horizons): each is read once
    codes, uniques = pd.factorize(cells.astype(str))
    text = np.asarray(uniques, dtype=object)
    looks_numeric = pd.Series(text).str.fullmatch(r"[+-]?\d+(\.0*)?").to_numpy(dtype=bool)
    text[looks_numeric] = [str(int(float(v))) for v in text[looks_numeric]]
    return text[codes]


def _model_task_of_rows(frame: pd.DataFrame, model_tasks: list[Mapping[str, Any]],
                        source: object) -> np.ndarray:
    """Each row's model task (index into ``model_tasks``): the one whose task-id values and
    output types the row holds. A row that fits none is refused with the first broken rule
    of the task it comes closest to (the most of its cells allowed)."""
    columns = task_id_columns(frame)
    integer: set[str] = set().union(*(_int_task_ids(t) for t in model_tasks))
    text = {c: _canonical_text(frame[c]) if c in integer else frame[c].astype(str).to_numpy()
            for c in columns}
    # pandas' hashed isin: numpy's on object arrays sorts them (a second per 100,000 rows)
    cells = {c: pd.Series(v) for c, v in text.items()}
    kinds = frame["output_type"].astype(object)
    fits = np.zeros((len(model_tasks), len(frame)), dtype=np.int64)
    for k, task in enumerate(model_tasks):
        for column in columns:
            allowed = [str(v) for v in _task_values(task["task_ids"].get(column))] or \
                list(NA_TEXT)
            fits[k] += cells[column].isin(allowed).to_numpy()
        fits[k] += kinds.isin(list(task["output_type"])).to_numpy()
    full = fits == len(columns) + 1
    owner = np.where(full.any(axis=0), np.argmax(full, axis=0), -1)
    unmatched = np.flatnonzero(owner < 0)
    if unmatched.size:
        row = int(unmatched[0])
        closest = model_tasks[int(np.argmax(fits[:, row]))]
        typed = _typed_columns(frame.iloc[[row]], closest, source)   # raises for a broken rule
        _cell_errors(typed, {name: _row_schema(closest, name)
                             for name in closest["output_type"]}, source)
        raise HubValidationError(f"{source} row {row + 2}: "
                                 f"{frame.iloc[row][columns].to_dict()} fits no model task "
                                 "of the round")
    return owner


def _typed_frame(parts: list[pd.DataFrame], model_tasks: list[Mapping[str, Any]]
                 ) -> pd.DataFrame:
    """The model tasks' typed rows in the file's order; an integer task id that some task
    leaves NA (a peak target's horizon) as pandas' nullable ``Int64``."""
    typed = pd.concat(parts).sort_index()
    ints: set[str] = set().union(*(_int_task_ids(t) for t in model_tasks))
    for column in ints & set(typed.columns):
        cells = typed[column]
        typed[column] = cells.astype(np.int64) if cells.notna().all() else cells.astype("Int64")
    return typed.reset_index(drop=True)


