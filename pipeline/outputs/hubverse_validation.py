"""A hubverse model-output file checked against its hub's ``tasks.json`` (no Prefect, no torch).

The validator (:func:`validate_model_output`) is generic over a hubverse v5 ``tasks.json`` of one
round definition and one model task: allowed task-id values (targets, horizons, locations, dates),
output types, quantile levels and sample-id text, finite values within the declared bounds,
``target_end_date = reference_date + 7·horizon``, complete non-decreasing quantile sets, sample
counts per compound task, sample ids owned by one compound task, no duplicated row. It works
column by column (each distinct task-id value checked once, values vectorized), so a round of
118,000 rows validates in well under a second.

The writers (:mod:`pipeline.outputs.hubverse`, :mod:`pipeline.outputs.hubverse_round`) validate
the text they are about to write here, so a refused file never replaces a good one.
"""
from __future__ import annotations

import io
import json
import os
import re
from collections.abc import Hashable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.errors import FlowcastError

_QUANTILE_TOL = 1e-12


class HubFormatError(FlowcastError):
    """A forecast or a hub file that does not meet the hub format (levels, NaN, dates...)."""



class HubValidationError(HubFormatError):
    """A model-output file that breaks the hub's ``tasks.json`` rules (names file, row, rule)."""


def load_tasks_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise HubValidationError(f"cannot read the hub tasks config {path}: {exc}") from exc


def frame_from_text(text: str, source: object) -> pd.DataFrame:
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
