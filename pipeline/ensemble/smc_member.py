"""The NF-seeded SMC forecast member: the paper's hybrid as a weekly forecaster.

At an origin the member sees only ``history`` (the backtest passes ``history.up_to(origin)``):

1. the forward joint flow (the weekly run's, trained on the same multi-wave prior as the flow
   member) estimates (S, I, R, β) at the first of the last ``filter_days`` days from the
   ``window`` days before it (fewer filtered days in a history's first weeks, at least
   :data:`MIN_FILTER_DAYS`);
2. those draws seed a particle filter on the prior's own renewal dynamics
   (:class:`pipeline.inference.smc_models.WaveRenewalModel`), which follows the reported cases
   to the origin (:func:`pipeline.inference.hybrid.nf_seeded_wave_smc`);
3. the filtered particles are simulated four weeks on, reporting noise included
   (:func:`pipeline.inference.hybrid.forecast_weekly_reports`): their weekly case counts give the
   23 hub quantiles; I = cases / N (the conversion's window is a week).

:meth:`NFSeededSMCMember.forecast_batch` runs many histories (origins, counties) as one batch of
independent filters; each history's forecast depends only on its own data and its position in
the batch.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import torch
from numpy.typing import NDArray

from pipeline.ensemble.members import quantile_forecast_from_weekly_cases
from pipeline.ensemble.targets import EpiHistory, QuantileForecast, TargetError
from pipeline.inference.estimate import Estimator, ObservationWindow, batch_window_context
from pipeline.inference.hybrid import WaveSMCConfig, forecast_weekly_reports, nf_seeded_wave_smc
from pipeline.systems.waves import WavePrior

SMC_MEMBER = "nf-smc"
MIN_FILTER_DAYS = 14


@dataclass(frozen=True, eq=False)
class NFSeededSMCMember:
    """Forecast member (:class:`pipeline.ensemble.members.Member`): NF-seeded SMC on the
    multi-wave model. ``estimator`` is the forward joint (S, I, R, β) flow with a ``window``-day
    context; ``prior`` the multi-wave prior it was trained on."""

    estimator: Estimator
    window: int
    prior: WavePrior = field(default_factory=WavePrior)
    name: str = SMC_MEMBER
    n_particles: int = 1000
    filter_days: int = 56
    chunk: int = 64                # histories per batch of filters (memory: chunk × particles)

    @property
    def lead_days(self) -> int:
        """Days before the filter's first day: the flow's context and a week of reports."""
        return max(self.window, 2 * self.prior.window_days)

    @property
    def days_needed(self) -> int:
        """The shortest history the member forecasts from (a filter over 2 weeks at least)."""
        return self.lead_days + MIN_FILTER_DAYS

    def filter_days_for(self, history: EpiHistory) -> int:
        """``filter_days``, or fewer when the history is shorter (its first weeks)."""
        return min(self.filter_days, len(history) - self.lead_days)

    def weekly_cases(self, histories: Sequence[EpiHistory], weeks: int,
                     seed: int) -> NDArray[np.float64]:
        """``(B, n_particles, weeks)`` simulated weekly reported cases after each history's
        origin; histories with equal filter lengths run as one batch of filters."""
        short = [h for h in histories if len(h) < self.days_needed]
        if short:
            raise TargetError(f"{self.name}: needs {self.days_needed} days of history, got "
                              f"{len(short[0])} (origin {short[0].origin.date()})")
        out = np.empty((len(histories), self.n_particles, weeks))
        lengths = np.array([self.filter_days_for(h) for h in histories])
        for days in np.unique(lengths):
            index = np.flatnonzero(lengths == days)
            for first in range(0, len(index), self.chunk):
                part = index[first:first + self.chunk]
                out[part] = self._chunk([histories[i] for i in part], int(days), weeks,
                                        seed + int(part[0]))
        return out

    def _chunk(self, histories: Sequence[EpiHistory], filter_days: int, weeks: int,
               seed: int) -> NDArray[np.float64]:
        windows = []
        for h in histories:
            start = len(h) - filter_days
            rows = slice(start - self.window, start)
            times = np.arange(len(h), dtype=np.float64)
            values = np.stack([h.S[rows], h.I[rows], h.R[rows]], axis=-1)
            windows.append(ObservationWindow(times[rows], values, float(times[start])))
        context, mask = batch_window_context(windows, "forward", self.window)
        length = filter_days + self.lead_days
        cases = torch.as_tensor(np.stack([h.cases[-length:] for h in histories]),
                                dtype=torch.float64)
        population = torch.tensor([float(h.population) for h in histories])
        settings = WaveSMCConfig(n_particles=self.n_particles, seed=seed, quantiles=())
        with torch.no_grad():
            run = nf_seeded_wave_smc(self.estimator, context, mask, cases, population,
                                     filter_days, self.prior, settings)
            return forecast_weekly_reports(run, weeks, seed + 7).numpy()

    def forecast_batch(self, histories: Sequence[EpiHistory], horizons: tuple[int, ...],
                       levels: NDArray[np.float64], seed: int) -> list[QuantileForecast]:
        """One :class:`QuantileForecast` per history, from one batch of filters."""
        weekly = self.weekly_cases(histories, max(horizons), seed)        # (B, n, W)
        index = [h - 1 for h in horizons]
        quantiles = np.moveaxis(np.quantile(weekly[:, :, index], levels, axis=1), 0, -1)
        return [quantile_forecast_from_weekly_cases(self.name, h.origin, tuple(horizons),
                                                    np.asarray(levels), q, h.population)
                for h, q in zip(histories, quantiles, strict=True)]

    def forecast(self, history: EpiHistory, horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int) -> QuantileForecast:
        return self.forecast_batch([history], horizons, levels, seed)[0]



@dataclass(frozen=True, eq=False)
class BatchedForecasts:
    """A member's forecasts at many origins made as one batch beforehand (each from its own
    ``history.up_to(origin)``), served to the backtest one origin at a time."""

    name: str
    forecasts: dict[pd.Timestamp, QuantileForecast]

    def forecast(self, history: EpiHistory, horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int) -> QuantileForecast:
        made = self.forecasts.get(history.origin)
        if made is None or made.horizons != tuple(horizons) or not np.array_equal(
                made.levels, np.asarray(levels)):
            raise TargetError(f"{self.name}: no batched forecast from {history.origin.date()} "
                              f"at horizons {horizons}")
        return made


def batched_smc_forecasts(member: NFSeededSMCMember, history: EpiHistory,
                          origins: Sequence[pd.Timestamp], horizons: tuple[int, ...],
                          levels: NDArray[np.float64], seed: int) -> BatchedForecasts:
    """The member at every origin with enough history, in one batch of filters, each from
    ``history.up_to(origin)`` only."""
    seen = [history.up_to(o) for o in origins]
    usable = [h for h in seen if len(h) >= member.days_needed]
    made = member.forecast_batch(usable, horizons, levels, seed) if usable else []
    return BatchedForecasts(member.name, {f.origin: f for f in made})
