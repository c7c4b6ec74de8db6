"""Quantile functions between and beyond the hub levels, PIT from quantiles, and recalibration.

**The continuous quantile function** of a set of quantiles q_1..q_Q at levels τ_1..τ_Q: piecewise
linear in (z, g(q)) with z = Φ⁻¹(τ) and g(v) = log(1 + v·unit), linearly extrapolated beyond the
outermost levels with the outermost segments' slopes. ``unit`` turns the target into case counts
(1 for ``cases``, N for ``I``), so g is log(1 + cases) for both: a log-normal forecast is
reproduced exactly, tails are log-normal-like, values stay ≥ 0, and I = cases/N interpolate
identically. Used for the PIT, for recalibrated levels and for sample paths.

**PIT from quantiles** (deterministic): PIT(y) = Φ(z(y)) with z(y) the inverse of the
piecewise-linear map above; where several quantiles equal y (a flat stretch, e.g. quantiles
clipped at 0) the PIT is the middle of that stretch's level range.

**Recalibration** from the PIT values of past forecasts at the same target × horizon (only
those whose truth was observed by the origin). Two maps from a level τ to the raw forecast's
level τ' whose quantile is published:

* ``probit-normal`` (the default): Φ⁻¹(τ') = σ Φ⁻¹(τ) with σ the standard deviation of the past
  PITs' probits over the last ``window`` (52) of them — a dispersion correction, one number per
  target × horizon. ``widen_only`` (default on) never lets σ fall below 1. Why: measured on the
  SF backtest (96 Saturday origins), every recalibration that may narrow — this one with a
  bias term, over 26, 52 or all past PITs, and the empirical map below — raised the published
  forecast's WIS by 2–4 % and lowered its coverage: the PITs of calm stretches say "too wide",
  and the narrowing they teach fails in the next wave. Widening only when the last year's PITs
  were under-dispersed costs nothing when the ensemble is calibrated.
* ``empirical`` (quantile recalibration, Kuleshov, Fenner & Ermon 2018, "Accurate
uncertainties for deep learning using calibrated regression", ICML): with p_1..p_n the PIT values
of past forecasts at the same target × horizon, the calibrated forecast's τ-quantile is the raw
forecast's quantile at level τ' = R⁻¹(τ), R the smoothed empirical CDF of the PITs (linear
through (0, 0), (p_(i), i/(n+1)), (1, 1)). With few PITs the map is shrunk to the identity on
the probit scale: Φ⁻¹(τ') = λ·Φ⁻¹(R⁻¹(τ)) + (1 − λ)·Φ⁻¹(τ), λ = n / (n + n0) (a mix of the
levels themselves, λ·R⁻¹(τ) + (1 − λ)·τ, could never move the 5 % level below (1 − λ)·5 %, so it
could not widen an over-confident forecast's tails). τ' is strictly increasing in τ, so the
recalibrated quantiles never cross.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr, ndtri

from pipeline.errors import FlowcastError


class CalibrationError(FlowcastError):
    """Levels, quantiles or PIT values that cannot be used for recalibration."""


@dataclass(frozen=True)
class CalibrationConfig:
    """``method``: ``probit-normal``, ``empirical`` (module docstring) or ``none`` (identity).
    ``shrinkage_pits`` n0: with n past PITs the map is n/(n + n0) of the fitted one.
    ``window``: the most recent PITs used (None: every past one)."""

    method: Literal["probit-normal", "empirical", "none"] = "probit-normal"
    shrinkage_pits: float = 10.0
    window: int | None = 52
    widen_only: bool = True
    min_level: float = 1e-9          # recalibrated levels stay within (min_level, 1 - min_level)

    def __post_init__(self) -> None:
        if self.shrinkage_pits < 0 or not 0 < self.min_level < 0.5:
            raise CalibrationError(f"invalid CalibrationConfig {self}")
        if self.method not in ("probit-normal", "empirical", "none"):
            raise CalibrationError(f"CalibrationConfig.method={self.method!r}: use "
                                   "'probit-normal', 'empirical' or 'none'")
        if self.window is not None and self.window < 1:
            raise CalibrationError(f"CalibrationConfig.window={self.window} must be >= 1")


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


def recalibrated_levels(levels: ArrayLike, past_pits: ArrayLike,
                        config: CalibrationConfig = CalibrationConfig()) -> NDArray[np.float64]:
    """τ' for each level τ from past PIT values (module docstring); identity without PITs."""
    lv = np.asarray(levels, dtype=np.float64)
    pits = np.asarray(past_pits, dtype=np.float64).ravel()
    pits = pits[np.isfinite(pits)]
    if config.window is not None:
        pits = pits[-config.window:]
    n = pits.size
    if n == 0 or config.method == "none":
        return lv.copy()
    if (pits < 0).any() or (pits > 1).any():
        raise CalibrationError("PIT values must lie in [0, 1]")
    lam = n / (n + config.shrinkage_pits)
    fitted = (_probit_normal_inverse(lv, pits, config) if config.method == "probit-normal"
              else _empirical_inverse(lv, pits, config))
    z = lam * fitted + (1.0 - lam) * ndtri(lv)   # strictly increasing when lam < 1
    return np.clip(ndtr(z), config.min_level, 1.0 - config.min_level)


def _empirical_inverse(levels: NDArray[np.float64], pits: NDArray[np.float64],
                       config: CalibrationConfig) -> NDArray[np.float64]:
    """Φ⁻¹(R⁻¹(τ)) with R the smoothed empirical CDF of the PITs."""
    n = pits.size
    ranks = np.arange(1, n + 1) / (n + 1.0)
    knots_p = np.concatenate([[0.0], np.sort(pits), [1.0]])
    knots_f = np.concatenate([[0.0], ranks, [1.0]])
    inverse = np.interp(levels, knots_f, knots_p)      # R⁻¹(τ), non-decreasing
    return ndtri(np.clip(inverse, config.min_level, 1.0 - config.min_level))


def _probit_normal_inverse(levels: NDArray[np.float64], pits: NDArray[np.float64],
                           config: CalibrationConfig) -> NDArray[np.float64]:
    """μ + σ Φ⁻¹(τ) with μ, σ the mean and standard deviation of the PITs' probits: the
    recalibration that corrects a bias and a dispersion error and nothing else (two numbers
    instead of a whole curve, so a few dozen PITs pin it down)."""
    probits = ndtri(np.clip(pits, config.min_level, 1.0 - config.min_level))
    sd = float(probits.std(ddof=1)) if probits.size > 1 else 1.0
    if config.widen_only:
        return max(sd, 1.0) * ndtri(levels)
    return float(probits.mean()) + max(sd, 1e-3) * ndtri(levels)


def recalibrate(levels: ArrayLike, values: ArrayLike, past_pits: ArrayLike, unit: float = 1.0,
                config: CalibrationConfig = CalibrationConfig()) -> NDArray[np.float64]:
    """Recalibrated quantiles ``(Q,)`` of one forecast ``values (Q,)`` at the same levels."""
    new = recalibrated_levels(levels, past_pits, config)
    out = quantiles_at(levels, values, new, unit)
    return np.maximum.accumulate(out, axis=-1)
