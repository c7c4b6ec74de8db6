"""Writing a backtest: the published forecast of every origin in hub format, the scores, the
weights and the summary.

``forecasts/<origin>-published.csv`` (hub-format rows of every place, with a ``place`` column
when the panel has more than one), ``scores.csv`` (one row per scored cell × target ×
forecaster), ``weights.csv`` (the published combination's weights) and ``summary.json``
(:meth:`~pipeline.backtest.result.BacktestResult.summary` and the caller's extras), each
written atomically.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.backtest.result import BacktestResult, QuantileForecast
from pipeline.combine.combiner import PUBLISHED
from pipeline.io import atomic_write_json, atomic_write_text
from pipeline.panels.quantiles import long_frame
from pipeline.panels.targets import DAYS_PER_WEEK, SHARE, format_level

HUB_COLUMNS = ("origin_date", "target", "horizon", "target_end_date", "output_type",
               "output_type_id", "value")


def hub_frame(forecast: QuantileForecast, population: int) -> pd.DataFrame:
    """Hub-format rows (:data:`HUB_COLUMNS`) of a forecast: quantiles of each target, and the
    sample paths' I and weekly counts (N·I, ``population`` N) when it has paths."""
    origin = forecast.origin
    level_ids = [format_level(lv) for lv in forecast.levels]
    frames = [long_frame(values, {"horizon": forecast.horizons, "output_type_id": level_ids}
                         ).assign(target=target, output_type="quantile")
              for target, values in forecast.values.items()]
    if forecast.paths is not None:
        i_paths = forecast.paths[:, :, 1].T                                  # (H, n)
        sample_ids = np.arange(i_paths.shape[1]).astype(str)
        frames += [long_frame(i_paths if target == SHARE else i_paths * population,
                              {"horizon": forecast.horizons, "output_type_id": sample_ids}
                              ).assign(target=target, output_type="sample")
                   for target in forecast.values]
    frame = pd.concat(frames, ignore_index=True)
    frame["origin_date"] = str(origin.date())
    frame["target_end_date"] = [str((origin + pd.Timedelta(days=DAYS_PER_WEEK * int(h))).date())
                                for h in frame["horizon"]]
    return frame[list(HUB_COLUMNS)]


def _csv(frame: pd.DataFrame) -> str:
    return frame.to_csv(index=False, float_format="%.10g", lineterminator="\n")


def write_backtest(result: BacktestResult, out_dir: str | Path,
                   extra: dict[str, Any] | None = None) -> list[Path]:
    """``forecasts/<origin>-published.csv``, ``scores.csv``, ``weights.csv``, ``summary.json``
    (module docstring)."""
    root = Path(out_dir)
    written = []
    published = result.quantiles(result.panel.count_target, PUBLISHED)
    for origin in result.origins:
        made = np.asarray(np.isfinite(published.at(origin=origin)).all(axis=(1, 2)),
                          dtype=bool)                                            # (C,)
        frames = [hub_frame(result.forecast_at(place, origin, PUBLISHED), int(population))
                  .assign(place=place)
                  for place, population, ok in zip(result.places, result.populations, made)
                  if ok]
        if not frames:
            continue
        frame = pd.concat(frames, ignore_index=True)
        if len(result.places) == 1:
            frame = frame.drop(columns="place")
        path = root / "forecasts" / f"{origin.date()}-published.csv"
        atomic_write_text(path, _csv(frame))
        written.append(path)
    scores = result.scores().copy()
    for col in ("origin_date", "target_end_date"):
        scores[col] = pd.to_datetime(scores[col]).dt.date.astype(str)
    atomic_write_text(root / "scores.csv", _csv(scores))
    atomic_write_text(root / "weights.csv", _csv(result.weights_frame()))
    atomic_write_json(root / "summary.json", {**result.summary(), **(extra or {})})
    return written + [root / "scores.csv", root / "weights.csv", root / "summary.json"]
