"""A round of a hubverse hub of many locations, such as the CDC COVID-19 Forecast Hub: its
model-output file and model metadata, validated before they are written (no Prefect, no torch).

The CDC hub has 53 locations, the targets ``wk inc covid hosp`` and ``wk inc covid prop ed
visits``, horizons −1..3, 23 quantiles and 200 samples per compound task {location, target}.
:func:`write_hub_round` writes a long frame in hubverse format, and its
``model-metadata/<model_id>.yml``, after validating the text it writes against the hub's own
``tasks.json`` (:mod:`pipeline.outputs.hubverse_validation`); :func:`compound_sample_ids`
numbers sample ids as that hub requires (one id per trajectory of one location and target,
shared by its horizons).
"""
from __future__ import annotations

import datetime as dt
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.io import atomic_write_text, sha256_bytes
from pipeline.outputs.hub_conform import conform_round
from pipeline.outputs.hubverse import (HUBVERSE_TASK_IDS, MODEL_OUTPUT_COLUMNS, hub_csv_text,
                                      model_output_path)
from pipeline.outputs.hubverse_validation import (HubFormatError, HubValidationError,
                                                  frame_from_text, frame_id_text,
                                                  validate_model_output_frame)
from pipeline.panels.targets import format_level

CDC_HUB_MODEL_ID = "flowcast-nfhub"   # team flowcast; the model's name is to be settled
_MODEL_ID = re.compile(r"^[A-Za-z0-9_+]+-[A-Za-z0-9_+]+$")


@dataclass(frozen=True)
class RoundFile:
    """What :func:`write_hub_round` wrote: the model-output file and its metadata file."""

    path: Path
    metadata_path: Path
    frame: pd.DataFrame
    reference_date: dt.date
    sha256: str
    notes: tuple[str, ...] = ()     # what following the hub's config changed or left out


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
        # a peak target has no horizon: NA, written as an empty cell
        "horizon": pd.to_numeric(frame["horizon"]).astype("Int64").to_numpy(dtype=object),
        "location": frame["location"].astype(str).to_numpy(),
        "target_end_date": dates["target_end_date"].to_numpy(),
        "output_type": kind, "output_type_id": text, "value": values})
    out["_kind"] = np.where(quantile, 0, 1)
    out["_level"] = np.where(quantile, levels, 0.0)
    out = out.sort_values(["_kind", "target", "location", "horizon", "_level"], kind="stable")
    return out.drop(columns=["_kind", "_level"]).reset_index(drop=True)


# the models' hubverse metadata (flowcast-nfhub, flowcast-nfens), shipped with the package so
# that a plain `pip install .` publishes
MODEL_METADATA_DIR = Path(__file__).resolve().parent / "model_metadata"


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

    The round first follows the hub's config (:func:`~pipeline.outputs.hub_conform.
    conform_round`: no file for a date the hub has no round for, its sample count, integer
    values, bounds); the file's text is validated against the hub's ``tasks`` (and the
    metadata against ``metadata_schema``) before anything is written; both files are then replaced atomically,
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
    conformed = conform_round(frame, tasks)
    text = hub_csv_text(_round_text_frame(conformed.frame, path))
    typed = validate_model_output_frame(frame_from_text(text, path), tasks, source=path)
    validate_model_metadata(metadata, model_id, metadata_schema)
    metadata_path = Path(hub_dir) / "model-metadata" / f"{model_id}.yml"
    atomic_write_text(path, text)
    atomic_write_text(metadata_path, yaml.safe_dump(dict(metadata), sort_keys=False,
                                                    allow_unicode=True, width=100))
    return RoundFile(path=path, metadata_path=metadata_path, frame=typed,
                     reference_date=reference_date, sha256=sha256_bytes(text.encode("utf-8")),
                     notes=conformed.notes)
