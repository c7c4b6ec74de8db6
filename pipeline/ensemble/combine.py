"""The published forecast: a weighted quantile average of the members, recalibrated, with paths.

1. **Weights** per target × horizon from past origins only: a member's forecast from origin o at
   horizon h is scored (usable) at origin t only when o + 7h ≤ t. Skill (``EnsembleConfig.skill``)
   over the last ``window`` origins where every member was scored:

   - ``"wis"`` (default): the member's mean WIS. The backtest's headline, relative WIS, is a
     ratio of summed WIS, dominated by the weeks with many cases; weighting by the same loss
     aims the combination at the figure it is judged by.
   - ``"relative-wis"``: the mean over origins of WIS / (the members' mean WIS at that origin),
     scale-free (every week counts alike, quiet or not).

   Weights are proportional to the inverse skill, shrunk to equal weights with n scored origins:
   w = n/(n + n0)·w_skill + n0/(n + n0)·(1/M).
2. **Quantile averaging** (Vincentization): the published τ-quantile is Σ_m w_m q_m(τ).
3. **Recalibration** of the average from the past PIT values of the (uncalibrated) average at the
   same target × horizon (:mod:`pipeline.ensemble.calibration`).
4. **Published = cases**; I = cases / N (N·I is the 7-day case count, L = 7), so the published
   I and cases are one forecast.
5. **Sample paths** (weekly S, I, R at origin + 7h) from the published case quantiles: ensemble
   copula coupling (Schefzik, Thorarinsdottir & Gneiting 2013) with the ranks of a member's
   paths when given (their weekly cases N·I_h), else comonotone draws (one level per path).
   I_h = C_h/N, S_h = S_{h−1} − C_h/N from the observed S at the origin (C_h at most the
   remaining susceptibles N·S_{h−1}, a physical bound), R_h = 1 − S_h − I_h. Non-negative,
   S non-increasing and R non-decreasing by construction (R_h − R_{h−1} = C_{h−1}/N ≥ 0, with
   C_0 = N·I at the origin); :func:`count_invalid` checks it.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from pipeline.errors import FlowcastError
from pipeline.ensemble.calibration import quantiles_at
from pipeline.ensemble.targets import EpiHistory, QuantileForecast

AverageScale = Literal["log", "linear"]

PUBLISHED = "published"
UNCALIBRATED = "ensemble-uncalibrated"


class EnsembleError(FlowcastError):
    """Members' forecasts that cannot be combined (different levels, horizons, origins)."""


@dataclass(frozen=True)
class EnsembleConfig:
    """How the members are averaged. ``weighting``: ``"equal"`` (published) or ``"skill"``
    (inverse mean WIS over the last ``window`` scored origins, shrunk towards equal with n0 =
    ``shrinkage_origins``); ``scale``: average log(1 + quantiles) (published) or the quantiles."""

    weighting: Literal["equal", "skill"] = "equal"
    scale: AverageScale = "log"
    window: int = 12
    shrinkage_origins: float = 4.0
    skill: Literal["wis", "relative-wis"] = "wis"

    def __post_init__(self) -> None:
        if self.window < 1 or self.shrinkage_origins < 0:
            raise EnsembleError(f"invalid EnsembleConfig {self}: window >= 1, shrinkage >= 0")
        if self.skill not in ("wis", "relative-wis"):
            raise EnsembleError(f"EnsembleConfig.skill={self.skill!r}: use 'wis' or "
                                "'relative-wis'")
        if self.weighting not in ("equal", "skill") or self.scale not in ("log", "linear"):
            raise EnsembleError(f"EnsembleConfig weighting={self.weighting!r} (equal|skill), "
                                f"scale={self.scale!r} (log|linear)")


def skill_weights(past_wis: NDArray[np.float64],
                  config: EnsembleConfig = EnsembleConfig()) -> NDArray[np.float64]:
    """Weights ``(M,)`` from past WIS ``(n, M)`` of M members at n past origins (oldest first;
    rows with a missing member are ignored). n = 0 gives equal weights."""
    wis = np.asarray(past_wis, dtype=np.float64)
    m = wis.shape[1]
    equal = np.full(m, 1.0 / m)
    if config.weighting == "equal":
        return equal
    wis = wis[np.isfinite(wis).all(axis=1)][-config.window:]
    scale = wis.mean(axis=1, keepdims=True) if wis.size else wis
    wis, scale = wis[scale[:, 0] > 0], scale[scale[:, 0] > 0]
    n = wis.shape[0]
    if n == 0:
        return equal
    loss = wis.mean(axis=0) if config.skill == "wis" else (wis / scale).mean(axis=0)
    skill = 1.0 / np.maximum(loss, 1e-300)
    skill /= skill.sum()
    lam = n / (n + config.shrinkage_origins)
    return lam * skill + (1.0 - lam) * equal


def vincentize(values: NDArray[np.float64], weights: NDArray[np.float64],
               scale: AverageScale = "linear") -> NDArray[np.float64]:
    """Quantile average: ``values (M, ..., Q)`` with weights ``(M,)`` → ``(..., Q)``.

    ``scale="log"`` averages log(1 + q): the weighted geometric mean of the members' quantiles
    (of counts + 1). Epidemic counts grow multiplicatively, so a member forecasting growth and one
    forecasting a plateau average to a damped growth *rate*, where the linear average is pulled
    to the larger member's scale."""
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != values.shape[:1] or abs(w.sum() - 1.0) > 1e-9 or (w < 0).any():
        raise EnsembleError(f"weights {w.tolist()} must be {values.shape[0]} non-negative "
                            "numbers summing to 1")
    if scale == "log":
        return np.expm1(np.tensordot(w, np.log1p(np.maximum(values, 0.0)), axes=1))
    if scale == "linear":
        return np.tensordot(w, values, axes=1)
    raise EnsembleError(f"average scale {scale!r}: use 'log' or 'linear'")


def check_compatible(forecasts: Sequence[QuantileForecast]) -> None:
    if not forecasts:
        raise EnsembleError("no member forecasts to combine")
    ref = forecasts[0]
    for f in forecasts[1:]:
        if (f.origin != ref.origin or f.horizons != ref.horizons
                or not np.array_equal(f.levels, ref.levels)):
            raise EnsembleError(f"{f.forecaster} ({f.origin.date()}, h={f.horizons}) does not "
                                f"match {ref.forecaster} ({ref.origin.date()}, h={ref.horizons}) "
                                "in origin, horizons or levels")


# ------------------------------------------------------------------------------- sample paths


def path_levels(n_paths: int, horizons: int, ranks_from: NDArray[np.float64] | None
                ) -> NDArray[np.float64]:
    """Levels ``(n, H)`` of each path's weekly cases: comonotone (k − ½)/n, or ECC: the levels
    in the order of the ranks of ``ranks_from (n, H)`` (a member's weekly cases per path)."""
    base = (np.arange(n_paths) + 0.5) / n_paths
    if ranks_from is None:
        return np.repeat(base[:, None], horizons, axis=1)
    if ranks_from.shape != (n_paths, horizons):
        raise EnsembleError(f"copula template has shape {ranks_from.shape}, expected "
                            f"{(n_paths, horizons)}")
    ranks = np.argsort(np.argsort(ranks_from, axis=0, kind="stable"), axis=0, kind="stable")
    return base[ranks]


def sample_paths(history: EpiHistory, levels: NDArray[np.float64],
                 case_quantiles: NDArray[np.float64], n_paths: int,
                 template_paths: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Weekly S/I/R paths ``(n, H, 3)`` at origin + 7h from case quantiles ``(H, Q)``."""
    n_h = case_quantiles.shape[0]
    n = float(history.population)
    template = None
    if template_paths is not None:
        if template_paths.shape[0] < n_paths or template_paths.shape[1] != n_h:
            raise EnsembleError(f"template paths {template_paths.shape} do not give {n_paths} "
                                f"paths over {n_h} horizons")
        template = template_paths[:n_paths, :, 1] * n        # weekly cases = N·I (L = 7)
    u = path_levels(n_paths, n_h, template)                      # (n, H)
    draws = quantiles_at(levels, case_quantiles, u.T, unit=1.0).T           # (n, H)
    s_prev = np.full(n_paths, float(history.S[-1]))
    out = np.empty((n_paths, n_h, 3))
    for k in range(n_h):
        cases = np.minimum(draws[:, k], n * s_prev)              # at most the susceptibles
        s_new = np.where(cases >= n * s_prev, 0.0, s_prev - cases / n)
        i_new = cases / n
        out[:, k, 0], out[:, k, 1] = s_new, i_new
        out[:, k, 2] = 1.0 - s_new - i_new
        s_prev = s_new
    return out


@dataclass(frozen=True)
class InvalidCounts:
    negative_fractions: int
    s_increases: int
    r_decreases: int
    negative_rates: int

    @property
    def total(self) -> int:
        return self.negative_fractions + self.s_increases + self.r_decreases + self.negative_rates

    def to_dict(self) -> dict[str, int]:
        return {"negative_fractions": self.negative_fractions, "s_increases": self.s_increases,
                "r_decreases": self.r_decreases, "negative_rates": self.negative_rates,
                "total": self.total}


def count_invalid(paths: NDArray[np.float64], start: NDArray[np.float64],
                  rates: NDArray[np.float64] | None = None) -> InvalidCounts:
    """Invalid values in ``paths (n, H, 3)`` starting from the observed ``start (3,)`` S, I, R:
    negative fractions, S increases, R decreases (each step, the first from the start), and
    negative rates in ``rates (n, ...)`` when given."""
    full = np.concatenate([np.broadcast_to(start, (paths.shape[0], 1, 3)), paths], axis=1)
    return InvalidCounts(
        negative_fractions=int((paths < 0).sum()),
        s_increases=int((np.diff(full[..., 0], axis=1) > 0).sum()),
        r_decreases=int((np.diff(full[..., 2], axis=1) < 0).sum()),
        negative_rates=int((rates < 0).sum()) if rates is not None else 0)


def add_counts(a: InvalidCounts, b: InvalidCounts) -> InvalidCounts:
    return InvalidCounts(a.negative_fractions + b.negative_fractions,
                         a.s_increases + b.s_increases, a.r_decreases + b.r_decreases,
                         a.negative_rates + b.negative_rates)


def member_matrix(forecasts: Mapping[str, QuantileForecast], names: Sequence[str],
                  target: str) -> NDArray[np.float64]:
    """``(M, H, Q)`` quantiles of ``target`` of the named members."""
    missing = [n for n in names if n not in forecasts or target not in forecasts[n].values]
    if missing:
        raise EnsembleError(f"members {missing} gave no {target} forecast")
    return np.stack([forecasts[n].values[target] for n in names])
