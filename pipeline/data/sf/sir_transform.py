"""Reported San Francisco cases, deaths and tests -> S, I, R proportions of the population.

DataSF publishes no recoveries ("these data do not reflect the number of COVID-19 recoveries"),
so R must be constructed. The paper says only that its SIR data come from "case, testing, and
death reports, obtained using a similar data transformation process as in [AlQadi2022]"; the
conversion below is our explicit, configurable version of that idea.

Definitions (counts of people; N = population; t = day; c_t = new cases on day t, optionally
corrected for under-ascertainment, d_t = new deaths; C_t, D_t their running totals including any
cases/deaths DataSF counts before the first day of the series; L = infectious period in days)::

    I_t = C_t - C_{t-L}             cases reported in the last L days (days t-L+1 .. t)
    R_t = C_{t-L} + D_t             earlier cases (recovered) + deaths     [include_deaths=True]
    S_t = N - I_t - R_t

and the proportions are S_t/N, I_t/N, R_t/N.

Assumptions (each a modelling choice, not a fact of the data):

1. A reported case is infectious for exactly L days from its specimen-collection date, then
   removed. Default L = 7 days. Infectiousness peaks around symptom onset and rarely lasts beyond
   10 days (CDC, "Ending Isolation and Precautions for People with COVID-19", 2020–2022; Wölfel
   et al., Nature 581, 2020: no culturable virus after day 8), so 7–10 days are all defensible;
   7 is chosen because reporting has a weekly rhythm: a window of whole weeks holds every
   weekday once, so I carries no day-of-week saw-tooth (a 10-day sum holds three weekdays twice:
   on the SF series, 2020-06 to 2022-03, its deviation from its own centred 7-day mean is 5.0 %
   at the median and 11.4 % at the 95th percentile; 2.3 % and 7.4 % for 7 days, where only the
   trend's curvature is left), and N·I is exactly the number of cases reported in the last week,
   the quantity the weekly forecast targets. A single fixed period is the
   simplest delay model; a gamma-distributed period would smooth I but adds a parameter the data
   cannot identify.
2. Specimen-collection date = infection-start date (ignores the incubation and testing delay,
   a shift of a few days that does not change proportions).
3. Deaths are removals on their date of death. DataSF deaths are also reported cases, so with
   ``include_deaths=True`` (default, the issue's definition "earlier cases + deaths") a person who
   died is counted in R twice once their case is older than L days. This overstates R by at most
   D_t/N (862/873,965 = 0.099 % of the population at the end of the SF series) and keeps R
   monotone. ``include_deaths=False`` gives R_t = C_{t-L} (deaths assumed among earlier cases).
4. Nobody is reinfected, nobody enters or leaves the population (closed SIR, N constant):
   S is "never a reported (or estimated) case". In SF by 2022 this is plainly false (reinfections,
   vaccination) — the SIR reading is the paper's, and S stays near 1 anyway.
5. Population N = 873,965 (2020 Census count for the City and County of San Francisco). DataSF's
   own age-group estimates sum to 881,549 (ACS); the choice moves proportions by 0.9 %.
6. Under-ascertainment (optional, :class:`AscertainmentConfig`; default *off*). Reported cases
   miss many infections, more so when test positivity is high (too few tests for the epidemic).
   When enabled, each day's cases are multiplied by

       m_t = a / (day_t + b) * p_t ** k + c

   with p_t the trailing 7-day test positivity sum(pos)/sum(pos+neg), day_t days since
   2020-02-12, and defaults a=1500, b=50, k=0.5, c=2: the prevalence-ratio model of Y. Gu,
   "Estimating True Infections — Revisited" (covid19-projections.com, 2020/2021), as we read it;
   a multiplier growing with sqrt(positivity) and shrinking as testing expanded. Related and
   validated against seroprevalence: Chiu & Ndeffo-Mbah, "Using test positivity and reported case
   rates to estimate state-level COVID-19 prevalence and seroprevalence in the United States",
   PLOS Comput. Biol. 17(9): e1009374 (2021). Corrected daily counts are rounded to whole
   people. Default off because the multiplier is a model with roughly factor-2 uncertainty and
   its coefficients were fitted to US states, not SF; on, it puts SF closer to the synthetic
   prior (see docs/data.md for the measured effect).

The arithmetic (:func:`sir_counts`, :func:`proportions`, and their exactness: S + I + R = N in
integers, 1 within one rounding in float64) is shared with California's counties:
:mod:`pipeline.data.core.sir_counts`.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd

from pipeline.data.core.sir_counts import DEFAULT_INFECTIOUS_PERIOD_DAYS, proportions, sir_counts
from pipeline.data.sf.datasf import SF_POPULATION_2020_CENSUS
from pipeline.data.sf.series import SeriesProvenance, SFSeries
from pipeline.errors import ConfigError, ValidationError


@dataclass(frozen=True)
class AscertainmentConfig:
    """m_t = scale / (days since reference_date + offset_days) * positivity**exponent + floor."""

    scale: float = 1500.0
    offset_days: float = 50.0
    exponent: float = 0.5
    floor: float = 2.0
    reference_date: str = "2020-02-12"
    positivity_window_days: int = 7

    def __post_init__(self) -> None:
        if self.positivity_window_days < 1 or self.offset_days <= 0 or self.floor < 1.0:
            raise ConfigError(f"invalid AscertainmentConfig {self}: need window >= 1, "
                              "offset_days > 0, floor >= 1 (never fewer infections than cases)")


@dataclass(frozen=True)
class SIRConversionConfig:
    population: int = SF_POPULATION_2020_CENSUS
    infectious_period_days: int = DEFAULT_INFECTIOUS_PERIOD_DAYS
    include_deaths: bool = True
    ascertainment: AscertainmentConfig | None = None

    def __post_init__(self) -> None:
        if self.population <= 0:
            raise ConfigError(f"population must be positive, got {self.population}")
        if self.infectious_period_days < 1:
            raise ConfigError(f"infectious_period_days must be >= 1, got "
                              f"{self.infectious_period_days}")


@dataclass(frozen=True)
class SIRProvenance:
    series: SeriesProvenance
    conversion: SIRConversionConfig

    def to_dict(self) -> dict[str, Any]:
        return {**self.series.to_dict(), "conversion": asdict(self.conversion)}


@dataclass(frozen=True)
class SIRSeries:
    """``frame``: date, S, I, R (proportions, float64); ``counts``: date, S, I, R (int64 people),
    multiplier (ascertainment factor, 1 when off); provenance incl. data vintage."""

    frame: pd.DataFrame
    counts: pd.DataFrame
    provenance: SIRProvenance


def trailing_positivity(positives: np.ndarray, negatives: np.ndarray, window: int) -> np.ndarray:
    """Trailing ``window``-day positivity sum(pos)/sum(pos+neg); days before the first test
    borrow the first defined value (the earliest days of the series have none)."""
    kernel = np.ones(window)
    pos = np.convolve(positives.astype(np.float64), kernel)[: len(positives)]
    total = np.convolve((positives + negatives).astype(np.float64), kernel)[: len(positives)]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = pos / total
    series = pd.Series(ratio).bfill().ffill()
    if series.isna().all():
        raise ValidationError("no tests recorded: test positivity undefined")
    return series.to_numpy()


def ascertainment_multiplier(dates: pd.Series, positives: np.ndarray, negatives: np.ndarray,
                             config: AscertainmentConfig) -> np.ndarray:
    days = (pd.to_datetime(dates) - pd.Timestamp(config.reference_date)).dt.days.to_numpy()
    days = np.maximum(days, 0).astype(np.float64)
    positivity = trailing_positivity(positives, negatives, config.positivity_window_days)
    return config.scale / (days + config.offset_days) * positivity ** config.exponent + config.floor


def to_sir(series: SFSeries, config: SIRConversionConfig = SIRConversionConfig()) -> SIRSeries:
    """Convert the combined SF series (needs new_cases; new_deaths when ``include_deaths``;
    positives/negatives when ascertainment is on) to S, I, R; see the module docstring."""
    frame = series.frame
    needed = ["new_cases"] + (["new_deaths"] if config.include_deaths else []) + (
        ["positives", "negatives"] if config.ascertainment is not None else [])
    missing = [c for c in needed if c not in frame]
    if missing:
        raise ConfigError(f"S/I/R conversion needs columns {missing}; load the series with the "
                          "deaths/tests datasets or change SIRConversionConfig")
    cases = frame["new_cases"].to_numpy(dtype=np.int64)
    cases_before = int(frame["cumulative_cases"].iloc[0] - cases[0])
    multiplier = np.ones(len(frame))
    if config.ascertainment is not None:
        multiplier = ascertainment_multiplier(frame["date"], frame["positives"].to_numpy(),
                                              frame["negatives"].to_numpy(), config.ascertainment)
        cases = np.rint(cases * multiplier).astype(np.int64)
    deaths = frame["new_deaths"].to_numpy(dtype=np.int64) if config.include_deaths else \
        np.zeros_like(cases)
    deaths_before = (int(frame["cumulative_deaths"].iloc[0] - deaths[0])
                     if config.include_deaths else 0)
    s, i, r = sir_counts(cases, deaths, cases_before=cases_before, deaths_before=deaths_before,
                         population=config.population,
                         infectious_period_days=config.infectious_period_days,
                         include_deaths=config.include_deaths)
    ps, pi, pr = proportions(s, i, r, config.population)
    dates = frame["date"].reset_index(drop=True)
    return SIRSeries(
        frame=pd.DataFrame({"date": dates, "S": ps, "I": pi, "R": pr}),
        counts=pd.DataFrame({"date": dates, "S": s, "I": i, "R": r, "multiplier": multiplier}),
        provenance=SIRProvenance(series.provenance, config))
