"""The continuous quantile function between and beyond the hub levels, and PIT from quantiles.

**The continuous quantile function** of a set of quantiles q_1..q_Q at levels τ_1..τ_Q: piecewise
linear in (z, g(q)) with z = Φ⁻¹(τ) and g(v) = log(1 + v·unit), linearly extrapolated beyond the
outermost levels with the outermost segments' slopes. ``unit`` turns the target into counts
(1 for a count, N for I), so g is log(1 + count) for both: a log-normal forecast is reproduced
exactly, tails are log-normal-like, values stay ≥ 0, and I = count/N interpolate identically.
Used for the PIT, for recalibrated levels, for mixtures and for sample paths.

**PIT from quantiles** (deterministic): PIT(y) = Φ(z(y)) with z(y) the inverse of the
piecewise-linear map above; where several quantiles equal y (a flat stretch, e.g. quantiles
clipped at 0) the PIT is the middle of that stretch's level range.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr, ndtri

from pipeline.errors import FlowcastError


class CalibrationError(FlowcastError):
    """Levels, quantiles or PIT values that do not fit together."""


LEVEL_TOLERANCE = 1e-6
MEDIAN = 0.5


def level_index(levels: ArrayLike, level: float) -> int:
    """The position of ``level`` among ``levels`` (the one way every module finds a level, the
    median's included); a level not among them is an error, never the nearest one."""
    lv = np.asarray(levels, dtype=np.float64)
    at = int(np.argmin(np.abs(lv - level))) if lv.size else -1
    if at < 0 or abs(lv[at] - level) > LEVEL_TOLERANCE:
        raise CalibrationError(f"level {level} is not among the levels {lv.tolist()}")
    return at


def median_index(levels: ArrayLike) -> int:
    """The position of the median (level 0.5) among ``levels``."""
    return level_index(levels, MEDIAN)


def _transform(values: NDArray[np.float64], unit: float) -> NDArray[np.float64]:
    return np.log1p(np.maximum(values, 0.0) * unit)


def _untransform(g: NDArray[np.float64], unit: float) -> NDArray[np.float64]:
    return np.maximum(np.expm1(g), 0.0) / unit


def quantiles_at(levels: ArrayLike, values: ArrayLike, new_levels: ArrayLike,
                 unit: float = 1.0) -> NDArray[np.float64]:
    """Quantiles ``(..., K)`` at ``new_levels`` (broadcastable to (..., K)) of the forecasts
    ``values (..., Q)`` given at ``levels (Q,)`` (module docstring: the continuous quantile
    function, tails extrapolated)."""
    lv = np.asarray(levels, dtype=np.float64)
    z = ndtri(lv)
    g = _transform(np.asarray(values, dtype=np.float64), unit)
    znew = ndtri(np.clip(np.asarray(new_levels, dtype=np.float64), 1e-12, 1 - 1e-12))
    znew = np.broadcast_to(znew, g.shape[:-1] + znew.shape[-1:])
    # segment index of each new z: 0 .. Q-2 (ends extrapolate the outer segments)
    seg = np.clip(np.searchsorted(z, znew, side="right") - 1, 0, lv.size - 2)
    z0, z1 = z[seg], z[seg + 1]
    g0 = np.take_along_axis(g, seg, axis=-1)
    g1 = np.take_along_axis(g, seg + 1, axis=-1)
    out = g0 + (g1 - g0) * (znew - z0) / (z1 - z0)
    return _untransform(out, unit)


def pit_from_quantiles(levels: ArrayLike, values: ArrayLike, observed: ArrayLike,
                       unit: float = 1.0) -> NDArray[np.float64]:
    """PIT ``(...)`` of ``observed (...)`` under quantile forecasts ``values (..., Q)``."""
    lv = np.asarray(levels, dtype=np.float64)
    z = ndtri(lv)
    g = _transform(np.asarray(values, dtype=np.float64), unit)
    y = _transform(np.asarray(observed, dtype=np.float64), unit)
    if g.shape[:-1] != y.shape or g.shape[-1] != lv.size:
        raise CalibrationError(f"quantiles {g.shape} and observations {y.shape} do not match "
                               f"{lv.size} levels")
    yk = y[..., None]
    below = np.sum(g < yk, axis=-1)          # knots strictly below y
    at = np.sum(g == yk, axis=-1)
    q = lv.size
    # tails: extrapolate the outer segments (flat outer segments: the PIT is the outer level)
    slope_lo = (g[..., 1] - g[..., 0]) / (z[1] - z[0])
    slope_hi = (g[..., -1] - g[..., -2]) / (z[-1] - z[-2])
    with np.errstate(divide="ignore", invalid="ignore"):
        z_lo = np.where(slope_lo > 0, z[0] + (y - g[..., 0]) / slope_lo, z[0])
        z_hi = np.where(slope_hi > 0, z[-1] + (y - g[..., -1]) / slope_hi, z[-1])
    # interior: y between knots below-1 and below (no tie)
    i0 = np.clip(below - 1, 0, q - 2)
    ga = np.take_along_axis(g, i0[..., None], axis=-1)[..., 0]
    gb = np.take_along_axis(g, (i0 + 1)[..., None], axis=-1)[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        z_in = z[i0] + (z[i0 + 1] - z[i0]) * (y - ga) / (gb - ga)
    # ties: the middle of the tied knots' levels
    first_tie = np.clip(below, 0, q - 1)
    last_tie = np.clip(below + at - 1, 0, q - 1)
    pit_tie = 0.5 * (lv[first_tie] + lv[last_tie])
    pit = np.where(below == 0, ndtr(z_lo),
                   np.where(below == q, ndtr(z_hi), ndtr(np.nan_to_num(z_in))))
    return np.where(at > 0, pit_tie, pit)

