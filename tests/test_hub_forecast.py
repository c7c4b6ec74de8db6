"""The hub_forecast flow end to end under prefect_test_harness, on the tiny preset and the hub's
real data (the last three NHSN/NSSP vintages of ``../shared/data/nhsn``, imported into a
temporary FLOWCAST_DATA_DIR, run offline): the round's file valid against the hub's tasks.json
and read back by hubdata, its report and track record; the same round again from the memo, byte
for byte; and an empty cache refused by name, the last good round kept.
"""
from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

pytestmark = pytest.mark.slow

NHSN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nhsn"
REFERENCE = "2025-09-27"          # the Saturday after the newest vintage (2025-09-24)
# NSSP reports no ED share for Missouri (29) and Puerto Rico (72)
LOCATIONS = {"wk inc covid hosp": 53, "wk inc covid prop ed visits": 51}
TARGETS = set(LOCATIONS)


@pytest.fixture(scope="module")
def hub_run(prefect_harness, tmp_path_factory):
    """One tiny round from the last three vintages of both targets; shared by the checks."""
    from flows.hub_forecast import hub_forecast
    from pipeline.data.hub.target_import import import_hub_time_series

    root = tmp_path_factory.mktemp("hub-run")
    series = pd.read_parquet(NHSN / "time-series.parquet")
    recent = series[pd.to_datetime(series["as_of"]) >= pd.Timestamp("2025-09-10")]
    recent.to_parquet(root / "time-series.parquet")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLOWCAST_DATA_DIR", str(root / "data"))
        import_hub_time_series(root / "time-series.parquet")
        first = hub_forecast(data_source="cache", output_dir=str(root / "reports"),
                             preset="tiny")
        files = {p: p.read_bytes() for p in (root / "reports").rglob("*.csv")}
        again = hub_forecast(data_source="cache", output_dir=str(root / "reports"),
                             preset="tiny")
    return root, first, files, again


def test_the_round_is_valid_for_the_hub_and_read_back_by_hubdata(hub_run):
    import hubdata

    root, first, _, _ = hub_run
    folder = Path(first["output_dir"])
    assert first["reference_date"] == REFERENCE and folder.name == REFERENCE
    assert not first["data_stale"]
    model_output = Path(first["model_output"])
    assert model_output == folder / "model-output" / "flowcast-nfhub" / \
        f"{REFERENCE}-flowcast-nfhub.csv"
    for name in ("report.html", "report.pdf", "summary.json", "track_record_scores.csv",
                 "model-metadata/flowcast-nfhub.yml"):
        assert (folder / name).stat().st_size > 0, name
    html = (folder / "report.html").read_text()
    assert "flowcast forecast hub round" in html and "likely rising" in html
    (folder / "hub-config").symlink_to(NHSN / "hub-config")
    back = hubdata.connect_hub(folder).get_dataset().to_table().to_pandas()
    (folder / "hub-config").unlink()
    assert back.groupby("target")["location"].nunique().to_dict() == LOCATIONS
    assert sorted(back["horizon"].unique()) == [-1, 0, 1, 2, 3]
    quantiles = back[back["output_type"] == "quantile"]
    assert quantiles.groupby(["target", "location", "horizon"]).size().eq(23).all()
    assert (back[back["output_type"] == "sample"].groupby(["target", "location", "horizon"])
            .size().eq(200).all())
    # monotone in the level, admissions counts non-negative, the ED share a share
    q = quantiles.assign(level=quantiles["output_type_id"].astype(float)).sort_values(
        ["target", "location", "horizon", "level"])
    assert (q.groupby(["target", "location", "horizon"])["value"].diff().dropna() >= 0).all()
    share = q[q["target"] == "wk inc covid prop ed visits"]["value"]
    assert share.between(0, 1).all() and (q["value"] >= 0).all()


def test_the_track_record_scores_every_earlier_round(hub_run):
    root, first, _, _ = hub_run
    folder = Path(first["output_dir"])
    summary = json.loads((folder / "summary.json").read_text())
    for target in TARGETS:
        rounds = summary[target]["rounds"]
        assert (rounds["n"], rounds["last"]) == (3, REFERENCE)
        assert summary[target]["n_locations"] == LOCATIONS[target]
    scores = pd.read_csv(folder / "track_record_scores.csv")
    assert {"published", "hub-baseline", "nf-weekly", "seasonal"} <= set(scores["model_id"])
    scored = scores.dropna(subset=["wis"])
    assert len(scored) > 0 and (scored["wis"] >= 0).all()


def test_the_same_round_again_is_the_same_bytes(hub_run):
    root, first, files, again = hub_run
    assert again["reference_date"] == first["reference_date"]
    assert {p: p.read_bytes() for p in (root / "reports").rglob("*.csv")} == files


def test_an_empty_cache_is_refused_by_name_and_the_last_round_kept(hub_run, tmp_path,
                                                                   monkeypatch):
    from flows.hub_forecast import hub_forecast

    root, _, files, _ = hub_run
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "empty"))
    state = hub_forecast(data_source="cache", output_dir=str(root / "reports"),
                         preset="tiny", return_state=True)
    assert state.is_failed()
    with pytest.raises(Exception, match=r"flowcast data import"):
        state.result()
    assert {p: p.read_bytes() for p in (root / "reports").rglob("*.csv")} == files
