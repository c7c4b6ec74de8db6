"""Pairwise relative skill: the "pairwise tournament" of Cramer et al. 2022 (PNAS 119(15)
e2113561119), as ``scoringutils::get_pairwise_comparisons`` computes it (v2; the hubverse's
``hubEvals`` calls it for its relative WIS).

Within one group of scores (all of them, or one value of the ``by`` columns):

* θ_ij = Σ s_i / Σ s_j over the forecasts **both** models i and j made (a forecast is one value
  of the ``unit`` columns, e.g. reference_date × location × horizon): the ratio of their mean
  scores on the common forecasts. A pair with no common forecast has no θ_ij and is skipped.
* θ_i = the geometric mean of θ_ij over every model j with a common forecast, **j = i included**
  (θ_ii = 1), as scoringutils does.
* relative skill scaled by a baseline b: θ_i / θ_b (the baseline's own is 1).

A model that forecast only some horizons or locations is compared with each other model on
what they share; nothing is imputed. Scores must be finite and non-negative (WIS, CRPS, ...).
Everything is sparse-matrix algebra over (group, model) × forecast: no loop over rows or groups.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import sparse

from pipeline.errors import FlowcastError


class PairwiseError(FlowcastError):
    """Scores that cannot enter a pairwise tournament (missing columns, duplicates, NaN,
    negative scores, a baseline absent from a group, a ratio with a zero denominator)."""


@dataclass(frozen=True, eq=False)
class PairwiseComparison:
    """The tournament's results.

    ``skill``: one row per group × model: the ``by`` columns, ``model``, ``n_forecasts`` (its
    forecasts in the group), ``mean_score`` (over them), ``relative_skill`` (θ_i) and, with a
    baseline, ``scaled_relative_skill`` (θ_i / θ_baseline); sorted by group then skill.
    ``ratios``: one row per ordered pair with common forecasts (self pairs included, ratio 1):
    the ``by`` columns, ``model``, ``compare_against``, ``n_common``, ``mean_scores_ratio``.
    """

    skill: pd.DataFrame
    ratios: pd.DataFrame
    baseline: str | None
    by: tuple[str, ...]


def _check_columns(scores: pd.DataFrame, model: str, metric: str, by: Sequence[str],
                   unit: Sequence[str]) -> None:
    needed = [model, metric, *by, *unit]
    missing = [c for c in needed if c not in scores.columns]
    if missing:
        raise PairwiseError(f"pairwise comparison: score columns {missing} are missing "
                            f"(have {list(scores.columns)})")
    if not unit:
        raise PairwiseError("pairwise comparison: no forecast-unit column left to match the "
                            "models' forecasts on")
    values = scores[metric].to_numpy(dtype=np.float64)
    bad = ~np.isfinite(values) | (values < 0)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise PairwiseError(f"pairwise comparison: {metric!r} must be finite and >= 0; row {row} "
                            f"({scores.iloc[row][[model, *unit]].to_dict()}) has {values[row]}")
    keys = [*by, *unit, model]
    dup = scores.duplicated(subset=keys).to_numpy()
    if dup.any():
        row = int(np.flatnonzero(dup)[0])
        raise PairwiseError(f"pairwise comparison: more than one score for "
                            f"{scores.iloc[row][keys].to_dict()}; the forecast unit {list(unit)} "
                            "must identify one forecast of a model")


def _codes(frame: pd.DataFrame, columns: Sequence[str]) -> np.ndarray:
    """One integer per distinct combination of ``columns`` (0 for every row if there are none)."""
    if not columns:
        return np.zeros(len(frame), dtype=np.int64)
    return frame.groupby(list(columns), sort=True, observed=True, dropna=False).ngroup() \
        .to_numpy(dtype=np.int64)


def pairwise_comparison(scores: pd.DataFrame, *, baseline: str | None = None,
                        by: Sequence[str] = (), model: str = "model_id", metric: str = "wis",
                        unit: Sequence[str] | None = None) -> PairwiseComparison:
    """The pairwise tournament of ``scores`` (one row per model × forecast) in every group of
    ``by`` (module docstring).

    ``unit``: the columns that identify a forecast (default: every column but ``model``,
    ``metric`` and ``by``; pass them when the frame carries other columns, e.g. other scores).
    ``baseline``: the model that scales the relative skill; it must have scores in every group.
    """
    by = tuple(by)
    if unit is None:
        unit = [c for c in scores.columns if c not in (model, metric, *by)]
    unit = [c for c in unit if c not in by]
    _check_columns(scores, model, metric, by, unit)
    if scores.empty:
        raise PairwiseError("pairwise comparison: no scores")
    frame = scores[[*by, model, *unit, metric]].reset_index(drop=True)
    frame[model] = frame[model].astype(str)
    values = frame[metric].to_numpy(dtype=np.float64)

    # A row of the matrices is one (group, model), a column one (group, forecast): forecasts of
    # different groups never share a column, so one product holds every group's tournament as
    # diagonal blocks.
    row = _codes(frame, [*by, model])
    col = _codes(frame, [*by, *unit])
    shape = (int(row.max()) + 1, int(col.max()) + 1)
    made = sparse.csr_matrix((np.ones(len(frame)), (row, col)), shape=shape)
    scored = sparse.csr_matrix((values, (row, col)), shape=shape)
    common = (made @ made.T).tocoo()                  # n_common[i, j] > 0: a pair with overlap
    pair_i, pair_j = common.row, common.col
    sums = (scored @ made.T).tocsr()                  # Σ s_i over the forecasts j also made
    sum_i = np.asarray(sums[pair_i, pair_j]).ravel()
    sum_j = np.asarray(sums[pair_j, pair_i]).ravel()

    rows = frame[[*by, model]].assign(_row=row).drop_duplicates("_row").sort_values("_row")
    rows = rows[[*by, model]].reset_index(drop=True)
    one_zero = (sum_i == 0) != (sum_j == 0)
    if one_zero.any():
        k = int(np.flatnonzero(one_zero)[0])
        first = rows.iloc[pair_i[k]]
        group = f" in the group {first[list(by)].to_dict()}" if by else ""
        raise PairwiseError(f"pairwise comparison: {first[model]!r} against "
                            f"{rows.iloc[pair_j[k]][model]!r}{group}: one of them has a total "
                            f"{metric!r} of 0 on their {int(common.data[k])} common forecasts, "
                            "so their ratio is 0 or infinite")
    both_zero = (sum_i == 0) & (sum_j == 0)            # two perfect forecasters: no ratio (NA)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(both_zero, np.nan, sum_i / np.where(sum_j == 0, 1.0, sum_j))
    valid = ~both_zero
    log_sum = np.bincount(pair_i[valid], weights=np.log(ratio[valid]), minlength=shape[0])
    n_valid = np.bincount(pair_i[valid], minlength=shape[0])
    with np.errstate(invalid="ignore"):
        theta = np.exp(log_sum / n_valid)

    n_forecasts = np.bincount(row, minlength=shape[0])
    mean_score = np.bincount(row, weights=values, minlength=shape[0]) / n_forecasts
    skill = rows.assign(n_forecasts=n_forecasts, mean_score=mean_score, relative_skill=theta)
    if baseline is not None:
        skill["scaled_relative_skill"] = theta / _baseline_theta(skill, baseline, by, model)
    ratios = pd.concat([rows.iloc[pair_i][list(by)].reset_index(drop=True),
                        pd.DataFrame({model: rows[model].to_numpy()[pair_i],
                                      "compare_against": rows[model].to_numpy()[pair_j],
                                      "n_common": common.data.astype(np.int64),
                                      "mean_scores_ratio": ratio})], axis=1)
    order = "scaled_relative_skill" if baseline is not None else "relative_skill"
    skill = skill.sort_values([*by, order, model], kind="stable").reset_index(drop=True)
    ratios = ratios.sort_values([*by, model, "compare_against"], kind="stable") \
        .reset_index(drop=True)
    return PairwiseComparison(skill=skill, ratios=ratios, baseline=baseline, by=by)


def _baseline_theta(skill: pd.DataFrame, baseline: str, by: Sequence[str],
                    model: str) -> np.ndarray:
    """θ of the baseline in each row's group; a group without the baseline is an error."""
    base = skill[skill[model] == baseline]
    if not by:
        if base.empty:
            raise PairwiseError(f"pairwise comparison: the baseline {baseline!r} has no scores "
                                f"(models: {sorted(skill[model].unique())})")
        return np.full(len(skill), float(base["relative_skill"].iloc[0]))
    merged = skill[list(by)].merge(base[[*by, "relative_skill"]], on=list(by), how="left")
    absent = merged["relative_skill"].isna().to_numpy()
    if absent.any():
        group = skill.iloc[int(np.flatnonzero(absent)[0])][list(by)].to_dict()
        raise PairwiseError(f"pairwise comparison: the baseline {baseline!r} has no scores in "
                            f"the group {group}")
    return merged["relative_skill"].to_numpy(dtype=np.float64)


def relative_skill(scores: pd.DataFrame, *, baseline: str, by: Sequence[str] = (),
                   model: str = "model_id", metric: str = "wis",
                   unit: Sequence[str] | None = None) -> pd.DataFrame:
    """The ``skill`` table of :func:`pairwise_comparison` scaled by ``baseline`` (e.g. the
    pairwise relative WIS of every model, per ``by`` group)."""
    return pairwise_comparison(scores, baseline=baseline, by=by, model=model, metric=metric,
                               unit=unit).skill
