"""California's test positivity, the weekly panels' other signal (issue 51).

The weekly share positive is checked against the real CDPH vintage's own columns summed by
pandas; gbqr reads a panel's signal exactly as it reads a released other signal, and never a
week after the cell's origin."""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from bench.faults_cdph import CDPH, GOOD_VINTAGE
from pipeline.data.california.cdph import TEST_COLUMNS, read_cdph_csv
from pipeline.members.boosting import BoostingConfig, PooledBoostingMember
from pipeline.panels.california import (PER_TESTS, POSITIVITY, county_panel, select_counties,
                                        weekly_positivity)
from pipeline.panels.history import WeeklyHistory
from pipeline.panels.panel import panel_cells
from tests.test_boosting import _leading_signal

PATH = CDPH / GOOD_VINTAGE / "covid19cases_test.csv"


@pytest.fixture(scope="module")
def vintage():  # type: ignore[no-untyped-def]
    return read_cdph_csv(PATH)


def _pandas_weekly_share(area: str) -> pd.Series:
    """The file's own columns, summed over weeks ending Saturday by pandas (whole weeks)."""
    raw = pd.read_csv(PATH, usecols=["date", "area", "total_tests", "positive_tests"])
    rows = raw[raw["area"] == area].dropna(subset=["date"])
    rows = rows.assign(date=pd.to_datetime(rows["date"])).set_index("date").sort_index()
    weekly = rows.resample("W-SAT").agg(["sum", "count"])
    whole = (weekly[("total_tests", "count")] == 7) & (weekly[("positive_tests", "count")] == 7)
    share = weekly[("positive_tests", "sum")] / weekly[("total_tests", "sum")]
    return (share * PER_TESTS)[whole]


def test_the_counties_weekly_positivity_is_the_files_own(vintage):
    """San Francisco's and Los Angeles's weekly share positive, every whole week up to the
    panel's last day, equals the file's daily columns summed by pandas (to 1e-9)."""
    panel = county_panel(vintage, select_counties(vintage))
    assert panel.signal is not None and set(panel.signal.places) == set(panel.places)
    for area in ("San Francisco", "Los Angeles"):
        weekly = panel.signal.histories[area]
        assert isinstance(weekly, WeeklyHistory)
        assert weekly.target == POSITIVITY and not weekly.depletes
        assert (weekly.dates.dayofweek == 5).all() and weekly.dates[-1] <= panel.last_date
        assert panel.last_date - weekly.dates[-1] < pd.Timedelta(days=7)
        expected = _pandas_weekly_share(area).reindex(weekly.dates)
        held = np.isfinite(expected.to_numpy())
        assert held.sum() > 80
        np.testing.assert_allclose(weekly.cases[held], expected.to_numpy()[held], rtol=1e-9)
    # San Francisco's share positive in the week ending 2021-01-09, the winter peak: 4-5 %
    sf = panel.signal.histories["San Francisco"]
    assert isinstance(sf, WeeklyHistory)
    assert 4_000 < sf.cases[sf.dates.get_loc(pd.Timestamp("2021-01-09"))] < 5_000


def test_a_week_with_a_day_missing_or_more_positives_than_tests_is_missing():
    dates = pd.date_range("2021-01-03", periods=21, freq="D")            # Sunday … Saturday × 3
    total = np.full(21, 100.0)
    positive = np.full(21, 5.0)
    total[9] = np.nan                                                     # week 2 lacks a day
    positive[14:] = 150.0                                                 # week 3: 150 of 100
    ends, share = weekly_positivity(dates, total, positive, dates[-1])
    assert list(ends) == list(pd.to_datetime(["2021-01-09", "2021-01-16", "2021-01-23"]))
    assert share[0] == pytest.approx(0.05 * PER_TESTS) and np.isnan(share[1:]).all()


def test_a_vintage_without_tests_gives_a_panel_without_signal(vintage):
    bare = dataclasses.replace(vintage, frame=vintage.frame.drop(columns=list(TEST_COLUMNS)))
    panel = county_panel(bare, ("San Francisco", "Alameda"))
    assert panel.signal is None
    assert bare.county("San Francisco").total_tests is None


def test_gbqr_reads_a_panels_signal_as_a_released_other_signal():
    """The same forecast from the panel's own signal as from the same series released by the
    panel's date; and the memo's identity of a cell names the signal."""
    target, other, end, _, _ = _leading_signal()
    with_signal = dataclasses.replace(target, signal=other)
    config = BoostingConfig(n_estimators=20)
    levels = np.array([0.1, 0.5, 0.9])
    own = PooledBoostingMember(config).forecast(
        panel_cells(with_signal, [end], seed=0), (1, 2), levels).count
    released = PooledBoostingMember(config, other=((end, other),)).forecast(
        panel_cells(target, [end], seed=0), (1, 2), levels).count
    np.testing.assert_array_equal(own, released)
    identity = PooledBoostingMember(config).cell_identity(end, with_signal)
    assert isinstance(identity, tuple) and identity[2] is other


def test_the_signal_after_a_cells_origin_is_not_read():
    """A cell ten weeks before the panel's end forecasts the same with the whole signal as with
    the signal cut at its origin; the panel's own cut (``up_to``) cuts its signal too."""
    target, other, end, _, _ = _leading_signal()
    origin = end - pd.Timedelta(weeks=10)
    config = BoostingConfig(n_estimators=20)
    levels = np.array([0.1, 0.5, 0.9])
    whole = dataclasses.replace(target, signal=other)
    cut = dataclasses.replace(target, signal=other.up_to(origin))
    forecast = [PooledBoostingMember(config).forecast(panel_cells(p, [origin], seed=0), (1, 2),
                                                      levels).count for p in (whole, cut)]
    np.testing.assert_array_equal(forecast[0], forecast[1])
    signal = whole.up_to(origin).signal
    assert signal is not None and signal.last_date == origin
    assert whole.only(["p0"]).signal is other
