"""Averaging the members' quantiles, and the weights of the average.

**Quantile averaging** (Vincentization, :func:`vincentize`): the τ-quantile is
Σ_m w_m q_m(τ), on the scale of log(1 + q) by default — the weighted geometric mean of the
members' quantiles (of counts + 1). Epidemic counts grow multiplicatively, so a member
forecasting growth and one forecasting a plateau average to a damped growth *rate*, where the
linear average is pulled to the larger member's scale. ``"mixture"``: the linear pool (the
average of the members' CDFs), wider where the members disagree — at the turns;
``"log-mixture"``: the log-scale midpoint of the two, level by level.

**Weights** per horizon from the scores known at the origin (:func:`fit_weights`):
``"equal"`` (published); ``"inverse-wis"`` — ∝ 1 / (each member's geometric mean over places of
its relative WIS) over the last scored origins, shrunk towards equal weights by
n / (n + n0); ``"stacking"`` — the weights on a simplex grid whose average had the lowest mean
over places of log(Σ WIS / Σ WIS of the hub baseline), shrunk the same way.

**Mixtures** (:func:`mix_quantiles`): the equal mixture of K forecasts (a nowcast's
completions) — the average of their CDFs, not of their quantiles — from stratified draws of each
component's quantile function.
"""
from __future__ import annotations

import itertools
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from pipeline.errors import FlowcastError
from pipeline.evaluation.quantile_function import quantiles_at
from pipeline.evaluation.scoring import quantiles_from_samples, weighted_interval_score

AverageScale = Literal["log", "linear", "mixture", "log-mixture"]
WeightMethod = Literal["stacking", "inverse-wis", "equal"]
_EPS_WIS = 1e-12


class EnsembleError(FlowcastError):
    """Members' forecasts that cannot be combined (shapes, names, weights, settings)."""


def vincentize(values: NDArray[np.float64], weights: NDArray[np.float64],
               scale: AverageScale = "linear") -> NDArray[np.float64]:
    """Quantile average: ``values (M, ..., Q)`` with weights ``(M,)`` → ``(..., Q)`` (module
    docstring)."""
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != values.shape[:1] or abs(w.sum() - 1.0) > 1e-9 or (w < 0).any():
        raise EnsembleError(f"weights {w.tolist()} must be {values.shape[0]} non-negative "
                            "numbers summing to 1")
    if scale == "log":
        return np.expm1(np.tensordot(w, np.log1p(np.maximum(values, 0.0)), axes=1))
    if scale == "linear":
        return np.tensordot(w, values, axes=1)
    if scale == "mixture":
        return weighted_mixture(values, w)
    if scale == "log-mixture":
        return np.expm1(0.5 * np.log1p(vincentize(values, w, "log"))
                        + 0.5 * np.log1p(weighted_mixture(values, w)))
    raise EnsembleError(f"average scale {scale!r}: use 'log', 'linear', 'mixture' or "
                        "'log-mixture'")


def scored_wis(levels: NDArray[np.float64], q: NDArray[np.float64], y: NDArray[np.float64]
               ) -> NDArray[np.float64]:
    """WIS of quantiles ``(..., Q)`` against ``y (...)``; NaN where ``y`` is not observed or
    the cell has no forecast (a non-finite quantile: a member left out there, or beyond its
    reach), which the weights and the calibration then pass over, as an unobserved cell."""
    forecast = np.asarray(np.isfinite(q).all(axis=-1), dtype=bool)
    seen = np.isfinite(y) & forecast
    out = weighted_interval_score(levels, np.where(forecast[..., None], q, 0.0),
                                  np.where(seen, y, 0.0)).wis
    return np.where(seen, out, np.nan)


def simplex_grid(members: int, step: float) -> NDArray[np.float64]:
    """Every weight vector of ``members`` non-negative multiples of ``step`` summing to 1."""
    n = int(round(1.0 / step))
    rows = [c for c in itertools.product(range(n + 1), repeat=members - 1) if sum(c) <= n]
    return np.array([list(c) + [n - sum(c)] for c in rows], dtype=np.float64) / n


def log_relative_wis_by_place(wis: NDArray[np.float64], baseline_wis: NDArray[np.float64]
                              ) -> NDArray[np.float64]:
    """Mean over places of log(Σ WIS / Σ baseline WIS); ``wis (..., C, n)``, NaN cells ignored
    (a member without a forecast there, the seasonal one before its climatology: compared on
    the cells it forecast)."""
    seen = np.isfinite(baseline_wis) & np.isfinite(wis)
    num = np.where(seen, wis, 0.0).sum(axis=-1) + _EPS_WIS
    den = np.where(seen, baseline_wis, 0.0).sum(axis=-1) + _EPS_WIS
    places = seen.any(axis=-1)                              # (..., C): each forecaster's own
    return (np.where(places, np.log(num / den), 0.0).sum(axis=-1)
            / np.maximum(places.sum(axis=-1), 1))


def grid_averages(values: NDArray[np.float64], grid: NDArray[np.float64], scale: AverageScale
                  ) -> NDArray[np.float64]:
    """The average ``(K, ..., Q)`` of ``values (M, ..., Q)`` under each weighting of ``grid``
    ``(K, M)``, on the cells every member forecast (a stand-in of 1 elsewhere: such a cell's
    truth is not scored)."""
    every = np.asarray(np.isfinite(values).all(axis=(0, -1)), dtype=bool)
    values = np.where(every[None, ..., None], values, 1.0)
    return np.stack([vincentize(values, w, scale) for w in grid])


class GridAverages:
    """The stacking's averages of past forecasts, each origin × horizon computed once.

    The stacking at origin j scores every weighting of the grid on the window of origins
    scored by then; the next origins' windows hold most of the same origins, and an average
    of a cell does not depend on the origin that reads it, so each is computed once
    (:func:`grid_averages`) and dropped when no later window can hold it. Without the store a
    window of n origins averages each past origin n times (the stacking of three members took
    most of an hour of a FluSight backtest)."""

    def __init__(self, values: NDArray[np.float64], step: float, scale: AverageScale) -> None:
        self.values = values                                             # (M, C, O, H, Q)
        self.grid = simplex_grid(values.shape[0], step)
        self.scale: AverageScale = scale
        self._made: dict[tuple[int, int], NDArray[np.float64]] = {}

    def at(self, origins: NDArray[np.intp], k: int) -> NDArray[np.float64]:
        """``(K, C, n, Q)``: each weighting's average of the cells of ``origins`` at horizon
        position ``k``."""
        if origins.size:
            first = int(origins.min())
            for key in [key for key in self._made if key[1] == k and key[0] < first]:
                del self._made[key]
        for i in origins:
            if (int(i), k) not in self._made:
                self._made[int(i), k] = grid_averages(self.values[:, :, int(i), k], self.grid,
                                                      self.scale)
        return np.stack([self._made[int(i), k] for i in origins], axis=2) if origins.size \
            else np.empty((len(self.grid), self.values.shape[1], 0, self.values.shape[-1]))


def fit_weights(method: WeightMethod, past_values: NDArray[np.float64],
                past_truth: NDArray[np.float64], past_baseline_wis: NDArray[np.float64],
                levels: NDArray[np.float64], n_origins: int, *, scale: AverageScale,
                shrinkage_origins: float, stacking_step: float,
                averages: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Weights ``(M,)`` from past quantiles ``(M, C, n, Q)``, truth ``(C, n)`` and the
    baseline's WIS ``(C, n)`` over ``n_origins`` scored origins (module docstring); the
    stacking's ``averages`` ``(K, C, n, Q)`` of the past cells when already made
    (:class:`GridAverages`)."""
    m = past_values.shape[0]
    equal = np.full(m, 1.0 / m)
    if method == "equal" or n_origins == 0 or m == 1:
        return equal
    lam = n_origins / (n_origins + shrinkage_origins)
    if method == "inverse-wis":
        member_wis = scored_wis(levels, past_values,
                                np.broadcast_to(past_truth, past_values.shape[:-1]))
        loss = np.exp(log_relative_wis_by_place(member_wis, past_baseline_wis))
        skill = 1.0 / np.maximum(loss, 1e-12)
        return lam * skill / skill.sum() + (1.0 - lam) * equal
    grid = simplex_grid(m, stacking_step)                                  # (K, M)
    # scored on the cells every member forecast (a stand-in elsewhere, its truth unseen)
    every = np.asarray(np.isfinite(past_values).all(axis=(0, -1)), dtype=bool)  # (C, n)
    past_truth = np.where(every, past_truth, np.nan)
    combined = (grid_averages(past_values, grid, scale) if averages is None
                else averages)                                             # (K, C, n, Q)
    wis = scored_wis(levels, combined, np.broadcast_to(past_truth, combined.shape[:-1]))
    loss = log_relative_wis_by_place(wis, past_baseline_wis)               # (K,)
    return lam * grid[int(np.argmin(loss))] + (1.0 - lam) * equal


MIX_LEVELS = 200


def weighted_mixture(values: NDArray[np.float64], weights: NDArray[np.float64],
                     n_levels: int = MIX_LEVELS) -> NDArray[np.float64]:
    """The mixture (linear pool: the weighted average of the CDFs) of ``values (M, ..., Q)``
    at the hub levels of :data:`HUB_QUANTILE_LEVELS`' kind, from stratified draws of each
    member's quantile function in proportion to its weight."""
    q = values.shape[-1]
    levels = _levels_of(q)
    counts = np.round(np.asarray(weights) * n_levels).astype(int)
    draws = [quantiles_at(levels, values[m], np.broadcast_to(
        (np.arange(c) + 0.5) / c, values.shape[1:-1] + (c,))) for m, c in enumerate(counts) if c]
    return quantiles_from_samples(np.concatenate(draws, axis=-1), levels)


def _levels_of(n_levels: int) -> NDArray[np.float64]:
    from pipeline.panels.targets import HUB_QUANTILE_LEVELS

    if n_levels != len(HUB_QUANTILE_LEVELS):
        raise EnsembleError(f"a mixture is taken at the hub's {len(HUB_QUANTILE_LEVELS)} "
                            f"levels, not {n_levels}")
    return np.asarray(HUB_QUANTILE_LEVELS)


def mix_quantiles(quantiles: NDArray[np.float64], levels: NDArray[np.float64],
                  n_levels: int = MIX_LEVELS) -> NDArray[np.float64]:
    """The equal mixture of K forecasts ``(K, ..., Q)`` as quantiles ``(..., Q)``: stratified
    draws of each component's quantile function, pooled."""
    u = (np.arange(n_levels) + 0.5) / n_levels
    draws = quantiles_at(levels, quantiles, np.broadcast_to(u, quantiles.shape[:-1]
                                                            + (n_levels,)))     # (K, ..., M)
    pooled = np.moveaxis(draws, 0, -2).reshape(*quantiles.shape[1:-1], -1)
    return quantiles_from_samples(pooled, levels)
