"""``--hub flu`` end to end on the library (tiny preset, offline) from FluSight's real releases
(``../shared/data/flusight``, imported with their revisions accepted into a temporary data
folder): an in-season round is written as FluSight's own ``tasks.json`` asks (100 integer paths
per location, the rate-change pmf of every location and horizon 0–3, no ED share: the data
have none) and read back by hubdata; an off-season round is not written, said by name; RSV,
whose hub config is not in reach, is refused by name."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.hub_places import PLACES, only_places

pytestmark = pytest.mark.slow

FLUSIGHT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "flusight"


def _round(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, first: str, last: str):
    """The round of FluSight's releases from ``first`` to ``last``, at a dozen places
    (tests/hub_places.py)."""
    from pipeline.data.hub.target_import import import_hub_time_series
    from pipeline.hub_round.run import HubRunConfig, run_hub_round

    series = only_places(pd.read_parquet(FLUSIGHT / "time-series.parquet"))
    as_of = pd.to_datetime(series["as_of"])
    series[(as_of >= pd.Timestamp(first)) & (as_of <= pd.Timestamp(last))] \
        .to_parquet(tmp_path / "time-series.parquet")
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "data"))
    import_hub_time_series(tmp_path / "time-series.parquet", accept_revisions=True)
    config = HubRunConfig.of_preset("tiny", disease="flu", data_source="cache",
                                    output_dir=str(tmp_path / "out"))
    return config, run_hub_round(config)


def test_an_in_season_flu_round_is_flusights(tmp_path, monkeypatch):
    import hubdata

    from pipeline.hub_round.publish import publish_hub_round
    config, run = _round(tmp_path, monkeypatch, "2025-02-05", "2025-02-19")
    assert list(run.results) == ["wk inc flu hosp"]          # no influenza ED vintage
    # without it the seasonal member reads the admissions' own earlier seasons: it forecasts
    # every location of the round (a climatology it waited for left it silent, and the
    # published average was the flow alone)
    assert "seasonal" not in run.results["wk inc flu hosp"].dropped_members()
    seasonal = run.results["wk inc flu hosp"].backtest.forecasts["wk inc flu hosp"]["seasonal"]
    assert np.isfinite(seasonal.values[:, -1]).all()
    # influenza's published average: the context flow and gbqr, as on the other hubs; the
    # weekly flow and the seasonal member are scored beside it (bench/results/flusight.json)
    assert set(run.results["wk inc flu hosp"].backtest.members) == {"nf-context", "gbqr"}
    published = publish_hub_round(run)
    assert published.reference_date == "2025-02-22"
    folder = published.folder
    (folder / "hub-config").symlink_to(FLUSIGHT / "hub-config")
    back = hubdata.connect_hub(folder).get_dataset().to_table().to_pandas()
    (folder / "hub-config").unlink()
    n_loc = len(run.results["wk inc flu hosp"].places)
    assert n_loc == len(PLACES)
    counts = back.groupby(["target", "output_type"]).size().to_dict()
    assert counts == {("wk inc flu hosp", "quantile"): n_loc * 5 * 23,
                      ("wk inc flu hosp", "sample"): n_loc * 5 * 100,
                      ("wk flu hosp rate change", "pmf"): n_loc * 4 * 5}
    samples = back[back.output_type == "sample"]
    assert (samples.value == np.round(samples.value)).all()
    assert samples.groupby("location").output_type_id.nunique().eq(100).all()
    pmf = back[back.output_type == "pmf"].groupby(["location", "horizon"]).value.sum()
    np.testing.assert_allclose(pmf, 1.0, atol=1e-6)
    # the pmf is the paths' own: its "increase or more" share at horizon 0 counts the
    # location's paths whose week rises beyond FluSight's stable bound
    from pipeline.outputs.derived_targets import category_edges, rate_change_rule
    result = run.results["wk inc flu hosp"]
    from pipeline.data.hub.locations import POPULATION
    c = result.places.index("US")
    paths = result.samples[c, -1]                                    # (n, H): 200 paths
    edges = category_edges(paths[:, 0], np.full(len(paths), POPULATION["US"]), 0,
                           rate_change_rule(pd.Timestamp("2025-02-22")))
    rising = np.sum(paths[:, 1] > edges[:, 2])
    us0 = back[(back.location == "US") & (back.horizon == 0) & (back.output_type == "pmf")]
    # each of the two categories holds its paths and half a path (PSEUDO_COUNT) of 5 halves
    assert us0.set_index("output_type_id").value[["increase", "large_increase"]].sum() == \
        pytest.approx((rising + 2 * 0.5) / (len(paths) + 5 * 0.5), rel=1e-6)


def test_no_round_off_season_and_the_rsv_hubs_config(tmp_path, monkeypatch):
    """Off season the round the data serve is none of the hub's: said from the releases'
    dates, before any member is built (no model trained, no cell forecast, nothing written)."""
    from pipeline.errors import ConfigError
    from pipeline.hub_round.publish import require_hub_config
    from pipeline.hub_round.run import HubRunConfig
    from pipeline.outputs.hub_conform import NoHubRoundError
    import pipeline.hub_round.run as run_module

    def never(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("a member was built off season")

    monkeypatch.setattr(run_module, "build_hub_members", never)
    with pytest.raises(NoHubRoundError, match=r"the flu hub takes no round for the reference "
                       r"date 2025-06-21 \(89 rounds, 2023-10-07 … 2026-05-30\): no round") \
            as raised:
        _round(tmp_path, monkeypatch, "2025-06-04", "2025-06-18")
    assert str(raised.value.reference) == "2025-06-21"
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.csv"))
    assert not (tmp_path / "data" / "models").exists()
    assert not (tmp_path / "data" / "forecast-memo").exists()
    monkeypatch.delenv("FLOWCAST_HUB_CONFIG", raising=False)
    # the RSV hub's config is beside the checkout now (issue 49): its round validates there
    assert require_hub_config(HubRunConfig(disease="rsv")) == FLUSIGHT.parent / "rsv" / \
        "hub-config"
    with pytest.raises(ConfigError, match="no readable tasks.json"):
        require_hub_config(HubRunConfig(disease="rsv", hub_config=str(tmp_path)))


def test_the_flow_ends_off_season_without_a_round(prefect_harness, tmp_path, monkeypatch):
    """The deployment's flow on an off-season week: no round, said by name, a result and not a
    failure (rc 0 from the command line); a due day the hub's calendar has no round open on is
    said before any work (the RSV hub off season: no data needed to know it)."""
    from flows.hub_forecast import hub_forecast
    from pipeline.data.hub.target_import import import_hub_time_series

    series = pd.read_parquet(FLUSIGHT / "time-series.parquet")
    as_of = pd.to_datetime(series["as_of"])
    series[as_of >= pd.Timestamp("2025-06-04")].to_parquet(tmp_path / "time-series.parquet")
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "data"))
    import_hub_time_series(tmp_path / "time-series.parquet", accept_revisions=True)
    result = hub_forecast(disease="flu", data_source="cache", output_dir=str(tmp_path / "out"),
                          preset="tiny")
    assert result["model_output"] is None and result["reference_date"] == "2025-06-21"
    assert "takes no round for the reference date 2025-06-21" in str(result["no_round"])
    assert not list((tmp_path / "out").rglob("*.csv"))
    monkeypatch.delenv("FLOWCAST_HUB_CONFIG", raising=False)
    import datetime as dt
    off = hub_forecast(disease="rsv", data_source="cache", output_dir=str(tmp_path / "out"),
                       preset="tiny", due=dt.date(2025, 7, 9))
    assert off["model_output"] is None and off["reference_date"] is None
    assert str(off["no_round"]).startswith("the rsv hub has no round open on 2025-07-09 (the "
                                           "rsv hub's 37 rounds, 2025-09-20 … 2026-05-30)")
