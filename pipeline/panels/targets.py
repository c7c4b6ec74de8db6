"""What is forecast: weekly counts at weekly horizons, at the Forecast Hub's quantile levels.

Every panel forecasts one weekly **count** per place: reported cases (DataSF, CDPH), hospital
admissions (NHSN), or the share of ED visits due to COVID-19 as a rate per 100,000 visits
(NSSP), each under the name its users know (``cases``, ``wk inc covid hosp``, …). A daily source
also has the infectious share **I** (:data:`SHARE`): with the product's infectious window L = 7
days, N·I(t) is exactly the trailing 7-day case count, so I at a week's end is the week's count
over N; the two are still scored separately (the hub baseline sees different histories: the
daily I series against the weekly counts).

Horizons are whole weeks after the origin (the last day a forecaster sees): the count of the
7-day week ending origin + 7h. A hub round's horizons −1 … 3 are counted from its reference
date instead (:mod:`pipeline.nowcast.hub_weeks`).
"""
from __future__ import annotations

from pipeline.errors import FlowcastError

# The COVID-19 Forecast Hub's 23 quantile levels, which every forecast here reports.
HUB_QUANTILE_LEVELS: tuple[float, ...] = (
    0.01, 0.025, 0.05, 0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50,
    0.55, 0.60, 0.65, 0.70, 0.75, 0.80, 0.85, 0.90, 0.95, 0.975, 0.99,
)
HORIZONS_WEEKS: tuple[int, ...] = (1, 2, 3, 4)
DAYS_PER_WEEK = 7
SATURDAY = 5

CASES = "cases"          # weekly reported cases of a daily source
SHARE = "I"              # the infectious share of a daily source: the week's cases / N
TARGETS: tuple[str, ...] = (SHARE, CASES)     # a daily source's targets, in report order


class TargetError(FlowcastError):
    """A history or forecast that does not fit the weekly targets (gaps, lengths, shapes)."""


def format_level(level: float) -> str:
    """A quantile level as hub files write it: ``0.025``, ``0.5``, ``0.1``."""
    return f"{level:.3f}".rstrip("0").rstrip(".")
