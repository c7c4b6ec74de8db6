"""California's panels: the counties of a CDPH vintage, and one place with the counties beside it.

* :func:`county_panel` — every county of at least ``min_population`` people (or the named ones)
  of a CDPH vintage, without its last ``trailing_days`` days (they were still filling in when it
  was downloaded: the nowcast's job, not the backtest's); the design set of the published
  forecast;
* :func:`place_panel` — one place's own series (San Francisco from DataSF, or a county) with
  California's counties as references: the pooled member learns from them, the place's own
  county series is left out of its pool;
* :func:`test_positivity` — the counties' weekly share of tests positive, the panels' other
  signal (:attr:`~pipeline.panels.panel.Panel.signal`): gbqr reads it beside the cases, as the
  hub's gbqr reads the ED share beside admissions. Testing grew tenfold through 2020, so cases
  rose with tests as well as with infections; the share positive moves with the epidemic.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.data.california.cdph import CDPHVintage
from pipeline.panels.history import History, WeeklyHistory, history_from_county
from pipeline.panels.panel import Panel
from pipeline.panels.targets import DAYS_PER_WEEK, SATURDAY

DEFAULT_MIN_POPULATION = 100_000
TRAILING_DAYS = 14
POSITIVITY = "test positivity"
# the share positive carried as positives per 100,000 tests (a rate, as the ED share per 100,000
# visits): the pooled member's scale reads it as a count on a population of 100,000
PER_TESTS = 100_000


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
    """The counties' histories from ``vintage`` without its last ``trailing_days`` days, their
    test positivity over the same days as its :attr:`~Panel.signal`."""
    last = vintage.as_of - pd.Timedelta(days=trailing_days)
    return Panel({c: history_from_county(vintage.county(c)).up_to(last) for c in counties},
                 name="california-counties", signal=test_positivity(vintage, counties, last))


def place_panel(place: str, history: History, references: Mapping[str, History],
                skipped: Mapping[str, str] | None = None, signal: Panel | None = None) -> Panel:
    """``place``'s own series, pooled with California's counties (``references``; ``skipped``:
    those the validation gate left out, with why; ``signal``: their test positivity)."""
    return Panel({place: history}, dict(references), dict(skipped or {}), name=place,
                 signal=signal)


def weekly_positivity(dates: pd.DatetimeIndex, total: np.ndarray, positive: np.ndarray,
                      last: pd.Timestamp) -> tuple[pd.DatetimeIndex, np.ndarray]:
    """The Saturdays ending whole weeks from ``dates`` to ``last`` and each week's positives per
    :data:`PER_TESTS` tests: NaN for a week with a day untested or unreported, or more
    positives than tests."""
    whole = dates[0] + pd.Timedelta(days=DAYS_PER_WEEK - 1)          # the first whole week's end
    first = whole + pd.Timedelta(days=(SATURDAY - whole.dayofweek) % DAYS_PER_WEEK)
    ends = pd.date_range(first, last, freq=f"{DAYS_PER_WEEK}D")
    offset = (ends - dates[0]).days.to_numpy()
    days = offset[:, None] - np.arange(DAYS_PER_WEEK)[None, ::-1]            # (W, 7)
    inside = (days >= 0) & (days < len(dates))
    pick = np.clip(days, 0, len(dates) - 1)
    tests = np.where(inside, total[pick], np.nan).sum(axis=1)
    positives = np.where(inside, positive[pick], np.nan).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where((tests > 0) & (positives <= tests), positives / tests, np.nan)
    return ends, share * PER_TESTS


def test_positivity(vintage: CDPHVintage, places: Sequence[str], last: pd.Timestamp
                    ) -> Panel | None:
    """``places``' weekly test positivity up to ``last`` (:func:`weekly_positivity`), the weeks
    ending on Saturdays as the panels' origins; None where the vintage has no tests."""
    histories: dict[str, WeeklyHistory] = {}
    for place in places:
        series = vintage.county(place)
        if series.total_tests is None or series.positive_tests is None:
            continue
        keep = series.dates <= last
        ends, share = weekly_positivity(series.dates[keep], series.total_tests[keep],
                                        series.positive_tests[keep], last)
        if len(ends) and np.isfinite(share).any():
            histories[place] = WeeklyHistory(ends, share, PER_TESTS, POSITIVITY, depletes=False)
    return Panel(histories, name=POSITIVITY) if histories else None
