"""Issue 49, item 7, on the real NHSN releases (``../shared/data/nhsn``): the round due
2025-09-24 whose newest admissions release ends 2025-09-06, 18 days before (inside the gate's
21-day lag: a stale origin, so the members forecast a step further), with gbqr (a published
member of admissions) returning no forecast at its furthest step. It used to fail the whole round (``ScoringError:
quantile values contain NaN or inf``, naming no member); it publishes without that member
there, and names it on the run (at a dozen places, tests/hub_places.py)."""
from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.hub_places import PLACES, only_places

pytestmark = pytest.mark.slow

NHSN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nhsn"
HOSP = "wk inc covid hosp"


def test_a_stale_origin_with_a_member_missing_its_last_step_publishes_and_names_it(
        tmp_path, monkeypatch):
    from pipeline.data.core.cache import data_folder
    from pipeline.data.hub.target_import import import_hub_time_series
    from pipeline.hub_round.publish import publish_hub_round
    from pipeline.hub_round.run import HubRunConfig, run_hub_round
    from pipeline.members.base import MemberForecast
    from pipeline.members.boosting import PooledBoostingMember

    forecast = PooledBoostingMember.forecast

    def no_last_step(self, cells, horizons, levels):  # noqa: ANN001, ANN202
        count = forecast(self, cells, horizons, levels).count.copy()
        count[:, -1, :] = np.nan           # no forecast at a step within its reach
        return MemberForecast(count)

    monkeypatch.setattr(PooledBoostingMember, "forecast", no_last_step)
    series = only_places(pd.read_parquet(NHSN / "time-series.parquet"))
    as_of, end = series["as_of"].astype(str), series["target_end_date"].astype(str)
    keep = ((as_of >= "2025-08-27") & (as_of <= "2025-09-10")) | (
        (as_of == "2025-09-24") & ((series["target"] != HOSP) | (end <= "2025-09-06")))
    series[keep].to_parquet(tmp_path / "time-series.parquet")
    with data_folder(tmp_path / "data"):
        import_hub_time_series(tmp_path / "time-series.parquet")
        run = run_hub_round(HubRunConfig.of_preset(
            "tiny", data_source="cache", output_dir=str(tmp_path / "reports"),
            hub_config=str(NHSN / "hub-config"), due=dt.date(2025, 9, 24)))
        published = publish_hub_round(run)
    assert run.provenance[HOSP].last_week == "2025-09-06"        # 18 days before the due date
    dropped = {(d.target, d.name): d.why for d in run.dropped if d.what == "member"}
    assert dropped[(HOSP, "gbqr")].startswith("non-finite quantiles in ")
    assert published.reference_date == "2025-09-27"
    frame = pd.read_csv(published.model_output, dtype={"location": str})
    hosp = frame[(frame["target"] == HOSP) & (frame["output_type"] == "quantile")]
    assert np.isfinite(hosp["value"]).all()
    assert hosp.groupby("horizon")["location"].nunique().to_dict() == {
        h: len(PLACES) for h in (-1, 0, 1, 2, 3)}
