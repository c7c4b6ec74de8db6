"""Forecasts of a total and of its parts that do not contradict each other (the US and the
states of the hub).

The US forecast and the states' are made separately, so the sum of the states' medians need not
be the US median (measured on the hub's 44 admissions rounds, before reconciling: the US median
differed from the sum of the states' by 3.8 % in the median round and horizon, 10 % at the 90th
percentile). **Top-down**: each state's quantiles are scaled by one factor per round and horizon,
so that the states' medians sum to the national median; the national forecast is left as it is
(the national series is the smoothest, and its own forecast the surest). The quantiles of a
state keep their shape (a common factor), so they stay ordered and non-negative.

Reconciling costs skill where the national forecast is the worse one (on the hub's 46
admissions rounds of 2025-11-29, the unreconciled forecast scored better at every horizon), so
it is applied at a round and horizon only where it scored at least as well on the outcomes then
known (:func:`reconciled_where_better`).
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.combine.average import EnsembleError, scored_wis
from pipeline.combine.combiner import KnownTruth, scored_before
from pipeline.evaluation.quantile_function import median_index


def reconcilable(places: Sequence[str], total: str, parts: Iterable[str]) -> bool:
    """Whether ``places`` hold the total and every one of its ``parts``: the total is never
    spread over a subset (issue 39: with three states missing, the other 49 were scaled up to
    the whole US median although the three carry about 5 % of US admissions)."""
    return total in places and set(parts) - {total} <= set(places)


def median_gap(quantiles: NDArray[np.float64], places: Sequence[str], total: str,
               levels: NDArray[np.float64]) -> NDArray[np.float64]:
    """log(total's median / Σ parts' medians) per cell ``(O, H)`` of quantiles
    ``(C, O, H, Q)``: 0 where they agree."""
    mid = median_index(levels)
    whole, parts = _split(quantiles[..., mid], places, total)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.log(whole / parts)


def top_down(quantiles: NDArray[np.float64], places: Sequence[str], total: str,
             levels: NDArray[np.float64]) -> NDArray[np.float64]:
    """The parts' quantiles scaled so their medians sum to the total's median (module
    docstring); cells without a total or parts are left as they are."""
    mid = median_index(levels)
    whole, parts = _split(quantiles[..., mid], places, total)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where((parts > 0) & np.isfinite(whole), whole / parts, 1.0)     # (O, H)
    out = quantiles.copy()
    others = [i for i, p in enumerate(places) if p != total]
    out[others] = quantiles[others] * factor[None, ..., None]
    return out


def _split(medians: NDArray[np.float64], places: Sequence[str], total: str
           ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    if total not in places:
        raise EnsembleError(f"no {total!r} among the places to reconcile with")
    index = list(places).index(total)
    others = np.delete(medians, index, axis=0)
    return medians[index], np.nansum(others, axis=0)


def reconciled_where_better(plain: NDArray[np.float64], reconciled: NDArray[np.float64],
                            baseline: NDArray[np.float64], truth_at: KnownTruth,
                            origins: Sequence[pd.Timestamp], horizons: tuple[int, ...],
                            levels: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                                  NDArray[np.bool_]]:
    """At each origin j and horizon k ``(C, O, H, Q)``: the ``reconciled`` quantiles where, on
    the outcomes known at j (:func:`~pipeline.combine.combiner.scored_before`, their values as
    ``truth_at(j)`` holds them), they scored at least as well as the ``plain`` ones, else the
    plain ones; reconciled before any outcome is known (the prior: the hub's forecasts should
    add up). Each place's WIS is taken relative to the ``baseline``'s there, so every place
    weighs alike and a large state does not decide for the others. Returns the quantiles and
    ``(O, H)`` where the reconciled ones were chosen."""
    known = scored_before(origins, horizons)                               # (O, O, H)
    chosen = np.ones(known.shape[1:], dtype=bool)
    for j in np.flatnonzero(known.any(axis=(1, 2))):
        truth = truth_at(int(j))
        past = known[j]                                                    # (O, H)
        wis = {name: np.where(past, scored_wis(levels, q, truth), np.nan)
               for name, q in (("plain", plain), ("reconciled", reconciled),
                               ("baseline", baseline))}
        scale = np.nansum(wis["baseline"], axis=1)                         # (C, H)
        with np.errstate(divide="ignore", invalid="ignore"):
            relative = {name: np.nansum(np.where(scale > 0, np.nansum(wis[name], axis=1) / scale,
                                                 np.nan), axis=0)        # (H,)
                        for name in ("plain", "reconciled")}
        chosen[j] = relative["reconciled"] <= relative["plain"]
    return np.where(chosen[None, :, :, None], reconciled, plain), chosen
