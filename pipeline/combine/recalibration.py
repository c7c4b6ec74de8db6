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
online rule (:class:`IntervalTracker`, ``"regime-aci"``) instead moves the intervals' widths a
little after each origin's outcomes, per phase of the epidemic, so it follows the phase it is
in, and leaves the median alone.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr, ndtri

from pipeline.evaluation.quantile_function import level_index, quantiles_at
from pipeline.evaluation.regimes import N_REGIMES

RecalibrationMethod = Literal["scale-regime", "scale", "bias-scale-regime", "bias-scale",
                              "widen-only", "regime-aci", "aggregated-aci", "none"]
RECALIBRATION_METHODS: tuple[str, ...] = ("scale-regime", "scale", "bias-scale-regime",
                                          "bias-scale", "widen-only", "regime-aci",
                                          "aggregated-aci", "none")
ONLINE_METHODS: tuple[str, ...] = ("regime-aci", "aggregated-aci")
# How one origin's misses move a phase's stretch: averaged over every newly scored forecast
# ("pooled": a phase seen rarely moves slowly) or over the phase's own ("per-regime": each phase
# is its own adaptive conformal inference)
TrackingStep = Literal["pooled", "per-regime"]
TRACKING_STEPS: tuple[str, ...] = ("pooled", "per-regime")
# Where a stretch acts: on the levels at which the average's quantile function is read
# ("levels"), on the quantiles' distances from the median ("values": q' = m + e^f (q − m)), or
# each quantile moved by the lesser of the two ("lesser", published). On long-tailed quantile
# functions a small stretch of levels is a large widening of values (the RSV ED share's 90 %
# interval 52 % wider for 1.3 points of coverage); on others a narrowing of values is the
# larger move (the ED share's 95 % interval covered a point less). Either reading alone
# over-moves some quantiles; the lesser move of the two holds both.
StretchSpace = Literal["levels", "values", "lesser"]
STRETCH_SPACES: tuple[str, ...] = ("levels", "values", "lesser")


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


# ------------------------------------------------- online: interval widths by adaptive conformal


@dataclass
class IntervalTracker:
    """Online calibration that reacts within a week or two (``"regime-aci"``): adaptive
    conformal inference (Gibbs & Candès 2021; the P term of conformal PID control, Angelopoulos,
    Candès & Tibshirani 2023) of the width of the inner (50 %) and outer (90 %, or 95 %)
    intervals, per phase of the epidemic (falling, flat, rising), pooled over places and
    horizons.

    State: a log stretch φ[regime, end]. After each origin, the N forecasts whose target week
    ended by then and were not yet counted (every place and horizon) move it:
    φ[r, e] += η Σ_{cells of regime r} (1{outcome outside interval e} − α_e) / N, with N all of
    them (``step="pooled"``) or those of regime r (``"per-regime"``). A forecast
    of a place in regime r is published with each level τ read at Φ(e^{f(τ)} Φ⁻¹(τ)) of the
    average's quantile function, f = φ[r, inner] within the inner interval, φ[r, outer] beyond
    the outer one, linear in |Φ⁻¹(τ)| between: the median is never moved (moving it chased the
    last weeks' errors), the intervals widen where they missed and narrow where they held.
    |φ| ≤ ``cap``. No constant of the rule was fitted to a panel; η is the one setting."""

    levels: NDArray[np.float64]
    rate: float
    outer: float
    cap: float = 1.0
    step: TrackingStep = "pooled"
    # each interval's misses in units of their standard deviation √(α(1−α)), relative to the
    # inner interval's: the outer interval (α = 0.05) otherwise moves 2.3 times slower
    standardized: bool = False
    # the share of its stretch each phase lets go of at every origin (0: it keeps it until
    # outcomes move it back): a surge's widening fades when nothing renews it
    leak: float = 0.0
    space: StretchSpace = "levels"

    def __post_init__(self) -> None:
        self.stretch = np.zeros((N_REGIMES, 2))
        cover = np.array([0.5, self.outer])
        self._alpha = 1.0 - cover
        self._unit = (0.5 / np.sqrt(self._alpha * (1.0 - self._alpha)) if self.standardized
                      else np.ones(2))
        self._low = np.array([level_index(self.levels, 0.5 - c / 2) for c in cover])
        self._up = np.array([level_index(self.levels, 0.5 + c / 2) for c in cover])
        z_end = ndtri(0.5 + cover / 2)
        self._z = ndtri(self.levels)
        self._outer_weight = np.clip((np.abs(self._z) - z_end[0]) / (z_end[1] - z_end[0]), 0, 1)

    def update(self, published: NDArray[np.float64], truth: NDArray[np.float64],
               regimes: NDArray[np.intp]) -> None:
        """The newly known forecasts of one origin: published quantiles ``(N, Q)``, truth
        ``(N,)`` (NaN: not observed), the regime at each forecast's origin ``(N,)``."""
        self.stretch *= 1.0 - self.leak
        seen = np.isfinite(truth) & np.isfinite(published).all(axis=-1)
        if not seen.any():
            return
        missed = self.missed(published[seen], truth[seen])                       # (n, 2)
        steps = np.zeros((N_REGIMES, 2))
        np.add.at(steps, regimes[seen], missed - self._alpha)
        counts = (np.bincount(regimes[seen], minlength=N_REGIMES)[:, None]
                  if self.step == "per-regime" else np.full((N_REGIMES, 1), int(seen.sum())))
        self.stretch = np.clip(
            self.stretch + self.rate * self._unit * steps / np.maximum(counts, 1),
            -self.cap, self.cap)

    @property
    def alpha(self) -> NDArray[np.float64]:
        """The miss rates the inner and outer intervals aim at."""
        return self._alpha

    def missed(self, published: NDArray[np.float64], truth: NDArray[np.float64]
               ) -> NDArray[np.bool_]:
        """Whether each outcome ``(n,)`` fell outside the inner and the outer interval of its
        quantiles ``(n, Q)``: ``(n, 2)``."""
        y = truth[:, None]
        return (y < published[:, self._low]) | (y > published[:, self._up])

    def apply(self, quantiles: NDArray[np.float64], regimes: NDArray[np.intp]
              ) -> NDArray[np.float64]:
        """Quantiles ``(C, Q)`` read at each place's regime's stretched levels (``space``
        "levels"), their distances from the median stretched by the same factor ("values"), or
        each moved by the lesser of the two ("lesser")."""
        phi = self.stretch[regimes]                                              # (C, 2)
        f = (1.0 - self._outer_weight) * phi[:, :1] + self._outer_weight * phi[:, 1:]
        if self.space == "levels":
            out = self._on_levels(quantiles, f)
        elif self.space == "values":
            out = self._on_values(quantiles, f)
        else:
            on_levels, on_values = self._on_levels(quantiles, f), self._on_values(quantiles, f)
            out = np.where(np.abs(on_values - quantiles) <= np.abs(on_levels - quantiles),
                           on_values, on_levels)
        return np.maximum.accumulate(np.maximum(out, 0.0), axis=-1)

    def _on_levels(self, quantiles: NDArray[np.float64], f: NDArray[np.float64]
                   ) -> NDArray[np.float64]:
        return quantiles_at(self.levels, quantiles, ndtr(np.exp(f) * self._z))

    def _on_values(self, quantiles: NDArray[np.float64], f: NDArray[np.float64]
                   ) -> NDArray[np.float64]:
        median = quantiles[:, level_index(self.levels, 0.5)][:, None]
        return median + np.exp(f) * (quantiles - median)


@dataclass
class AggregatedTracker:
    """Adaptive conformal inference at several rates η, chosen by skill with coverage as the
    constraint (``"aggregated-aci"``; after AgACI, Zaffran et al. 2022). Each expert is an
    :class:`IntervalTracker` that learns from its own forecasts; an expert at η = 0 is the
    average uncalibrated. The published quantiles are the experts' level-wise average over the
    **admissible** ones: those whose intervals have so far covered within ``tolerance`` of their
    levels (5 points of the 50 % interval, 2.5 of the outer one), or while none has, those nearer
    to it than the slowest expert (in units of the tolerance, the worse of the two intervals).
    They are weighted by exp(−(L_e / min L − 1) / ``temperature``), L_e the expert's WIS summed
    over every outcome known so far, each outcome's WIS over the experts' mean WIS of it, so that
    every place and week counts alike whatever its size. A temperature of 0.01: an expert 1 %
    worse (the bound a calibration may cost) weighs e⁻¹ of the best.

    The published weights follow the rule's with a half-life of ``smoothing_origins`` origins
    (None: at once): when an expert's coverage crosses the tolerance, the rule's weights jump
    (on San Francisco's 2021-03-27 the fastest expert alone became admissible, and the week
    was published at 2.7 times the uncalibrated WIS); followed, the change is spread over a
    few origins, and the rule's long-run choice is unchanged."""

    experts: tuple[IntervalTracker, ...]
    temperature: float = 0.01
    tolerance: tuple[float, float] = (0.05, 0.025)
    # the half-life, in origins, of what an outcome counts towards the experts' losses and
    # coverage (None: every outcome counts alike for ever)
    memory_origins: float | None = None
    smoothing_origins: float | None = None

    def __post_init__(self) -> None:
        self.loss = np.zeros(len(self.experts))
        self.missed = np.zeros((len(self.experts), 2))
        self.scored = 0.0
        self._decay = 1.0 if self.memory_origins is None else 0.5 ** (1.0 / self.memory_origins)
        self._follow = (1.0 if self.smoothing_origins is None
                        else 1.0 - 0.5 ** (1.0 / self.smoothing_origins))
        self._published: NDArray[np.float64] | None = None

    @property
    def admissible(self) -> NDArray[np.bool_]:
        """The experts whose coverage so far is within the tolerance; while none is, those
        nearer to it than the slowest expert (η = 0: the average uncalibrated), so that the
        calibration never publishes coverage farther off than no calibration."""
        if self.scored == 0:
            return np.ones(len(self.experts), dtype=bool)
        alpha = np.stack([e.alpha for e in self.experts])                     # (E, 2)
        off = (np.abs(self.missed / self.scored - alpha) / np.asarray(self.tolerance)).max(axis=1)
        if (off <= 1.0).any():
            return off <= 1.0
        nearer = off < off[int(np.argmin([e.rate for e in self.experts]))]
        return nearer if nearer.any() else off <= off.min()

    @property
    def weights(self) -> NDArray[np.float64]:
        """The published weights: the rule's (:attr:`rule_weights`), followed with a half-life
        of ``smoothing_origins`` origins."""
        return self.rule_weights if self._published is None else self._published

    @property
    def rule_weights(self) -> NDArray[np.float64]:
        """The skill weights among the admissible experts, from the outcomes known now."""
        allowed = self.admissible
        if self.scored == 0:
            return allowed / allowed.sum()
        excess = self.loss / self.loss[allowed].min() - 1.0
        w = np.where(allowed, np.exp(-np.clip(excess, 0.0, None) / self.temperature), 0.0)
        return w / w.sum()

    def expert_quantiles(self, quantiles: NDArray[np.float64], regimes: NDArray[np.intp]
                         ) -> NDArray[np.float64]:
        """Each expert's quantiles ``(E, C, Q)`` of the average's ``(C, Q)``."""
        return np.stack([e.apply(quantiles, regimes) for e in self.experts])

    def combine(self, experts: NDArray[np.float64]) -> NDArray[np.float64]:
        """The published quantiles ``(..., Q)`` of the experts' ``(E, ..., Q)``."""
        return np.tensordot(self.weights, experts, axes=1)

    def update(self, experts: NDArray[np.float64], truth: NDArray[np.float64],
               regimes: NDArray[np.intp], wis: NDArray[np.float64]) -> None:
        """The newly known forecasts of one origin: each expert's quantiles ``(E, N, Q)``, truth
        ``(N,)``, regimes ``(N,)`` and each expert's WIS of them ``(E, N)`` (NaN: unscored).
        Called once per origin, also when nothing became known: the published weights move
        towards the rule's at every origin."""
        self._learn(experts, truth, regimes, wis)
        rule = self.rule_weights
        self._published = (rule if self._published is None or self.scored == 0
                           else (1.0 - self._follow) * self._published + self._follow * rule)

    def _learn(self, experts: NDArray[np.float64], truth: NDArray[np.float64],
               regimes: NDArray[np.intp], wis: NDArray[np.float64]) -> None:
        for expert, quantiles in zip(self.experts, experts):
            expert.update(quantiles, truth, regimes)
        self.loss *= self._decay
        self.missed *= self._decay
        self.scored *= self._decay
        finite = np.isfinite(wis).all(axis=0)
        mean = np.where(finite, wis, 0.0).mean(axis=0)
        seen = finite & (mean > 0)
        if not seen.any():
            return
        self.loss += (wis[:, seen] / mean[seen]).sum(axis=1)
        self.missed += np.stack([e.missed(q[seen], truth[seen]).sum(axis=0)
                                 for e, q in zip(self.experts, experts)])
        self.scored += float(seen.sum())
