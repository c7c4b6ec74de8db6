"""The published forecast of a panel: members averaged, with weights and recalibration that may
be learnt from every place at once.

At origin t, horizon h, the scores known are those of forecasts from origins o with
o + 7h ≤ t (their target week has ended), in **every** place of the panel.

**Published** (``PooledConfig()``): the equal-weight average of the members' log(1 + quantile)
— the geometric mean of their quantiles — with no recalibration. On the cross-county backtest
(``bench/results/backtest_counties.json``, ``variants``) every choice below that learns from
recent scores made the forecast worse: pooled stacking and inverse-WIS weights chased the
current regime, and every recalibration (bias and scale, per growth regime, scale only, widen
only) taught in one phase of a wave failed in the next. They are kept as the variants the
benchmark reports beside the published forecast:

1. **Weights** per horizon (``PooledConfig.weights``): ``"equal"``; ``"stacking"`` — the weights
   on a simplex grid (step ``stacking_step``) whose average had the lowest mean over places of
   log(Σ WIS / Σ WIS of the hub baseline) over the last ``window_origins`` scored origins, shrunk
   towards equal weights by n / (n + ``shrinkage_origins``); ``"inverse-wis"`` — ∝ 1 / (each
   member's geometric-mean relative WIS), shrunk the same way.
2. **Average** (``scale``): ``"log"`` (geometric mean of quantiles) or ``"linear"`` (Vincentization).
3. **Recalibration** (``calibration``) from the PITs of the average's past forecasts in every
   place over the last ``calibration_window_origins`` scored origins, by horizon:
   Φ⁻¹(τ') = μ + σ Φ⁻¹(τ), μ and σ the mean and standard deviation of the PITs' probits;
   ``"bias-scale-regime"`` fits μ, σ separately per **regime** of the forecast's place at its
   origin (falling, flat or rising over the last week, :func:`growth_regimes`), shrunk towards
   the all-regime fit; ``"scale-regime"``/``"scale"`` without the bias; ``"widen-only"``
   (σ ≥ 1, no bias: the SF-only design of before); ``"none"`` (published).

Everything is computed on weekly cases; I = cases / N.
"""
from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr, ndtri

from pipeline.ensemble.calibration import pit_from_quantiles, quantiles_at
from pipeline.ensemble.combine import AverageScale, EnsembleError, vincentize
from pipeline.evaluation.scoring import weighted_interval_score

WeightMethod = Literal["stacking", "inverse-wis", "equal"]
CalibrationMethod = Literal["scale-regime", "scale", "bias-scale-regime", "bias-scale",
                            "widen-only", "none"]
CALIBRATION_METHODS: tuple[str, ...] = ("scale-regime", "scale", "bias-scale-regime",
                                        "bias-scale", "widen-only", "none")
N_REGIMES = 3                       # falling, flat, rising
FLAT_LOG_GROWTH = 0.1               # |log(C_0 / C_-1)| below this is "flat" (±10 % a week)
_EPS_WIS = 1e-12


@dataclass(frozen=True)
class PooledConfig:
    """The pooled combiner's settings (module docstring)."""

    weights: WeightMethod = "equal"
    scale: AverageScale = "log"
    window_origins: int = 12
    stacking_step: float = 0.05
    shrinkage_origins: float = 2.0
    calibration: CalibrationMethod = "none"
    calibration_window_origins: int = 8
    shrinkage_pits: float = 50.0
    min_level: float = 1e-4

    def __post_init__(self) -> None:
        if self.weights not in ("stacking", "inverse-wis", "equal"):
            raise EnsembleError(f"PooledConfig.weights={self.weights!r}: use stacking, "
                                "inverse-wis or equal")
        if self.scale not in ("log", "linear"):
            raise EnsembleError(f"PooledConfig.scale={self.scale!r}: use log or linear")
        if self.calibration not in CALIBRATION_METHODS:
            raise EnsembleError(f"PooledConfig.calibration={self.calibration!r}; use one of "
                                f"{CALIBRATION_METHODS}")
        if (self.window_origins < 1 or self.calibration_window_origins < 1
                or not 0 < self.stacking_step <= 0.5 or self.shrinkage_origins < 0
                or self.shrinkage_pits < 0):
            raise EnsembleError(f"invalid PooledConfig {self}")


@dataclass(frozen=True, eq=False)
class PooledForecast:
    """``published`` and ``uncalibrated`` case quantiles ``(C, O, H, Q)``; ``weights``
    ``(O, H, M)``; ``calibration`` ``(O, H, R, 2)``: μ, σ per regime."""

    published: NDArray[np.float64]
    uncalibrated: NDArray[np.float64]
    weights: NDArray[np.float64]
    calibration: NDArray[np.float64]


def growth_regimes(last_weeks: NDArray[np.float64]) -> NDArray[np.intp]:
    """Regime 0 (falling), 1 (flat), 2 (rising) from the last two weekly counts ``(..., 2)``."""
    growth = np.log(last_weeks[..., 1] + 0.5) - np.log(last_weeks[..., 0] + 0.5)
    return np.where(growth < -FLAT_LOG_GROWTH, 0, np.where(growth > FLAT_LOG_GROWTH, 2, 1))


def simplex_grid(members: int, step: float) -> NDArray[np.float64]:
    """Every weight vector of ``members`` non-negative multiples of ``step`` summing to 1."""
    n = int(round(1.0 / step))
    rows = [c for c in itertools.product(range(n + 1), repeat=members - 1) if sum(c) <= n]
    grid = np.array([list(c) + [n - sum(c)] for c in rows], dtype=np.float64) / n
    return grid


def _log_relative_wis_by_place(wis: NDArray[np.float64], baseline_wis: NDArray[np.float64]
                               ) -> NDArray[np.float64]:
    """Mean over places of log(Σ WIS / Σ baseline WIS); ``wis (..., C, n)``, NaN cells ignored."""
    seen = np.isfinite(baseline_wis)
    num = np.where(seen, wis, 0.0).sum(axis=-1) + _EPS_WIS
    den = np.where(seen, baseline_wis, 0.0).sum(axis=-1) + _EPS_WIS
    places = seen.any(axis=-1)
    return np.where(places, np.log(num / den), 0.0).sum(axis=-1) / max(int(places.sum()), 1)


def _wis(levels: NDArray[np.float64], q: NDArray[np.float64], y: NDArray[np.float64]
         ) -> NDArray[np.float64]:
    seen = np.isfinite(y)
    out = weighted_interval_score(levels, q, np.where(seen, y, 0.0)).wis
    return np.where(seen, out, np.nan)


def fit_weights(past_values: NDArray[np.float64], past_truth: NDArray[np.float64],
                past_baseline_wis: NDArray[np.float64], levels: NDArray[np.float64],
                n_origins: int, config: PooledConfig) -> NDArray[np.float64]:
    """Weights ``(M,)`` from past quantiles ``(M, C, n, Q)``, truth ``(C, n)`` and the
    baseline's WIS ``(C, n)`` over ``n_origins`` scored origins."""
    m = past_values.shape[0]
    equal = np.full(m, 1.0 / m)
    if config.weights == "equal" or n_origins == 0 or m == 1:
        return equal
    lam = n_origins / (n_origins + config.shrinkage_origins)
    if config.weights == "inverse-wis":
        member_wis = _wis(levels, past_values, np.broadcast_to(past_truth, past_values.shape[:-1]))
        loss = np.exp(_log_relative_wis_by_place(member_wis, past_baseline_wis))
        skill = 1.0 / np.maximum(loss, 1e-12)
        return lam * skill / skill.sum() + (1.0 - lam) * equal
    grid = simplex_grid(m, config.stacking_step)                           # (K, M)
    combined = np.stack([vincentize(past_values, w, config.scale) for w in grid])  # (K, C, n, Q)
    wis = _wis(levels, combined, np.broadcast_to(past_truth, combined.shape[:-1]))
    loss = _log_relative_wis_by_place(wis, past_baseline_wis)              # (K,)
    return lam * grid[int(np.argmin(loss))] + (1.0 - lam) * equal


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


def fit_calibration(pits: NDArray[np.float64], regimes: NDArray[np.intp],
                    config: PooledConfig) -> NDArray[np.float64]:
    """μ, σ per regime ``(R, 2)`` from past PITs and their cells' regimes (flattened)."""
    out = np.tile(np.array([0.0, 1.0]), (N_REGIMES, 1))
    method = config.calibration
    if method == "none":
        return out
    probits = ndtri(np.clip(pits, config.min_level, 1.0 - config.min_level))
    with_bias = method.startswith("bias")
    mu, sigma = fit_bias_scale(probits, config.shrinkage_pits, with_bias)
    if method == "widen-only":
        out[:, 1] = max(sigma, 1.0)
        return out
    out[:] = (mu, sigma)
    if not method.endswith("regime"):
        return out
    for r in range(N_REGIMES):
        mu_r, sigma_r = fit_bias_scale(probits[regimes == r], 0.0, with_bias)
        n_r = int(np.isfinite(probits[regimes == r]).sum())
        lam = n_r / (n_r + config.shrinkage_pits)
        out[r] = (lam * mu_r + (1 - lam) * mu, lam * sigma_r + (1 - lam) * sigma)
    return out


def calibrated_levels(levels: NDArray[np.float64], mu_sigma: NDArray[np.float64],
                      min_level: float) -> NDArray[np.float64]:
    """τ' ``(..., Q)`` with Φ⁻¹(τ') = μ + σ Φ⁻¹(τ) for each ``mu_sigma (..., 2)``."""
    z = mu_sigma[..., :1] + np.maximum(mu_sigma[..., 1:], 1e-3) * ndtri(levels)
    return np.clip(ndtr(z), min_level, 1.0 - min_level)


def combine_panel(members: Mapping[str, NDArray[np.float64]], baseline: NDArray[np.float64],
                  truth: NDArray[np.float64], regimes: NDArray[np.intp],
                  levels: NDArray[np.float64], horizons: tuple[int, ...],
                  config: PooledConfig = PooledConfig()) -> PooledForecast:
    """The published case quantiles of every cell from the members' ``(C, O, H, Q)`` quantiles,
    the hub baseline's, the truth ``(C, O, H)`` and each cell's regime ``(C, O)``. At origin
    index j and horizon h only origins i ≤ j − h are scored (weekly origins: their target weeks
    have ended by origin j)."""
    names = list(members)
    values = np.stack([members[n] for n in names])                        # (M, C, O, H, Q)
    _, n_c, n_o, n_h, _ = values.shape
    if len(horizons) != n_h or baseline.shape != values.shape[1:]:
        raise EnsembleError(f"member quantiles {values.shape[1:]}, baseline {baseline.shape} "
                            f"and {len(horizons)} horizons do not match")
    baseline_wis = _wis(levels, baseline, truth)                           # (C, O, H)
    uncal = np.empty(values.shape[1:])
    published = np.empty(values.shape[1:])
    weights = np.empty((n_o, n_h, len(names)))
    calibration = np.empty((n_o, n_h, N_REGIMES, 2))
    pits = np.full(truth.shape, np.nan)
    for k, h in enumerate(horizons):
        for j in range(n_o):
            last = j - h                                    # newest scored origin
            first = max(0, last - config.window_origins + 1)
            past = slice(first, last + 1)
            n_scored = max(0, last + 1 - first)
            weights[j, k] = fit_weights(values[:, :, past, k], truth[:, past, k],
                                        baseline_wis[:, past, k], levels, n_scored, config)
            uncal[:, j, k] = vincentize(values[:, :, j, k], weights[j, k], config.scale)
            cal_past = slice(max(0, last - config.calibration_window_origins + 1), last + 1)
            calibration[j, k] = fit_calibration(pits[:, cal_past, k].ravel(),
                                                regimes[:, cal_past].ravel(), config)
            new_levels = calibrated_levels(levels, calibration[j, k][regimes[:, j]],
                                           config.min_level)
            cal = quantiles_at(levels, uncal[:, j, k], new_levels)
            published[:, j, k] = np.maximum.accumulate(cal, axis=-1)
            seen = np.isfinite(truth[:, j, k])
            pits[seen, j, k] = pit_from_quantiles(levels, uncal[seen, j, k], truth[seen, j, k])
    return PooledForecast(published, uncal, weights, calibration)
