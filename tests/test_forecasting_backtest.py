"""The real-time backtest: discipline, weights from the past only, scores, real-data end to end."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest
from scipy.stats import norm

from pipeline.ensemble.backtest import (HUB_COLUMNS, BacktestConfig, backtest_origins,
                                           run_realtime_backtest, score_forecasts,
                                           summarize, summarize_forecaster)
from pipeline.forecast.sources import sf_history
from pipeline.ensemble.hub_baseline import HubBaseline
from pipeline.ensemble.calibration import CalibrationConfig
from pipeline.ensemble.combine import PUBLISHED, UNCALIBRATED, EnsembleConfig, skill_weights
from pipeline.ensemble.members import quantile_forecast_from_weekly_cases
from pipeline.ensemble.targets import EpiHistory, observed_targets
from tests.forecasting_helpers import POPULATION, LogNormalMember, random_walk_history
from tests.test_datasf_client import EXPORTS

LEVELS5 = np.array([0.05, 0.25, 0.5, 0.75, 0.95])


@pytest.fixture(scope="module")
def sf(datasf_dir, tmp_path_factory) -> EpiHistory:
    from pipeline.data.csv_import import import_csv_exports
    from pipeline.data.series import SFDataConfig, load_sf_series
    from pipeline.data.sir_transform import to_sir

    root = tmp_path_factory.mktemp("bt-data")
    import_csv_exports([datasf_dir / EXPORTS[k] for k in ("cases", "deaths", "tests")],
                       data_dir=root)
    series = load_sf_series(SFDataConfig(data_dir=root), offline=True)
    return sf_history(series, to_sir(series))


def test_scores_per_target_and_horizon_hand_computed():
    origin = pd.Timestamp("2021-03-03")
    fc = quantile_forecast_from_weekly_cases("m", origin, (1,), LEVELS5,
                                             np.array([[6.0, 8.0, 10.0, 12.0, 14.0]]), POPULATION)
    rows = score_forecasts([fc], {"cases": np.array([13.0]), "I": np.array([13.0 / POPULATION])},
                           POPULATION)
    by = {r["target"]: r for r in rows}
    # K = 2, scale 1/2.5: dispersion (0.05·8 + 0.25·4)/2.5 = 0.56; under (½·3 + 1)/2.5 = 1.0
    assert by["cases"]["dispersion"] == pytest.approx(0.56)
    assert by["cases"]["underprediction"] == pytest.approx(1.0)
    assert by["cases"]["overprediction"] == 0.0 and by["cases"]["wis"] == pytest.approx(1.56)
    assert not by["cases"]["covered_50"] and by["cases"]["covered_90"]
    z75, z95 = norm.ppf(0.75), norm.ppf(0.95)
    frac = (np.log(14) - np.log(13)) / (np.log(15) - np.log(13))    # log1p of 13 between 12, 14
    assert by["cases"]["pit"] == pytest.approx(norm.cdf(z75 + frac * (z95 - z75)))
    assert by["I"]["wis"] == pytest.approx(1.56 / POPULATION)          # same week, scaled
    assert by["I"]["pit"] == pytest.approx(by["cases"]["pit"], abs=1e-12)
    # relative WIS is a ratio of sums over the same cells, per horizon and all
    cells = pd.DataFrame({"horizon": [1, 1, 2], "origin_date": [1, 2, 1], "wis": [1.0, 3.0, 1.0],
                          "covered_50": [True, False, True], "covered_90": [True] * 3,
                          "pit": [0.05, 0.5, 0.95], "dispersion": [1, 1, 1],
                          "overprediction": [0, 2, 0], "underprediction": [0, 0, 0]})
    base = cells.assign(wis=[2.0, 2.0, 4.0])
    s = summarize_forecaster(cells, base, (1, 2))
    assert s["relative_wis_vs_baseline"] == {"h1": 1.0, "h2": 0.25, "all": 5 / 8}
    assert s["coverage50"] == pytest.approx(2 / 3)
    assert s["pit_histogram"]["counts"] == [1, 0, 0, 0, 0, 1, 0, 0, 0, 1]


def test_ensemble_weights_use_only_forecasts_scored_by_the_origin():
    history = random_walk_history(40, seed=2)
    members = [LogNormalMember("sharp", 0.1), LogNormalMember("wide", 0.6)]
    config = BacktestConfig(ensemble=EnsembleConfig(weighting="skill", shrinkage_origins=4.0),
                            n_paths=50)
    result = run_realtime_backtest(history, members, config)
    w = result.weights.set_index(["origin_date", "horizon", "member"])["weight"]
    scores = result.scores.set_index(["forecaster", "target", "horizon", "origin_date"])["wis"]
    origins = result.origins
    for k, t in enumerate(origins):
        for h in (1, 2, 3, 4):
            usable = [o for o in origins[:k] if o + pd.Timedelta(days=7 * h) <= t]
            assert len(usable) == max(0, k - h + 1)
            past = np.array([[scores[(m.name, "cases", h, o)] for m in members]
                             for o in usable]).reshape(len(usable), 2)
            expected = skill_weights(past, config.ensemble)
            got = [w[(t, h, m.name)] for m in members]
            np.testing.assert_allclose(got, expected, rtol=1e-12)
    assert w[(origins[0], 1, "sharp")] == 0.5 and w[(origins[3], 4, "wide")] == 0.5


def test_recalibration_in_the_backtest_fixes_an_over_confident_member():
    history = random_walk_history(110, seed=4, sigma=0.3)
    result = run_realtime_backtest(history, [LogNormalMember("overconfident", 0.08)],
                                   BacktestConfig(n_paths=20, calibration=CalibrationConfig()))
    s = summarize(result)["by_target"]["cases"]
    raw, pub = s[UNCALIBRATED], s[PUBLISHED]
    assert raw["coverage90"] < 0.45 and raw["coverage50"] < 0.2          # measured 0.30 / 0.09
    assert pub["coverage90"] > raw["coverage90"] + 0.3
    assert pub["relative_wis_vs_baseline"]["all"] < raw["relative_wis_vs_baseline"]["all"]


def test_a_forecast_is_unchanged_when_data_after_its_origin_change(sf):
    config = BacktestConfig(last_origin=pd.Timestamp("2021-03-31").date(), n_paths=50)
    t = backtest_origins(sf, config)[-1]
    keep = int(np.searchsorted(sf.dates, t, side="right"))
    altered = dataclasses.replace(sf, cases=np.concatenate([sf.cases[:keep], sf.cases[keep:] * 10]),
                                  I=np.concatenate([sf.I[:keep], sf.I[keep:] * 10]))
    members = [HubBaseline(), LogNormalMember("lognormal", 0.3)]
    a = run_realtime_backtest(sf, members, config).forecasts[t]
    b = run_realtime_backtest(altered, members, config).forecasts[t]
    assert not np.array_equal(observed_targets(sf, t)["cases"],
                              observed_targets(altered, t)["cases"])
    for name in ("hub-baseline", "lognormal", "autoets", UNCALIBRATED, PUBLISHED):
        for target in ("I", "cases"):
            assert np.array_equal(a[name].values[target], b[name].values[target]), name
    assert np.array_equal(a[PUBLISHED].paths, b[PUBLISHED].paths)


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
    # --no-nf: the flat baseline and growth-qr (no CDPH counties in this cache: SF alone)
    assert set(scores["forecaster"]) == {"hub-baseline", "growth-qr", "autoets", UNCALIBRATED,
                                         PUBLISHED}
    assert len(scores) == 5 * 2 * 4 * 4       # forecasters × targets × horizons × origins
    summary = json.loads((out / "summary.json").read_text())
    assert summary["invalid_values"] == 0 and summary["n_origins"] == 4
    rel = summary["by_target"]["I"]["autoets"]["relative_wis_vs_baseline"]
    assert set(rel) == {"h1", "h2", "h3", "h4", "all"}
    assert summary["by_target"]["cases"]["hub-baseline"]["relative_wis_vs_baseline"]["all"] == 1.0
