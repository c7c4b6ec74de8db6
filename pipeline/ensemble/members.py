"""Ensemble members: the interface every weekly forecaster implements, and the member list.

A member sees only an :class:`~pipeline.ensemble.targets.EpiHistory` (the data up to its
origin; the backtest passes ``history.up_to(origin)``) and returns quantiles of BOTH targets at
the requested weekly horizons and levels.

Members that model weekly case counts get ``I`` for free: with the product's infectious window
L = 7 days, N·I(t) is exactly the number of cases reported in the 7 days ending t, so the
h-week-ahead ``I`` quantiles are the ``cases`` quantiles divided by N
(:func:`quantile_forecast_from_weekly_cases`).
"""
from __future__ import annotations

from typing import Protocol

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.ensemble.targets import EpiHistory, QuantileForecast, TargetError


class Member(Protocol):
    """A weekly forecaster: ``forecast`` must use nothing of the world but ``history``."""

    @property
    def name(self) -> str: ...

    def forecast(self, history: EpiHistory, horizons: tuple[int, ...],
                 levels: NDArray[np.float64], seed: int) -> QuantileForecast: ...


def quantile_forecast_from_weekly_cases(name: str, origin: pd.Timestamp, horizons: tuple[int, ...],
                                        levels: NDArray[np.float64],
                                        weekly_case_quantiles: NDArray[np.float64],
                                        population: int,
                                        paths: NDArray[np.float64] | None = None
                                        ) -> QuantileForecast:
    """A :class:`QuantileForecast` from weekly case quantiles ``(H, Q)``; ``I = cases / N``."""
    cases = np.asarray(weekly_case_quantiles, dtype=np.float64)
    if cases.shape != (len(horizons), len(levels)):
        raise TargetError(f"{name}: weekly case quantiles have shape {cases.shape}, expected "
                          f"{(len(horizons), len(levels))} (horizons × levels)")
    if population <= 0:
        raise TargetError(f"{name}: population must be positive, got {population}")
    return QuantileForecast(forecaster=name, origin=pd.Timestamp(origin), horizons=tuple(horizons),
                            levels=np.asarray(levels, dtype=np.float64),
                            values={"cases": cases, "I": cases / float(population)}, paths=paths)
