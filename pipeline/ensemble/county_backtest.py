"""The cross-county real-time backtest: every California county as the design set.

Every county with at least ``min_population`` people in a CDPH vintage is forecast at every
Saturday origin with four weeks of truth. Real-time discipline as in the single-series backtest:
each cell (county × origin) sees its own county's data up to its origin only, and the published
forecast's weights and recalibration use only the scores of forecasts whose target week had
ended by the origin, pooled across counties (:mod:`pipeline.ensemble.pooled`).

The vintage's last ``trailing_days`` days (default 14) are cut before anything is forecast or
scored: they were still filling in when it was downloaded (the nowcast's job, not this one's).

Summary (:func:`summarize_panel`), per target (``cases``, ``I``) × forecaster, never pooled
across targets:

* ``gmean_relative_wis.{h1..h4, all}``: the geometric mean over counties of each county's
  relative WIS (Σ WIS / Σ WIS of the hub baseline over the same cells) — the Forecast Hub's way
  of comparing across locations;
* ``share_beating_baseline.{h1..h4, all}``: the share of counties whose relative WIS is < 1;
* ``coverage50``, ``coverage90`` (and per horizon), a 10-bin PIT histogram, pooled over cells;
* ``per_county.<county>.{h1..h4, all}``: each county's relative WIS.
"""
from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.cdph import CDPHVintage
from pipeline.ensemble.calibration import pit_from_quantiles
from pipeline.ensemble.combine import PUBLISHED, UNCALIBRATED
from pipeline.ensemble.hub_baseline import HUB_BASELINE, HubBaseline, HubBaselineConfig
from pipeline.ensemble.members import Member
from pipeline.ensemble.panel import (BatchMember, Panel, cell_histories, member_forecast_arrays,
                                     truth_arrays, weekly_origins)
from pipeline.ensemble.pooled import PooledConfig, combine_panel, growth_regimes
from pipeline.ensemble.targets import (HORIZONS_WEEKS, HUB_QUANTILE_LEVELS, TARGETS,
                                       history_from_county)
from pipeline.evaluation.scoring import interval_coverage, weighted_interval_score
from pipeline.progress import ProgressReporter, SilentProgress

PIT_BINS = 10
DEFAULT_MIN_POPULATION = 100_000


@dataclass(frozen=True)
class CountyBacktestConfig:
    """Which counties and origins; the published combiner and the variants scored beside it."""

    min_population: int = DEFAULT_MIN_POPULATION
    trailing_days: int = 14
    min_history_weeks: int = 8
    horizons: tuple[int, ...] = HORIZONS_WEEKS
    levels: tuple[float, ...] = HUB_QUANTILE_LEVELS
    seed: int = 0
    # The hub baseline resamples its differences; 10,000 draws per cell (reichlab: 100,000) keep
    # the Monte Carlo error of its 1 % quantile under 0.1 percentage points of level, at a tenth
    # of the cost over thousands of cells.
    baseline_samples: int = 10_000
    published: PooledConfig = field(default_factory=PooledConfig)
    variants: tuple[tuple[str, PooledConfig], ...] = ()


def county_panel(vintage: CDPHVintage, counties: Sequence[str], trailing_days: int) -> Panel:
    """The counties' histories from ``vintage`` without its last ``trailing_days`` days."""
    last = vintage.as_of - pd.Timedelta(days=trailing_days)
    return Panel({c: history_from_county(vintage.county(c)).up_to(last) for c in counties})


@dataclass(frozen=True, eq=False)
class PanelBacktestResult:
    """``forecasts[target][forecaster]``: quantiles ``(C, O, H, Q)``; ``truth[target]``
    ``(C, O, H)``; ``weights`` ``(O, H, M)`` of the published combination."""

    places: tuple[str, ...]
    origins: tuple[pd.Timestamp, ...]
    horizons: tuple[int, ...]
    levels: NDArray[np.float64]
    populations: NDArray[np.float64]
    members: tuple[str, ...]
    forecasts: dict[str, dict[str, NDArray[np.float64]]]
    truth: dict[str, NDArray[np.float64]]
    weights: NDArray[np.float64]
    seconds: dict[str, float]
    config: CountyBacktestConfig


def cell_regimes(panel: Panel, origins: Sequence[pd.Timestamp]) -> NDArray[np.intp]:
    """Each cell's growth regime ``(C, O)`` from the last two weeks of cases before its origin."""
    out = np.empty((len(panel.places), len(origins)), dtype=np.intp)
    for c, history in enumerate(panel.histories.values()):
        cumulative = np.concatenate([[0], np.cumsum(history.cases)])
        ends = np.searchsorted(history.dates.to_numpy(dtype=np.int64),
                               np.array([o.value for o in origins])) + 1
        last_two = np.stack([cumulative[ends - 7] - cumulative[ends - 14],
                             cumulative[ends] - cumulative[ends - 7]], axis=-1)
        out[c] = growth_regimes(last_two.astype(np.float64))
    return out


def run_panel_backtest(panel: Panel, members: Sequence[Member | BatchMember],
                       config: CountyBacktestConfig = CountyBacktestConfig(),
                       progress: ProgressReporter | None = None) -> PanelBacktestResult:
    """Every member and the hub baseline at every cell, then the pooled published forecast and
    the variants (module docstring)."""
    progress = progress or SilentProgress()
    levels = np.asarray(config.levels, dtype=np.float64)
    horizons = tuple(config.horizons)
    origins = weekly_origins(panel.dates, min_history_weeks=config.min_history_weeks,
                             horizon_weeks=max(horizons))
    cells = cell_histories(panel, origins)
    shape = (len(panel.places), len(origins))
    seconds: dict[str, float] = {}
    forecasts: dict[str, dict[str, NDArray[np.float64]]] = {t: {} for t in TARGETS}
    for member in (*members, HubBaseline(HubBaselineConfig(n_samples=config.baseline_samples))):
        started = time.perf_counter()
        arrays = member_forecast_arrays(member, cells, shape, horizons, levels, config.seed,
                                        progress)
        seconds[member.name] = time.perf_counter() - started
        for t in TARGETS:
            forecasts[t][member.name] = arrays[t]
    started = time.perf_counter()
    truth = truth_arrays(panel, origins, horizons)
    regimes = cell_regimes(panel, origins)
    names = tuple(m.name for m in members)
    member_cases = {n: forecasts["cases"][n] for n in names}
    baseline = forecasts["cases"][HUB_BASELINE]
    pooled = combine_panel(member_cases, baseline, truth["cases"], regimes, levels, horizons,
                           config.published)
    population = panel.populations[:, None, None, None]
    for name, values in ((PUBLISHED, pooled.published), (UNCALIBRATED, pooled.uncalibrated)):
        forecasts["cases"][name], forecasts["I"][name] = values, values / population
    for name, variant in config.variants:
        values = combine_panel(member_cases, baseline, truth["cases"], regimes, levels,
                               horizons, variant).published
        forecasts["cases"][name], forecasts["I"][name] = values, values / population
    seconds["combine"] = time.perf_counter() - started
    return PanelBacktestResult(panel.places, tuple(origins), horizons, levels, panel.populations,
                               names, forecasts, truth, pooled.weights, seconds, config)


def run_county_backtest(vintage: CDPHVintage, members: Sequence[Member | BatchMember],
                        config: CountyBacktestConfig = CountyBacktestConfig(),
                        counties: Sequence[str] | None = None,
                        progress: ProgressReporter | None = None) -> PanelBacktestResult:
    """:func:`run_panel_backtest` on ``counties`` (default: every county with at least
    ``config.min_population`` people) of a CDPH vintage."""
    chosen = (tuple(counties) if counties is not None
              else vintage.counties_with_population(config.min_population))
    return run_panel_backtest(county_panel(vintage, chosen, config.trailing_days), members,
                              config, progress)


# ---------------------------------------------------------------------------------- summaries


def _relative_wis(wis: NDArray[np.float64], base: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per place Σ WIS / Σ baseline WIS over its cells (last axis)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.nansum(wis, axis=-1) / np.nansum(base, axis=-1)


def _gmean(ratios: NDArray[np.float64]) -> float | None:
    finite = ratios[np.isfinite(ratios) & (ratios > 0)]
    return float(np.exp(np.log(finite).mean())) if finite.size else None


def _score_arrays(values: NDArray[np.float64], truth: NDArray[np.float64],
                  levels: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    seen = np.isfinite(truth)
    y = np.where(seen, truth, 0.0)
    nan = np.where(seen, 1.0, np.nan)
    return {"wis": weighted_interval_score(levels, values, y).wis * nan,
            "c50": interval_coverage(levels, values, y, 0.5) * nan,
            "c90": interval_coverage(levels, values, y, 0.9) * nan,
            "pit": pit_from_quantiles(levels, values, y) * nan}


def summarize_forecaster(values: NDArray[np.float64], base_wis: NDArray[np.float64],
                         truth: NDArray[np.float64], levels: NDArray[np.float64],
                         horizons: Sequence[int], places: Sequence[str],
                         unit: NDArray[np.float64]) -> dict[str, Any]:
    """One forecaster on one target: ``values (C, O, H, Q)``; ``unit (C, 1, 1)`` turns the
    target into counts for the PIT (N for I, 1 for cases)."""
    scores = _score_arrays(values * unit[..., None], truth * unit, levels)
    keys = [f"h{h}" for h in horizons]
    per_h = np.stack([_relative_wis(scores["wis"][:, :, k], base_wis[:, :, k])
                      for k in range(len(horizons))], axis=1)               # (C, H)
    overall = _relative_wis(scores["wis"].reshape(len(places), -1),
                            base_wis.reshape(len(places), -1))              # (C,)
    gmean = {k: _gmean(per_h[:, i]) for i, k in enumerate(keys)} | {"all": _gmean(overall)}
    share = {k: float(np.mean(per_h[:, i] < 1)) for i, k in enumerate(keys)} | {
        "all": float(np.mean(overall < 1))}
    pit = scores["pit"][np.isfinite(scores["pit"])]
    hist, _ = np.histogram(pit, bins=PIT_BINS, range=(0.0, 1.0))
    return {
        "gmean_relative_wis": gmean,
        "share_beating_baseline": share,
        "coverage50": float(np.nanmean(scores["c50"])),
        "coverage90": float(np.nanmean(scores["c90"])),
        "coverage_by_horizon": {k: {"coverage50": float(np.nanmean(scores["c50"][:, :, i])),
                                    "coverage90": float(np.nanmean(scores["c90"][:, :, i]))}
                                for i, k in enumerate(keys)},
        "pit_histogram": {"bins": PIT_BINS, "counts": hist.astype(int).tolist()},
        "per_county": {p: {k: float(per_h[c, i]) for i, k in enumerate(keys)}
                       | {"all": float(overall[c])} for c, p in enumerate(places)},
        "n_scored": int(np.isfinite(scores["wis"]).sum()),
    }


def summarize_panel(result: PanelBacktestResult) -> dict[str, Any]:
    """The JSON summary (module docstring)."""
    by_target: dict[str, dict[str, Any]] = {}
    for target in TARGETS:
        unit = (result.populations if target == "I"
                else np.ones_like(result.populations))[:, None, None]
        truth = result.truth[target]
        base = result.forecasts[target][HUB_BASELINE]
        base_wis = _score_arrays(base * unit[..., None], truth * unit, result.levels)["wis"]
        by_target[target] = {
            name: summarize_forecaster(values, base_wis, truth, result.levels, result.horizons,
                                       result.places, unit)
            for name, values in result.forecasts[target].items()}
    mean_weights = result.weights.mean(axis=0)                              # (H, M)
    return {
        "by_target": by_target,
        "n_counties": len(result.places),
        "counties": list(result.places),
        "n_origins": len(result.origins),
        "origins": {"first": str(result.origins[0].date()),
                    "last": str(result.origins[-1].date())},
        "members": list(result.members),
        "mean_weights": {f"h{h}": dict(zip(result.members, map(float, mean_weights[k])))
                         for k, h in enumerate(result.horizons)},
        "config": _config_dict(result.config),
        "seconds": {k: round(v, 2) for k, v in result.seconds.items()},
    }


def _config_dict(config: CountyBacktestConfig) -> dict[str, Any]:
    out = asdict(config)
    out["variants"] = {name: asdict(v) for name, v in config.variants}
    return out


def weights_frame(result: PanelBacktestResult) -> pd.DataFrame:
    """origin, horizon, member, weight of the published combination."""
    o, h, m = np.meshgrid(np.arange(len(result.origins)), np.arange(len(result.horizons)),
                          np.arange(len(result.members)), indexing="ij")
    return pd.DataFrame({"origin_date": [result.origins[i].date() for i in o.ravel()],
                         "horizon": [result.horizons[i] for i in h.ravel()],
                         "member": [result.members[i] for i in m.ravel()],
                         "weight": result.weights.ravel()})


def published_counts(result: PanelBacktestResult) -> Mapping[str, NDArray[np.float64]]:
    return {t: result.forecasts[t][PUBLISHED] for t in TARGETS}
