"""What a hub's ``tasks.json`` asks of a round, read for the writer (no Prefect, no torch).

A hubverse ``tasks.json`` holds round definitions, each with model tasks (a set of task-id
values, e.g. one target, and the output types it takes). The round writer follows it rather
than the product's constants: which rounds exist (FluSight has none off season), the sample
count of a target (``min``/``max_samples_per_task``), whether its values are ``integer``, and
their bounds (a share is at most 1). The validator (:mod:`pipeline.outputs.hubverse_validation`)
checks a file against the same config.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pipeline.errors import FlowcastError

NA_TEXT = ("", "NA")          # how a task id without a value is written in a hubverse CSV
# A hub's tasks.json is tens of KB (FluSight's 44 KB) and nested about a dozen levels: a file
# past these bounds is refused before it is parsed (issue 49: a 300 MB one held the round past
# 15 minutes; a deeply nested one crashed the parser with RecursionError).
MAX_TASKS_BYTES = 4 << 20
MAX_TASKS_DEPTH = 64


class HubFormatError(FlowcastError):
    """A forecast or a hub file that does not meet the hub format (levels, NaN, dates...)."""


class HubValidationError(HubFormatError):
    """A model-output file that breaks the hub's ``tasks.json`` rules (names file, row, rule)."""


def task_values(spec: Mapping[str, Any] | None) -> list[Any]:
    """A task id's (or output-type id's) allowed values: required, then optional."""
    if not spec:
        return []
    return list(spec.get("required") or []) + list(spec.get("optional") or [])


def round_id_column(round_def: Mapping[str, Any]) -> str | None:
    """The task id naming a round (``reference_date``) when rounds are read from a variable."""
    return str(round_def["round_id"]) if round_def.get("round_id_from_variable") else None


def round_ids(round_def: Mapping[str, Any]) -> list[str]:
    """Every round id a round definition covers (its round-id column's values)."""
    column = round_id_column(round_def)
    if column is None:
        return [str(round_def["round_id"])]
    return sorted({str(v) for task in round_def["model_tasks"]
                   for v in task_values(task["task_ids"].get(column))})


def find_round(tasks: Mapping[str, Any], round_id: str) -> Mapping[str, Any] | None:
    """The round definition holding ``round_id`` (a reference date as ``YYYY-MM-DD``)."""
    for round_def in tasks.get("rounds") or []:
        if round_id in round_ids(round_def):
            return round_def
    return None


def hub_round_ids(tasks: Mapping[str, Any]) -> list[str]:
    """Every round id of the hub, sorted."""
    return sorted({r for round_def in tasks.get("rounds") or [] for r in round_ids(round_def)})


def has_round(tasks: Mapping[str, Any], reference_date: dt.date) -> bool:
    """Does the hub take a round for ``reference_date``? (FluSight: only in season.)"""
    return find_round(tasks, reference_date.isoformat()) is not None


def target_model_task(tasks: Mapping[str, Any], reference_date: dt.date,
                      target: str) -> Mapping[str, Any] | None:
    """The model task of ``target`` in the round of ``reference_date`` (None: not asked)."""
    round_def = find_round(tasks, reference_date.isoformat())
    if round_def is None:
        return None
    for task in round_def["model_tasks"]:
        if target in task_values(task["task_ids"].get("target")):
            return task
    return None


@dataclass(frozen=True)
class ValueRule:
    """One output type's values: ``integer`` or ``double``, and their bounds."""

    integer: bool
    minimum: float | None
    maximum: float | None


@dataclass(frozen=True)
class OutputRules:
    """What one target's model task asks: its output types, the value rule of each, the sample
    count per compound task (None: no samples), its compound task ids, and its horizons."""

    output_types: tuple[str, ...]
    values: Mapping[str, ValueRule]
    n_samples: int | None
    compound: tuple[str, ...]
    horizons: tuple[int, ...]
    output_type_ids: Mapping[str, tuple[Any, ...]]


def output_rules(model_task: Mapping[str, Any]) -> OutputRules:
    """A model task's rules (:class:`OutputRules`). The sample count is the least the hub
    takes (``min_samples_per_task``): every path beyond it would be dropped or refused."""
    kinds = model_task["output_type"]
    values = {kind: ValueRule(integer=spec["value"]["type"] == "integer",
                              minimum=spec["value"].get("minimum"),
                              maximum=spec["value"].get("maximum"))
              for kind, spec in kinds.items()}
    n_samples, compound = None, ()
    if "sample" in kinds:
        params = kinds["sample"]["output_type_id_params"]
        n_samples = int(params.get("min_samples_per_task", params.get("max_samples_per_task",
                                                                      1)))
        compound = tuple(params.get("compound_taskid_set") or ())
    ids = {kind: tuple(task_values(spec.get("output_type_id")))
           for kind, spec in kinds.items() if "output_type_id" in spec}
    horizons = tuple(int(h) for h in task_values(model_task["task_ids"].get("horizon")))
    return OutputRules(tuple(kinds), values, n_samples, compound, horizons, ids)


def describe_rounds(ids: Sequence[str]) -> str:
    """The hub's rounds in a message: how many, the first and the last."""
    if not ids:
        return "the hub lists no round"
    return f"{len(ids)} rounds, {ids[0]} … {ids[-1]}"
