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
* ``"none"`` — the identity.

On the cross-county backtest every one of them was worse than none: a window learnt in one
phase of a wave fails in the next (``bench/results/backtest_counties.json``, variants). The
online rule (:class:`QuantileTracker`, ``"tracking"`` and ``"tracking-regime"``) instead moves
every level a little after each origin's outcomes, so it follows the phase it is in.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr, ndtri

from pipeline.evaluation.regimes import N_REGIMES

RecalibrationMethod = Literal["scale-regime", "scale", "bias-scale-regime", "bias-scale",
                              "widen-only", "tracking", "tracking-regime", "none"]
RECALIBRATION_METHODS: tuple[str, ...] = ("scale-regime", "scale", "bias-scale-regime",
                                          "bias-scale", "widen-only", "tracking",
                                          "tracking-regime", "none")
TRACKING: tuple[str, ...] = ("tracking", "tracking-regime")


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


# --------------------------------------------------------------- online: quantile tracking


@dataclass
class QuantileTracker:
    """Online calibration that reacts within a week or two: conformal quantile tracking
    (Angelopoulos, Candès & Tibshirani 2023, "Conformal PID control", its P term) of the width
    of each side of the forecast, per horizon and, with ``by_regime``, per phase of the epidemic.

    The median is left as the average has it (shifting it chased the last weeks' errors and cost
    skill); each side's distance from the median on log(1 + q) is scaled by e^φ. When the
    outcomes of an origin's forecasts become known (their target week has ended), each side's φ
    moves by its miss rate over the places of the panel (of the same regime):
    φ_up ← φ_up + η · mean over the upper levels τ of (share of outcomes above q_τ − (1 − τ)),
    φ_low likewise below. Too many outcomes above the 95 % quantile widen the upper side at the
    next origin; calm weeks bring it back. η in log units per origin; |φ| ≤ ``cap``."""

    levels: NDArray[np.float64]
    rate: float
    by_regime: bool
    cap: float = 1.5

    def __post_init__(self) -> None:
        self.scales = np.zeros((N_REGIMES if self.by_regime else 1, 2))     # (low, up) φ
        self._mid = int(np.argmin(np.abs(self.levels - 0.5)))

    def update(self, published: NDArray[np.float64], truth: NDArray[np.float64],
               regimes: NDArray[np.intp]) -> None:
        """One origin's outcomes: published quantiles ``(C, Q)``, truth ``(C,)`` (NaN: not
        observed), each place's regime ``(C,)``."""
        seen = np.isfinite(truth) & np.isfinite(published).all(axis=-1)
        if not seen.any():
            return
        y, q = truth[seen, None], published[seen]
        low, up = self.levels < 0.5, self.levels > 0.5
        below = (y < q[:, low]).astype(np.float64) - self.levels[low]            # (n, L)
        above = (y > q[:, up]).astype(np.float64) - (1.0 - self.levels[up])
        groups = regimes[seen] if self.by_regime else np.zeros(int(seen.sum()), dtype=np.intp)
        for group in np.unique(groups):
            rows = groups == group
            step = np.array([below[rows].mean(), above[rows].mean()])
            self.scales[group] = np.clip(self.scales[group] + self.rate * step,
                                         -self.cap, self.cap)

    def apply(self, quantiles: NDArray[np.float64], regimes: NDArray[np.intp]
              ) -> NDArray[np.float64]:
        """Quantiles ``(C, Q)`` with each side scaled by its regime's e^φ, kept ordered."""
        rows = regimes if self.by_regime else np.zeros(len(quantiles), dtype=np.intp)
        g = np.log1p(np.maximum(quantiles, 0.0))
        median = g[:, self._mid:self._mid + 1]
        side = np.where(self.levels < 0.5, 0, 1)                                 # (Q,)
        stretch = np.exp(self.scales[rows][:, side])                             # (C, Q)
        shifted = np.expm1(median + stretch * (g - median))
        return np.maximum.accumulate(np.maximum(shifted, 0.0), axis=-1)
