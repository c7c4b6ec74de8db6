"""Proper scores for probabilistic forecasts: weighted interval score, interval coverage, PIT.

Definitions (Bracher, Ray, Gneiting & Reich 2021, "Evaluating epidemic forecasts in an interval
format", PLOS Comput Biol 17(2): e1008618):

* Interval score of the central (1 - α) interval [l, u] for an observation y::

      IS_α(l, u; y) = (u - l) + (2/α)(l - y)·1[y < l] + (2/α)(y - u)·1[y > u]

* Weighted interval score over K central intervals and the median m, weights w_0 = 1/2 and
  w_k = α_k / 2::

      WIS = 1 / (K + 1/2) · ( w_0 |y - m| + Σ_k w_k IS_{α_k}(l_k, u_k; y) )

  Equivalently WIS = Σ_τ 2·QS_τ / (2K + 1) over the 2K + 1 quantile levels τ, with the pinball
  loss QS_τ(q; y) = (1[y ≤ q] - τ)(q - y); the tests check both forms. For many equally spaced
  levels WIS approaches the CRPS.

* Decomposition (WIS = dispersion + overprediction + underprediction), each scaled by 1/(K+1/2):

      dispersion      = Σ_k (α_k / 2)(u_k - l_k)
      overprediction  = w_0 (m - y)·1[y < m] + Σ_k (l_k - y)·1[y < l_k]
      underprediction = w_0 (y - m)·1[y > m] + Σ_k (y - u_k)·1[y > u_k]

  The median's absolute error is split into over- or under-prediction according to its sign
  (the convention of the Forecast Hub evaluations and ``scoringutils``).

* Interval coverage: the indicator l ≤ y ≤ u (closed interval) for the central 50% and 90%
  intervals, i.e. the quantile pairs (0.25, 0.75) and (0.05, 0.95).

* PIT from an ensemble of n samples x_1..x_n: with the empirical CDF F̂(y) = #{x_i ≤ y}/n and its
  left limit F̂(y-) = #{x_i < y}/n,

  - ``method="randomized"`` (default): PIT = F̂(y-) + V·(F̂(y) - F̂(y-)), V ~ U(0, 1) drawn from a
    seeded generator (Czado, Gneiting & Held 2009). Without ties this is F̂(y) exactly; with ties
    (e.g. clipped proportions, integer counts) it spreads the mass so that a calibrated forecast
    gives a uniform histogram.
  - ``method="mid"``: PIT = (F̂(y-) + F̂(y)) / 2, deterministic (mid-rank), slightly
    under-dispersed for a calibrated forecast when n is small.

Everything is vectorized: quantile values are arrays (..., Q) with the levels on the last axis,
observations are arrays (...), samples are arrays (..., n).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pipeline.errors import FlowcastError

_LEVEL_TOL = 1e-9
# The product's one interval convention: the median and the central 50 % and 90 % intervals.
CENTRAL_LEVELS: tuple[float, ...] = (0.05, 0.25, 0.5, 0.75, 0.95)


class ScoringError(FlowcastError):
    """Quantile levels, values or observations that cannot be scored (shape, NaN, asymmetry)."""


@dataclass(frozen=True)
class WISComponents:
    """WIS and its three additive parts, each an array with the observations' shape."""

    wis: NDArray[np.float64]
    dispersion: NDArray[np.float64]
    overprediction: NDArray[np.float64]
    underprediction: NDArray[np.float64]


def _as_levels(levels: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(levels, dtype=np.float64)
    if arr.ndim != 1 or arr.size == 0:
        raise ScoringError(f"quantile levels must be a non-empty 1-D array, got shape {arr.shape}")
    if np.any(~np.isfinite(arr)) or np.any(arr <= 0) or np.any(arr >= 1):
        raise ScoringError(f"quantile levels must lie strictly in (0, 1), got {arr.tolist()}")
    if np.any(np.diff(arr) <= 0):
        raise ScoringError(f"quantile levels must be strictly increasing, got {arr.tolist()}")
    return arr


def _check_quantile_inputs(levels: NDArray[np.float64], values: ArrayLike,
                           observed: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    q = np.asarray(values, dtype=np.float64)
    y = np.asarray(observed, dtype=np.float64)
    if q.shape[-1:] != levels.shape:
        raise ScoringError(f"quantile values have {q.shape[-1:]} levels on the last axis, "
                           f"expected {levels.size} (values shape {q.shape})")
    if q.shape[:-1] != y.shape:
        raise ScoringError(f"quantile values shape {q.shape} does not match observations "
                           f"shape {y.shape} (expected observations.shape + (Q,))")
    if not np.all(np.isfinite(q)):
        raise ScoringError("quantile values contain NaN or inf")
    if not np.all(np.isfinite(y)):
        raise ScoringError("observations contain NaN or inf")
    if np.any(np.diff(q, axis=-1) < 0):
        raise ScoringError("quantile values decrease along the level axis (quantile crossing)")
    return q, y


def _central_pairs(levels: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp],
                                                         NDArray[np.float64], int]:
    """Indices of (lower, upper) quantiles of each central interval, their α, and the median index."""
    n = levels.size
    if n % 2 != 1:
        raise ScoringError(f"WIS needs an odd number of levels (pairs + median), got {n}")
    mid = n // 2
    if abs(levels[mid] - 0.5) > _LEVEL_TOL:
        raise ScoringError(f"WIS needs the median level 0.5, middle level is {levels[mid]}")
    lower = np.arange(mid)
    upper = n - 1 - lower
    if np.any(np.abs(levels[lower] + levels[upper] - 1.0) > _LEVEL_TOL):
        raise ScoringError(f"quantile levels are not symmetric around 0.5: {levels.tolist()}")
    alphas = 2.0 * levels[lower]
    return lower, upper, alphas, mid


def interval_score(lower: ArrayLike, upper: ArrayLike, observed: ArrayLike,
                   alpha: float) -> NDArray[np.float64]:
    """IS_α of the central (1-α) interval [lower, upper] (unweighted, Bracher et al. eq. 1)."""
    if not 0 < alpha <= 1:
        raise ScoringError(f"alpha must lie in (0, 1], got {alpha}")
    l, u, y = (np.asarray(a, dtype=np.float64) for a in (lower, upper, observed))
    return ((u - l) + (2.0 / alpha) * np.clip(l - y, 0.0, None)
            + (2.0 / alpha) * np.clip(y - u, 0.0, None))


def weighted_interval_score(levels: ArrayLike, values: ArrayLike,
                            observed: ArrayLike) -> WISComponents:
    """WIS and its decomposition for quantile forecasts ``values (..., Q)`` at ``levels (Q,)``.

    ``levels`` must be symmetric around 0.5 and include it (e.g. the 23 hub levels: K = 11).
    """
    lv = _as_levels(levels)
    q, y = _check_quantile_inputs(lv, values, observed)
    lo_idx, up_idx, alphas, mid = _central_pairs(lv)
    lo, up, med = q[..., lo_idx], q[..., up_idx], q[..., mid]
    y_k = y[..., None]
    scale = 1.0 / (alphas.size + 0.5)
    dispersion = scale * np.sum(alphas / 2.0 * (up - lo), axis=-1)
    over = scale * (0.5 * np.clip(med - y, 0.0, None)
                    + np.sum(np.clip(lo - y_k, 0.0, None), axis=-1))
    under = scale * (0.5 * np.clip(y - med, 0.0, None)
                     + np.sum(np.clip(y_k - up, 0.0, None), axis=-1))
    return WISComponents(wis=dispersion + over + under, dispersion=dispersion,
                         overprediction=over, underprediction=under)


def quantile_score(levels: ArrayLike, values: ArrayLike, observed: ArrayLike) -> NDArray[np.float64]:
    """Pinball loss QS_τ(q; y) = (1[y ≤ q] - τ)(q - y) for every level: shape (..., Q)."""
    lv = _as_levels(levels)
    q, y = _check_quantile_inputs(lv, values, observed)
    y_k = y[..., None]
    return ((y_k <= q).astype(np.float64) - lv) * (q - y_k)


def interval_coverage(levels: ArrayLike, values: ArrayLike, observed: ArrayLike,
                      central_level: float) -> NDArray[np.bool_]:
    """Whether y lies in the closed central ``central_level`` interval, e.g. 0.5 or 0.9."""
    lv = _as_levels(levels)
    q, y = _check_quantile_inputs(lv, values, observed)
    tail = (1.0 - central_level) / 2.0
    idx_lo = np.flatnonzero(np.abs(lv - tail) < _LEVEL_TOL)
    idx_up = np.flatnonzero(np.abs(lv - (1.0 - tail)) < _LEVEL_TOL)
    if idx_lo.size != 1 or idx_up.size != 1:
        raise ScoringError(f"central {central_level:.0%} interval needs levels {tail:g} and "
                           f"{1 - tail:g}; available {lv.tolist()}")
    return (q[..., idx_lo[0]] <= y) & (y <= q[..., idx_up[0]])


def pit_values(samples: ArrayLike, observed: ArrayLike,
               method: Literal["randomized", "mid"] = "randomized",
               seed: int = 0) -> NDArray[np.float64]:
    """PIT of ``observed (...)`` under the ensemble ``samples (..., n)`` (see module docstring)."""
    x = np.asarray(samples, dtype=np.float64)
    y = np.asarray(observed, dtype=np.float64)
    if x.ndim < 1 or x.shape[:-1] != y.shape or x.shape[-1] == 0:
        raise ScoringError(f"samples shape {x.shape} must be observations shape {y.shape} + (n,)")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ScoringError("samples or observations contain NaN or inf")
    n = x.shape[-1]
    below = np.sum(x < y[..., None], axis=-1) / n
    at_or_below = np.sum(x <= y[..., None], axis=-1) / n
    if method == "mid":
        return (below + at_or_below) / 2.0
    if method == "randomized":
        v = np.random.default_rng(seed).uniform(size=y.shape)
        return below + v * (at_or_below - below)
    raise ScoringError(f"unknown PIT method {method!r}; use 'randomized' or 'mid'")


def quantiles_from_samples(samples: ArrayLike, levels: ArrayLike) -> NDArray[np.float64]:
    """Quantiles (..., Q) of an ensemble (..., n) by linear interpolation (Hyndman-Fan type 7)."""
    lv = _as_levels(levels)
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] == 0:
        raise ScoringError(f"samples need a non-empty last (sample) axis, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ScoringError("samples contain NaN or inf")
    return np.moveaxis(np.quantile(x, lv, axis=-1, method="linear"), 0, -1)
