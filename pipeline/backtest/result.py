"""A backtest's result: every forecaster's quantiles at every cell, the truth, the weights and
the published sample paths, with its summary and score table computed once.

``forecasts[target][forecaster]`` are :class:`~pipeline.panels.quantiles.Quantiles` (places ×
origins × horizons × levels, labelled; NaN where a forecaster made no forecast),
``truth[target]`` the :class:`~pipeline.panels.quantiles.Observed` of the same cells. The summary
(:meth:`BacktestResult.summary`) is :mod:`pipeline.evaluation.summary` per target × forecaster
with the run's facts; :meth:`BacktestResult.scores` the long table of scored cells;
:meth:`BacktestResult.forecast_at` one cell's forecast (the report's and the hub file's view).
"""
from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.members.isolation import MemberFailure
from pipeline.combine.average import EnsembleError
from pipeline.combine.combiner import PUBLISHED, UNCALIBRATED
from pipeline.combine.paths import InvalidCounts, add_counts, count_invalid
from pipeline.combine.plausibility import share_beyond
from pipeline.evaluation.summary import calibration_cost, regime_masks, summarize_forecaster
from pipeline.members.hub_baseline import HUB_BASELINE
from pipeline.panels.history import EpiHistory, History
from pipeline.panels.panel import Panel
from pipeline.panels.quantiles import Observed, Quantiles, long_frame, positions
from pipeline.panels.targets import DAYS_PER_WEEK, SHARE, TargetError

if TYPE_CHECKING:
    from pipeline.backtest.config import BacktestConfig

SCORE_COLUMNS = ("place", "forecaster", "target", "horizon", "origin_date", "target_end_date",
                 "observed", "median", "wis", "dispersion", "overprediction", "underprediction",
                 "covered_50", "covered_90", "covered_95", "pit", "regime")


@dataclass(frozen=True, eq=False)
class QuantileForecast:
    """One forecaster's forecast of one place from one origin: ``values[target]`` ``(H, Q)``
    (horizons × ascending levels, non-decreasing along the levels); ``paths``: weekly S/I/R
    sample paths ``(n, H, 3)`` at origin + 7h when the forecaster has them."""

    forecaster: str
    origin: pd.Timestamp
    horizons: tuple[int, ...]
    levels: NDArray[np.float64]
    values: dict[str, NDArray[np.float64]]
    paths: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        shape = (len(self.horizons), len(self.levels))
        for target, arr in self.values.items():
            if arr.shape != shape:
                raise TargetError(f"{self.forecaster} at {self.origin.date()}: {target} quantiles "
                                  f"have shape {arr.shape}, expected {shape}")
            if not np.isfinite(arr).all():
                raise TargetError(f"{self.forecaster} at {self.origin.date()}: {target} "
                                  "quantiles are not finite")
            if (np.diff(arr, axis=-1) < -1e-12 * np.abs(arr[..., 1:]).max(initial=1.0)).any():
                raise TargetError(f"{self.forecaster} at {self.origin.date()}: {target} "
                                  "quantiles decrease along the levels")


@dataclass(frozen=True, eq=False)
class BacktestResult:
    """The arrays of a backtest (module docstring). ``regimes`` ``(C, O)``; ``weights``
    ``(O, H, M)`` of the published combination; ``paths`` ``(C, O, n, H, 3)`` of the published
    forecast (None: not drawn); ``reported`` ``(O,)``: the origins kept (the others were a
    warm-up of the combiner)."""

    panel: Panel
    origins: tuple[pd.Timestamp, ...]
    horizons: tuple[int, ...]
    levels: NDArray[np.float64]
    members: tuple[str, ...]
    references: tuple[str, ...]
    forecasts: dict[str, dict[str, Quantiles]]
    truth: dict[str, Observed]
    regimes: NDArray[np.intp]
    weights: NDArray[np.float64]
    paths: NDArray[np.float64] | None
    reported: NDArray[np.bool_]
    seconds: dict[str, float]
    config: BacktestConfig
    # the members the guard left out, and where (pipeline.members.isolation)
    failures: dict[str, MemberFailure] = dataclasses.field(default_factory=dict)
    # (C, O, H, 2) the published bound on the count target's quantiles (None: not bounded;
    # pipeline.combine.plausibility)
    bounds: NDArray[np.float64] | None = None

    @property
    def places(self) -> tuple[str, ...]:
        return self.panel.places

    @property
    def populations(self) -> NDArray[np.float64]:
        return self.panel.populations

    @property
    def targets(self) -> tuple[str, ...]:
        return tuple(self.forecasts)

    def quantiles(self, target: str, forecaster: str = PUBLISHED) -> Quantiles:
        """``forecaster``'s quantiles of ``target``, labelled (places × origins × horizons ×
        levels)."""
        return self.forecasts[target][forecaster]

    def reported_only(self) -> BacktestResult:
        """The result at the reported origins only."""
        keep = np.asarray(self.reported, dtype=bool)
        if keep.all():
            return self
        if not keep.any():
            raise EnsembleError("no reported origin in the backtest")
        return self._subset(None, keep)

    def for_places(self, places: Sequence[str]) -> BacktestResult:
        """The same backtest restricted to ``places`` (their forecasts are unchanged: pooled
        members learnt from every place of the panel)."""
        unknown = [p for p in places if p not in self.places]
        if unknown:
            raise EnsembleError(f"places {unknown} are not in the backtest ({len(self.places)} "
                                f"places: {', '.join(self.places[:5])}, …)")
        return self._subset(tuple(places), np.ones(len(self.origins), dtype=bool))

    def _subset(self, places: tuple[str, ...] | None, keep: NDArray[np.bool_]
                ) -> BacktestResult:
        """``places`` (None: all) at the origins ``keep`` marks (a mask: two hub rounds may
        share an origin), every forecast, truth and array cut alike."""
        c = (np.arange(len(self.places)) if places is None
             else np.array(positions(self.places, list(places), "place")))
        o = np.flatnonzero(keep)
        cells = np.ix_(c, o)
        return dataclasses.replace(
            self, panel=self.panel if places is None else self.panel.only(places),
            origins=tuple(self.origins[i] for i in o),
            forecasts={t: {n: q.select(places=places, origins=keep) for n, q in f.items()}
                       for t, f in self.forecasts.items()},
            truth={t: v.select(places=places, origins=keep) for t, v in self.truth.items()},
            regimes=self.regimes[cells],
            weights=self.weights[o], paths=None if self.paths is None else self.paths[cells],
            reported=self.reported[o],
            bounds=None if self.bounds is None else self.bounds[cells],
            failures={n: MemberFailure(f.cells[cells], f.why) for n, f in self.failures.items()})

    def dropped_members(self, index: int = -1) -> dict[str, str]:
        """The members the guard left out at origin ``index`` (at one place or more), and why
        (:mod:`pipeline.members.isolation`); a member with no forecast at all there (the
        seasonal one before its climatology was released) too."""
        failed = {name: failure.why for name, failure in self.failures.items()
                  if failure.cells[:, index].any()}
        made = self.forecasts[self.panel.count_target]
        silent = {name: "no forecast for this round" for name in self.members
                  if name in made and name not in failed
                  and np.isnan(made[name].values[:, index]).all()}
        return failed | silent

    # ------------------------------------------------------------------------ one cell's view

    def forecast_at(self, place: str, origin: pd.Timestamp, forecaster: str = PUBLISHED
                    ) -> QuantileForecast:
        """One forecaster's forecast of ``place`` from ``origin`` (the published one with its
        sample paths)."""
        origin = pd.Timestamp(origin)
        values = {t: self.quantiles(t, forecaster).at(place=place, origin=origin)
                  for t, f in self.forecasts.items() if forecaster in f}
        paths = (self.paths[positions(self.places, [place], "place")[0],
                            positions(self.origins, [origin], "origin")[0]]
                 if forecaster == PUBLISHED and self.paths is not None else None)
        return QuantileForecast(forecaster, origin, self.horizons, self.levels, values, paths)

    def forecasters_at(self, place: str, origin: pd.Timestamp) -> dict[str, QuantileForecast]:
        """Every forecaster that forecast ``place`` from ``origin``."""
        count = self.panel.count_target
        return {n: self.forecast_at(place, origin, n) for n in self.forecasts[count]
                if np.isfinite(self.quantiles(count, n).at(place=place, origin=origin)).all()}

    # ---------------------------------------------------------------------------- summaries

    def summary(self) -> dict[str, Any]:
        """The JSON summary (computed once; treat it as read-only)."""
        return self._summary

    @functools.cached_property
    def _summary(self) -> dict[str, Any]:
        by_target: dict[str, dict[str, Any]] = {}
        costs: dict[str, dict[str, Any]] = {}
        cost_variants: dict[str, dict[str, Any]] = {}
        of_members = [v.name for v in self.config.variants if v.members is None]
        for target in self.targets:
            unit = self._unit(target)
            truth = self.truth[target]
            masks = regime_masks(self.regimes, self.truth[self.panel.count_target].values,
                                 len(self.horizons))
            scored = {name: q.score(truth, unit) for name, q in self.forecasts[target].items()}
            base = scored[HUB_BASELINE].wis
            by_target[target] = {
                name: summarize_forecaster(s, base, self.horizons, self.places, masks)
                for name, s in scored.items()}
            if UNCALIBRATED not in scored:
                continue
            # each forecaster's WIS over the published members' average uncalibrated: the
            # published calibration's cost, and each variant of the same members'
            def cost(name: str) -> dict[str, Any]:
                return calibration_cost(scored[name].wis, scored[UNCALIBRATED].wis,
                                        self.origins)
            if PUBLISHED in scored:
                costs[target] = cost(PUBLISHED)
            cost_variants[target] = {n: cost(n) for n in of_members if n in scored}
        out: dict[str, Any] = {
            "by_target": by_target,
            "calibration_cost": costs,
            "calibration_cost_variants": cost_variants,
            "n_places": len(self.places), "places": list(self.places),
            "n_origins": len(self.origins),
            "origins": {"first": str(self.origins[0].date()),
                        "last": str(self.origins[-1].date())},
            "members": list(self.members), "references": list(self.references),
            "mean_weights": {f"h{h}": dict(zip(self.members,
                                               map(float, self.weights.mean(axis=0)[k])))
                             for k, h in enumerate(self.horizons)},
            "config": _config_dict(self.config),
            "seconds": {k: round(v, 2) for k, v in self.seconds.items()},
        }
        if self.bounds is not None:
            out["plausibility"] = self.plausibility()
        if self.paths is not None:
            invalid = self.invalid_counts()
            out["invalid_values"] = invalid.total
            out["invalid_values_detail"] = invalid.to_dict()
        return out

    def plausibility(self) -> dict[str, Any]:
        """The published bound (:mod:`pipeline.combine.plausibility`) and, for every
        forecaster of the count target, the share of its quantiles beyond it (the published
        forecast's is 0: it is held within it)."""
        bound = self.config.combine.bounded
        if self.bounds is None or bound is None:
            raise EnsembleError("this backtest's published forecast was not bounded")
        count = self.forecasts[self.panel.count_target]
        return {"bound": dataclasses.asdict(bound),
                "cells_bounded": float(np.isfinite(self.bounds).any(axis=-1).mean()),
                "share_beyond": {name: share_beyond(q.values, self.bounds)
                                 for name, q in count.items()}}

    def _unit(self, target: str) -> NDArray[np.float64]:
        """Turns the target into counts for the PIT: N for I, 1 for a count."""
        ones = np.ones_like(self.populations)
        return (self.populations if target == SHARE else ones)[:, None, None]

    def invalid_counts(self) -> InvalidCounts:
        """Invalid values in the published paths (negative fractions, S rising, R falling)."""
        total = InvalidCounts(0, 0, 0, 0)
        if self.paths is None:
            return total
        for c, place in enumerate(self.places):
            history = self.panel.histories[place]
            for o, origin in enumerate(self.origins):
                if not np.isfinite(self.paths[c, o]).all():
                    continue
                start = _state_at(history, origin)
                total = add_counts(total, count_invalid(self.paths[c, o], start))
        return total

    def scores(self) -> pd.DataFrame:
        """One row per scored cell × target × forecaster (:data:`SCORE_COLUMNS`)."""
        return self._scores

    @functools.cached_property
    def _scores(self) -> pd.DataFrame:
        frames = []
        origins = pd.DatetimeIndex(list(self.origins))
        for target in self.targets:
            truth = self.truth[target].values
            for name, q in self.forecasts[target].items():
                s = q.score(self.truth[target], self._unit(target))
                c, o, h = np.nonzero(np.isfinite(s.wis))
                horizon = np.asarray(self.horizons)[h]
                frames.append(pd.DataFrame({
                    "place": np.asarray(self.places, dtype=object)[c], "forecaster": name,
                    "target": target, "horizon": horizon, "origin_date": origins[o],
                    "target_end_date": origins[o] + pd.to_timedelta(DAYS_PER_WEEK * horizon,
                                                                    unit="D"),
                    "observed": truth[c, o, h], "median": s.median[c, o, h],
                    "wis": s.wis[c, o, h], "dispersion": s.dispersion[c, o, h],
                    "overprediction": s.overprediction[c, o, h],
                    "underprediction": s.underprediction[c, o, h],
                    **{f"covered_{round(100 * cov)}": v[c, o, h] > 0
                       for cov, v in s.covered.items()},
                    "pit": s.pit[c, o, h], "regime": self.regimes[c, o]}))
        return pd.concat(frames, ignore_index=True).reindex(columns=list(SCORE_COLUMNS))

    def weights_frame(self) -> pd.DataFrame:
        """origin, horizon, member, weight of the published combination."""
        return long_frame(self.weights, {
            "origin_date": np.array([o.date() for o in self.origins], dtype=object),
            "horizon": self.horizons, "member": self.members}, value="weight")


def _state_at(history: History, origin: pd.Timestamp) -> NDArray[np.float64]:
    """S, I, R at ``origin`` of a daily history (a weekly one: S from its counts, I the last
    week's count over N)."""
    seen = history.up_to(origin)
    if isinstance(seen, EpiHistory):
        return np.array([seen.S[-1], seen.I[-1], seen.R[-1]])
    s = float(seen.susceptible_at_weeks()[-1])
    i = float(np.nan_to_num(seen.weekly_cases()[-1])) / seen.population
    return np.array([s, i, 1.0 - s - i])


def _config_dict(config: Any) -> dict[str, Any]:
    out = dataclasses.asdict(config)
    out["variants"] = {v.name: {"combine": dataclasses.asdict(v.combine), "members": v.members}
                       for v in config.variants}
    return out
