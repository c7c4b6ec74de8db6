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

from pipeline.members.base import MemberForecast, quantiles_of_samples
from pipeline.panels.history import EpiHistory, History
from pipeline.panels.panel import Cells, Panel, panel_cells
from pipeline.panels.targets import TargetError
from pipeline.inference.estimate import Estimator, ObservationWindow, batch_window_context
from pipeline.inference.hybrid import WaveSMCConfig, forecast_weekly_reports, nf_seeded_wave_smc
from pipeline.systems.waves import WavePrior

SMC_MEMBER = "nf-smc"
MIN_FILTER_DAYS = 14


@dataclass(frozen=True, eq=False)
class NFSeededSMCMember:
    """Forecast member (:class:`pipeline.members.base.Member`): NF-seeded SMC on the
    multi-wave model. ``estimator`` is the forward joint (S, I, R, β) flow with a ``window``-day
    context; ``prior`` the multi-wave prior it was trained on."""

    estimator: Estimator
    window: int
    prior: WavePrior = field(default_factory=WavePrior)
    name: str = SMC_MEMBER
    seed: int = 0
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

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """Weekly count quantiles ``(B, H, Q)`` from one batch of filters (drawn from
        ``seed`` and each chunk's position, not the cells' seeds: the filters of a chunk share
        one generator)."""
        daily = [h for h in cells.histories if isinstance(h, EpiHistory)]
        if len(daily) != len(cells):
            raise TargetError(f"{self.name}: filters daily case counts; got a weekly series")
        weekly = self.weekly_cases(daily, max(horizons), self.seed)            # (B, n, W)
        return MemberForecast(quantiles_of_samples(weekly[:, :, [h - 1 for h in horizons]],
                                                   np.asarray(levels)))


@dataclass(frozen=True, eq=False)
class PrecomputedMember:
    """A member's forecasts made beforehand (the run filters the SMC member in a forked child
    while the other members load), served to the backtest by (place, origin)."""

    name: str
    forecasts: dict[tuple[str, pd.Timestamp], NDArray[np.float64]]
    horizons: tuple[int, ...]

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        """The forecasts made beforehand; NaN (no forecast) at a cell it did not make (an
        origin with too short a history for the filter)."""
        if tuple(horizons) != self.horizons:
            raise TargetError(f"{self.name}: forecasts were made at horizons {self.horizons}, "
                              f"not {tuple(horizons)}")
        missing = np.full((len(horizons), len(levels)), np.nan)
        return MemberForecast(np.stack([self.forecasts.get(key, missing) for key in
                                        zip(cells.places, cells.origins)]))

    def covers(self, place: str, origin: pd.Timestamp) -> bool:
        return (place, origin) in self.forecasts


def batched_smc_forecasts(member: NFSeededSMCMember, history: History, place: str,
                          origins: Sequence[pd.Timestamp], horizons: tuple[int, ...],
                          levels: NDArray[np.float64]) -> PrecomputedMember:
    """The member at every origin with enough history, in one batch of filters, each from
    ``history.up_to(origin)`` only."""
    usable = [o for o in origins if len(history.up_to(o)) >= member.days_needed]
    made = {}
    if usable:
        cells = panel_cells(Panel({place: history}), usable, 0)
        quantiles = member.forecast(cells, horizons, levels).count
        made = {(place, o): q for o, q in zip(usable, quantiles)}
    return PrecomputedMember(member.name, made, tuple(horizons))
