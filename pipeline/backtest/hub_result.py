"""The result of the hub's rounds (:func:`~pipeline.backtest.hub_rounds.run_hub_rounds`): every
forecaster's quantiles per location × round × hub horizon × level in the hub's units, the truth
of the latest vintage, the published sample trajectories; scores, summaries and each round's
hub file read from it.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.backtest.result import BacktestResult
from pipeline.combine.average import EnsembleError
from pipeline.combine.combiner import PUBLISHED, UNCALIBRATED
from pipeline.evaluation.hub_leaderboard import SCORED_HORIZONS
from pipeline.evaluation.summary import calibration_cost, regime_masks, summarize_forecaster
from pipeline.members.hub_baseline import HUB_BASELINE
from pipeline.nowcast.revisions import WeekNowcast
from pipeline.panels.hub import HubRound
from pipeline.panels.quantiles import Observed, Quantiles, long_frame
from pipeline.panels.targets import format_level

# the published forecast with the states as forecast, and with them always reconciled
UNRECONCILED = "published-unreconciled"
RECONCILED = "published-reconciled"


@dataclass(frozen=True, eq=False)
class HubRoundsResult:
    """Every round of one target (module docstring). ``forecasts[name]`` (locations × rounds ×
    horizons × levels) and ``truth`` in the hub's units, labelled by reference date;
    ``samples`` ``(C, R, n, H)`` of the published forecast; ``gap`` ``(R, S)``: log(US median /
    Σ states' medians) before reconciliation; ``reconciled`` ``(R, S)``: the rounds and steps
    where the published forecast was reconciled (None: never, a share or no national total)."""

    target: str
    rounds: tuple[HubRound, ...]
    places: tuple[str, ...]
    horizons: tuple[int, ...]
    levels: NDArray[np.float64]
    forecasts: dict[str, Quantiles]
    truth: Observed
    samples: NDArray[np.float64] | None
    backtest: BacktestResult
    nowcasts: tuple[WeekNowcast, ...]
    gap: NDArray[np.float64] | None
    reconciled: NDArray[np.bool_] | None
    seconds: dict[str, float]

    @property
    def references(self) -> tuple[pd.Timestamp, ...]:
        return tuple(r.reference for r in self.rounds)

    def dropped_members(self, index: int = -1) -> dict[str, str]:
        """The members the guard left out of round ``index``, and why
        (:meth:`BacktestResult.dropped_members`)."""
        return self.backtest.dropped_members(index)

    def target_ends(self) -> NDArray[np.datetime64]:
        """``(R, H)`` the week each round's horizon ends."""
        return np.array([[r.target_end(h) for h in self.horizons] for r in self.rounds],
                        dtype="datetime64[ns]")

    def summary(self, forecaster: str = PUBLISHED,
                horizons: Sequence[int] | None = None) -> dict[str, Any]:
        """The one summary of every backtest (:func:`~pipeline.evaluation.summary.
        summarize_forecaster`) of ``forecaster`` at the hub ``horizons`` (default: all),
        against the hub baseline, by the phase of the epidemic at each round's origin."""
        # a horizon the rounds do not have is refused by name (Quantiles.select)
        steps = list(self.horizons) if horizons is None else list(horizons)
        truth = self.truth.select(horizons=steps)
        scores = self.forecasts[forecaster].select(horizons=steps).score(truth)
        base = self.forecasts[HUB_BASELINE].select(horizons=steps).score(truth).wis
        return summarize_forecaster(scores, base, steps, self.places,
                                    regime_masks(self.backtest.regimes, truth.values,
                                                 len(steps)))

    def calibration_cost(self, horizons: Sequence[int] | None = None,
                         forecasters: Sequence[str] = (PUBLISHED,)) -> dict[str, dict[str, Any]]:
        """Each of ``forecasters``' WIS over the published members' average uncalibrated at
        the hub ``horizons`` (default: all), over every round and in its worst window of
        consecutive rounds (:func:`~pipeline.evaluation.summary.calibration_cost`)."""
        steps = list(horizons or self.horizons)
        truth = self.truth.select(horizons=steps)

        def wis(name: str) -> NDArray[np.float64]:
            return self.forecasts[name].select(horizons=steps).score(truth).wis
        uncalibrated = wis(UNCALIBRATED)
        return {name: calibration_cost(wis(name), uncalibrated, self.references)
                for name in forecasters}

    def reconciliation(self) -> dict[str, Any] | None:
        """How far apart the national median and the states' sum were before reconciling, and
        the share of rounds at each weekly step where the published forecast was reconciled
        (None: no national total to reconcile to)."""
        if self.gap is None:
            return None
        out: dict[str, Any] = {"median_abs_log_gap_before": float(np.nanmedian(np.abs(self.gap))),
                               "p90_abs_log_gap_before": float(np.nanquantile(np.abs(self.gap),
                                                                              0.9))}
        if self.reconciled is not None:
            out["share_of_rounds_reconciled_by_step"] = {
                str(step): float(self.reconciled[:, k].mean())
                for k, step in enumerate(self.backtest.horizons)}
        return out

    def variants_of_members(self) -> tuple[str, ...]:
        """The variants of the published members (another calibration, another average)."""
        return tuple(v.name for v in self.backtest.config.variants
                     if v.members is None and v.name in self.forecasts)

    def scores(self, forecasters: Sequence[str] | None = None) -> pd.DataFrame:
        """One row per scored (forecaster, round, horizon, location): WIS and its parts,
        50 %/95 % coverage, in the hub's units."""
        frames = []
        ends = self.target_ends()
        for name in forecasters or list(self.forecasts):
            s = self.forecasts[name].score(self.truth)
            c, r, h = np.nonzero(np.isfinite(s.wis))
            frames.append(pd.DataFrame({
                "model_id": name, "reference_date": np.asarray(self.references,
                                                               dtype="datetime64[ns]")[r],
                "target": self.target, "horizon": np.asarray(self.horizons)[h],
                "location": np.asarray(self.places, dtype=object)[c],
                "target_end_date": ends[r, h], "observed": self.truth.values[c, r, h],
                "wis": s.wis[c, r, h], "dispersion": s.dispersion[c, r, h],
                "overprediction": s.overprediction[c, r, h],
                "underprediction": s.underprediction[c, r, h],
                "coverage_50": s.covered[0.5][c, r, h],
                "coverage_95": s.covered[0.95][c, r, h]}))
        return pd.concat(frames, ignore_index=True)

    def quantiles(self, forecaster: str = PUBLISHED) -> Quantiles:
        """``forecaster``'s quantiles, labelled: locations × rounds (reference dates) × hub
        horizons × levels."""
        return self.forecasts[forecaster]

    def horizon_index(self, horizon: int) -> int:
        """The position of hub ``horizon`` along the horizons' axis."""
        if horizon not in self.horizons:
            raise EnsembleError(f"horizon {horizon} is not among the round's {self.horizons}")
        return self.horizons.index(horizon)

    def draws(self, horizon: int, index: int = -1) -> NDArray[np.float64]:
        """``(C, n)`` the published sample trajectories at hub ``horizon`` of round
        ``index``."""
        if self.samples is None:
            raise EnsembleError("the rounds were forecast without sample trajectories")
        return self.samples[:, index, :, self.horizon_index(horizon)]

    def round_frame(self, index: int, forecaster: str = PUBLISHED) -> pd.DataFrame:
        """Round ``index``'s forecast in the hubverse format (quantiles and, for the published
        forecast, the sample trajectories: one id per location × target, across horizons)."""
        rnd = self.rounds[index]
        values = self.forecasts[forecaster].values[:, index]                 # (C, H, Q)
        keep = np.isfinite(values).all(axis=(1, 2))
        places = np.asarray(self.places)[keep]
        frames = [long_frame(values[keep], {
            "location": places, "horizon": self.horizons,
            "output_type_id": [format_level(lv) for lv in self.levels]}
        ).assign(output_type="quantile")]
        if forecaster == PUBLISHED and self.samples is not None:
            draws = self.samples[keep, index]                                 # (C', n, H)
            n = draws.shape[1]
            sampled = long_frame(draws, {"location": places, "output_type_id": np.arange(n),
                                         "horizon": self.horizons})
            # one trajectory id per location and draw, shared by its horizons
            ids = np.arange(len(places))[:, None, None] * n + np.arange(n)[None, :, None] + 1
            sampled["output_type_id"] = np.broadcast_to(ids, draws.shape).reshape(-1).astype(str)
            frames.append(sampled.assign(output_type="sample"))
        frame = pd.concat(frames, ignore_index=True)
        ends = {h: str(rnd.target_end(h).date()) for h in self.horizons}
        frame["target_end_date"] = frame["horizon"].map(ends)
        frame.insert(0, "reference_date", str(rnd.reference.date()))
        frame.insert(1, "target", self.target)
        return frame[["reference_date", "target", "horizon", "location", "target_end_date",
                      "output_type", "output_type_id", "value"]]


def summary_by_horizon(result: HubRoundsResult, forecaster: str = PUBLISHED
                       ) -> dict[str, Any]:
    """Coverage of a forecaster (50 %, 95 %) per hub horizon, over the horizons the hub scores
    (``"h0-3"``: 0 … 3) and over every horizon (``"all"``: −1 included)."""
    s = result.summary(forecaster)
    scored = result.summary(forecaster, [h for h in result.horizons if h in SCORED_HORIZONS])

    def hub(coverage: dict[str, Any]) -> dict[str, Any]:
        return {k: coverage[k] for k in ("coverage50", "coverage95")}

    return ({k: hub(v) for k, v in s["coverage_by_horizon"].items()}
            | {"h0-3": hub(scored), "all": hub(s)})
