"""Recalibration of the average from the PITs of its past forecasts, pooled over places.

At origin t and horizon h the PITs known are those of the average's forecasts whose target
week had ended by t, in every place of the panel. The map from a level τ to the raw level τ'
whose quantile is published: Φ⁻¹(τ') = μ + σ Φ⁻¹(τ), μ and σ from the probits of the PITs of
the last ``window`` scored origins:

* ``"bias-scale"`` — μ, σ their mean and standard deviation, shrunk towards (0, 1) by
  n / (n + n0); ``"scale"`` — σ their root mean square, μ = 0;
* ``"…-regime"`` — fitted separately per **regime** of the forecast's place at its origin
  (falling, flat or rising, :mod:`pipeline.evaluation.regimes`), shrunk towards the all-regime
  fit;
* ``"widen-only"`` — σ ≥ 1, no bias (the SF-only design of before);
* ``"none"`` — the identity (published).

On the cross-county backtest every one of them was worse than none: a window learnt in one
phase of a wave fails in the next (``bench/results/backtest_counties.json``, variants).
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr, ndtri

from pipeline.evaluation.regimes import N_REGIMES

RecalibrationMethod = Literal["scale-regime", "scale", "bias-scale-regime", "bias-scale",
                              "widen-only", "none"]
RECALIBRATION_METHODS: tuple[str, ...] = ("scale-regime", "scale", "bias-scale-regime",
                                          "bias-scale", "widen-only", "none")


def fit_bias_scale(probits: NDArray[np.float64], shrinkage: float, with_bias: bool
                   ) -> tuple[float, float]:
    """(μ, σ) of probits, shrunk towards (0, 1) by n / (n + shrinkage). Without a bias term σ
    is the root mean square of the probits (the spread about 0 that the levels must cover)."""
    z = probits[np.isfinite(probits)]
    if z.size < 2:
        return 0.0, 1.0
    lam = z.size / (z.size + shrinkage)
    if with_bias:
        return lam * float(z.mean()), lam * float(z.std(ddof=1)) + (1.0 - lam)
    return 0.0, lam * float(np.sqrt(np.mean(z ** 2))) + (1.0 - lam)


def fit_recalibration(method: RecalibrationMethod, pits: NDArray[np.float64],
                      regimes: NDArray[np.intp], *, shrinkage_pits: float, min_level: float
                      ) -> NDArray[np.float64]:
    """μ, σ per regime ``(R, 2)`` from past PITs and their cells' regimes (flattened)."""
    out = np.tile(np.array([0.0, 1.0]), (N_REGIMES, 1))
    if method == "none":
        return out
    probits = ndtri(np.clip(pits, min_level, 1.0 - min_level))
    with_bias = method.startswith("bias")
    mu, sigma = fit_bias_scale(probits, shrinkage_pits, with_bias)
    if method == "widen-only":
        out[:, 1] = max(sigma, 1.0)
        return out
    out[:] = (mu, sigma)
    if not method.endswith("regime"):
        return out
    for r in range(N_REGIMES):
        mu_r, sigma_r = fit_bias_scale(probits[regimes == r], 0.0, with_bias)
        n_r = int(np.isfinite(probits[regimes == r]).sum())
        if n_r == 0:
            continue                            # no past forecast in this phase: the pooled fit
        lam = n_r / (n_r + shrinkage_pits)
        out[r] = (lam * mu_r + (1 - lam) * mu, lam * sigma_r + (1 - lam) * sigma)
    return out


def calibrated_levels(levels: NDArray[np.float64], mu_sigma: NDArray[np.float64],
                      min_level: float) -> NDArray[np.float64]:
    """τ' ``(..., Q)`` with Φ⁻¹(τ') = μ + σ Φ⁻¹(τ) for each ``mu_sigma (..., 2)``."""
    z = mu_sigma[..., :1] + np.maximum(mu_sigma[..., 1:], 1e-3) * ndtri(levels)
    return np.clip(ndtr(z), min_level, 1.0 - min_level)
