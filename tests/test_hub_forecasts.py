"""Every team's forecasts of the CDC COVID-19 Forecast Hub's design period
(``../shared/data/nhsn``, read in place): read as a typed frame, scored with WIS against the
latest vintage, and ranked by pairwise relative WIS (hub baseline = 1). Also a hub's
model-output folder read as hubverse partitions it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.data.hub.team_forecasts import (HubDataError, quantile_table, read_excluded_locations,
                                              read_hub_forecasts, read_model_output_dir,
                                              read_target_data, target_data_vintages)
from pipeline.evaluation.hub_leaderboard import (LeaderboardConfig, hub_leaderboard,
                                                 leaderboard_scores, score_quantile_forecasts)

NHSN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nhsn"
HOSP = "wk inc covid hosp"

# The design-period leaderboard under the hub's conventions (LeaderboardConfig()): admissions,
# horizons 0-3, US and states, excluded_locations.toml applied, every forecast whose week the
# latest vintage (2025-09-24) observes; model -> (relative WIS, forecasts scored).
LEADERBOARD = {
    "UGA_flucast-INFLAenza": (0.666, 5035), "CFA_Pyrenew-Pyrenew_HE_COVID": (0.709, 2859),
    "CovidHub-ensemble": (0.730, 8638), "CFA_Pyrenew-PyrenewHEW_COVID": (0.775, 1735),
    "UMass-ar6_pooled": (0.818, 7305), "OHT_JHU-nbxd": (0.881, 7737),
    "UMass-gbqr": (0.899, 7305), "NEU_ISI-AdaptiveEnsemble": (0.925, 6035),
    "CMU-TimeSeries": (0.953, 8426), "CEPH-Rtrend_covid": (0.969, 8638),
    "CFA_Pyrenew-Pyrenew_HW_COVID": (0.978, 2275), "CovidHub-baseline": (1.000, 8638),
    "Metaculus-cp": (1.027, 42), "JHU_CSSE-CSSE_Ensemble": (1.051, 3580),
    "CFA_Pyrenew-Pyrenew_H_COVID": (1.060, 3554), "Google_SAI-Ensemble": (1.061, 2528),
    "UM-DeepOutbreak": (1.266, 5564), "CFA-EpiAutoGP": (1.316, 490),
    "MOBS-GLEAM_COVID": (1.337, 5916), "CMU-climate_baseline": (2.252, 8426),
}


@pytest.fixture(scope="module")
def scored() -> tuple[pd.DataFrame, pd.DataFrame]:
    if not (NHSN / "hub-forecasts.parquet").exists():
        pytest.fail(f"the hub's real files expected at {NHSN} (../shared beside the repo)")
    frame = read_hub_forecasts(NHSN / "hub-forecasts.parquet", targets=[HOSP],
                               horizons=[0, 1, 2, 3])
    truth = read_target_data(NHSN / "time-series.parquet", HOSP)
    scores = score_quantile_forecasts(quantile_table(frame), truth)
    return scores, read_excluded_locations(NHSN / "excluded_locations.toml")


def test_typed_frame_of_the_hubs_forecasts():
    frame = read_hub_forecasts(NHSN / "hub-forecasts.parquet", models=["CovidHub-baseline"],
                               horizons=[-1])
    assert list(frame.columns) == ["model_id", "reference_date", "target", "horizon",
                                   "location", "target_end_date", "output_type_id", "value"]
    assert str(frame["reference_date"].dtype) == "datetime64[s]"
    assert frame["horizon"].dtype == np.int64 and frame["value"].dtype == np.float64
    assert list(frame["model_id"].cat.categories) == ["CovidHub-baseline"]
    assert set(frame["target"]) == {HOSP, "wk inc covid prop ed visits"}
    table = quantile_table(frame)
    assert table.values.shape == (len(frame) // 23, 23) and table.levels[11] == 0.5
    assert (np.diff(table.values, axis=1) >= 0).all()
    # 53 locations of admissions over 44 rounds (2024-11-23 .. 2025-09-27)
    hosp = table.tasks[table.tasks["target"] == HOSP]
    assert hosp["location"].nunique() == 53 and hosp["reference_date"].nunique() == 44
    assert ((hosp["target_end_date"] - hosp["reference_date"]).dt.days == -7).all()
    with pytest.raises(HubDataError, match="each of the 23 levels .* must appear once"):
        quantile_table(frame.drop(index=frame.index[5]))


def test_truth_is_one_vintage_of_the_time_series():
    latest = read_target_data(NHSN / "time-series.parquet", HOSP)
    vintages = target_data_vintages(NHSN / "time-series.parquet", HOSP)
    assert len(vintages) == 44 and vintages[-1] == pd.Timestamp("2025-09-24")
    assert len(latest) == 46 * 53 and latest["target_end_date"].max() == pd.Timestamp("2025-09-20")
    first = read_target_data(NHSN / "time-series.parquet", HOSP, as_of="2024-11-20")
    assert len(first) == 2 * 53
    with pytest.raises(HubDataError, match="no vintage as_of 2024-11-21"):
        read_target_data(NHSN / "time-series.parquet", HOSP, as_of="2024-11-21")


def test_wis_of_a_real_forecast_is_the_pinball_form(scored):
    scores, _ = scored
    row = scores[(scores.model_id == "CovidHub-baseline") & (scores.location == "US")
                 & (scores.reference_date == "2025-01-11") & (scores.horizon == 0)].iloc[0]
    frame = read_hub_forecasts(NHSN / "hub-forecasts.parquet", models=["CovidHub-baseline"],
                               targets=[HOSP], horizons=[0])
    q = frame[(frame.location == "US") & (frame.reference_date == "2025-01-11")] \
        .sort_values("output_type_id")
    levels, values, y = q.output_type_id.to_numpy(), q.value.to_numpy(), row.observed
    pinball = ((y <= values) - levels) * (values - y)       # WIS = 2/23 · Σ pinball losses
    assert row.observed == 15297.0
    assert row.wis == pytest.approx(2 * pinball.sum() / 23, rel=1e-12)
    assert row.wis == pytest.approx(1503.3234, abs=1e-4)
    assert row.dispersion + row.overprediction + row.underprediction == pytest.approx(row.wis)
    assert not row.coverage_50 and row.coverage_95


def test_design_period_leaderboard(scored):
    scores, exclusions = scored
    table = hub_leaderboard(scores, LeaderboardConfig(), exclusions)
    assert list(table.model_id) == list(LEADERBOARD)            # ranked best first
    got = {m: (round(r, 3), n) for m, r, n in
           zip(table.model_id, table.relative_wis, table.n_forecasts, strict=True)}
    assert got == LEADERBOARD
    ensemble = table.set_index("model_id").loc["CovidHub-ensemble"]
    assert ensemble.n_rounds == 43 and ensemble.mean_wis == pytest.approx(39.1311, abs=1e-4)
    assert ensemble.coverage_50 == pytest.approx(0.5379, abs=1e-4)
    assert ensemble.coverage_95 == pytest.approx(0.9459, abs=1e-4)
    # excluded_locations.toml removes the first round's 40 listed locations, those alone
    listed = scores.location.isin(exclusions.location) & (scores.reference_date == "2024-11-23")
    kept = leaderboard_scores(scores, LeaderboardConfig(), exclusions)
    assert len(scores) - len(kept) == listed.sum() == 1376    # of 9 models, some not everywhere
    assert not (kept.location.isin(exclusions.location)
                & (kept.reference_date == "2024-11-23")).any()
    # the same tournament without the exclusions, for the states alone, and per horizon
    plain = hub_leaderboard(scores, LeaderboardConfig(apply_exclusions=False), exclusions)
    assert plain.set_index("model_id").loc["CovidHub-ensemble", "relative_wis"] == \
        pytest.approx(0.7148, abs=1e-4)
    states = hub_leaderboard(scores, LeaderboardConfig(locations="states"), exclusions)
    assert states.model_id.iloc[0] == "CovidHub-ensemble"
    assert states.relative_wis.iloc[0] == pytest.approx(0.7561, abs=1e-4)
    by_h = hub_leaderboard(scores, LeaderboardConfig(), exclusions, by=("horizon",))
    ensemble_h = by_h[by_h.model_id == "CovidHub-ensemble"].set_index("horizon").relative_wis
    np.testing.assert_allclose(ensemble_h.loc[[0, 1, 2, 3]], [0.807, 0.756, 0.709, 0.680],
                               atol=5e-4)
    assert set(by_h[by_h.horizon == 2].model_id) & {"CFA_Pyrenew-Pyrenew_HE_COVID"} == set()


def test_model_output_folder_read_as_hubverse_partitions_it(tmp_path):
    levels = [0.25, 0.5, 0.75]
    rows = [{"reference_date": "2025-01-11", "target": HOSP, "horizon": h, "location": loc,
             "target_end_date": str((pd.Timestamp("2025-01-11") + pd.Timedelta(weeks=h)).date()),
             "output_type": "quantile", "output_type_id": str(lv), "value": 10.0 * (h + 2) + lv}
            for h in (0, 1) for loc in ("US", "06") for lv in levels]
    samples = [{**rows[0], "output_type": "sample", "output_type_id": f"s{k}", "value": 3.0}
               for k in range(4)]
    for model in ("teamA-m1", "teamB-m2"):
        folder = tmp_path / "model-output" / model
        folder.mkdir(parents=True)
        frame = pd.DataFrame(rows + samples)
        if model == "teamA-m1":
            frame.to_csv(folder / f"2025-01-11-{model}.csv", index=False)
        else:
            frame.assign(value=frame.value * 2).to_parquet(folder / f"2025-01-11-{model}.parquet")
    (tmp_path / "model-output" / "teamA-m1" / "README.md").write_text("not a round")
    read = read_model_output_dir(tmp_path)
    assert len(read) == 2 * len(rows) and set(read.model_id) == {"teamA-m1", "teamB-m2"}
    assert read["location"].cat.categories.tolist() == ["06", "US"]       # "06" stays text
    table = quantile_table(read)
    assert table.values.shape == (8, 3)
    a = table.values[(table.tasks.model_id == "teamA-m1").to_numpy()]
    b = table.values[(table.tasks.model_id == "teamB-m2").to_numpy()]
    np.testing.assert_allclose(b, 2 * a)
    assert read_model_output_dir(tmp_path, models=["teamB-m2"]).model_id.nunique() == 1
    stray = tmp_path / "model-output" / "teamA-m1" / "2025-01-18-teamC-m3.csv"
    stray.write_text("x")
    with pytest.raises(HubDataError, match="'teamC-m3' in the file name differs"):
        read_model_output_dir(tmp_path)


def test_forecasts_that_cannot_be_ranked_are_refused_by_name():
    from pipeline.data.hub.team_forecasts import QuantileTable
    from pipeline.errors import ConfigError
    from pipeline.evaluation.hub_leaderboard import LeaderboardError

    tasks = pd.DataFrame({"model_id": ["a", "b"],
                          "reference_date": pd.to_datetime(["2025-01-11"] * 2), "target": HOSP, "horizon": 0, "location": "US",
                          "target_end_date": pd.to_datetime(["2025-01-11"] * 2)})
    table = QuantileTable(tasks=tasks, levels=np.array([0.25, 0.5, 0.75]),
                          values=np.array([[1.0, 2.0, 3.0], [1.0, 3.0, 2.0]]))
    truth = pd.DataFrame({"target_end_date": pd.to_datetime(["2025-01-11"]), "location": ["US"],
                          "value": [2.0]})
    with pytest.raises(LeaderboardError, match="'model_id': 'b'.*quantiles decrease"):
        score_quantile_forecasts(table, truth)
    ok = score_quantile_forecasts(QuantileTable(tasks.iloc[:1], table.levels, table.values[:1]),
                                  truth)
    assert ok.wis.item() == pytest.approx((0.5 * 0 + 0.25 * 2) / 1.5)   # median exact, IS_0.5=2
    assert ok.coverage_50.item() == 1.0 and np.isnan(ok.coverage_95.item())  # no 0.025 level
    with pytest.raises(LeaderboardError, match="lacks the columns \\['value'\\]"):
        score_quantile_forecasts(table, truth.drop(columns="value"))
    with pytest.raises(ConfigError, match="locations='State'"):
        LeaderboardConfig(locations="State")  # type: ignore[arg-type]
