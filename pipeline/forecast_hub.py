"""Hub-format forecast files (COVID-19 Forecast Hub / hubverse model-output CSV).

One row per (target, horizon, output type, output type id)::

    reference_date, target, horizon, target_end_date, location, output_type, output_type_id, value

* ``reference_date``: the forecast's reference date (ISO date) — the last day of data used.
* ``target``: ``"S prop"``, ``"I prop"``, ``"R prop"`` — the SIR compartment as a proportion of
  the population (our model's unit; not an incidence count).
* ``horizon``: weeks ahead, 1–4; ``target_end_date = reference_date + 7·horizon`` days.
* ``location``: ``"06075"`` (San Francisco County FIPS code), as hubverse uses FIPS strings.
* ``output_type = "quantile"``: ``output_type_id`` is the quantile level, one of the 23 standard
  levels (0.01, 0.025, 0.05, 0.10, …, 0.95, 0.975, 0.99); quantiles are computed from all sample
  paths by linear interpolation (Hyndman–Fan type 7).
* ``output_type = "sample"``: ``output_type_id`` is the sample index ``0..199``; the same index
  across targets and horizons is the same joint trajectory (hubverse "compound task id set"
  = {target, horizon}). The first 200 paths are kept: paths are i.i.d., so any 200 are as good.

``output_type_id`` is written as text (quantile levels as ``0.025``, sample ids as ``17``) as
hubverse does for mixed output types.
"""
from __future__ import annotations

import datetime as dt
import io
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from pipeline.errors import FlowcastError
from pipeline.io import atomic_write_text, sha256_bytes
from pipeline.scoring import quantiles_from_samples

HUB_QUANTILE_LEVELS: tuple[float, ...] = (
    0.01, 0.025, 0.05, 0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50,
    0.55, 0.60, 0.65, 0.70, 0.75, 0.80, 0.85, 0.90, 0.95, 0.975, 0.99,
)
HUB_COLUMNS: tuple[str, ...] = ("reference_date", "target", "horizon", "target_end_date",
                                "location", "output_type", "output_type_id", "value")
SF_COUNTY_FIPS = "06075"
COMPARTMENTS: tuple[str, ...] = ("S", "I", "R")
_QUANTILE_TOL = 1e-12


class HubFormatError(FlowcastError):
    """Forecast samples or a hub CSV that do not meet the hub format (levels, NaN, dates...)."""


@dataclass(frozen=True)
class HubConfig:
    """What to write: horizons in weeks, number of sample paths, levels, location."""

    horizons_weeks: tuple[int, ...] = (1, 2, 3, 4)
    n_sample_paths: int = 200
    quantile_levels: tuple[float, ...] = HUB_QUANTILE_LEVELS
    location: str = SF_COUNTY_FIPS


def target_name(compartment: str) -> str:
    return f"{compartment} prop"


def _format_level(level: float) -> str:
    return f"{level:.3f}".rstrip("0").rstrip(".")


def _horizon_indices(dates: pd.DatetimeIndex, reference_date: pd.Timestamp,
                     horizons_weeks: Sequence[int]) -> tuple[np.ndarray, list[pd.Timestamp]]:
    ends = [reference_date + pd.Timedelta(days=7 * h) for h in horizons_weeks]
    position = {d: i for i, d in enumerate(dates)}
    missing = [e.date().isoformat() for e in ends if e not in position]
    if missing:
        raise HubFormatError(f"sample paths cover {dates[0].date()}..{dates[-1].date()} but the "
                             f"target end dates {missing} (reference {reference_date.date()} + "
                             f"7·horizon days) are not among them")
    return np.array([position[e] for e in ends]), ends


def hub_forecast_frame(samples: ArrayLike, dates: Sequence[dt.date] | pd.DatetimeIndex,
                       reference_date: dt.date, config: HubConfig = HubConfig()) -> pd.DataFrame:
    """Quantile and sample rows for S, I, R from paths ``samples (n, horizon_days, 3)``.

    ``dates (horizon_days,)`` are the daily dates of the path's steps (after the reference
    date); the value at ``reference_date + 7h`` is the h-week-ahead forecast.
    """
    paths = np.asarray(samples, dtype=np.float64)
    if paths.ndim != 3 or paths.shape[2] != len(COMPARTMENTS):
        raise HubFormatError(f"samples must have shape (n_samples, horizon_days, 3) for S, I, R; "
                             f"got {paths.shape}")
    if not np.all(np.isfinite(paths)):
        bad = int(np.sum(~np.isfinite(paths)))
        raise HubFormatError(f"samples contain {bad} NaN/inf values; refusing to write a forecast")
    if paths.shape[0] < config.n_sample_paths:
        raise HubFormatError(f"{config.n_sample_paths} sample paths required, got {paths.shape[0]}")
    index = pd.DatetimeIndex(pd.to_datetime(list(dates))).normalize()
    if len(index) != paths.shape[1]:
        raise HubFormatError(f"{len(index)} dates for {paths.shape[1]} path steps")
    ref = pd.Timestamp(reference_date).normalize()
    steps, ends = _horizon_indices(index, ref, config.horizons_weeks)

    at_horizons = paths[:, steps, :]                                   # (n, H, 3)
    levels = np.asarray(config.quantile_levels)
    quantiles = quantiles_from_samples(np.moveaxis(at_horizons, 0, -1), levels)  # (H, 3, Q)
    kept = at_horizons[: config.n_sample_paths]                        # (n_keep, H, 3)

    n_h, n_c, n_q, n_s = len(steps), len(COMPARTMENTS), levels.size, kept.shape[0]
    h_grid = np.asarray(config.horizons_weeks)
    end_strings = np.array([e.date().isoformat() for e in ends])
    targets = np.array([target_name(c) for c in COMPARTMENTS])
    quantile_rows = pd.DataFrame({
        "horizon": np.repeat(h_grid, n_c * n_q),
        "target_end_date": np.repeat(end_strings, n_c * n_q),
        "target": np.tile(np.repeat(targets, n_q), n_h),
        "output_type": "quantile",
        "output_type_id": np.tile([_format_level(lv) for lv in levels], n_h * n_c),
        "value": quantiles.reshape(-1),
    })
    sample_values = np.transpose(kept, (1, 2, 0))                      # (H, 3, n_keep)
    sample_rows = pd.DataFrame({
        "horizon": np.repeat(h_grid, n_c * n_s),
        "target_end_date": np.repeat(end_strings, n_c * n_s),
        "target": np.tile(np.repeat(targets, n_s), n_h),
        "output_type": "sample",
        "output_type_id": np.tile(np.arange(n_s).astype(str), n_h * n_c),
        "value": sample_values.reshape(-1),
    })
    frame = pd.concat([quantile_rows, sample_rows], ignore_index=True)
    frame["reference_date"] = ref.date().isoformat()
    frame["location"] = config.location
    frame = frame[list(HUB_COLUMNS)]
    validate_hub_frame(frame, config)
    return frame


def validate_hub_frame(frame: pd.DataFrame, config: HubConfig = HubConfig()) -> None:
    """Raise ``HubFormatError`` naming the first problem: columns, NaN, levels, monotonicity."""
    missing = [c for c in HUB_COLUMNS if c not in frame.columns]
    if missing:
        raise HubFormatError(f"hub frame lacks columns {missing}")
    if frame[list(HUB_COLUMNS)].isna().any().any():
        cols = [c for c in HUB_COLUMNS if frame[c].isna().any()]
        raise HubFormatError(f"hub frame has missing values in columns {cols}")
    bad_types = sorted(set(frame["output_type"]) - {"quantile", "sample"})
    if bad_types:
        raise HubFormatError(f"unknown output_type values {bad_types}")
    ref = pd.to_datetime(frame["reference_date"])
    end = pd.to_datetime(frame["target_end_date"])
    wrong_end = (end - ref).dt.days.to_numpy() != 7 * frame["horizon"].astype(int).to_numpy()
    if wrong_end.any():
        row = frame.loc[wrong_end].iloc[0]
        raise HubFormatError(f"target_end_date {row['target_end_date']} is not reference_date "
                             f"{row['reference_date']} + 7·horizon ({row['horizon']})")
    q = frame[frame["output_type"] == "quantile"].copy()
    q["level"] = q["output_type_id"].astype(float)
    expected = np.asarray(config.quantile_levels)
    for (target, horizon), group in q.groupby(["target", "horizon"], sort=False):
        group = group.sort_values("level")
        levels = group["level"].to_numpy()
        if levels.size != expected.size or np.any(np.abs(levels - expected) > 1e-9):
            raise HubFormatError(f"{target} horizon {horizon}: quantile levels "
                                 f"{levels.tolist()} differ from the {expected.size} standard ones")
        if np.any(np.diff(group["value"].to_numpy()) < -_QUANTILE_TOL):
            raise HubFormatError(f"{target} horizon {horizon}: quantile values decrease with the "
                                 f"level (crossing quantiles)")


def hub_csv_text(frame: pd.DataFrame) -> str:
    buffer = io.StringIO()
    frame.to_csv(buffer, index=False, float_format="%.8g", lineterminator="\n")
    return buffer.getvalue()


def write_hub_csv(frame: pd.DataFrame, path: str | os.PathLike[str],
                  config: HubConfig = HubConfig()) -> str:
    """Validate and write the CSV atomically; return its sha256."""
    validate_hub_frame(frame, config)
    text = hub_csv_text(frame)
    atomic_write_text(path, text)
    return sha256_bytes(text.encode("utf-8"))


def read_hub_csv(path: str | os.PathLike[str], config: HubConfig = HubConfig()) -> pd.DataFrame:
    """Read and validate a hub CSV (``output_type_id`` and ``location`` stay text)."""
    try:
        frame = pd.read_csv(path, dtype={"output_type_id": str, "location": str,
                                         "reference_date": str, "target_end_date": str})
    except (OSError, pd.errors.ParserError) as exc:
        raise HubFormatError(f"cannot read hub CSV {path}: {exc}") from exc
    validate_hub_frame(frame, config)
    return frame
