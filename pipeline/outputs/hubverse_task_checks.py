"""A model-output file's rules that span rows, per model task of a hub's ``tasks.json``: the
required task-id values of required output types, ``target_end_date = reference_date +
7·horizon``, no duplicated row, complete non-decreasing quantile sets, complete pmfs summing
to 1, ``min``/``max_samples_per_task`` per ``compound_taskid_set`` with a sample id owned by one
compound task and covering each of its tasks. Vectorized over rows (codes per task, bincount);
each check raises :class:`~pipeline.outputs.hub_tasks.HubValidationError` naming the file, the
row or the task, and the rule. Called by :mod:`pipeline.outputs.hubverse_validation`.
"""
from __future__ import annotations

from collections.abc import Hashable, Mapping
from typing import Any

import numpy as np
import pandas as pd

from pipeline.outputs.hub_tasks import HubValidationError, task_values

_QUANTILE_TOL = 1e-12


def _task_values(spec: Mapping[str, Any] | None) -> list[Any]:
    return task_values(spec)


def file_row(frame: pd.DataFrame, position: int) -> int:
    """The file's row number (header = 1) of the frame's ``position``-th row."""
    return int(frame.index[position]) + 2


def check_required_values(frame: pd.DataFrame, model_task: Mapping[str, Any],
                           source: object) -> None:
    """A task id's required values are all present for each output type the hub requires
    (hubverse: required task-id values × required output types must be submitted)."""
    for kind, spec in model_task["output_type"].items():
        if not spec.get("is_required"):
            continue
        rows = frame[(frame["output_type"] == kind).to_numpy()]
        for column, values in model_task["task_ids"].items():
            wanted = list((values or {}).get("required") or [])
            absent = sorted({str(v) for v in wanted} - set(rows[column].astype(str)))
            if absent:
                raise HubValidationError(f"{source}: {kind} rows of the task "
                                         f"{_target_of(model_task)} lack the required "
                                         f"{column} values {absent}")


def _target_of(model_task: Mapping[str, Any]) -> str:
    return "/".join(str(v) for v in _task_values(model_task["task_ids"].get("target"))) or "?"


def check_dates(frame: pd.DataFrame, source: object) -> None:
    """``target_end_date = reference_date + 7·horizon`` where a row has both (a step-ahead
    target; the peak targets have neither)."""
    if not {"reference_date", "target_end_date", "horizon"} <= set(frame.columns):
        return
    dated = frame["horizon"].notna().to_numpy() & frame["target_end_date"].notna().to_numpy()
    if not dated.any():
        return
    part = frame[dated]
    ref = pd.to_datetime(part["reference_date"])
    end = pd.to_datetime(part["target_end_date"])
    bad = ((end - ref).dt.days != 7 * part["horizon"].astype(int)).to_numpy()
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise HubValidationError(f"{source} row {file_row(part, k)}: target_end_date "
                                 f"{part['target_end_date'].iloc[k]} is not reference_date "
                                 f"{part['reference_date'].iloc[k]} + 7·horizon "
                                 f"({part['horizon'].iloc[k]})")


_PMF_TOL = 1e-6      # a pmf's probabilities, written to 8 significant digits, sum to 1


def check_pmfs(frame: pd.DataFrame, model_task: Mapping[str, Any], source: object) -> None:
    """Every pmf task has each required category and its probabilities sum to 1."""
    spec = model_task["output_type"]["pmf"]["output_type_id"]
    required = [str(v) for v in spec.get("required") or []]
    p = frame[(frame["output_type"] == "pmf").to_numpy()]
    if p.empty:
        return
    task = _task_codes(p)
    ids = p["output_type_id"].astype(str).to_numpy()
    n_required = np.bincount(task, weights=np.isin(ids, required).astype(np.float64),
                             minlength=task.max() + 1)
    short = np.flatnonzero(n_required < len(required))
    if short.size:
        rows = task == short[0]
        absent = [c for c in required if c not in set(ids[rows])]
        label = _task_label(p, tuple(p[rows].iloc[0][task_id_columns(p)]))
        raise HubValidationError(f"{source}: pmf task {label} lacks the categories {absent}")
    total = np.bincount(task, weights=p["value"].to_numpy(dtype=np.float64))
    off = np.flatnonzero(np.abs(total - 1.0) > _PMF_TOL)
    if off.size:
        rows = task == off[0]
        label = _task_label(p, tuple(p[rows].iloc[0][task_id_columns(p)]))
        raise HubValidationError(f"{source}: pmf task {label} sums to {total[off[0]]:.8g}, "
                                 "not 1")


def task_id_columns(frame: pd.DataFrame) -> list[str]:
    return [c for c in frame.columns if c not in ("output_type", "output_type_id", "value")]


def check_duplicates(frame: pd.DataFrame, source: object) -> None:
    keys = [*task_id_columns(frame), "output_type", "output_type_id"]
    dup = frame.duplicated(subset=keys, keep=False).to_numpy()
    if dup.any():
        row = int(np.flatnonzero(dup)[0])
        raise HubValidationError(f"{source} row {file_row(frame, row)}: duplicated row "
                                 f"{frame.iloc[row][keys].to_dict()}")


def _task_codes(frame: pd.DataFrame) -> np.ndarray:
    """One integer per distinct task (the task-id columns' values)."""
    return frame.groupby(task_id_columns(frame), sort=False, dropna=False).ngroup() \
        .to_numpy(dtype=np.int64)


def check_quantile_sets(frame: pd.DataFrame, model_task: Mapping[str, Any],
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
        label = _task_label(frame, tuple(q[rows].iloc[0][task_id_columns(frame)]))
        raise HubValidationError(f"{source}: quantile task {label} lacks the levels {absent} "
                                 f"(incomplete quantile set: {len(found)} of {len(levels)})")
    order = np.lexsort((level, task))
    values = q["value"].to_numpy(dtype=np.float64)[order]
    same_task = task[order][1:] == task[order][:-1]
    falling = same_task & (np.diff(values) < -_QUANTILE_TOL)
    if falling.any():
        first = q.iloc[order[int(np.flatnonzero(falling)[0])]]
        label = _task_label(frame, tuple(first[task_id_columns(frame)]))
        raise HubValidationError(f"{source}: quantile task {label} has values that decrease as "
                                 "the level rises (crossing quantiles)")


def check_sample_counts(frame: pd.DataFrame, model_task: Mapping[str, Any],
                         source: object) -> None:
    params = model_task["output_type"]["sample"]["output_type_id_params"]
    samples = frame[(frame["output_type"] == "sample").to_numpy()]
    if samples.empty:
        return
    compound = list(params.get("compound_taskid_set") or task_id_columns(frame))
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
    per_task = samples.assign(_id=ids).groupby(task_id_columns(frame), sort=True)["_id"] \
        .nunique().rename("_count").reset_index()
    expected = per_compound.rename("_want").reset_index()
    check = per_task.merge(expected, on=compound, how="left")
    wrong = check[check["_count"] != check["_want"]]
    if not wrong.empty:
        row = wrong.iloc[0]
        label = _task_label(frame, tuple(row[task_id_columns(frame)]))
        raise HubValidationError(f"{source}: sample task {label} has {int(row['_count'])} "
                                 f"samples, its compound task has {int(row['_want'])}: each "
                                 "sample must cover every target and horizon")


def _as_tuple(key: Hashable) -> tuple[Hashable, ...]:
    """A groupby key as a tuple (pandas gives a scalar when grouping by one column)."""
    return key if isinstance(key, tuple) else (key,)


def _task_label(frame: pd.DataFrame, task: Hashable) -> str:
    names = task_id_columns(frame)
    return ", ".join(f"{n}={v}" for n, v in zip(names, _as_tuple(task), strict=True))
