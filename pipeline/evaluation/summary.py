"""The one scoring path of every backtest: forecasts of many places and origins → scores →
summaries, per target × horizon, never pooled across targets.

:func:`score_cells` scores a forecaster's quantiles ``(C, O, H, Q)`` against the truth
``(C, O, H)`` cell by cell (WIS and its parts, 50 %/90 %/95 % coverage, PIT, median; NaN where
not observed or not forecast). :func:`summarize_forecaster` turns a forecaster's scores and the
hub baseline's into its summary:

* ``relative_wis_vs_baseline.{h…, all}`` — Σ WIS / Σ WIS of the hub baseline over the cells both
  scored (the figure of a single series);
* ``gmean_relative_wis.{h…, all}`` — the geometric mean over places of each place's ratio, the
  Forecast Hub's way of comparing across locations; ``share_beating_baseline`` — the share of
  places whose ratio is < 1; ``per_place`` — each place's ratio (panels of more than one place);
* ``coverage50``, ``coverage90``, ``coverage95`` (and per horizon), each overall one with its
  95 % moving-block bootstrap interval over origins (``coverage50_interval``, …;
  :mod:`pipeline.evaluation.bootstrap`: how far a miss is from chance), ``mean_wis``, the WIS
  parts' shares, a 10-bin PIT histogram;
* ``by_regime.{falling, flat, rising, largest10}`` — the same relative WIS and coverage (with
  its interval) over the cells whose origin was in that phase
  (:mod:`pipeline.evaluation.regimes`) and over the cells of each place's largest 10 % of
  observed weekly counts (intervals that hold on average can fail exactly when the epidemic
  turns).

:func:`calibration_cost` is what a calibration costs (or saves) in WIS: the published forecast's
Σ WIS over the same average's before calibration, on the cells both scored, over every origin
and in each window of consecutive origins (a calibration that holds on average may not let go
of a past surge: its worst window says so).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from pipeline.evaluation.bootstrap import coverage_interval
from pipeline.evaluation.quantile_function import median_index, pit_from_quantiles
from pipeline.evaluation.regimes import REGIME_NAMES
from pipeline.evaluation.scoring import interval_coverage, weighted_interval_score

PIT_BINS = 10
COVERAGES = (0.5, 0.9, 0.95)
LARGEST_SHARE = 0.1


@dataclass(frozen=True, eq=False)
class CellScores:
    """Scores ``(C, O, H)`` of one forecaster on one target (NaN: not scored)."""

    wis: NDArray[np.float64]
    dispersion: NDArray[np.float64]
    overprediction: NDArray[np.float64]
    underprediction: NDArray[np.float64]
    covered: Mapping[float, NDArray[np.float64]]     # by central interval (0.5, 0.9, 0.95)
    pit: NDArray[np.float64]
    median: NDArray[np.float64]


def score_cells(values: NDArray[np.float64], truth: NDArray[np.float64],
                levels: NDArray[np.float64], unit: NDArray[np.float64] | float = 1.0
                ) -> CellScores:
    """Scores of quantiles ``values (..., Q)`` against ``truth (...)``; ``unit`` turns the
    target into counts for the PIT (N for I, 1 for a count)."""
    seen = np.isfinite(truth) & np.isfinite(values).all(axis=-1)
    nan = np.where(seen, 1.0, np.nan)
    q = np.where(seen[..., None], values, 0.0)
    y = np.where(seen, truth, 0.0)
    parts = weighted_interval_score(levels, q, y)
    u = np.broadcast_to(np.asarray(unit, dtype=np.float64), y.shape)
    mid = median_index(levels)
    return CellScores(
        wis=parts.wis * nan, dispersion=parts.dispersion * nan,
        overprediction=parts.overprediction * nan, underprediction=parts.underprediction * nan,
        covered={c: interval_coverage(levels, q, y, c).astype(np.float64) * nan
                 for c in COVERAGES if _has_interval(levels, c)},
        pit=pit_from_quantiles(levels, q * u[..., None], y * u) * nan,
        median=q[..., mid] * nan)


def _has_interval(levels: NDArray[np.float64], coverage: float) -> bool:
    lo = (1.0 - coverage) / 2.0
    return bool(np.isclose(levels, lo).any() and np.isclose(levels, 1.0 - lo).any())


def _ratio(num: float, den: float) -> float | None:
    return float(num / den) if den > 0 else None


def _sums_ratio(wis: NDArray[np.float64], base: NDArray[np.float64]) -> float | None:
    both = np.isfinite(wis) & np.isfinite(base)
    return _ratio(float(wis[both].sum()), float(base[both].sum())) if both.any() else None


def _place_ratios(wis: NDArray[np.float64], base: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per place (first axis) Σ WIS / Σ baseline WIS over the cells both scored."""
    both = np.isfinite(wis) & np.isfinite(base)
    axes = tuple(range(1, wis.ndim))
    num = np.where(both, wis, 0.0).sum(axis=axes)
    den = np.where(both, base, 0.0).sum(axis=axes)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(both.any(axis=axes), num / den, np.nan)


def _gmean(ratios: NDArray[np.float64]) -> float | None:
    finite = ratios[np.isfinite(ratios) & (ratios > 0)]
    return float(np.exp(np.log(finite).mean())) if finite.size else None


def _mean(values: NDArray[np.float64]) -> float | None:
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else None


def _coverage(scores: CellScores, mask: NDArray[np.bool_] | None = None
              ) -> dict[str, float | None]:
    return {f"coverage{round(100 * c)}": _mean(v if mask is None else v[mask])
            for c, v in scores.covered.items()}


def _coverage_intervals(scores: CellScores, mask: NDArray[np.bool_]
                        ) -> dict[str, list[float] | None]:
    """The 95 % moving-block bootstrap interval of each coverage (origins resampled)."""
    out: dict[str, list[float] | None] = {}
    for c, v in scores.covered.items():
        interval = coverage_interval(v, mask)
        out[f"coverage{round(100 * c)}_interval"] = None if interval is None else list(interval)
    return out


def _masked_summary(scores: CellScores, base_wis: NDArray[np.float64],
                    mask: NDArray[np.bool_]) -> dict[str, Any]:
    wis = np.where(mask, scores.wis, np.nan)
    base = np.where(mask, base_wis, np.nan)
    scored = mask & np.isfinite(scores.wis)
    return {"relative_wis_vs_baseline": _sums_ratio(wis, base),
            "gmean_relative_wis": _gmean(_place_ratios(wis, base)),
            **_coverage(scores, scored), **_coverage_intervals(scores, scored),
            "n_scored": int(scored.sum())}


def regime_masks(regimes: NDArray[np.intp], truth: NDArray[np.float64], n_horizons: int
                 ) -> dict[str, NDArray[np.bool_]]:
    """Cells ``(C, O, H)`` by the phase of their origin, and each place's largest 10 % of
    observed weekly counts."""
    phase = np.broadcast_to(regimes[..., None], regimes.shape + (n_horizons,))
    out = {name: phase == r for r, name in enumerate(REGIME_NAMES)}
    flat = truth.reshape(truth.shape[0], -1)
    with np.errstate(invalid="ignore"):
        cut = np.array([np.nanquantile(row, 1.0 - LARGEST_SHARE) if np.isfinite(row).any()
                        else np.inf for row in flat])
        out["largest10"] = truth >= cut[:, None, None]
    return out


def summarize_forecaster(scores: CellScores, base_wis: NDArray[np.float64],
                         horizons: Sequence[int], places: Sequence[str],
                         masks: Mapping[str, NDArray[np.bool_]] | None = None
                         ) -> dict[str, Any]:
    """One forecaster on one target (module docstring); arrays are ``(C, O, H)``."""
    keys = [f"h{h}" for h in horizons]
    wis = scores.wis
    per_h = np.stack([_place_ratios(wis[:, :, k], base_wis[:, :, k])
                      for k in range(len(horizons))], axis=1)                # (C, H)
    overall = _place_ratios(wis, base_wis)                                   # (C,)
    pit = scores.pit[np.isfinite(scores.pit)]
    hist, _ = np.histogram(pit, bins=PIT_BINS, range=(0.0, 1.0))
    total = np.nansum(wis)
    out: dict[str, Any] = {
        "relative_wis_vs_baseline": {k: _sums_ratio(wis[:, :, i], base_wis[:, :, i])
                                     for i, k in enumerate(keys)}
                                    | {"all": _sums_ratio(wis, base_wis)},
        "gmean_relative_wis": {k: _gmean(per_h[:, i]) for i, k in enumerate(keys)}
                              | {"all": _gmean(overall)},
        "share_beating_baseline": {k: _share_below_one(per_h[:, i]) for i, k in enumerate(keys)}
                                  | {"all": _share_below_one(overall)},
        **_coverage(scores),
        **_coverage_intervals(scores, np.isfinite(wis)),
        "coverage_by_horizon": {k: _coverage(_at_horizon(scores, i)) for i, k in enumerate(keys)},
        "mean_wis": {k: _mean(wis[:, :, i]) for i, k in enumerate(keys)},
        "wis_parts_share": {p: _ratio(float(np.nansum(getattr(scores, p))), float(total))
                            for p in ("dispersion", "overprediction", "underprediction")},
        "pit_histogram": {"bins": PIT_BINS, "counts": hist.astype(int).tolist()},
        "n_scored": int(np.isfinite(wis).sum()),
    }
    if len(places) > 1:
        out["per_place"] = {p: {k: _finite_or_none(per_h[c, i]) for i, k in enumerate(keys)}
                            | {"all": _finite_or_none(overall[c])} for c, p in enumerate(places)}
    if masks is not None:
        out["by_regime"] = {name: _masked_summary(scores, base_wis, mask)
                            for name, mask in masks.items()}
    return out


def _share_below_one(ratios: NDArray[np.float64]) -> float | None:
    finite = ratios[np.isfinite(ratios)]
    return float(np.mean(finite < 1)) if finite.size else None


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def _at_horizon(scores: CellScores, k: int) -> CellScores:
    return CellScores(scores.wis[:, :, k], scores.dispersion[:, :, k],
                      scores.overprediction[:, :, k], scores.underprediction[:, :, k],
                      {c: v[:, :, k] for c, v in scores.covered.items()}, scores.pit[:, :, k],
                      scores.median[:, :, k])


# the windows a calibration's cost is read over: 15 consecutive origins (about a season's turn)
COST_WINDOW_ORIGINS = 15


def calibration_cost(published_wis: NDArray[np.float64], uncalibrated_wis: NDArray[np.float64],
                     origins: Sequence[Any], window: int = COST_WINDOW_ORIGINS
                     ) -> dict[str, Any]:
    """Σ WIS published / Σ WIS uncalibrated ``(C, O, H)`` over every origin (``all``) and over
    each ``window`` consecutive origins: the worst window, its first and last origin, and how
    many windows there were (``None`` where nothing is scored)."""
    both = np.isfinite(published_wis) & np.isfinite(uncalibrated_wis)
    num = np.where(both, published_wis, 0.0).sum(axis=(0, 2))                    # (O,)
    den = np.where(both, uncalibrated_wis, 0.0).sum(axis=(0, 2))
    out: dict[str, Any] = {"all": _ratio(float(num.sum()), float(den.sum())),
                           "window_origins": window, "worst_window": None, "n_windows": 0}
    if len(num) < window:
        return out
    kernel = np.ones(window)
    num_w, den_w = np.convolve(num, kernel, "valid"), np.convolve(den, kernel, "valid")
    seen = den_w > 0
    if not seen.any():
        return out
    ratios = np.where(seen, num_w / np.where(seen, den_w, 1.0), -np.inf)
    worst = int(np.argmax(ratios))
    return out | {"worst_window": float(ratios[worst]), "n_windows": int(seen.sum()),
                  "worst_window_origins": [_day(origins[worst]),
                                           _day(origins[worst + window - 1])]}


def _day(origin: Any) -> str:
    return str(np.datetime_as_string(np.datetime64(origin, "D")))
