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

from pipeline.data.cdph import CDPHVintage, read_cdph_csv
from pipeline.ensemble.combine import vincentize
from pipeline.ensemble.county_backtest import (CountyBacktestConfig, for_places,
                                               run_panel_backtest, select_counties,
                                               summarize_panel, write_panel_backtest)
from pipeline.ensemble.growth_regression import (GrowthRegressionConfig, PooledGrowthMember,
                                                 growth_regression_quantiles, weekly_sums_ending)
from pipeline.ensemble.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.ensemble.nf_finetune import FineTuneConfig, fit_finetuned_member, refit_dates
from pipeline.ensemble.nf_member import (GrowthModelConfig, NFGrowthMember, SyntheticWindows,
                                         train_growth_model)
from pipeline.ensemble.panel import Panel, weekly_grid, weekly_origins
from pipeline.ensemble.targets import HUB_QUANTILE_LEVELS, history_from_county
from pipeline.errors import FlowcastError
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
    return (NFGrowthMember(train_growth_model(TINY_FLOW, synthetic.dataset)[0], TINY_FLOW,
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
    config = CountyBacktestConfig()
    before = run_panel_backtest(panel, _members(panel, origins, tiny_flow), config)
    after = run_panel_backtest(altered, _members(altered, origins, tiny_flow), config)
    upto = np.array([o <= cut for o in before.origins])
    assert before.origins == after.origins and upto.sum() >= 30
    for name in (*before.members, "published"):
        a, b = before.forecasts["cases"][name], after.forecasts["cases"][name]
        np.testing.assert_array_equal(a[:, upto], b[:, upto], err_msg=name)
        assert not np.array_equal(a[:, ~upto], b[:, ~upto]), name
    fresno = COUNTIES.index("Fresno")
    assert not np.array_equal(before.truth["cases"][fresno, ~upto],
                              after.truth["cases"][fresno, ~upto])


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
    """San Francisco forecast on its own with the other counties as reference equals its row of
    the panel forecast (same weeks, same pool)."""
    panel = _panel(vintage)
    origins = weekly_origins(panel.dates)
    weekly, index = weekly_grid(panel, origins)
    member = PooledGrowthMember()
    rows = member.forecast_panel(weekly, index, (1, 2, 3, 4), LEVELS)
    sf = COUNTIES.index("San Francisco")
    others = [h for c, h in panel.histories.items() if c != "San Francisco"]
    single = PooledGrowthMember(tuple(others))
    origin = origins[40]
    history = panel.histories["San Francisco"].up_to(origin)
    got = single.forecast(history, (1, 2, 3, 4), LEVELS, 0).values["cases"]
    # the panel's calendar starts at the data's first whole week, the single series at its own
    # first whole week ending on the origin's weekday: the same weeks
    np.testing.assert_allclose(got, rows[sf, 40], rtol=1e-9)


def test_weekly_sums_ending_matches_direct_sums():
    dates = pd.date_range("2021-01-01", periods=30)
    cases = np.arange(30, dtype=np.float64)
    sums = weekly_sums_ending(cases, dates, dates[20], 4)
    assert np.isnan(sums[0])                     # days −7 … −1 are before the series
    np.testing.assert_array_equal(sums[1:], [cases[0:7].sum(), cases[7:14].sum(),
                                             cases[14:21].sum()])


def test_summary_restriction_and_files(vintage, tmp_path):
    panel = _panel(vintage)
    members = [HubBaseline(HubBaselineConfig(n_samples=1_000)), PooledGrowthMember()]
    result = run_panel_backtest(panel, members, CountyBacktestConfig())
    summary = summarize_panel(result)
    cases = summary["by_target"]["cases"]
    assert summary["n_counties"] == 5 and set(cases) >= {"published", "growth-qr",
                                                         "hub-baseline"}
    assert cases["hub-baseline"]["gmean_relative_wis"]["all"] == pytest.approx(1.0)
    sf = for_places(result, ["San Francisco"])
    one = summarize_panel(sf)["by_target"]["cases"]["published"]
    assert one["gmean_relative_wis"]["all"] == pytest.approx(
        cases["published"]["per_county"]["San Francisco"]["all"])
    written = write_panel_backtest(sf, tmp_path / "out")
    assert [p.name for p in written] == ["summary.json", "scores.csv", "weights.csv"]
    scores = pd.read_csv(written[1])
    assert set(scores["place"]) == {"San Francisco"}
    assert json.loads(written[0].read_text())["n_counties"] == 1
    with pytest.raises(FlowcastError, match="San Fransisco"):
        select_counties(vintage, CountyBacktestConfig(), ["San Fransisco"])
