"""The weekly_forecast flow end to end under prefect_test_harness, on the tiny preset and the
recorded real DataSF exports (imported into a temporary FLOWCAST_DATA_DIR, run offline), plus the
fetch faults: DataSF down with a cache (completes, stale) and without one (fails, last good kept).
"""
from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import requests
import responses

from pipeline.data.sf.sir_transform import SF_POPULATION_2020_CENSUS


pytestmark = pytest.mark.slow

# Cases end 2022-03-16; minus the 14 days still under revision -> the last day kept.
EXPECTED_REFERENCE_DATE = "2022-03-02"
HUB_LEVELS = 23
ORIGIN = "2022-02-26"        # the last Saturday of data: the published forecast's origin
ROUND = "2022-03-19"         # the hub round of the run's date (2022-03-02 + 14 days)


@pytest.fixture(scope="module")
def good_run(prefect_harness, datasf_dir, tmp_path_factory):
    """One tiny run importing the real exports; shared by the checks below."""
    from flows.weekly_forecast import weekly_forecast

    root = tmp_path_factory.mktemp("good-run")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLOWCAST_DATA_DIR", str(root / "data"))
        result = weekly_forecast(preset="tiny", data_source="import",
                                 import_from=[str(datasf_dir)], output_dir=str(root / "reports"),
                                 seed=0)
    return root, result


def test_outputs_exist_with_real_numbers(good_run):
    root, result = good_run
    out = Path(result["output_dir"])
    assert result["reference_date"] == EXPECTED_REFERENCE_DATE
    assert out == root / "reports" / EXPECTED_REFERENCE_DATE and not result["data_stale"]
    assert not result["model_reused"]  # a fresh data dir: the flow trained the pair
    for name in result["files"]:
        assert (out / name).stat().st_size > 0, name

    sir = pd.read_csv(out / "sir_series.csv")
    assert sir["date"].iloc[0] == "2020-03-03" and sir["date"].iloc[-1] == EXPECTED_REFERENCE_DATE
    np.testing.assert_allclose(sir[["S", "I", "R"]].sum(axis=1), 1.0, atol=1e-12)

    for name in ["rollout_forward_7d.csv", "rollout_backward_28d.csv"]:
        roll = pd.read_csv(out / name).dropna(subset=["mean"])
        assert len(roll) > 0
        assert (roll["lower_2sigma"] <= roll["mean"]).all() and (roll["mean"] <= roll["upper_2sigma"]).all()

    params = pd.read_csv(out / "parameter_estimates.csv")
    assert set(params["component"]) == {"S", "I", "R", "beta", "gamma", "Rt"}
    assert (params["q0.025"] <= params["q0.5"]).all() and (params["q0.5"] <= params["q0.975"]).all()
    estimated = params[params["component"] != "gamma"]
    assert np.isfinite(params[["mean", "std"]].to_numpy()).all() and (estimated["std"] > 0).all()
    # γ is the conversion's 1/7 per day on every day, not an estimate
    np.testing.assert_allclose(params.loc[params["component"] == "gamma", "q0.5"], 1 / 7)

    nll = pd.read_csv(out / "nll_table.csv")
    assert list(nll["direction"]) == ["forward", "backward"] and np.isfinite(nll["mean_nll"]).all()

    smc = pd.read_csv(out / "smc_bands.csv")
    assert (smc["lower_3sigma"] <= smc["mean"]).all() and (smc["mean"] <= smc["upper_3sigma"]).all()

    # the published forecast: weekly cases and I at the four Saturdays after the last Saturday
    hub = pd.read_csv(out / "hub_forecast.csv", dtype={"output_type_id": str})
    assert (hub["origin_date"] == ORIGIN).all()
    assert set(hub["target"]) == {"I", "cases"} and sorted(hub["horizon"].unique()) == [1, 2, 3, 4]
    end = pd.to_datetime(hub["target_end_date"]) - pd.Timestamp(ORIGIN)
    assert (end.dt.days == 7 * hub["horizon"]).all()
    quantiles = hub[hub["output_type"] == "quantile"]
    assert quantiles["output_type_id"].nunique() == HUB_LEVELS
    q = quantiles.assign(level=quantiles["output_type_id"].astype(float)).sort_values("level")
    assert (q.groupby(["target", "horizon"])["value"].diff().dropna() >= 0).all()
    assert (hub["value"] >= 0).all()
    by_target = q.pivot_table(index=["horizon", "level"], columns="target", values="value")
    np.testing.assert_allclose(by_target["cases"], by_target["I"] * SF_POPULATION_2020_CENSUS, rtol=1e-9)
    members = pd.read_csv(out / "member_forecasts.csv")
    # nf-smc: the NF-seeded SMC on the same model, scored beside the members, not averaged
    # no CDPH counties in this data dir: gbqr learns from SF alone and nf-real is left out
    assert set(members["forecaster"]) == {"autoets", "gbqr", "nf-growth", "hub-baseline",
                                          "nf-smc", "ensemble-uncalibrated"}

    # the hubverse file of the same forecast, valid under hub-config/tasks.json
    from pipeline.outputs.hubverse_validation import load_tasks_config, validate_model_output

    tasks = load_tasks_config(Path(__file__).resolve().parents[1] / "hub-config" / "tasks.json")
    submission = out / "model-output" / "flowcast-nfens" / f"{ROUND}-flowcast-nfens.csv"
    frame = validate_model_output(submission, tasks)
    cases_h0 = frame[(frame["target"] == "wk inc case") & (frame["horizon"] == 0)
                     & (frame["output_type"] == "quantile")].sort_values("output_type_id")
    same_week = q[(q["target"] == "cases") & (q["target_end_date"] == ROUND)]
    np.testing.assert_allclose(cases_h0["value"].to_numpy(), same_week["value"].to_numpy(),
                               rtol=1e-7)

    # its real-time backtest: every Saturday origin, scored per target and horizon
    summary = json.loads((out / "results.json").read_text())
    skill = summary["backtest"]
    assert set(skill) == {"I", "cases"}
    assert set(skill["cases"]) == {"h1", "h2", "h3", "h4", "all"}
    assert all(v is not None and np.isfinite(v) and v > 0 for v in skill["cases"].values())
    scores = pd.read_csv(out / "backtest_scores.csv")
    assert set(scores["forecaster"]) == {"autoets", "gbqr", "nf-growth", "hub-baseline",
                                         "nf-smc", "ensemble-uncalibrated", "published"}
    assert scores["origin_date"].max() < ORIGIN     # the latest origin has no truth yet
    np.testing.assert_allclose(scores["wis"], scores[["dispersion", "overprediction",
                                                      "underprediction"]].sum(axis=1))
    backtest = json.loads((out / "backtest_summary.json").read_text())
    assert backtest["invalid_values"] == 0
    assert backtest["by_target"]["cases"]["published"]["relative_wis_vs_baseline"] == \
        skill["cases"]

    assert (out / "report.pdf").read_bytes()[:5] == b"%PDF-"
    report = (out / "report.html").read_text()
    assert EXPECTED_REFERENCE_DATE in report and "Stale data" not in report
    for heading in ("Transformer + KE", "Mamba-SSM", "MLP"):
        assert heading in report, heading
    index = json.loads((root / "reports" / "index.json").read_text())
    assert [r["reference_date"] for r in index["runs"]] == [EXPECTED_REFERENCE_DATE]
    assert index["runs"][0]["data_vintage"].startswith("2022-03-21")


def test_artifacts_published_with_stable_keys(good_run):
    from prefect.artifacts import Artifact

    from flows.weekly_forecast import (ARTIFACT_NLL, ARTIFACT_PARAMS, ARTIFACT_REPORT,
                                       ARTIFACT_SUMMARY)

    nll = Artifact.get(ARTIFACT_NLL)
    assert nll is not None and nll.type == "table"
    rows = json.loads(nll.data) if isinstance(nll.data, str) else nll.data
    assert {r["direction"] for r in rows} == {"forward", "backward"}
    params = Artifact.get(ARTIFACT_PARAMS)
    assert params is not None and params.type == "table"
    report = Artifact.get(ARTIFACT_REPORT)
    assert report is not None and report.type == "markdown"  # link artifacts render as markdown
    assert "report.html" in report.data
    assert Artifact.get(ARTIFACT_SUMMARY) is not None


def test_second_run_reuses_model_and_reproduces(good_run, tmp_path, monkeypatch):
    """Same data dir, same seed, data from the cache: model reused, numbers identical."""
    from flows.weekly_forecast import weekly_forecast

    root, first = good_run
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(root / "data"))
    again = weekly_forecast(preset="tiny", data_source="cache", output_dir=str(tmp_path), seed=0)
    assert again["model_reused"] and again["model_key"] == first["model_key"]
    for name in ["latest_estimates.csv", "parameter_estimates.csv", "smc_bands.csv",
                 "nll_table.csv", "hub_forecast.csv", "backtest_scores.csv",
                 "member_forecasts.csv"]:
        assert (Path(again["output_dir"]) / name).read_bytes() == \
            (Path(first["output_dir"]) / name).read_bytes(), name


def _datasf_down(rsps: responses.RequestsMock) -> None:
    rsps.add(responses.GET, re.compile(r"https://data\.sfgov\.org/.*"),
             body=requests.ConnectionError("network unreachable (test)"))


def test_fetch_fails_with_cache_completes_and_says_stale(good_run, tmp_path, monkeypatch):
    """The good run's data dir holds the imported cache (and its trained model)."""
    from flows.weekly_forecast import weekly_forecast

    root, _ = good_run
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(root / "data"))
    with responses.RequestsMock(assert_all_requests_are_fired=False) as rsps:
        _datasf_down(rsps)
        result = weekly_forecast(preset="tiny", data_source="live",
                                 output_dir=str(tmp_path / "reports"))
        attempts = len(rsps.calls)
    assert attempts == 3  # 1 + 2 HTTP retries of the tiny preset; the other 2 datasets: cache
    assert result["data_stale"]
    report = (Path(result["output_dir"]) / "report.html").read_text()
    assert "Stale data" in report and "DataSF could not be reached" in report
    index = json.loads((tmp_path / "reports" / "index.json").read_text())
    assert index["runs"][0]["data_stale"] is True


def test_fetch_fails_without_cache_fails_clearly_and_keeps_last_good(good_run, tmp_path,
                                                                     monkeypatch):
    from flows.weekly_forecast import weekly_forecast

    root, first = good_run
    reports = root / "reports"
    before = {p: p.read_bytes() for p in reports.rglob("*") if p.is_file()}
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "empty-data"))
    with responses.RequestsMock(assert_all_requests_are_fired=False) as rsps:
        _datasf_down(rsps)
        state = weekly_forecast(preset="tiny", data_source="live", output_dir=str(reports),
                                return_state=True)
        attempts = len(rsps.calls)
    assert state.is_failed()
    with pytest.raises(Exception, match=r"flowcast data import"):
        state.result()
    assert attempts == 2 * 3  # (1 + 1 task retry) x (1 + 2 HTTP retries) on the first dataset
    after = {p: p.read_bytes() for p in reports.rglob("*") if p.is_file()}
    assert after == before


def test_a_member_that_fails_leaves_the_run_degraded_and_named(good_run, tmp_path, monkeypatch):
    """The weekly run follows a hub round's rule (pipeline.members.isolation): a member that
    raises is left out of the published forecast, the others average, and the run says so —
    in its state, results.json and page 1 of the report."""
    import shutil

    from flows.weekly_forecast import DEGRADED_STATE_NAME, weekly_forecast
    from pipeline.members.boosting import PooledBoostingMember

    root, first = good_run
    # the good run's cache and models, without its memo of member forecasts (read back, a
    # memoised forecast would not meet the injected failure)
    shutil.copytree(root / "data", tmp_path / "data",
                    ignore=shutil.ignore_patterns("forecast-memo"))
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "data"))

    def broken(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        raise RuntimeError("injected failure")

    monkeypatch.setattr(PooledBoostingMember, "forecast", broken)
    state = weekly_forecast(preset="tiny", data_source="cache",
                            output_dir=str(tmp_path / "reports"), seed=0, return_state=True)
    assert state.is_completed() and state.name == DEGRADED_STATE_NAME
    assert "gbqr" in state.message and "injected failure" in state.message
    result = state.result()
    assert result["model_reused"] and result["degraded"]
    assert result["dropped"] == [{"what": "member", "target": "cases", "name": "gbqr",
                                  "why": "raised RuntimeError: injected failure"}]
    out = Path(result["output_dir"])
    assert json.loads((out / "results.json").read_text())["dropped"] == result["dropped"]
    report = (out / "report.html").read_text()
    assert "Member gbqr left out of the published forecast" in report
    # the forecast still stands on the other members: finite, and not the good run's
    good = pd.read_csv(Path(first["output_dir"]) / "hub_forecast.csv")
    degraded = pd.read_csv(out / "hub_forecast.csv")
    assert np.isfinite(degraded["value"]).all() and len(degraded) == len(good)
    assert not np.allclose(degraded["value"], good["value"])


# ------------------------------------------------- run_forecast without Prefect == the flow

def test_run_forecast_without_prefect_equals_the_flow(good_run, datasf_dir, tmp_path,
                                                      monkeypatch):
    """``run_forecast`` on the flow's config, in a fresh data dir (so it trains its own pair),
    gives typed results whose tables are byte-identical to the flow's files."""
    from typing import get_args

    from flows.weekly_forecast import flow_config
    from pipeline.backtest.track_record import TrackRecord
    from pipeline.forecast import ForecastResults, run_forecast
    from pipeline.forecast.publish import write_tables
    from pipeline.forecast.run import Step
    from pipeline.inference.rollout import RolloutResult
    from pipeline.inference.smc import SMCResult
    from pipeline.models.estimator import ConditionalEstimator

    root, flow_result = good_run
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "data"))
    flow_run_config = flow_config("tiny", encoder=None, data_source="import",
                                  import_from=[str(datasf_dir)],
                                  output_dir=str(root / "reports"), seed=0,
                                  datasf_base_url=None)
    # the forecast's members trained in a background process (off in the flow's tiny run):
    # the same models, so the same tables
    config = dataclasses.replace(flow_run_config, training=dataclasses.replace(
        flow_run_config.training, background_members=True))
    # the data folder travels on the config (read from the environment by flow_config, once):
    # the run, its background process included, never reads the variable again
    assert config.data.data_dir == str(tmp_path / "data")
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "elsewhere"))
    results = run_forecast(config)
    assert not (tmp_path / "elsewhere").exists()
    assert (tmp_path / "data" / "models").is_dir() and (tmp_path / "data" / "forecast-memo").is_dir()

    assert isinstance(results, ForecastResults) and results.config == config
    assert isinstance(results.models.forward, ConditionalEstimator)
    assert not results.models.reused and results.models.key == flow_result["model_key"]
    assert results.reference_date == EXPECTED_REFERENCE_DATE and not results.stale
    assert set(results.rollouts) == {(d, w) for d in ("forward", "backward") for w in (7, 28)}
    assert all(isinstance(r, RolloutResult) for r in results.rollouts.values())
    assert tuple(results.future.samples.shape) == (200, 28, 4)    # S, I, R, beta
    assert isinstance(results.smc.result, SMCResult) and len(results.smc.dates) == 28
    assert isinstance(results.weekly, TrackRecord)
    assert str(results.weekly.origin.date()) == ORIGIN
    # every step timed, in the flow's task names, and the flow ran the same steps (DataSF's
    # fetch: a county's, fetch-cdph, is the other)
    steps = [s for s in get_args(Step) if s not in ("fetch-cdph", "train-forecast-members")]
    assert list(results.timings) == [*steps, "train-forecast-members"]
    assert list(flow_result["step_seconds"]) == steps

    out = tmp_path / "direct"
    files = write_tables(results, out)
    flow_dir = Path(flow_result["output_dir"])
    compared = [f for f in files if f.endswith(".csv")]
    assert "hub_forecast.csv" in compared and len(compared) >= 12
    for name in compared:
        assert (out / name).read_bytes() == (flow_dir / name).read_bytes(), name

    # Again on the stored models, the track record's memo removed: the weekly forecast is made
    # in a forked child (published_forecast.start_weekly_forecast) beside the estimates; same
    # tables.
    from pipeline.forecast.published_forecast import forecast_memo_path

    forecast_memo_path(config.data.place, config.data.folder).unlink()
    again = run_forecast(config)
    assert again.models.reused and again.weekly.memo_reads is not None
    assert again.weekly.memo_reads[0] < again.weekly.memo_reads[1] / 2   # made anew, not read
    assert "train-forecast-members" not in again.timings      # nothing trained in the background
    rerun = tmp_path / "rerun"
    for name in write_tables(again, rerun):
        if name.endswith(".csv"):
            assert (rerun / name).read_bytes() == (out / name).read_bytes(), name
