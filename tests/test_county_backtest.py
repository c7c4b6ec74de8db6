"""Issue 19: the cross-county backtest and the published forecast's design on real CDPH data.

Real counties from the latest shared CDPH vintage (``../shared/data/cdph``, read in place): the
real-time discipline across counties (a forecast is unchanged when any county's data after its
origin are altered, through every member and the combination), the growth regression against
a known growth rate, the log-scale average against its closed form, and ``flowcast backtest
--county``."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from pipeline.data.california.cdph import CDPHVintage, read_cdph_csv
from pipeline.backtest.backtest import OneVintage, run_backtest
from pipeline.backtest.writers import write_backtest
from pipeline.combine.average import vincentize
from pipeline.errors import FlowcastError
from pipeline.members.nf.flow import SyntheticWindows, train_flow
from pipeline.members.nf.growth import GrowthModelConfig, NFGrowthMember
from pipeline.members.nf.real import FineTuneConfig, fit_finetuned_member
from pipeline.members.nf.refit import refit_dates
from pipeline.members.growth_regression import PooledGrowthMember, growth_regression_quantiles
from pipeline.members.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.panels.california import select_counties
from pipeline.panels.history import history_from_county
from pipeline.panels.panel import Panel, panel_cells, weeks_ending, weekly_origins
from pipeline.panels.targets import HUB_QUANTILE_LEVELS
from pipeline.systems.waves import WavePrior

REPO = Path(__file__).resolve().parents[1]
LATEST = (REPO.parent / "shared" / "data" / "cdph" / "ofaye98__CSC508_Mentor_Class"
          / "covid19cases_test.csv")
COUNTIES = ("Alameda", "Fresno", "Los Angeles", "Sacramento", "San Francisco")
LEVELS = np.asarray(HUB_QUANTILE_LEVELS)
TINY_FLOW = GrowthModelConfig(n_trajectories=120, iterations=30, batch_size=256,
                              prior=WavePrior(days=140))


@pytest.fixture(scope="module")
def vintage() -> CDPHVintage:
    if not LATEST.is_file():
        pytest.fail(f"the real CDPH vintage of 2021-11-04 is expected at {LATEST}")
    return read_cdph_csv(LATEST)


def _panel(vintage: CDPHVintage, altered: str | None = None,
           after: pd.Timestamp | None = None) -> Panel:
    """Five counties without the vintage's last 14 days; ``altered``'s cases after ``after``
    tripled (and one day's count made absurd)."""
    last = vintage.as_of - pd.Timedelta(days=14)
    histories = {}
    for county in COUNTIES:
        series = vintage.county(county)
        if county == altered and after is not None:
            cases = series.cases.copy()
            later = series.dates > after
            cases[later] *= 3
            cases[np.flatnonzero(later)[3]] += 50_000
            series = dataclasses.replace(series, cases=cases)
        histories[county] = history_from_county(series).up_to(last)
    return Panel(histories)


@pytest.fixture(scope="module")
def tiny_flow() -> tuple[NFGrowthMember, SyntheticWindows]:
    synthetic = SyntheticWindows(TINY_FLOW)
    return (NFGrowthMember(train_flow(TINY_FLOW, synthetic.dataset)[0], TINY_FLOW,
                           n_samples=200), synthetic)


def _members(panel: Panel, origins: list[pd.Timestamp],
             tiny_flow: tuple[NFGrowthMember, SyntheticWindows]) -> list:
    flow, synthetic = tiny_flow
    real = fit_finetuned_member(flow, synthetic, list(panel.histories.values()),
                                refit_dates(origins, 13),
                                FineTuneConfig(iterations=5, batch_size=128, min_windows=50))
    assert len(real.models) >= 3               # refits before and after the altered date
    return [HubBaseline(HubBaselineConfig(n_samples=2_000)), PooledGrowthMember(), flow, real]


def test_a_forecast_is_unchanged_when_any_county_changes_after_its_origin(vintage, tiny_flow):
    """Every member (the flat baseline, the pooled regression, the flow, the flow fine-tuned on
    every county's windows) and the published combination: cells at origins up to the cut are
    identical to the last bit when Fresno's later data are altered; later cells change."""
    panel = _panel(vintage)
    origins = weekly_origins(panel.dates)
    cut = origins[len(origins) // 2]
    altered = _panel(vintage, "Fresno", cut)
    before = run_backtest(OneVintage(panel), _members(panel, origins, tiny_flow), origins)
    after = run_backtest(OneVintage(altered), _members(altered, origins, tiny_flow), origins)
    upto = np.array([o <= cut for o in before.origins])
    assert before.origins == after.origins and upto.sum() >= 30
    for name in (*before.members, "published"):
        a, b = before.forecasts["cases"][name].values, after.forecasts["cases"][name].values
        np.testing.assert_array_equal(a[:, upto], b[:, upto], err_msg=name)
        assert not np.array_equal(a[:, ~upto], b[:, ~upto]), name
    fresno = COUNTIES.index("Fresno")
    assert not np.array_equal(before.truth["cases"].values[fresno, ~upto],
                              after.truth["cases"].values[fresno, ~upto])


def test_log_average_is_the_geometric_mean_of_counts_plus_one():
    rng = np.random.default_rng(3)
    a = np.sort(rng.gamma(2.0, 500.0, size=(4, 23)), axis=-1)
    b = 3.0 * a + 2.0
    np.testing.assert_allclose(vincentize(np.stack([a, b]), np.array([0.5, 0.5]), "log"),
                               np.sqrt((1 + a) * (1 + b)) - 1, rtol=1e-12)
    np.testing.assert_allclose(vincentize(np.stack([a, b]), np.array([0.25, 0.75]), "linear"),
                               0.25 * a + 0.75 * b, rtol=1e-12)
    with pytest.raises(FlowcastError, match="summing to 1"):
        vincentize(np.stack([a, b]), np.array([0.5, 0.6]), "log")


def test_growth_regression_recovers_a_known_growth_rate():
    """Six places growing at 8 % a week (levels 200 … 20,000, ±3 % multiplicative noise): the
    median h-week forecast is the last count × e^{0.08 h} within 2 %, and the 5–95 % interval
    holds the noise's spread, not more than a few percent."""
    rng = np.random.default_rng(0)
    weeks = np.arange(60)
    scale = np.array([200, 500, 1_000, 2_000, 8_000, 20_000])[:, None]
    weekly = scale * np.exp(0.08 * weeks)[None] * np.exp(rng.normal(0, 0.03, (6, 60)))
    origin = np.array([50])
    q = growth_regression_quantiles(weekly, origin, (1, 2, 3, 4), LEVELS)
    median = q[:, 0, :, 11]
    expected = weekly[:, 50, None] * np.exp(0.08 * np.arange(1, 5))[None]
    # the fit uses the smoothed recent growth, so a noisy last count shifts it a little
    np.testing.assert_allclose(median / expected, 1.0, atol=0.06)
    np.testing.assert_allclose(np.median(median / expected), 1.0, atol=0.02)
    width = q[:, 0, :, 20] / q[:, 0, :, 2]
    assert (width > 1.03).all() and (width < 1.5).all()


def test_growth_regression_sees_no_count_after_its_origin():
    rng = np.random.default_rng(1)
    weekly = rng.gamma(5.0, 200.0, size=(5, 40))
    origins = np.arange(10, 40, dtype=np.intp)
    q = growth_regression_quantiles(weekly, origins, (1, 2, 3, 4), LEVELS)
    changed = weekly.copy()
    changed[:, 26:] *= 10.0
    q2 = growth_regression_quantiles(changed, origins, (1, 2, 3, 4), LEVELS)
    upto = origins <= 25
    np.testing.assert_array_equal(q[:, upto], q2[:, upto])
    assert not np.allclose(q[:, ~upto], q2[:, ~upto])


def test_pooled_member_for_one_place_equals_the_panel_row(vintage):
    """San Francisco forecast on its own with the other counties as references equals its row
    of the panel forecast (same weeks, same pool), and so does a cell whose own history is a
    version of its own (the batched regression of a nowcast's completions) pools that version."""
    panel = _panel(vintage)
    origins = weekly_origins(panel.dates)
    member = PooledGrowthMember()
    rows = member.forecast(panel_cells(panel, origins[40:41], 0), (1, 2, 3, 4), LEVELS).count
    sf = COUNTIES.index("San Francisco")
    alone = panel.only(["San Francisco"])
    got = member.forecast(panel_cells(alone, origins[40:41], 0), (1, 2, 3, 4), LEVELS).count
    np.testing.assert_allclose(got[0], rows[sf], rtol=1e-9)
    cells = panel_cells(alone, origins[40:41], 0)
    doubled = dataclasses.replace(cells, histories=(dataclasses.replace(
        cells.histories[0], cases=cells.histories[0].cases * 2),))
    batched = member.forecast(doubled, (1, 2, 3, 4), LEVELS).count
    # a cell with its own version of the place's data (a nowcast completion) pools that
    # version in place of its panel row: doubled counts forecast about double
    np.testing.assert_allclose(np.median(batched[0, :, 11] / got[0, :, 11]), 2.0, rtol=0.1)


def test_weeks_ending_matches_direct_sums():
    dates = pd.date_range("2021-01-01", periods=30)
    cases = np.arange(30, dtype=np.int64)
    history = history_from_county_like(dates, cases)
    sums = weeks_ending(history, dates[20], 4)
    assert np.isnan(sums[0])                     # days −7 … −1 are before the series
    np.testing.assert_array_equal(sums[1:], [cases[0:7].sum(), cases[7:14].sum(),
                                             cases[14:21].sum()])


def history_from_county_like(dates: pd.DatetimeIndex, cases: np.ndarray):
    from pipeline.panels.history import EpiHistory

    zeros = np.zeros(len(dates))
    return EpiHistory(dates, cases, 1.0 - zeros, zeros, zeros, 1_000_000)


def test_summary_restriction_and_files(vintage, tmp_path):
    panel = _panel(vintage)
    members = [HubBaseline(HubBaselineConfig(n_samples=1_000)), PooledGrowthMember()]
    origins = weekly_origins(panel.dates)
    result = run_backtest(OneVintage(panel), members, origins)
    summary = result.summary()
    cases = summary["by_target"]["cases"]
    assert summary["n_places"] == 5 and set(cases) >= {"published", "growth-qr",
                                                       "hub-baseline"}
    assert cases["hub-baseline"]["gmean_relative_wis"]["all"] == pytest.approx(1.0)
    assert set(cases["published"]["by_regime"]) == {"falling", "flat", "rising", "largest10"}
    sf = result.for_places(["San Francisco"])
    one = sf.summary()["by_target"]["cases"]["published"]
    assert one["gmean_relative_wis"]["all"] == pytest.approx(
        cases["published"]["per_place"]["San Francisco"]["all"])
    written = write_backtest(sf, tmp_path / "out")
    assert [p.name for p in written[-3:]] == ["scores.csv", "weights.csv", "summary.json"]
    assert len(written) == 3 + len(origins)         # a hub-format forecast per origin
    scores = pd.read_csv(written[-3])
    assert set(scores["place"]) == {"San Francisco"}
    assert json.loads(written[-1].read_text())["n_places"] == 1
    with pytest.raises(FlowcastError, match="San Fransisco"):
        select_counties(vintage, counties=["San Fransisco"])
