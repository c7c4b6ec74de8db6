"""Cases/deaths/tests -> S, I, R proportions: hand-computed examples and the real SF series."""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from pipeline.data.sf.csv_import import import_csv_exports
from pipeline.data.sf.series import (DataVintage, SeriesProvenance, SFDataConfig, SFSeries,
                                     load_sf_series)
from pipeline.data.core.sir_counts import sir_counts
from pipeline.data.sf.sir_transform import (SF_POPULATION_2020_CENSUS, AscertainmentConfig,
                                            SIRConversionConfig, ascertainment_multiplier, to_sir,
                                            trailing_positivity)
from pipeline.errors import ConfigError
from tests.test_datasf_client import EXPORTS

EPS = np.finfo(np.float64).eps


def small_series(new_cases, new_deaths, *, cases_before=0, deaths_before=0, pos=None, neg=None,
                 start="2020-03-03") -> SFSeries:
    n = len(new_cases)
    frame = pd.DataFrame({
        "date": pd.date_range(start, periods=n, freq="D").astype("datetime64[us]"),
        "new_cases": new_cases, "cumulative_cases": cases_before + np.cumsum(new_cases),
        "new_deaths": new_deaths, "cumulative_deaths": deaths_before + np.cumsum(new_deaths),
        "positives": pos if pos is not None else [0] * n,
        "negatives": neg if neg is not None else [0] * n})
    vintage = DataVintage("2022-03-21T04:30:01", "2026-01-01T00:00:00", str(frame.date[0].date()),
                          str(frame.date.iloc[-1].date()), 14)
    return SFSeries(frame, SeriesProvenance(vintage, ()))


def test_hand_computed_example():
    # N = 100, L = 2, new cases c = [1, 2, 3, 0, 0], new deaths d = [0, 0, 0, 1, 0]
    #   C_t       = [1, 3, 6, 6, 6]          running total of cases
    #   C_{t-2}   = [0, 0, 1, 3, 6]          (0 before the series: no earlier cases)
    #   I = C_t - C_{t-2}      = [1, 3, 5, 3, 0]
    #   D_t       = [0, 0, 0, 1, 1]
    #   R = C_{t-2} + D_t      = [0, 0, 1, 4, 7]
    #   S = 100 - I - R        = [99, 97, 94, 93, 93]
    sir = to_sir(small_series([1, 2, 3, 0, 0], [0, 0, 0, 1, 0]),
                 SIRConversionConfig(population=100, infectious_period_days=2))
    c = sir.counts
    assert c["I"].tolist() == [1, 3, 5, 3, 0]
    assert c["R"].tolist() == [0, 0, 1, 4, 7]
    assert c["S"].tolist() == [99, 97, 94, 93, 93]
    assert (c["multiplier"] == 1.0).all()
    np.testing.assert_array_equal(sir.frame["I"], [0.01, 0.03, 0.05, 0.03, 0.0])
    np.testing.assert_array_equal(sir.frame["R"], [0.0, 0.0, 0.01, 0.04, 0.07])
    np.testing.assert_allclose(sir.frame["S"], [0.99, 0.97, 0.94, 0.93, 0.93], rtol=0, atol=EPS)


def test_cases_and_deaths_before_the_series_are_removed_from_day_one():
    # Same series but DataSF's cumulative says 10 cases and 2 deaths before day 0:
    #   C_{t-2} = [10, 10, 11, 13, 16];  I unchanged = [1, 3, 5, 3, 0]
    #   R = C_{t-2} + D_t = [10+2, 10+2, 11+2, 13+3, 16+3] = [12, 12, 13, 16, 19]
    sir = to_sir(small_series([1, 2, 3, 0, 0], [0, 0, 0, 1, 0], cases_before=10,
                              deaths_before=2),
                 SIRConversionConfig(population=100, infectious_period_days=2))
    assert sir.counts["I"].tolist() == [1, 3, 5, 3, 0]
    assert sir.counts["R"].tolist() == [12, 12, 13, 16, 19]


def test_without_deaths_r_is_earlier_cases_only():
    # R = C_{t-2} = [0, 0, 1, 3, 6];  S = 100 - I - R = [99, 97, 94, 94, 94]
    sir = to_sir(small_series([1, 2, 3, 0, 0], [0, 0, 0, 1, 0]),
                 SIRConversionConfig(population=100, infectious_period_days=2,
                                     include_deaths=False))
    assert sir.counts["R"].tolist() == [0, 0, 1, 3, 6]
    assert sir.counts["S"].tolist() == [99, 97, 94, 94, 94]


def test_ascertainment_multiplier_hand_computed():
    # positives 1, negatives 3 every day -> trailing positivity p = 1/4 on every day.
    # Day 0 = 2020-03-03 is 20 days after 2020-02-12.  m_t = 1500/(day + 50) * p**0.5 + 2:
    #   m_0 = 1500/70 * 0.5 + 2 = 12.714285...   c_0 = rint(1 * 12.714) = 13
    #   m_1 = 1500/71 * 0.5 + 2 = 12.563380...   c_1 = rint(2 * 12.563) = rint(25.13) = 25
    #   m_2 = 1500/72 * 0.5 + 2 = 12.416666...   c_2 = rint(3 * 12.417) = rint(37.25) = 37
    # With L = 2: C = [13, 38, 75, 75, 75], C_{t-2} = [0, 0, 13, 38, 75]
    #   I = [13, 38, 62, 37, 0];  R = C_{t-2} + D = [0, 0, 13, 39, 76]
    series = small_series([1, 2, 3, 0, 0], [0, 0, 0, 1, 0], pos=[1] * 5, neg=[3] * 5)
    sir = to_sir(series, SIRConversionConfig(population=1000, infectious_period_days=2,
                                             ascertainment=AscertainmentConfig()))
    np.testing.assert_allclose(sir.counts["multiplier"][:3],
                               [1500 / 70 * 0.5 + 2, 1500 / 71 * 0.5 + 2, 1500 / 72 * 0.5 + 2],
                               rtol=1e-15)
    assert sir.counts["I"].tolist() == [13, 38, 62, 37, 0]
    assert sir.counts["R"].tolist() == [0, 0, 13, 39, 76]
    assert (sir.counts["S"] + sir.counts["I"] + sir.counts["R"] == 1000).all()


def test_trailing_positivity_window_and_days_without_tests():
    pos = np.array([0, 0, 1, 3, 0])
    neg = np.array([0, 0, 3, 1, 4])
    # day 0, 1: no tests yet -> borrow the first defined value (day 2: 1/4)
    # day 3: window 2 -> (1+3)/(4+4) = 0.5; day 4: (3+0)/(4+4) = 0.375
    np.testing.assert_allclose(trailing_positivity(pos, neg, 2), [0.25, 0.25, 0.25, 0.5, 0.375])
    mult = ascertainment_multiplier(pd.Series(pd.to_datetime(["2020-02-01"])), np.array([1]),
                                    np.array([0]), AscertainmentConfig())
    assert mult[0] == pytest.approx(1500 / 50 * 1.0 + 2)  # before the reference date: day 0


def test_sir_counts_conserve_population_for_any_lag():
    rng = np.random.default_rng(3)
    cases = rng.integers(0, 50, size=200)
    deaths = rng.integers(0, 2, size=200)
    for lag in (1, 7, 199, 200, 500):  # includes lags longer than the series
        s, i, r = sir_counts(cases, deaths, cases_before=5, deaths_before=1, population=10**5,
                             infectious_period_days=lag)
        assert (s + i + r == 10**5).all() and (np.diff(r) >= 0).all() and (i >= 0).all()
        window = np.convolve(cases, np.ones(lag, dtype=np.int64))[:200]
        np.testing.assert_array_equal(i, window)  # I = sum of the last L days' cases


def test_invalid_configs_are_refused():
    with pytest.raises(ConfigError, match="population must be positive"):
        SIRConversionConfig(population=0)
    with pytest.raises(ConfigError, match="infectious_period_days must be >= 1"):
        SIRConversionConfig(infectious_period_days=0)
    with pytest.raises(ConfigError, match="floor >= 1"):
        AscertainmentConfig(floor=0.5)
    with pytest.raises(ConfigError, match=r"I \+ R exceeds the population 10"):
        to_sir(small_series([5, 5, 5], [0, 0, 0]), SIRConversionConfig(population=10))


# --------------------------------------------------------------------------- real SF data


@pytest.fixture(scope="module")
def sf_series(datasf_dir, tmp_path_factory) -> SFSeries:
    """The real exports imported once into a module cache (explicit dir: the env is per test)."""
    root = tmp_path_factory.mktemp("sir-data")
    import_csv_exports([datasf_dir / EXPORTS[k] for k in ("cases", "deaths", "tests")],
                       data_dir=root)
    return load_sf_series(SFDataConfig(data_dir=root), offline=True)


@pytest.mark.parametrize("config", [
    SIRConversionConfig(),
    SIRConversionConfig(include_deaths=False, infectious_period_days=7),
    SIRConversionConfig(ascertainment=AscertainmentConfig()),
], ids=["default", "no-deaths-L7", "ascertainment"])
def test_real_series_invariants(sf_series, config):
    sir = to_sir(sf_series, config)
    s, i, r = (sir.frame[k].to_numpy() for k in "SIR")
    counts = sir.counts
    assert (counts["S"] + counts["I"] + counts["R"] == config.population).all()   # exact
    assert np.abs((s + i + r) - 1.0).max() <= EPS
    assert np.mean(s + i + r == 1.0) > 0.99  # measured: the float sum is exactly 1 on most days
    assert (np.diff(r) >= 0).all() and (i >= 0).all() and (s > 0).all()
    assert (np.diff(s) <= 0).all()  # nobody returns to S in a closed SIR reading
    assert sir.provenance.to_dict()["vintage"]["data_as_of"] == "2022-03-21T04:30:01"
    assert sir.provenance.to_dict()["conversion"]["population"] == config.population


def test_real_series_default_values_from_the_exports(sf_series):
    sir = to_sir(sf_series)
    f = sf_series.frame.set_index("date")
    last = pd.Timestamp("2022-03-02")
    # R on the last kept day = cases through 2022-02-23 (7 days earlier) + deaths through 03-02.
    expected_r = f.loc[:"2022-02-23", "new_cases"].sum() + f.loc[:last, "new_deaths"].sum()
    expected_i = f.loc["2022-02-24":last, "new_cases"].sum()
    assert sir.counts["R"].iloc[-1] == expected_r and sir.counts["I"].iloc[-1] == expected_i
    assert sir.frame["I"].iloc[-1] == expected_i / SF_POPULATION_2020_CENSUS
    # The Omicron wave (Dec 2021-Jan 2022) is the peak of I.
    peak = sir.frame.loc[sir.frame["I"].idxmax(), "date"]
    assert pd.Timestamp("2021-12-20") <= peak <= pd.Timestamp("2022-01-20")
    # The peak week: 16,686 cases reported in the week ending 2022-01-08 (I = weekly cases / N).
    assert 0.018 < sir.frame["I"].max() < 0.022


def test_population_scaling_halves_proportions_exactly(sf_series):
    base = to_sir(sf_series)
    double = to_sir(sf_series, SIRConversionConfig(population=2 * SF_POPULATION_2020_CENSUS))
    np.testing.assert_array_equal(double.counts["I"], base.counts["I"])  # counts: same people
    np.testing.assert_array_equal(double.frame["I"], base.frame["I"] / 2)  # exact: power of 2
    np.testing.assert_array_equal(double.frame["R"], base.frame["R"] / 2)


def test_ascertainment_raises_i_by_at_least_the_floor(sf_series):
    off = to_sir(sf_series)
    on = to_sir(sf_series, SIRConversionConfig(ascertainment=AscertainmentConfig()))
    m = on.counts["multiplier"].to_numpy()
    assert m.min() >= 2.0 and m.max() > 5.0
    # rint(c * m) >= 2c for m >= 2, so every window sum at least doubles.
    assert (on.counts["I"] >= 2 * off.counts["I"]).all()
    # Early (spring 2020: few tests, high positivity) the multiplier is much larger than late.
    dates = on.counts["date"]
    assert m[dates < "2020-05-01"].mean() > 2 * m[dates > "2021-06-01"].mean()
    bigger_floor = dataclasses.replace(AscertainmentConfig(), floor=3.0)
    on3 = to_sir(sf_series, SIRConversionConfig(ascertainment=bigger_floor))
    np.testing.assert_allclose(on3.counts["multiplier"], m + 1.0, rtol=0, atol=1e-12)
