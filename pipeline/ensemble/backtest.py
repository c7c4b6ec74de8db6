"""Real-time backtest of the weekly forecast: what a user would have published at each origin.

For every weekly origin t (oldest first):

1. every member forecasts from ``history.up_to(t)`` only (and the references ``hub-baseline`` and
   ``autoets`` when they are not members);
2. the published forecast combines the members' current forecasts with weights and a
   recalibration fitted to **past scores only**: a forecast from origin o at horizon h is scored,
   and usable, at t only when o + 7h ≤ t (:mod:`pipeline.ensemble.combine`);
3. every forecaster is scored per target × horizon against the truth (when observed): WIS and
   its parts, 50 %/90 % coverage, PIT (from quantiles, deterministic).

Summaries (:func:`summarize`) are per target × horizon and never pooled across targets:
``by_target.<I|cases>.<forecaster>.relative_wis_vs_baseline.{h1..h4, all}`` = Σ WIS / Σ WIS of
``hub-baseline`` over the same cells, ``coverage50``, ``coverage90``, per-horizon coverage and a
10-bin PIT histogram. :func:`write_backtest` writes one hub-format CSV per origin (the published
forecast), ``scores.csv`` and ``summary.json``.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.errors import FlowcastError
from pipeline.ensemble.autoets import AutoETSMember
from pipeline.ensemble.hub_baseline import HUB_BASELINE, HubBaseline
from pipeline.ensemble.calibration import (CalibrationConfig, pit_from_quantiles,
                                              recalibrate)
from pipeline.ensemble.combine import (PUBLISHED, UNCALIBRATED, EnsembleConfig,
                                           InvalidCounts, add_counts, check_compatible,
                                           count_invalid, member_matrix, sample_paths,
                                           skill_weights, vincentize)
from pipeline.ensemble.members import Member, quantile_forecast_from_weekly_cases
from pipeline.ensemble.targets import (DAYS_PER_WEEK, HORIZONS_WEEKS, HUB_QUANTILE_LEVELS,
                                       TARGETS, EpiHistory, QuantileForecast, format_level,
                                       observed_targets)
from pipeline.io import atomic_write_json, atomic_write_text
from pipeline.progress import ProgressReporter, SilentProgress
from pipeline.evaluation.scoring import interval_coverage, weighted_interval_score

PIT_BINS = 10
PUBLISHED_BASIS = "cases"      # the ensemble is built on cases; I = cases / N
SCORE_COLUMNS = ("forecaster", "target", "horizon", "origin_date", "target_end_date", "observed",
                 "median", "wis", "dispersion", "overprediction", "underprediction",
                 "covered_50", "covered_90", "pit")
HUB_COLUMNS = ("origin_date", "target", "horizon", "target_end_date", "output_type",
               "output_type_id", "value")


class BacktestError(FlowcastError):
    """A backtest that cannot run: no origins in range, too short a history, bad dates."""


@dataclass(frozen=True)
class BacktestConfig:
    """Which origins, which horizons and levels, and the ensemble's settings.

    Origins fall every ``step_days`` days on ``origin_weekday`` (0 = Monday; None: the weekday of
    the history's last day) between ``first_origin`` and ``last_origin`` (None: unbounded), with
    at least ``min_history_weeks`` weeks of data, and (``scored_only``) the truth of the longest
    horizon observed. ``warm_up``: the ensemble also learns from the weekly origins before
    ``first_origin`` (run, scored, not reported), so the published forecast at a date does not
    depend on where the backtest starts — as it would not have for a user.
    """

    first_origin: dt.date | None = None
    last_origin: dt.date | None = None
    step_days: int = 7
    origin_weekday: int | None = None
    min_history_weeks: int = 8
    scored_only: bool = True
    horizons: tuple[int, ...] = HORIZONS_WEEKS
    levels: tuple[float, ...] = HUB_QUANTILE_LEVELS
    n_paths: int = 200
    seed: int = 0
    warm_up: bool = True
    ensemble: EnsembleConfig = field(default_factory=EnsembleConfig)
    # No recalibration by default: on the cross-county backtest every recalibration from past
    # PITs (widen-only, bias + scale, per regime) made the published forecast worse
    # (bench/results/backtest_counties.json, variants).
    calibration: CalibrationConfig = field(
        default_factory=lambda: CalibrationConfig(method="none"))

    def __post_init__(self) -> None:
        if self.step_days < 1 or self.min_history_weeks < 2 or self.n_paths < 1:
            raise BacktestError(f"invalid BacktestConfig: step_days={self.step_days} >= 1, "
                                f"min_history_weeks={self.min_history_weeks} >= 2, "
                                f"n_paths={self.n_paths} >= 1 required")
        if self.origin_weekday is not None and not 0 <= self.origin_weekday <= 6:
            raise BacktestError(f"origin_weekday={self.origin_weekday} must be 0 (Monday)..6")
        if not self.horizons or min(self.horizons) < 1:
            raise BacktestError(f"horizons {self.horizons} must be weeks >= 1")
        if (self.first_origin and self.last_origin and self.first_origin > self.last_origin):
            raise BacktestError(f"first origin {self.first_origin} is after the last "
                                f"{self.last_origin}")


@dataclass(frozen=True, eq=False)
class BacktestResult:
    """``forecasts[origin][forecaster]``: every forecast made; ``scores``: one row per
    (forecaster, target, horizon, origin) with observed truth (:data:`SCORE_COLUMNS`);
    ``weights``: origin, horizon, member, weight of the published average."""

    config: BacktestConfig
    origins: tuple[pd.Timestamp, ...]
    forecasts: dict[pd.Timestamp, dict[str, QuantileForecast]]
    scores: pd.DataFrame
    weights: pd.DataFrame
    invalid: InvalidCounts
    members: tuple[str, ...]
    population: int
    seconds: float

    @property
    def published(self) -> list[QuantileForecast]:
        return [self.forecasts[o][PUBLISHED] for o in self.origins]


# ------------------------------------------------------------------------------------ origins


def backtest_origins(history: EpiHistory, config: BacktestConfig) -> list[pd.Timestamp]:
    """The weekly origins of ``config`` within ``history`` (oldest first)."""
    dates = history.dates
    last = dates[-1]
    weekday = last.weekday() if config.origin_weekday is None else config.origin_weekday
    anchor = last - pd.Timedelta(days=(last.weekday() - weekday) % 7)
    earliest = dates[0] + pd.Timedelta(days=DAYS_PER_WEEK * config.min_history_weeks - 1)
    latest = anchor
    if config.scored_only:
        latest = min(latest, last - pd.Timedelta(days=DAYS_PER_WEEK * max(config.horizons)))
    if config.first_origin is not None:
        earliest = max(earliest, pd.Timestamp(config.first_origin))
    if config.last_origin is not None:
        latest = min(latest, pd.Timestamp(config.last_origin))
    steps = np.arange(0, (anchor - dates[0]).days + 1, config.step_days)
    candidates = [anchor - pd.Timedelta(days=int(s)) for s in steps]
    origins = sorted(o for o in candidates if earliest <= o <= latest)
    if not origins:
        raise BacktestError(f"no weekly origins between {earliest.date()} and {latest.date()} in "
                            f"a history of {dates[0].date()} … {last.date()} (at least "
                            f"{config.min_history_weeks} weeks of data"
                            + (f" and {max(config.horizons)} weeks of truth" if config.scored_only
                               else "") + " needed)")
    return origins


def origin_seed(seed: int, origin: pd.Timestamp) -> int:
    """A member's seed at ``origin``: depends on the date, not on which origins run."""
    return int(np.random.SeedSequence([seed, origin.toordinal()]).generate_state(1)[0])


# ---------------------------------------------------------------------------------- scoring


def _unit(target: str, population: int) -> float:
    return float(population) if target == "I" else 1.0


def score_forecasts(forecasts: Sequence[QuantileForecast], truth: dict[str, NDArray[np.float64]],
                    population: int) -> list[dict[str, Any]]:
    """Score rows (:data:`SCORE_COLUMNS`) of forecasts from one origin, observed horizons only."""
    rows: list[dict[str, Any]] = []
    if not forecasts:
        return rows
    ref = forecasts[0]
    levels = ref.levels
    mid = int(np.argmin(np.abs(levels - 0.5)))
    for target in TARGETS:
        y = truth[target]
        seen = np.flatnonzero(np.isfinite(y))
        if seen.size == 0:
            continue
        q = np.stack([f.values[target][seen] for f in forecasts])          # (F, h, Q)
        yy = np.broadcast_to(y[seen], q.shape[:-1])
        parts = weighted_interval_score(levels, q, yy)
        c50 = interval_coverage(levels, q, yy, 0.5)
        c90 = interval_coverage(levels, q, yy, 0.9)
        pit = pit_from_quantiles(levels, q, yy, _unit(target, population))
        for i, f in enumerate(forecasts):
            for j, k in enumerate(seen):
                h = ref.horizons[k]
                rows.append({
                    "forecaster": f.forecaster, "target": target, "horizon": h,
                    "origin_date": ref.origin, "target_end_date":
                        ref.origin + pd.Timedelta(days=DAYS_PER_WEEK * h),
                    "observed": float(yy[i, j]), "median": float(q[i, j, mid]),
                    "wis": float(parts.wis[i, j]), "dispersion": float(parts.dispersion[i, j]),
                    "overprediction": float(parts.overprediction[i, j]),
                    "underprediction": float(parts.underprediction[i, j]),
                    "covered_50": bool(c50[i, j]), "covered_90": bool(c90[i, j]),
                    "pit": float(pit[i, j])})
    return rows


class _PastScores:
    """Score rows kept for the ensemble: looked up by (forecaster, target, horizon), usable at
    origin t when their target end date ≤ t."""

    def __init__(self) -> None:
        self._rows: dict[tuple[str, str, int], list[tuple[pd.Timestamp, pd.Timestamp, float,
                                                          float]]] = defaultdict(list)

    def add(self, rows: Sequence[dict[str, Any]]) -> None:
        for r in rows:
            self._rows[(r["forecaster"], r["target"], r["horizon"])].append(
                (r["origin_date"], r["target_end_date"], r["wis"], r["pit"]))

    def known_at(self, forecaster: str, target: str, horizon: int, t: pd.Timestamp
                 ) -> dict[pd.Timestamp, tuple[float, float]]:
        return {o: (w, p) for o, end, w, p in self._rows[(forecaster, target, horizon)]
                if end <= t}


def past_wis_matrix(past: _PastScores, names: Sequence[str], target: str, horizon: int,
                    t: pd.Timestamp) -> NDArray[np.float64]:
    """WIS ``(n, M)`` of the named members at the past origins where all were scored by ``t``."""
    known = [past.known_at(n, target, horizon, t) for n in names]
    common = sorted(set.intersection(*(set(k) for k in known))) if known else []
    return np.array([[k[o][0] for k in known] for o in common]).reshape(len(common), len(names))


# --------------------------------------------------------------------------- the published one


def publish(history: EpiHistory, current: dict[str, QuantileForecast], members: Sequence[str],
            past: _PastScores, config: BacktestConfig
            ) -> tuple[QuantileForecast, QuantileForecast, NDArray[np.float64]]:
    """(published, uncalibrated ensemble, weights (H, M)) at ``history.origin`` from the members'
    current forecasts and the scores known at the origin."""
    t = history.origin
    levels = np.asarray(config.levels, dtype=np.float64)
    check_compatible([current[n] for n in members])
    values = member_matrix(current, members, PUBLISHED_BASIS)              # (M, H, Q)
    weights = np.stack([skill_weights(past_wis_matrix(past, members, PUBLISHED_BASIS, h, t),
                                      config.ensemble) for h in config.horizons])   # (H, M)
    raw = np.stack([vincentize(values[:, k], weights[k], config.ensemble.scale)
                    for k in range(len(config.horizons))])
    calibrated = np.stack([
        recalibrate(levels, raw[k],
                    [p for _, (_, p) in sorted(past.known_at(UNCALIBRATED, PUBLISHED_BASIS, h,
                                                             t).items())],
                    unit=1.0, config=config.calibration)
        for k, h in enumerate(config.horizons)])
    template = next((current[n].paths for n in members if current[n].paths is not None), None)
    paths = sample_paths(history, levels, calibrated, config.n_paths, template)
    uncal = quantile_forecast_from_weekly_cases(UNCALIBRATED, t, config.horizons, levels, raw,
                                 history.population)
    pub = quantile_forecast_from_weekly_cases(PUBLISHED, t, config.horizons, levels, calibrated,
                               history.population, paths)
    return pub, uncal, weights


def run_realtime_backtest(history: EpiHistory, members: Sequence[Member],
                          config: BacktestConfig = BacktestConfig(),
                          progress: ProgressReporter | None = None, *,
                          references: Sequence[Member] = ()) -> BacktestResult:
    """The real-time backtest over ``config``'s origins (module docstring). ``references``:
    further forecasters scored beside the members (e.g. the NF-seeded SMC member) that the
    published ensemble does not average; the hub baseline and AutoETS are scored too, unless a
    member or a reference of that name is given."""
    progress = progress or SilentProgress()
    started = time.perf_counter()
    names = [m.name for m in members]
    if len(set(names)) != len(names) or not names:
        raise BacktestError(f"members need distinct names, got {names}")
    if PUBLISHED in names or UNCALIBRATED in names:
        raise BacktestError(f"member names {PUBLISHED!r}/{UNCALIBRATED!r} are reserved")
    given = [*names, *(r.name for r in references)]
    scored: list[Member] = [*(r for r in (HubBaseline(), AutoETSMember()) if r.name not in given),
                            *(r for r in references if r.name not in names)]
    levels = np.asarray(config.levels, dtype=np.float64)
    origins = backtest_origins(history, config)
    run_origins = (backtest_origins(history, dataclasses.replace(config, first_origin=None))
                   if config.warm_up else origins)
    reported = set(origins)
    past = _PastScores()
    forecasts: dict[pd.Timestamp, dict[str, QuantileForecast]] = {}
    rows: list[dict[str, Any]] = []
    weight_rows: list[dict[str, Any]] = []
    invalid = InvalidCounts(0, 0, 0, 0)
    for origin in run_origins:
        seen = history.up_to(origin)
        seed = origin_seed(config.seed, origin)
        current = {m.name: m.forecast(seen, config.horizons, levels, seed)
                   for m in (*members, *scored)}
        pub, uncal, weights = publish(seen, current, names, past, config)
        current[UNCALIBRATED], current[PUBLISHED] = uncal, pub
        new_rows = score_forecasts(list(current.values()),
                                   observed_targets(history, origin, config.horizons),
                                   history.population)
        past.add(new_rows)
        if origin not in reported:
            continue
        assert pub.paths is not None
        invalid = add_counts(invalid, count_invalid(
            pub.paths, np.array([seen.S[-1], seen.I[-1], seen.R[-1]])))
        for k, h in enumerate(config.horizons):
            weight_rows.extend({"origin_date": origin, "horizon": h, "member": n,
                                "weight": float(weights[k, i])} for i, n in enumerate(names))
        rows.extend(new_rows)
        forecasts[origin] = current
        progress.advance(1, origin=str(origin.date()))
    scores = pd.DataFrame(rows, columns=list(SCORE_COLUMNS))
    return BacktestResult(config, tuple(origins), forecasts, scores, pd.DataFrame(weight_rows),
                          invalid, tuple(names), history.population,
                          time.perf_counter() - started)


# ---------------------------------------------------------------------------------- summaries


def _ratio(num: float, den: float) -> float | None:
    return float(num / den) if den > 0 else None


def summarize_forecaster(cells: pd.DataFrame, baseline: pd.DataFrame,
                         horizons: Sequence[int]) -> dict[str, Any]:
    """Summary of one forecaster on one target; ``cells``/``baseline`` are its and the
    baseline's score rows (matched on horizon and origin)."""
    merged = cells.merge(baseline[["horizon", "origin_date", "wis"]],
                         on=["horizon", "origin_date"], suffixes=("", "_baseline"))
    rel: dict[str, float | None] = {}
    mean_wis: dict[str, float | None] = {}
    cov: dict[str, dict[str, float | None]] = {}
    for h in horizons:
        m = merged[merged["horizon"] == h]
        rel[f"h{h}"] = _ratio(m["wis"].sum(), m["wis_baseline"].sum())
        c = cells[cells["horizon"] == h]
        mean_wis[f"h{h}"] = float(c["wis"].mean()) if len(c) else None
        cov[f"h{h}"] = {"coverage50": float(c["covered_50"].mean()) if len(c) else None,
                        "coverage90": float(c["covered_90"].mean()) if len(c) else None}
    rel["all"] = _ratio(merged["wis"].sum(), merged["wis_baseline"].sum())
    hist, _ = np.histogram(cells["pit"].to_numpy(), bins=PIT_BINS, range=(0.0, 1.0))
    total = cells["wis"].sum()
    return {
        "relative_wis_vs_baseline": rel,
        "coverage50": float(cells["covered_50"].mean()) if len(cells) else None,
        "coverage90": float(cells["covered_90"].mean()) if len(cells) else None,
        "coverage_by_horizon": cov,
        "mean_wis": mean_wis,
        "wis_parts_share": {p: _ratio(cells[p].sum(), total)
                            for p in ("dispersion", "overprediction", "underprediction")},
        "pit_histogram": {"bins": PIT_BINS, "counts": hist.astype(int).tolist()},
        "n_scored": int(len(cells)),
    }


def summarize(result: BacktestResult) -> dict[str, Any]:
    """The JSON summary: ``by_target.<target>.<forecaster>`` (see the module docstring)."""
    scores = result.scores
    by_target: dict[str, dict[str, Any]] = {}
    for target in TARGETS:
        t_scores = scores[scores["target"] == target]
        base = t_scores[t_scores["forecaster"] == HUB_BASELINE]
        by_target[target] = {
            name: summarize_forecaster(t_scores[t_scores["forecaster"] == name], base,
                                       result.config.horizons)
            for name in t_scores["forecaster"].unique()}
    weights = (result.weights.groupby(["horizon", "member"])["weight"].mean().unstack()
               if len(result.weights) else pd.DataFrame())
    cfg = asdict(result.config)
    return {
        "by_target": by_target,
        "invalid_values": result.invalid.total,
        "invalid_values_detail": result.invalid.to_dict(),
        "n_origins": len(result.origins),
        "origins": {"first": str(result.origins[0].date()), "last": str(result.origins[-1].date())},
        "members": list(result.members),
        "published_basis": f"{PUBLISHED_BASIS}; I = cases / N",
        "mean_weights": {f"h{h}": {m: float(w) for m, w in row.items()}
                         for h, row in weights.iterrows()},
        "config": cfg,
        "seconds": {"backtest": round(result.seconds, 2)},
    }


# ------------------------------------------------------------------------------------ writing


def hub_frame(forecast: QuantileForecast, population: int) -> pd.DataFrame:
    """Hub-format rows (:data:`HUB_COLUMNS`) of a forecast: quantiles of I and cases, and the
    sample paths' I and weekly cases (N·I, ``population`` N) when it has paths."""
    origin = forecast.origin
    frames = []
    for target in TARGETS:
        values = forecast.values[target]
        n_h, n_q = values.shape
        h = np.repeat(np.asarray(forecast.horizons), n_q)
        frames.append(pd.DataFrame({
            "target": target, "horizon": h, "output_type": "quantile",
            "output_type_id": np.tile([format_level(lv) for lv in forecast.levels], n_h),
            "value": values.reshape(-1)}))
    if forecast.paths is not None:
        i_paths = forecast.paths[:, :, 1].T                                  # (H, n)
        n_h, n_s = i_paths.shape
        for target, vals in (("I", i_paths), ("cases", i_paths * population)):
            frames.append(pd.DataFrame({
                "target": target, "horizon": np.repeat(np.asarray(forecast.horizons), n_s),
                "output_type": "sample", "output_type_id": np.tile(np.arange(n_s).astype(str),
                                                                   n_h),
                "value": vals.reshape(-1)}))
    frame = pd.concat(frames, ignore_index=True)
    frame["origin_date"] = str(origin.date())
    frame["target_end_date"] = [str((origin + pd.Timedelta(days=DAYS_PER_WEEK * int(h))).date())
                                for h in frame["horizon"]]
    return frame[list(HUB_COLUMNS)]


def _csv(frame: pd.DataFrame) -> str:
    return frame.to_csv(index=False, float_format="%.10g", lineterminator="\n")


def write_backtest(result: BacktestResult, out_dir: str | Path,
                   extra: dict[str, Any] | None = None) -> list[Path]:
    """``forecasts/<origin>.csv`` (published, hub format), ``scores.csv``, ``summary.json``."""
    root = Path(out_dir)
    written = []
    for forecast in result.published:
        path = root / "forecasts" / f"{forecast.origin.date()}-published.csv"
        atomic_write_text(path, _csv(hub_frame(forecast, result.population)))
        written.append(path)
    scores = result.scores.copy()
    for col in ("origin_date", "target_end_date"):
        scores[col] = pd.to_datetime(scores[col]).dt.date.astype(str)
    atomic_write_text(root / "scores.csv", _csv(scores))
    atomic_write_json(root / "summary.json", {**summarize(result), **(extra or {})})
    written += [root / "scores.csv", root / "summary.json"]
    return written
