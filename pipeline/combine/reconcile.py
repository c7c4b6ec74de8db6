"""Forecasts of a total and of its parts that do not contradict each other (the US and the
states of the hub).

The US forecast and the states' are made separately, so the sum of the states' medians need not
be the US median (measured on the hub's 44 admissions rounds, before reconciling: the US median
differed from the sum of the states' by 3.8 % in the median round and horizon, 10 % at the 90th
percentile). **Top-down**: each state's quantiles are scaled by one factor per round and horizon,
so that the states' medians sum to the national median; the national forecast is left as it is
(the national series is the smoothest, and its own forecast the surest). The quantiles of a
state keep their shape (a common factor), so they stay ordered and non-negative.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import NDArray

from pipeline.combine.average import EnsembleError
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
