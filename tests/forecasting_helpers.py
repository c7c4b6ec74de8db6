"""Synthetic histories and members for the tests of pipeline.ensemble (no I/O)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.sir_transform import proportions, sir_counts
from pipeline.ensemble.members import quantile_forecast_from_weekly_cases
from pipeline.ensemble.targets import EpiHistory, QuantileForecast

POPULATION = 100_000


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


@dataclass(frozen=True)
class LogNormalMember:
    """Forecasts weekly cases log-normal around last week's count with spread ``sigma``·√h."""

    name: str
    sigma: float

    def forecast(self, history: EpiHistory, horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int) -> QuantileForecast:
        from scipy.stats import norm

        last = history.weekly_cases()[-1]
        z = norm.ppf(levels)
        h = np.asarray(horizons, dtype=np.float64)[:, None]
        q = np.exp(np.log(max(last, 0.5)) + self.sigma * np.sqrt(h) * z)
        return quantile_forecast_from_weekly_cases(self.name, history.origin, horizons, levels, q,
                                                   history.population)
