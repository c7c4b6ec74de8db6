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

import dataclasses
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.cdph import CDPHVintage
from pipeline.ensemble.calibration import pit_from_quantiles
from pipeline.ensemble.combine import PUBLISHED, UNCALIBRATED, EnsembleError
from pipeline.ensemble.hub_baseline import HUB_BASELINE, HubBaseline
from pipeline.ensemble.members import Member
from pipeline.ensemble.panel import (BatchMember, Panel, PoolingMember, member_forecast_arrays,
                                     truth_arrays, weekly_grid, weekly_origins)
from pipeline.ensemble.pooled import PooledConfig, PooledForecast, combine_panel, growth_regimes
from pipeline.ensemble.targets import (HORIZONS_WEEKS, HUB_QUANTILE_LEVELS, TARGETS,
                                       history_from_county)
from pipeline.evaluation.scoring import interval_coverage, weighted_interval_score
from pipeline.io import atomic_write_json, atomic_write_text
from pipeline.progress import ProgressReporter, SilentProgress

PIT_BINS = 10
DEFAULT_MIN_POPULATION = 100_000


@dataclass(frozen=True)
class Variant:
    """A design alternative scored beside the published forecast: another combiner over the
    same members, or the published combiner over a subset of them (``members``)."""

    name: str
    pooled: PooledConfig = field(default_factory=PooledConfig)
    members: tuple[str, ...] | None = None


@dataclass(frozen=True)
class CountyBacktestConfig:
    """Which counties and origins; the published combiner and the variants scored beside it."""

    min_population: int = DEFAULT_MIN_POPULATION
    trailing_days: int = 14
    min_history_weeks: int = 8
    horizons: tuple[int, ...] = HORIZONS_WEEKS
    levels: tuple[float, ...] = HUB_QUANTILE_LEVELS
    seed: int = 0
    published: PooledConfig = field(default_factory=PooledConfig)
    variants: tuple[Variant, ...] = ()


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
    weekly, index = weekly_grid(panel, origins)
    last_two = np.stack([weekly[:, index - 1], weekly[:, index]], axis=-1)
    return growth_regimes(last_two)


AnyMember = Member | BatchMember | PoolingMember


def run_panel_backtest(panel: Panel, members: Sequence[AnyMember],
                       config: CountyBacktestConfig = CountyBacktestConfig(),
                       references: Sequence[AnyMember] = (),
                       progress: ProgressReporter | None = None) -> PanelBacktestResult:
    """Every member and reference at every cell, then the published combination of the members
    and the variants (module docstring). The hub baseline is scored always: as a member when it
    is one, else as a reference."""
    progress = progress or SilentProgress()
    levels = np.asarray(config.levels, dtype=np.float64)
    horizons = tuple(config.horizons)
    names = tuple(m.name for m in members)
    if not names or len(set(names)) != len(names) or {PUBLISHED, UNCALIBRATED} & set(names):
        raise EnsembleError(f"members need distinct names other than {PUBLISHED!r} and "
                            f"{UNCALIBRATED!r}, got {names}")
    if HUB_BASELINE not in names and not any(r.name == HUB_BASELINE for r in references):
        references = (*references, HubBaseline())
    origins = weekly_origins(panel.dates, min_history_weeks=config.min_history_weeks,
                             horizon_weeks=max(horizons))
    seconds: dict[str, float] = {}
    forecasts: dict[str, dict[str, NDArray[np.float64]]] = {t: {} for t in TARGETS}
    for member in (*members, *references):
        started = time.perf_counter()
        arrays = member_forecast_arrays(member, panel, origins, horizons, levels, config.seed,
                                        progress)
        seconds[member.name] = time.perf_counter() - started
        for t in TARGETS:
            forecasts[t][member.name] = arrays[t]
    started = time.perf_counter()
    truth = truth_arrays(panel, origins, horizons)
    regimes = cell_regimes(panel, origins)
    baseline = forecasts["cases"][HUB_BASELINE]
    population = panel.populations[:, None, None, None]

    def combine(chosen: Sequence[str], pooled: PooledConfig) -> PooledForecast:
        return combine_panel({n: forecasts["cases"][n] for n in chosen}, baseline,
                             truth["cases"], regimes, levels, horizons, pooled)

    published = combine(names, config.published)
    for name, values in ((PUBLISHED, published.published),
                         (UNCALIBRATED, published.uncalibrated)):
        forecasts["cases"][name], forecasts["I"][name] = values, values / population
    seconds["combine"] = time.perf_counter() - started
    started = time.perf_counter()
    for variant in config.variants:
        values = combine(variant.members or names, variant.pooled).published
        forecasts["cases"][variant.name], forecasts["I"][variant.name] = values, values / population
    seconds["variants"] = time.perf_counter() - started
    return PanelBacktestResult(panel.places, tuple(origins), horizons, levels, panel.populations,
                               names, forecasts, truth, published.weights, seconds, config)


def run_county_backtest(vintage: CDPHVintage, members: Sequence[AnyMember],
                        config: CountyBacktestConfig = CountyBacktestConfig(),
                        counties: Sequence[str] | None = None,
                        references: Sequence[AnyMember] = (),
                        progress: ProgressReporter | None = None) -> PanelBacktestResult:
    """:func:`run_panel_backtest` on ``counties`` (default: every county with at least
    ``config.min_population`` people) of a CDPH vintage."""
    return run_panel_backtest(county_panel(vintage, select_counties(vintage, config, counties),
                                           config.trailing_days),
                              members, config, references, progress)


def select_counties(vintage: CDPHVintage, config: CountyBacktestConfig,
                    counties: Sequence[str] | None = None) -> tuple[str, ...]:
    """``counties`` (checked against the vintage), or every county with at least
    ``config.min_population`` people."""
    if counties is None:
        return vintage.counties_with_population(config.min_population)
    for county in counties:
        vintage.county(county)                  # names the county and suggests a spelling
    return tuple(counties)


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
            "c50": interval_coverage(levels, values, y, 0.5).astype(np.float64) * nan,
            "c90": interval_coverage(levels, values, y, 0.9).astype(np.float64) * nan,
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
    out["variants"] = {v.name: {"pooled": asdict(v.pooled), "members": v.members}
                       for v in config.variants}
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


def for_places(result: PanelBacktestResult, places: Sequence[str]) -> PanelBacktestResult:
    """The same backtest restricted to ``places`` (their forecasts are unchanged: the pooled
    members learnt from every place of the panel)."""
    unknown = [p for p in places if p not in result.places]
    if unknown:
        raise EnsembleError(f"places {unknown} are not in the backtest ({len(result.places)} "
                            f"places: {', '.join(result.places[:5])}, …)")
    keep = np.array([result.places.index(p) for p in places])
    return dataclasses.replace(
        result, places=tuple(places), populations=result.populations[keep],
        forecasts={t: {n: v[keep] for n, v in f.items()} for t, f in result.forecasts.items()},
        truth={t: v[keep] for t, v in result.truth.items()})


def scores_frame(result: PanelBacktestResult) -> pd.DataFrame:
    """One row per place × origin × horizon × target × forecaster with observed truth: the
    truth, the forecast's median and WIS, 50 %/90 % coverage."""
    mid = int(np.argmin(np.abs(result.levels - 0.5)))
    frames = []
    for target in TARGETS:
        truth = result.truth[target]
        for name, values in result.forecasts[target].items():
            scores = _score_arrays(values, truth, result.levels)
            c, o, h = np.nonzero(np.isfinite(truth))
            frames.append(pd.DataFrame({
                "place": np.asarray(result.places)[c],
                "origin_date": [str(result.origins[i].date()) for i in o],
                "horizon": np.asarray(result.horizons)[h], "target": target, "forecaster": name,
                "observed": truth[c, o, h], "median": values[c, o, h, mid],
                "wis": scores["wis"][c, o, h], "covered_50": scores["c50"][c, o, h] > 0,
                "covered_90": scores["c90"][c, o, h] > 0}))
    return pd.concat(frames, ignore_index=True)


def write_panel_backtest(result: PanelBacktestResult, out_dir: str | Path,
                         extra: Mapping[str, Any] | None = None) -> list[Path]:
    """``summary.json`` (:func:`summarize_panel`), ``scores.csv`` (:func:`scores_frame`) and
    ``weights.csv`` of the published combination, written atomically."""
    root = Path(out_dir)
    written = [root / "summary.json", root / "scores.csv", root / "weights.csv"]
    atomic_write_json(written[0], {**summarize_panel(result), **(extra or {})})
    atomic_write_text(written[1], scores_frame(result).to_csv(index=False))
    atomic_write_text(written[2], weights_frame(result).to_csv(index=False))
    return written
