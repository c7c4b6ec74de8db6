"""The real-time backtest: discipline, weights from the past only, scores, real-data end to end."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest
from scipy.stats import norm

from pipeline.backtest.config import BacktestConfig

from pipeline.backtest.backtest import OneVintage, run_backtest
from pipeline.backtest.writers import HUB_COLUMNS
from pipeline.combine.combiner import PUBLISHED, UNCALIBRATED, CombineConfig
from pipeline.evaluation.summary import calibration_cost, score_cells, summarize_forecaster
from pipeline.forecast.sources import sf_history
from pipeline.members.hub_baseline import HubBaseline
from pipeline.panels.history import EpiHistory
from pipeline.panels.panel import Panel, weekly_origins
from tests.forecasting_helpers import POPULATION, LogNormalMember, random_walk_history
from tests.test_datasf_client import EXPORTS

LEVELS5 = np.array([0.05, 0.25, 0.5, 0.75, 0.95])


@pytest.fixture(scope="module")
def sf(datasf_dir, tmp_path_factory) -> EpiHistory:
    from pipeline.data.sf.csv_import import import_csv_exports
    from pipeline.data.sf.series import SFDataConfig, load_sf_series
    from pipeline.data.sf.sir_transform import to_sir

    root = tmp_path_factory.mktemp("bt-data")
    import_csv_exports([datasf_dir / EXPORTS[k] for k in ("cases", "deaths", "tests")],
                       data_dir=root)
    series = load_sf_series(SFDataConfig(data_dir=root), offline=True)
    return sf_history(series, to_sir(series))


def _backtest(history: EpiHistory, members, config: BacktestConfig = BacktestConfig(),
              **origin_options):
    origins = weekly_origins(history.dates, scored_only=False, **origin_options)
    return run_backtest(OneVintage(Panel({"place": history})), members, origins, config)


def test_scores_per_target_and_horizon_hand_computed():
    q = np.array([6.0, 8.0, 10.0, 12.0, 14.0])[None, None, None]           # (C, O, H, Q)
    cases = score_cells(q, np.array([[[13.0]]]), LEVELS5)
    share = score_cells(q / POPULATION, np.array([[[13.0 / POPULATION]]]), LEVELS5,
                        np.array([[[POPULATION]]], dtype=float))
    # K = 2, scale 1/2.5: dispersion (0.05·8 + 0.25·4)/2.5 = 0.56; under (½·3 + 1)/2.5 = 1.0
    assert cases.dispersion[0, 0, 0] == pytest.approx(0.56)
    assert cases.underprediction[0, 0, 0] == pytest.approx(1.0)
    assert cases.overprediction[0, 0, 0] == 0.0 and cases.wis[0, 0, 0] == pytest.approx(1.56)
    assert cases.covered[0.5][0, 0, 0] == 0.0 and cases.covered[0.9][0, 0, 0] == 1.0
    z75, z95 = norm.ppf(0.75), norm.ppf(0.95)
    frac = (np.log(14) - np.log(13)) / (np.log(15) - np.log(13))    # log1p of 13 between 12, 14
    assert cases.pit[0, 0, 0] == pytest.approx(norm.cdf(z75 + frac * (z95 - z75)))
    assert share.wis[0, 0, 0] == pytest.approx(1.56 / POPULATION)      # same week, scaled
    assert share.pit[0, 0, 0] == pytest.approx(cases.pit[0, 0, 0], abs=1e-12)
    # relative WIS: a ratio of sums over the cells both scored, per horizon and all; per place
    # for the geometric mean over places
    wis = np.array([[[1.0, 1.0], [3.0, np.nan]], [[2.0, 2.0], [2.0, 2.0]]])   # (C=2, O=2, H=2)
    base = np.array([[[2.0, 4.0], [2.0, 4.0]], [[2.0, 2.0], [2.0, 2.0]]])
    nan = np.full(wis.shape, np.nan)
    scores = type(cases)(wis, nan, nan, nan, {0.5: np.where(np.isfinite(wis), 1.0, np.nan)},
                         np.where(np.isfinite(wis), 0.5, np.nan), nan)
    s = summarize_forecaster(scores, base, (1, 2), ("a", "b"))
    assert s["relative_wis_vs_baseline"] == {"h1": 8 / 8, "h2": 5 / 8, "all": 13 / 16}
    assert s["per_place"]["a"] == {"h1": 1.0, "h2": 0.25, "all": 5 / 8}
    assert s["gmean_relative_wis"]["all"] == pytest.approx(np.sqrt(5 / 8 * 1.0))
    assert s["share_beating_baseline"]["all"] == 0.5 and s["n_scored"] == 7
    assert s["pit_histogram"]["counts"] == [0, 0, 0, 0, 0, 7, 0, 0, 0, 0]


def test_calibration_cost_over_every_origin_and_its_worst_window_hand_computed():
    """20 origins, 2 places, 1 horizon: the calibration costs 50 % at origins 3 and 4 and
    saves 10 % everywhere else; the first window of 15 holding both (and the cell not scored)
    is the worst."""
    origins = pd.date_range("2024-01-06", periods=20, freq="7D")
    uncalibrated = np.full((2, 20, 1), 2.0)
    published = np.full((2, 20, 1), 1.8)
    published[:, 3:5] = 3.0
    published[1, 7] = np.nan                         # not scored: left out of both sums
    cost = calibration_cost(published, uncalibrated, list(origins), window=15)
    assert cost["all"] == pytest.approx((4 * 3.0 + 35 * 1.8) / (39 * 2.0))
    assert cost["worst_window"] == pytest.approx((4 * 3.0 + 25 * 1.8) / (29 * 2.0))
    assert cost["worst_window_origins"] == ["2024-01-06", "2024-04-13"]
    assert cost["n_windows"] == 6
    assert calibration_cost(published[:, :10], uncalibrated[:, :10], list(origins[:10]),
                            window=15)["worst_window"] is None


def test_the_published_forecast_at_an_origin_uses_only_the_past():
    """Truth after an origin changes neither its members' forecasts nor its weights."""
    history = random_walk_history(40, seed=2)
    members = [LogNormalMember("sharp", 0.1), LogNormalMember("wide", 0.6)]
    config = BacktestConfig(combine=CombineConfig(weights="inverse-wis", shrinkage_origins=4.0))
    result = _backtest(history, members, config)
    t = result.origins[20]
    keep = int(np.searchsorted(history.dates, t, side="right"))
    altered = dataclasses.replace(history, cases=np.concatenate(
        [history.cases[:keep], history.cases[keep:] * 3]))
    again = _backtest(altered, members, config)
    for o in range(21):
        np.testing.assert_array_equal(result.weights[o], again.weights[o])
        np.testing.assert_array_equal(result.forecasts["cases"][PUBLISHED].values[:, o],
                                      again.forecasts["cases"][PUBLISHED].values[:, o])
    assert not np.array_equal(result.weights[25:], again.weights[25:])
    # no past score at the first origin: equal weights
    np.testing.assert_allclose(result.weights[0], 0.5)


def test_recalibration_in_the_backtest_fixes_an_over_confident_member():
    history = random_walk_history(110, seed=4, sigma=0.3)
    result = _backtest(history, [LogNormalMember("overconfident", 0.08)],
                       BacktestConfig(combine=CombineConfig(
                           calibration="scale", calibration_window_origins=52,
                           shrinkage_pits=10, min_level=1e-9)))
    s = result.summary()["by_target"]["cases"]
    raw, pub = s[UNCALIBRATED], s[PUBLISHED]
    assert raw["coverage90"] < 0.45 and raw["coverage50"] < 0.2          # measured 0.30 / 0.09
    assert pub["coverage90"] > raw["coverage90"] + 0.3
    assert pub["relative_wis_vs_baseline"]["all"] < raw["relative_wis_vs_baseline"]["all"]
    # the calibration's cost is the published Σ WIS over the uncalibrated, from the scores
    scores = result.scores()
    cases = scores[scores["target"] == "cases"].groupby("forecaster")["wis"].sum()
    cost = result.summary()["calibration_cost"]["cases"]
    assert cost["all"] == pytest.approx(cases[PUBLISHED] / cases[UNCALIBRATED], rel=1e-12)
    assert cost["all"] < 1 and cost["worst_window"] >= cost["all"]


def test_a_forecast_is_unchanged_when_data_after_its_origin_change(sf):
    last = pd.Timestamp("2021-03-31")
    config = BacktestConfig(n_paths=50)
    t = weekly_origins(sf.dates, scored_only=False, last=last)[-1]
    keep = int(np.searchsorted(sf.dates, t, side="right"))
    altered = dataclasses.replace(sf, cases=np.concatenate([sf.cases[:keep], sf.cases[keep:] * 10]),
                                  I=np.concatenate([sf.I[:keep], sf.I[keep:] * 10]))
    members = [HubBaseline(), LogNormalMember("lognormal", 0.3)]
    a = _backtest(sf, members, config, last=last)
    b = _backtest(altered, members, config, last=last)
    assert not np.array_equal(a.truth["cases"].values[0, -1], b.truth["cases"].values[0, -1])
    for name in ("hub-baseline", "lognormal", UNCALIBRATED, PUBLISHED):
        for target in ("I", "cases"):
            assert np.array_equal(a.forecasts[target][name].values[0, -1],
                                  b.forecasts[target][name].values[0, -1]), name
    assert a.paths is not None and b.paths is not None
    assert np.array_equal(a.paths[0, -1], b.paths[0, -1])


def test_backtest_cli_on_the_real_data_writes_hub_forecasts_scores_and_summary(
        datasf_dir, tmp_path):
    from typer.testing import CliRunner

    from pipeline.cli import _register, app
    from pipeline.forecast.sources import import_exports

    import_exports([str(datasf_dir)])           # into this test's FLOWCAST_DATA_DIR
    _register()
    out = tmp_path / "bt"
    res = CliRunner().invoke(app, ["backtest", "--from", "2021-12-01", "--to", "2021-12-25",
                                   "--out", str(out), "--no-nf"])
    assert res.exit_code == 0, res.output
    files = sorted(p.name for p in (out / "forecasts").iterdir())
    # the weekly forecast's origins: Saturdays (its weeks are epiweeks)
    assert files == [f"2021-12-{d:02d}-published.csv" for d in (4, 11, 18, 25)]
    frame = pd.read_csv(out / "forecasts" / files[0], dtype={"output_type_id": str})
    assert tuple(frame.columns) == HUB_COLUMNS
    q = frame[frame["output_type"] == "quantile"]
    assert len(q) == 2 * 4 * 23 and (frame[frame["output_type"] == "sample"].shape[0]
                                     == 2 * 4 * 200)
    cases = q[q["target"] == "cases"]["value"].to_numpy()
    i_prop = q[q["target"] == "I"]["value"].to_numpy()
    np.testing.assert_allclose(i_prop * 873_965, cases, rtol=1e-9)      # I = cases / N
    scores = pd.read_csv(out / "scores.csv")
    # --no-nf: the flat baseline and gbqr (no CDPH counties in this cache: SF alone)
    assert set(scores["forecaster"]) == {"hub-baseline", "gbqr", "autoets", UNCALIBRATED,
                                         PUBLISHED}
    assert len(scores) == 5 * 2 * 4 * 4       # forecasters × targets × horizons × origins
    assert {"covered_95", "regime"} <= set(scores.columns)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["invalid_values"] == 0 and summary["n_origins"] == 4
    assert set(scores["regime"]) <= {0, 1, 2} and set(scores["place"]) == {"San Francisco"}
    rel = summary["by_target"]["I"]["autoets"]["relative_wis_vs_baseline"]
    assert set(rel) == {"h1", "h2", "h3", "h4", "all"}
    assert summary["by_target"]["cases"]["hub-baseline"]["relative_wis_vs_baseline"]["all"] == 1.0


def test_the_tracking_rate_variants_change_eta_alone():
    """One tracker at η = 0.15 (published until 2026-11-29), a third and twice it, in place of
    the aggregate, named as every backtest's results name them, every other setting the
    published combiner's."""
    import dataclasses

    from pipeline.backtest.config import tracking_rate_variants
    from pipeline.combine.combiner import CombineConfig

    hub = CombineConfig(beyond_reach="reachable-members", outer_interval=0.95)
    variants = tracking_rate_variants(hub)
    assert [v.name for v in variants] == ["v-regime-aci eta=0.05", "v-regime-aci eta=0.15",
                                          "v-regime-aci eta=0.3"]
    assert [v.combine.tracking_rate for v in variants] == [0.05, 0.15, 0.3]
    assert hub.calibration == "aggregated-aci" and hub.tracking_standardized
    assert all(v.combine.calibration == "regime-aci" and not v.combine.tracking_standardized
               and dataclasses.replace(v.combine, tracking_rate=hub.tracking_rate,
                                       calibration=hub.calibration,
                                       tracking_standardized=True) == hub
               and v.members is None for v in variants)
    assert tracking_rate_variants(hub, prefix="")[0].name == "regime-aci eta=0.05"


def test_a_short_track_record_keeps_the_latest_origins_and_reports_among_them(sf):
    """``recent_origins`` (the tiny preset's short track record): the latest N Saturdays; the
    scored ones start where the forecast ones do, so every reported origin is forecast."""
    from pipeline.backtest.track_record import TrackRecordConfig
    from pipeline.errors import ConfigError

    every = TrackRecordConfig().origins(sf)
    short = TrackRecordConfig(recent_origins=30)
    assert short.origins(sf) == every[-30:]
    scored = short.origins(sf, scored_only=True)
    assert scored[0] == every[-30] and set(scored) <= set(every[-30:])
    assert scored == [o for o in TrackRecordConfig().origins(sf, scored_only=True)
                      if o >= every[-30]]
    assert TrackRecordConfig(recent_origins=10_000).origins(sf) == every
    with pytest.raises(ConfigError, match="recent_origins=0 must be >= 1"):
        TrackRecordConfig(recent_origins=0)


def test_the_truth_at_many_origins_is_the_truth_at_each(sf):
    """``observed_at`` (the hub backtests' truth per round, at once) equals ``observed`` at each
    origin, on San Francisco's daily history and on a weekly count series; an origin that is
    not a date of the history (or after it) has no truth."""
    from pipeline.panels.history import WeeklyHistory

    weekly = WeeklyHistory(pd.date_range("2024-11-02", periods=30, freq="7D"),
                           np.arange(30.0) ** 1.5, 1_000_000, "wk inc covid hosp")
    for history, step in ((sf, "1D"), (weekly, "7D")):
        n = len(history)
        origins = list(history.dates[[n // 4, n // 2, 3 * n // 4, n - 2]])
        horizons = (-1, 0, 1, 2)
        many = history.observed_at([*origins, history.dates[-1] + pd.Timedelta(step),
                                    history.dates[3] + pd.Timedelta(hours=12)], horizons)
        for target, values in many.items():
            assert values.shape == (6, 4)
            for o, origin in enumerate(origins):
                np.testing.assert_array_equal(values[o],
                                              history.observed(origin, horizons)[target])
            assert np.isnan(values[4:]).all()
            assert np.isfinite(values[:3]).all() and np.isnan(values[3, -1])
