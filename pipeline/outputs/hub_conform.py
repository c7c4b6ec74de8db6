"""A round made to follow its hub's ``tasks.json`` before it is written: the config, not the
product's constants, decides (:mod:`pipeline.outputs.hub_tasks`).

* **Rounds**: a reference date the hub lists no round for (FluSight off season) is
  :class:`NoHubRoundError`: no file, said by name (the flow ends with rc 0).
* **Sample count**: of more paths than the hub takes, the first ``min_samples_per_task``
  sample ids of each compound task are kept (the paths are exchangeable draws).
* What the hub does not ask for (a target, a horizon, too few samples) is not mended here:
  the validator refuses it by name.
* **Value type**: ``integer`` values (FluSight's admission samples) are rounded to whole counts.
* **Bounds**: a value above the declared maximum (an ED share above 1) is set to it and counted
  in the notes: the hub's bound is the target's units (a share is at most 1). A value below
  the minimum (a negative count) is an error the writer refuses, not a unit.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.outputs.hub_tasks import (HubValidationError, describe_rounds, has_round,
                                        hub_round_ids, output_rules, target_model_task)


class NoHubRoundError(HubValidationError):
    """The hub takes no round for this reference date (FluSight off season); ``reference``:
    the round the data would have served, where one is known."""

    def __init__(self, message: str, reference: dt.date | None = None) -> None:
        super().__init__(message)
        self.reference = reference


@dataclass(frozen=True)
class ConformedRound:
    """The round as the hub asks for it, and what was changed or left out to get there."""

    frame: pd.DataFrame
    notes: tuple[str, ...]


def require_round(tasks: Mapping[str, Any], reference: pd.Timestamp, hub: str = "the hub"
                  ) -> None:
    """Raise :class:`NoHubRoundError` when ``hub`` takes no round for ``reference``."""
    day = pd.Timestamp(reference).date()
    if not has_round(tasks, day):
        raise no_round_error(hub, day, hub_round_ids(tasks))


def no_round_error(hub: str, reference: dt.date, rounds: Sequence[str]) -> NoHubRoundError:
    """What is said when ``hub`` (whose rounds are ``rounds``) takes no round for
    ``reference``."""
    return NoHubRoundError(f"{hub} takes no round for the reference date {reference} "
                           f"({describe_rounds(rounds)}): no round written", reference)


def conform_round(frame: pd.DataFrame, tasks: Mapping[str, Any]) -> ConformedRound:
    """``frame`` (one reference date, long hubverse format) following ``tasks`` (module
    docstring)."""
    reference = pd.Timestamp(frame["reference_date"].iloc[0])
    require_round(tasks, reference)
    notes: list[str] = []
    parts = []
    for target, part in frame.groupby("target", sort=False):
        model_task = target_model_task(tasks, reference.date(), str(target))
        # a target the hub has no task for is left to the validator to refuse by name
        parts.append(part if model_task is None else
                     _conform_target(part, str(target), model_task, notes))
    return ConformedRound(pd.concat(parts, ignore_index=True), tuple(notes))


def _conform_target(part: pd.DataFrame, target: str, model_task: Mapping[str, Any],
                    notes: list[str]) -> pd.DataFrame:
    rules = output_rules(model_task)
    if rules.n_samples is not None:
        part = _thinned_samples(part, target, rules.n_samples)
    part = part.copy()
    values = part["value"].to_numpy(dtype=np.float64).copy()
    for kind, rule in rules.values.items():
        rows = (part["output_type"] == kind).to_numpy()
        if rule.maximum is not None:
            high = float(rule.maximum)
            beyond = rows & np.isfinite(values) & (values > high)
            if beyond.any():
                notes.append(f"{target}: {int(beyond.sum())} {kind} values above the hub's "
                             f"bound {high:g} (the largest {values[beyond].max():.6g}) set to it")
                values[beyond] = high
        if rule.integer:
            values[rows] = np.round(values[rows])
    part["value"] = values
    return part


def _thinned_samples(part: pd.DataFrame, target: str, n_samples: int) -> pd.DataFrame:
    """The first ``n_samples`` sample ids of each location (the compound task of one round
    and target), every horizon of a kept id kept."""
    sample = (part["output_type"] == "sample").to_numpy()
    if not sample.any():
        return part
    ids = part.loc[sample, ["location", "output_type_id"]].astype(str)
    unique = ids.drop_duplicates()
    unique = unique.assign(_rank=unique.groupby("location", sort=False).cumcount().to_numpy())
    rank = ids.merge(unique, on=["location", "output_type_id"], how="left")["_rank"] \
        .to_numpy()
    keep = np.ones(len(part), dtype=bool)
    keep[np.flatnonzero(sample)] = rank < n_samples
    return part[keep]
