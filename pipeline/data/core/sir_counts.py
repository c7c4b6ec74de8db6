"""Daily counts of cases and deaths -> S, I, R counts and proportions of a population: the
product's S/I/R conversion, shared by San Francisco's DataSF series
(:mod:`pipeline.data.sf.sir_transform`, where the assumptions behind it are argued) and
California's counties (:mod:`pipeline.data.california.cdph`).

Definitions (counts of people; N = population; t = day; c_t = new cases on day t, optionally
corrected for under-ascertainment, d_t = new deaths; C_t, D_t their running totals including any
cases/deaths counted before the first day of the series; L = infectious period in days)::

    I_t = C_t - C_{t-L}             cases reported in the last L days (days t-L+1 .. t)
    R_t = C_{t-L} + D_t             earlier cases (recovered) + deaths     [include_deaths=True]
    S_t = N - I_t - R_t

and the proportions are S_t/N, I_t/N, R_t/N.

Exactness: counts are integers with S_t + I_t + R_t = N exactly (checked). The float
proportions are I = I_t/N, R = R_t/N and S = (1 - I) - R, so S is the exact complement by
definition and S + I + R evaluates to 1 within one rounding (<= 2**-52). Forcing the float sum to
be exactly 1.0 is not always possible: for ~0.2 % of random (I, R) pairs we found no float64 S
within 8 ulp with (S + I) + R == 1.0.
"""
from __future__ import annotations

import numpy as np

from pipeline.errors import ConfigError, ValidationError

DEFAULT_INFECTIOUS_PERIOD_DAYS = 7


def sir_counts(new_cases: np.ndarray, new_deaths: np.ndarray, *, cases_before: int,
               deaths_before: int, population: int, infectious_period_days: int,
               include_deaths: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S, I, R) integer counts from daily counts; see the module docstring for the formulas."""
    cumulative = cases_before + np.cumsum(new_cases.astype(np.int64))
    lag = infectious_period_days
    earlier = np.concatenate([np.full(min(lag, len(cumulative)), cases_before, dtype=np.int64),
                              cumulative[:-lag] if lag < len(cumulative) else
                              np.empty(0, dtype=np.int64)])
    infected = cumulative - earlier
    removed = earlier + ((deaths_before + np.cumsum(new_deaths.astype(np.int64)))
                         if include_deaths else 0)
    susceptible = population - infected - removed
    if (susceptible < 0).any():
        raise ConfigError(f"I + R exceeds the population {population:,} "
                          f"(max I + R = {int((infected + removed).max()):,}); the ascertainment "
                          "multiplier or the population is wrong")
    return susceptible, infected, removed


def proportions(susceptible: np.ndarray, infected: np.ndarray, removed: np.ndarray,
                population: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """I = I_count/N, R = R_count/N (correctly rounded) and S = (1 - I) - R, the complement.

    The integer counts satisfy S + I + R = N exactly; in float64 S is defined as the complement,
    so S + I + R = 1 up to the rounding of one addition (|error| <= 2**-52, measured).
    ``susceptible`` is only used to check the counts are consistent.
    """
    if not np.array_equal(susceptible + infected + removed,
                          np.full_like(susceptible, population)):
        raise ValidationError("S + I + R counts do not add up to the population")
    i = infected / population
    r = removed / population
    return (1.0 - i) - r, i, r
