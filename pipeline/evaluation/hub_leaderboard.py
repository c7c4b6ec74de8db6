"""A forecast hub's teams scored: every quantile forecast's WIS and interval coverage against
the observed target data, and the leaderboard by pairwise relative WIS.

* WIS: :func:`pipeline.evaluation.scoring.weighted_interval_score` — with the hub's 23 levels,
  the median's absolute error (weight 1/2) and the 11 central intervals (weights α/2), divided
  by 11.5 (Bracher et al. 2021), as ``scoringutils::wis`` and the hubverse compute it.
* a forecast is scored when its week is observed in the truth frame (an inner join on
  ``target_end_date`` and ``location``); the hubs score against the latest vintage.
* the leaderboard (:func:`hub_leaderboard`): pairwise relative WIS
  (:mod:`pipeline.evaluation.pairwise`) over the forecasts that :class:`LeaderboardConfig`
  keeps, scaled by the hub's baseline.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pandas as pd

from pipeline.data.hub.team_forecasts import TASK_COLUMNS, QuantileTable
from pipeline.errors import ConfigError, FlowcastError
from pipeline.evaluation.pairwise import pairwise_comparison
from pipeline.evaluation.scoring import interval_coverage, weighted_interval_score

US = "US"
# The horizons the hub scores (−1, the week still being reported, is submitted but not scored)
SCORED_HORIZONS: tuple[int, ...] = (0, 1, 2, 3)
SCORE_COLUMNS: tuple[str, ...] = (*TASK_COLUMNS, "observed", "wis", "dispersion",
                                  "overprediction", "underprediction", "coverage_50",
                                  "coverage_95")
FORECAST_UNIT: tuple[str, ...] = ("reference_date", "target", "horizon", "location",
                                  "target_end_date")


class LeaderboardError(FlowcastError):
    """Scores or a truth frame that cannot make a leaderboard (columns, no forecast left)."""


def score_quantile_forecasts(table: QuantileTable, truth: pd.DataFrame) -> pd.DataFrame:
    """WIS (and its parts) and 50 % / 95 % coverage (1.0 or 0.0; NaN when the levels lack the
    interval) of every forecast of ``table`` whose week ``truth`` (``target_end_date, location,
    value``; with a ``target`` column, matched on it too) observes; one row per forecast,
    :data:`SCORE_COLUMNS`."""
    keys = ["target_end_date", "location"] + (["target"] if "target" in truth.columns else [])
    missing = [c for c in [*keys, "value"] if c not in truth.columns]
    if missing:
        raise LeaderboardError(f"truth frame lacks the columns {missing} (has "
                               f"{list(truth.columns)})")
    observed = truth[[*keys, "value"]].rename(columns={"value": "observed"})
    observed = observed.assign(target_end_date=pd.to_datetime(observed["target_end_date"])
                               .astype("datetime64[s]"),
                               location=observed["location"].astype(str))
    if observed.duplicated(keys).any():
        raise LeaderboardError(f"truth frame has more than one value for some {keys}: pass one "
                               "vintage")
    tasks = table.tasks.assign(_row=np.arange(len(table.tasks)))
    tasks = tasks.astype({k: str for k in keys if k != "target_end_date"})
    joined = tasks.merge(observed, on=keys, how="inner", sort=False)
    rows = joined["_row"].to_numpy()
    values = table.values[rows]
    y = joined["observed"].to_numpy(dtype=np.float64)
    crossing = (np.diff(values, axis=1) < 0).any(axis=1)
    if crossing.any():
        task = table.tasks.iloc[rows[int(np.flatnonzero(crossing)[0])]].to_dict()
        raise LeaderboardError(f"forecast {task}: quantiles decrease as the level rises "
                               f"({int(crossing.sum())} forecasts cross); a hub validator "
                               "would have refused them")
    parts = weighted_interval_score(table.levels, values, y)
    scores = table.tasks.iloc[rows].reset_index(drop=True).assign(
        observed=y, wis=parts.wis, dispersion=parts.dispersion,
        overprediction=parts.overprediction, underprediction=parts.underprediction,
        coverage_50=_coverage(table.levels, values, y, 0.5),
        coverage_95=_coverage(table.levels, values, y, 0.95))
    return scores[list(SCORE_COLUMNS)]


def _coverage(levels: np.ndarray, values: np.ndarray, y: np.ndarray,
              central: float) -> np.ndarray:
    """1.0 / 0.0 whether y lies in the central interval; NaN for levels without its bounds."""
    tail = (1.0 - central) / 2.0
    if not (np.isclose(levels, tail).any() and np.isclose(levels, 1.0 - tail).any()):
        return np.full(y.shape, np.nan)
    return interval_coverage(levels, values, y, central).astype(np.float64)


@dataclass(frozen=True)
class LeaderboardConfig:
    """Which forecasts enter the tournament.

    ``locations``: ``"all"`` (US and the states), ``"states"`` (US left out) or ``"US"``;
    ``apply_exclusions``: leave out the (round, location) pairs of the hub's
    ``excluded_locations.toml``; ``complete_rounds_only``: only rounds whose every horizon's
    week is observed (else every observed forecast counts); ``models``: the tournament's
    models (None: every model in the scores)."""

    target: str = "wk inc covid hosp"
    horizons: tuple[int, ...] = SCORED_HORIZONS
    locations: Literal["all", "states", "US"] = "all"
    apply_exclusions: bool = True
    complete_rounds_only: bool = False
    baseline: str = "CovidHub-baseline"
    models: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if self.locations not in ("all", "states", "US"):
            raise ConfigError(f"LeaderboardConfig.locations={self.locations!r}: use 'all', "
                              "'states' or 'US'")
        if not self.horizons:
            raise ConfigError("LeaderboardConfig.horizons is empty")


def leaderboard_scores(scores: pd.DataFrame, config: LeaderboardConfig,
                       exclusions: pd.DataFrame | None = None) -> pd.DataFrame:
    """The rows of ``scores`` that enter the tournament under ``config``."""
    kept = scores[(scores["target"].astype(str) == config.target).to_numpy()
                  & scores["horizon"].isin(config.horizons).to_numpy()]
    location = kept["location"].astype(str)
    if config.locations == "states":
        kept = kept[(location != US).to_numpy()]
    elif config.locations == "US":
        kept = kept[(location == US).to_numpy()]
    if config.apply_exclusions and exclusions is not None and not exclusions.empty:
        pairs = exclusions.assign(reference_date=pd.to_datetime(exclusions["reference_date"])
                                  .astype("datetime64[s]"),
                                  location=exclusions["location"].astype(str), _excluded=True)
        flagged = kept[["reference_date", "location"]].astype({"location": str}).merge(
            pairs.drop_duplicates(), on=["reference_date", "location"], how="left")
        kept = kept[flagged["_excluded"].isna().to_numpy()]
    if config.complete_rounds_only:
        last_week = scores["target_end_date"].max()
        reach = kept["reference_date"] + pd.Timedelta(weeks=max(config.horizons))
        kept = kept[(reach <= last_week).to_numpy()]
    if config.models is not None:
        kept = kept[kept["model_id"].astype(str).isin(config.models).to_numpy()]
    if kept.empty:
        raise LeaderboardError(f"no forecast is left for the leaderboard under {config}")
    return kept


def hub_leaderboard(scores: pd.DataFrame, config: LeaderboardConfig = LeaderboardConfig(),
                    exclusions: pd.DataFrame | None = None,
                    by: Sequence[str] = ()) -> pd.DataFrame:
    """Pairwise relative WIS of every model (per ``by`` group, e.g. ``("horizon",)``) on the
    forecasts ``config`` keeps: ``model_id``, ``n_forecasts``, ``n_rounds``, ``mean_wis``,
    ``relative_wis`` (θ_i / θ_baseline), ``coverage_50``, ``coverage_95``; best first."""
    kept = leaderboard_scores(scores, config, exclusions)
    kept = kept.assign(model_id=kept["model_id"].astype(str))
    unit = [c for c in FORECAST_UNIT if c not in by]
    skill = pairwise_comparison(kept[[*by, "model_id", *unit, "wis"]], baseline=config.baseline,
                                by=by, unit=unit).skill
    summary = kept.groupby([*by, "model_id"], observed=True).agg(
        n_rounds=("reference_date", "nunique"), coverage_50=("coverage_50", "mean"),
        coverage_95=("coverage_95", "mean")).reset_index()
    table = skill.rename(columns={"mean_score": "mean_wis",
                                  "scaled_relative_skill": "relative_wis"})
    table = table.merge(summary, on=[*by, "model_id"], how="left")
    return table[[*by, "model_id", "n_forecasts", "n_rounds", "mean_wis", "relative_wis",
                  "coverage_50", "coverage_95"]]
