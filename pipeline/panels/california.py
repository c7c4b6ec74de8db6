"""California's panels: the counties of a CDPH vintage, and one place with the counties beside it.

* :func:`county_panel` — every county of at least ``min_population`` people (or the named ones)
  of a CDPH vintage, without its last ``trailing_days`` days (they were still filling in when it
  was downloaded: the nowcast's job, not the backtest's); the design set of the published
  forecast;
* :func:`place_panel` — one place's own series (San Francisco from DataSF, or a county) with
  California's counties as references: the pooled member learns from them, the place's own
  county series is left out of its pool.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import pandas as pd

from pipeline.data.california.cdph import CDPHVintage
from pipeline.panels.history import History, history_from_county
from pipeline.panels.panel import Panel

DEFAULT_MIN_POPULATION = 100_000
TRAILING_DAYS = 14


def select_counties(vintage: CDPHVintage, min_population: int = DEFAULT_MIN_POPULATION,
                    counties: Sequence[str] | None = None) -> tuple[str, ...]:
    """``counties`` (checked against the vintage), or every county with at least
    ``min_population`` people."""
    if counties is None:
        return vintage.counties_with_population(min_population)
    for county in counties:
        vintage.county(county)                  # names the county and suggests a spelling
    return tuple(counties)


def county_panel(vintage: CDPHVintage, counties: Sequence[str],
                 trailing_days: int = TRAILING_DAYS) -> Panel:
    """The counties' histories from ``vintage`` without its last ``trailing_days`` days."""
    last = vintage.as_of - pd.Timedelta(days=trailing_days)
    return Panel({c: history_from_county(vintage.county(c)).up_to(last) for c in counties},
                 name="california-counties")


def place_panel(place: str, history: History, references: Mapping[str, History],
                skipped: Mapping[str, str] | None = None) -> Panel:
    """``place``'s own series, pooled with California's counties (``references``; ``skipped``:
    those the validation gate left out, with why)."""
    return Panel({place: history}, dict(references), dict(skipped or {}), name=place)
