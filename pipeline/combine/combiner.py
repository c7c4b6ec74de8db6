"""The one combiner: the members' forecasts of every place and origin → the published forecast.

Input: each member's quantiles of the panel's count target ``(C, O, H, Q)`` (places × origins ×
horizons × levels), the hub baseline's, the truth ``(C, O, H)`` and each cell's regime. At
origin t and horizon h only the scores of forecasts whose target week had ended by t are known
(origin o with o + 7h ≤ t), in every place of the panel: the weights and the recalibration are
learnt from those, nothing later. A single series is a panel of one place.

**Published** (``CombineConfig()``): equal weights; the level-wise log-scale midpoint of the
members' quantile average (the geometric mean of their quantiles) and their linear pool (the
average of their CDFs: wider where the members disagree, at the turns); then the online
calibration of the intervals' widths per phase of the epidemic, which leaves the median alone:
adaptive conformal trackers at η = 0, 0.05, 0.15 and 0.3, each interval's misses in units of
their own standard deviation, aggregated by their skill among those whose intervals cover
(``"aggregated-aci"``, :class:`~pipeline.combine.recalibration.AggregatedTracker`; since
2026-11-30 its published weights follow that choice with a half-life of 2 origins instead of
jumping when an expert's coverage crosses the tolerance; and each quantile is moved by the
lesser of the stretch's two readings, on the levels of the average's quantile function and on
the quantile's distance from the median: ``tracking_space="lesser"``). Last,
every quantile of a count is held at or above the lowest count the panel's own history allows:
no fall faster than its places had shown from weeks at that level (``FALLS_BOUND``,
:mod:`pipeline.combine.plausibility`; rises are left open: a new variant may outgrow them
all). One tracker at η = 0.15 (``"regime-aci"``) was published until 2026-11-29: it cost up to
1.3 % of WIS where the average already covered (the counties) and its 95 % interval moved too
slowly where it did not (hub admissions). Designed on California's counties and checked on San
Francisco and the hub's rounds (``bench/results/calibration.json``): the average alone (log
scale, no recalibration: the published rule until 2026-11) held its intervals on average but
not at the turns; every weight learnt from recent scores and every recalibration from a window
of past PITs made it worse.
They are kept as the variants every backtest reports beside it: weights
(:mod:`pipeline.combine.average`: ``inverse-wis``, ``stacking``), the log and linear averages,
the mixture, and the window recalibrations (:mod:`pipeline.combine.recalibration`). The I of a
daily source is the count over N: the published I and count are one forecast.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.combine.average import (AverageScale, EnsembleError, GridAverages, WeightMethod,
                                      fit_weights, scored_wis, vincentize)
from pipeline.evaluation.quantile_function import pit_from_quantiles, quantiles_at
from pipeline.combine.recalibration import (ONLINE_METHODS, RECALIBRATION_METHODS,
                                            STRETCH_SPACES, TRACKING_STEPS, AggregatedTracker,
                                            IntervalTracker, RecalibrationMethod, StretchSpace,
                                            TrackingStep, calibrated_levels, fit_recalibration)
from pipeline.combine.plausibility import FALLS_BOUND, PlausibilityConfig
from pipeline.evaluation.regimes import N_REGIMES
from pipeline.members.base import Member, MemberForecast, forecast_within_reach
from pipeline.panels.panel import Cells
from pipeline.panels.targets import DAYS_PER_WEEK

PUBLISHED = "published"
UNCALIBRATED = "ensemble-uncalibrated"
RESERVED_NAMES = (PUBLISHED, UNCALIBRATED)
BeyondReach = Literal["missing", "reachable-members"]


@dataclass(frozen=True)
class CombineConfig:
    """How the members are combined (module docstring)."""

    weights: WeightMethod = "equal"
    scale: AverageScale = "log-mixture"
    window_origins: int = 12
    stacking_step: float = 0.05
    shrinkage_origins: float = 2.0
    calibration: RecalibrationMethod = "aggregated-aci"
    calibration_window_origins: int = 8
    shrinkage_pits: float = 50.0
    min_level: float = 1e-4
    tracking_rate: float = 0.15         # η of the single online calibration ("regime-aci")
    tracking_step: TrackingStep = "pooled"
    tracking_standardized: bool = True    # each interval's misses in their own units
    tracking_leak: float = 0.0          # the share of a stretch let go at every origin
    # where the online calibration's stretch acts (recalibration.StretchSpace): each quantile
    # moved by the lesser of its reading on levels and on values about the median (published
    # since 2026-11-30); on levels alone, published until then
    tracking_space: StretchSpace = "lesser"
    # the experts' η of "aggregated-aci" (0: the average uncalibrated) and their temperature
    tracking_rates: tuple[float, ...] = (0.0, 0.05, 0.15, 0.3)
    aggregation_temperature: float = 0.01
    # the half-life in origins of the outcomes that choose among them (None: all alike)
    aggregation_memory_origins: float | None = None
    # the half-life in origins with which the published weights follow the rule's (None: at once)
    aggregation_smoothing_origins: float | None = 2.0
    outer_interval: float = 0.9         # the outer interval it holds (the hub's: 0.95)
    # where a member has no forecast (beyond a flow's four weeks): no published forecast, or
    # the same average over the members that reach it — a different forecaster, to be named so
    beyond_reach: BeyondReach = "missing"
    # quantiles held within the changes the panel's history has shown (None: not held;
    # pipeline.combine.plausibility): published, falls only (FALLS_BOUND)
    bounded: PlausibilityConfig | None = field(default_factory=lambda: FALLS_BOUND)

    def __post_init__(self) -> None:
        if self.beyond_reach not in ("missing", "reachable-members"):
            raise EnsembleError(f"CombineConfig.beyond_reach={self.beyond_reach!r}: use "
                                "missing or reachable-members")
        if self.weights not in ("stacking", "inverse-wis", "equal"):
            raise EnsembleError(f"CombineConfig.weights={self.weights!r}: use stacking, "
                                "inverse-wis or equal")
        if self.scale not in ("log", "linear", "mixture", "log-mixture"):
            raise EnsembleError(f"CombineConfig.scale={self.scale!r}: use log, linear, "
                                "mixture or log-mixture")
        if self.tracking_space not in STRETCH_SPACES:
            raise EnsembleError(f"CombineConfig.tracking_space={self.tracking_space!r}: use one "
                                f"of {STRETCH_SPACES}")
        if self.tracking_step not in TRACKING_STEPS:
            raise EnsembleError(f"CombineConfig.tracking_step={self.tracking_step!r}: use one "
                                f"of {TRACKING_STEPS}")
        if self.calibration not in RECALIBRATION_METHODS:
            raise EnsembleError(f"CombineConfig.calibration={self.calibration!r}: use one of "
                                f"{RECALIBRATION_METHODS}")
        if (self.window_origins < 1 or self.calibration_window_origins < 1
                or not 0 < self.stacking_step <= 0.5 or self.shrinkage_origins < 0
                or self.shrinkage_pits < 0 or self.tracking_rate < 0
                or not self.tracking_rates or min(self.tracking_rates) < 0
                or self.aggregation_temperature <= 0 or not 0 <= self.tracking_leak < 1
                or (self.aggregation_memory_origins is not None
                    and self.aggregation_memory_origins <= 0)
                or (self.aggregation_smoothing_origins is not None
                    and self.aggregation_smoothing_origins <= 0)):
            raise EnsembleError(f"invalid CombineConfig {self}")


# The published rule until 2026-11: the log-scale average alone (scored beside the published).
LOG_AVERAGE = CombineConfig(scale="log", calibration="none", bounded=None)


@dataclass(frozen=True, eq=False)
class CombinedForecast:
    """``published`` and ``uncalibrated`` count quantiles ``(C, O, H, Q)``; ``weights``
    ``(O, H, M)``; ``calibration`` ``(O, H, R, 2)``: μ, σ per regime."""

    published: NDArray[np.float64]
    uncalibrated: NDArray[np.float64]
    weights: NDArray[np.float64]
    calibration: NDArray[np.float64]


def scored_before(origins: Sequence[pd.Timestamp], horizons: Sequence[int]
                  ) -> NDArray[np.bool_]:
    """``known[j, i, k]``: the forecast from origin i at horizon k is scored at origin j (its
    target week ended by origin j)."""
    days = pd.DatetimeIndex(list(origins)).to_numpy(dtype="datetime64[D]").astype(np.int64)
    steps = DAYS_PER_WEEK * np.asarray(horizons, dtype=np.int64)
    return days[None, :, None] + steps[None, None, :] <= days[:, None, None]


# The truth as known at origin index j, (C, O, H): for vintaged data, the values of the vintage
# then (a later revision must not teach the combiner); None: the one truth given.
KnownTruth = Callable[[int], NDArray[np.float64]]


def combine(members: Mapping[str, NDArray[np.float64]], baseline: NDArray[np.float64],
            truth: NDArray[np.float64], regimes: NDArray[np.intp], levels: NDArray[np.float64],
            horizons: tuple[int, ...], origins: Sequence[pd.Timestamp],
            config: CombineConfig = CombineConfig(), *,
            truth_at: KnownTruth | None = None,
            dropped: Mapping[str, NDArray[np.bool_]] | None = None) -> CombinedForecast:
    """The published count quantiles of every cell (module docstring) from the members'
    ``(C, O, H, Q)`` quantiles (NaN where a member has no forecast: it is left out of that
    cell's equal-weight average), the hub baseline's, the truth ``(C, O, H)`` and each cell's
    regime ``(C, O)``, origin j learning only from the cells :func:`scored_before` it.
    ``dropped[name]`` ``(C, O)``: the cells where a member failed (:mod:`pipeline.backtest.
    isolation`): left out there, the baseline standing in where every member failed."""
    names = list(members)
    if not names:
        raise EnsembleError("no member forecasts to combine")
    values = np.stack([members[n] for n in names])                        # (M, C, O, H, Q)
    failed = (None if not dropped else
              np.stack([np.asarray(dropped.get(n, np.zeros(values.shape[1:3], dtype=bool)),
                                   dtype=bool) for n in names]))          # (M, C, O)
    _, n_c, n_o, n_h, _ = values.shape
    if len(horizons) != n_h or baseline.shape != values.shape[1:] or len(origins) != n_o:
        raise EnsembleError(f"member quantiles {values.shape[1:]}, baseline {baseline.shape}, "
                            f"{len(origins)} origins and {len(horizons)} horizons do not match")
    known = scored_before(origins, horizons)                               # (O, O, H)
    tracker = _online_tracker(config, levels)
    experts = np.empty((len(tracker.experts) if tracker else 0, *values.shape[1:]))
    counted = np.zeros((n_o, n_h), dtype=bool)
    uncal = np.empty(values.shape[1:])
    published = np.empty(values.shape[1:])
    weights = np.empty((n_o, n_h, len(names)))
    calibration = np.empty((n_o, n_h, N_REGIMES, 2))
    wis_truth = truth
    baseline_wis = scored_wis(levels, baseline, truth)                     # (C, O, H)
    stacked = (GridAverages(values, config.stacking_step, config.scale)
               if config.weights == "stacking" and len(names) > 1 else None)
    for j in range(n_o):
        if truth_at is not None:
            wis_truth = truth_at(j)
            baseline_wis = scored_wis(levels, baseline, wis_truth)
        if tracker is not None:                  # the outcomes that became known by origin j
            new = known[j] & ~counted
            counted |= new
            i, k = np.nonzero(new)
            scored = experts[:, :, i, k].reshape(len(experts), -1, len(levels))
            y = wis_truth[:, i, k].reshape(-1)
            tracker.update(scored, y, regimes[:, i].reshape(-1),
                           scored_wis(levels, scored, np.broadcast_to(y, scored.shape[:2])))
        for k in range(n_h):
            past = np.flatnonzero(known[j, :, k])
            fit = past[-config.window_origins:]
            weights[j, k] = fit_weights(config.weights, values[:, :, fit, k],
                                        wis_truth[:, fit, k], baseline_wis[:, fit, k], levels,
                                        len(fit), scale=config.scale,
                                        shrinkage_origins=config.shrinkage_origins,
                                        stacking_step=config.stacking_step,
                                        averages=None if stacked is None or not fit.size
                                        else stacked.at(fit, k))
            uncal[:, j, k] = _average(values[:, :, j, k], weights[j, k], config,
                                      None if failed is None else failed[:, :, j],
                                      baseline[:, j, k])
            if tracker is not None:
                calibration[j, k] = np.nan
                experts[:, :, j, k] = tracker.expert_quantiles(uncal[:, j, k], regimes[:, j])
                published[:, j, k] = tracker.combine(experts[:, :, j, k])
                continue
            recent = past[-config.calibration_window_origins:]
            pits = (_pits(levels, uncal[:, recent, k], wis_truth[:, recent, k])
                    if config.calibration != "none" else np.empty(0))
            calibration[j, k] = fit_recalibration(
                config.calibration, pits, regimes[:, recent].ravel(),
                shrinkage_pits=config.shrinkage_pits, min_level=config.min_level)
            new_levels = calibrated_levels(levels, calibration[j, k][regimes[:, j]],
                                           config.min_level)
            cal = quantiles_at(levels, uncal[:, j, k], new_levels)
            published[:, j, k] = np.maximum.accumulate(cal, axis=-1)
    return CombinedForecast(np.where(np.isfinite(uncal), published, np.nan), uncal, weights,
                            calibration)


def _online_tracker(config: CombineConfig, levels: NDArray[np.float64]
                    ) -> AggregatedTracker | None:
    """The online calibration of ``config`` (None: a window recalibration or none): one
    tracker at η (``"regime-aci"``), or experts at each of ``tracking_rates``."""
    if config.calibration not in ONLINE_METHODS:
        return None
    rates = (config.tracking_rates if config.calibration == "aggregated-aci"
             else (config.tracking_rate,))
    return AggregatedTracker(tuple(
        IntervalTracker(levels, rate, config.outer_interval, step=config.tracking_step,
                        standardized=config.tracking_standardized, leak=config.tracking_leak,
                        space=config.tracking_space)
        for rate in rates),
        config.aggregation_temperature, memory_origins=config.aggregation_memory_origins,
        smoothing_origins=config.aggregation_smoothing_origins)


def _pits(levels: NDArray[np.float64], quantiles: NDArray[np.float64],
          truth: NDArray[np.float64]) -> NDArray[np.float64]:
    """PITs ``(C·n,)`` of the scored cells of quantiles ``(C, n, Q)`` (NaN elsewhere)."""
    out = np.full(truth.shape, np.nan)
    seen = np.isfinite(truth) & np.isfinite(quantiles).all(axis=-1)
    out[seen] = pit_from_quantiles(levels, quantiles[seen], truth[seen])
    return out.ravel()


def _average(values: NDArray[np.float64], weights: NDArray[np.float64], config: CombineConfig,
             dropped: NDArray[np.bool_] | None = None,
             floor: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """The weighted average ``(C, Q)`` of ``values (M, C, Q)``; where a member is missing (NaN:
    beyond its reach) NaN, or (``reachable-members``) the average of the others, their weights
    renormalised. A member ``dropped`` ``(M, C)`` at a cell (it failed there) is left out of
    that cell's average whatever ``beyond_reach`` says; a cell every member failed takes
    ``floor`` ``(C, Q)`` (the hub baseline)."""
    scale = config.scale
    present = np.asarray(np.isfinite(values).all(axis=-1), dtype=bool)    # (M, C)
    if present.all():
        return vincentize(values, weights, scale)
    failed: NDArray[np.bool_] = (np.zeros_like(present) if dropped is None
                                 else dropped & ~present)
    out = np.full(values.shape[1:], np.nan)
    # "missing": a member beyond its reach (not one that failed) leaves the cell unforecast
    open_cells = (np.asarray((present | failed).all(axis=0), dtype=bool)
                  if config.beyond_reach == "missing" else np.ones(values.shape[1], dtype=bool))
    patterns: NDArray[np.bool_] = (np.unique(present[:, open_cells], axis=1).T
                                   if open_cells.any() else np.zeros((0, len(present)), bool))
    for pattern in patterns:                                               # few patterns
        cells = open_cells & (present == pattern[:, None]).all(axis=0)
        if not pattern.any():
            continue
        w = weights[pattern] / weights[pattern].sum()
        out[cells] = vincentize(values[pattern][:, cells], w, scale)
    if floor is not None:
        floored = open_cells & ~present.any(axis=0) & failed.any(axis=0)
        out[floored] = floor[floored]
    return out


@dataclass(frozen=True, eq=False)
class Ensemble:
    """The average at one time, where no past score is known (a nowcast's completions): the
    members' equal-weight average on ``config.scale``, with no calibration (it learns from past
    scores: :func:`combine`), a member
    beyond its reach left out per ``config.beyond_reach``. Its members' quantiles are exposed
    (:meth:`member_quantiles`) beside the combination (:meth:`combine`), so that a nowcast's
    completions are mixed per member before the members are averaged."""

    members: tuple[Member, ...]
    config: CombineConfig = CombineConfig(calibration="none")
    name: str = PUBLISHED

    def __post_init__(self) -> None:
        if not self.members:
            raise EnsembleError("an ensemble needs at least one member")
        if self.config.weights != "equal" or self.config.calibration != "none":
            raise EnsembleError(f"{self.name}: weights {self.config.weights!r} and "
                                f"recalibration {self.config.calibration!r} learn from past "
                                "scores: combine a backtest's forecasts instead")

    @property
    def member_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.members)

    def member_quantiles(self, cells: Cells, horizons: tuple[int, ...],
                         levels: NDArray[np.float64]) -> NDArray[np.float64]:
        """Count quantiles ``(M, B, H, Q)`` of every member, NaN beyond a member's reach."""
        return np.stack([forecast_within_reach(m, cells, horizons, levels).count
                         for m in self.members])

    def combine(self, member_quantiles: NDArray[np.float64]) -> NDArray[np.float64]:
        """The published quantiles ``(..., Q)`` from the members' ``(M, ..., Q)``."""
        m = member_quantiles.shape[0]
        flat = member_quantiles.reshape(m, -1, member_quantiles.shape[-1])
        return _average(flat, np.full(m, 1.0 / m), self.config).reshape(
            member_quantiles.shape[1:])

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        return MemberForecast(self.combine(self.member_quantiles(cells, horizons, levels)))
