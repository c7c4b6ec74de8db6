"""Synthetic histories and members for the tests of the forecasting engine (no I/O)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.backtest.result import QuantileForecast
from pipeline.data.core.sir_counts import proportions, sir_counts
from pipeline.members.base import Member, MemberForecast
from pipeline.panels.history import EpiHistory, History
from pipeline.panels.panel import Cells, Panel
from pipeline.panels.targets import HUB_QUANTILE_LEVELS

POPULATION = 100_000
LEVELS = np.asarray(HUB_QUANTILE_LEVELS)


def history_from_cases(cases: NDArray[np.int64], start: str = "2021-01-06",
                       population: int = POPULATION) -> EpiHistory:
    """An EpiHistory whose S/I/R come from the product's conversion with L = 7, no deaths."""
    cases = np.asarray(cases, dtype=np.int64)
    s, i, r = sir_counts(cases, np.zeros_like(cases), cases_before=0, deaths_before=0,
                         population=population, infectious_period_days=7)
    ps, pi, pr = proportions(s, i, r, population)
    dates = pd.date_range(start, periods=len(cases), freq="D")
    return EpiHistory(dates, cases, ps, pi, pr, population)


def random_walk_history(n_weeks: int, seed: int, sigma: float = 0.25,
                        level: float = 700.0) -> EpiHistory:
    """Daily cases whose weekly totals follow a log random walk (step sd ``sigma``)."""
    rng = np.random.default_rng(seed)
    weekly = level * np.exp(np.cumsum(rng.normal(0.0, sigma, n_weeks)))
    daily = rng.poisson(np.repeat(weekly / 7.0, 7))
    return history_from_cases(daily)


def forecast_one(member: Member, history: History, horizons: tuple[int, ...] = (1, 2, 3, 4),
                 seed: int = 0, levels: NDArray[np.float64] = LEVELS,
                 panel: Panel | None = None, place: str = "place") -> QuantileForecast:
    """``member``'s forecast of one history (its own one-place panel unless given)."""
    own = panel if panel is not None else Panel({place: history})
    made = member.forecast(Cells.of([history], [seed], [place], [own]), horizons, levels)
    values = {t: v[0] for t, v in made.values((history,)).items()}
    return QuantileForecast(member.name, history.origin, tuple(horizons), levels, values,
                            None if made.paths is None else made.paths[0])


@dataclass(frozen=True)
class LogNormalMember:
    """Forecasts weekly cases log-normal around last week's count with spread ``sigma``·√h."""

    name: str
    sigma: float

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        from scipy.stats import norm

        last = np.array([max(h.weekly_cases()[-1], 0.5) for h in cells.histories])
        h = np.sqrt(np.asarray(horizons, dtype=np.float64))
        z = norm.ppf(levels)
        return MemberForecast(np.exp(np.log(last)[:, None, None]
                                     + self.sigma * h[None, :, None] * z[None, None, :]))
