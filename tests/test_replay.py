"""The hub round replayed through the real flow (``hub_forecast`` under prefect_test_harness, the
tiny preset, the hub's real releases of ``../shared/data/nhsn`` from 2025-08-20 on) with a
failure injected; every one still gives a valid round file (validated against the hub's
tasks.json again, read back by hubdata) that names what it dropped. Also: the replay sees only
the releases up to each Wednesday, and a rerun replays only the Wednesdays not done."""
from __future__ import annotations

import dataclasses
import io
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from tests.hub_places import PLACES, only_places

pytestmark = pytest.mark.slow

NHSN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nhsn"
HOSP, ED = "wk inc covid hosp", "wk inc covid prop ed visits"
DUE = "2025-09-24"                # the last release; its round is 2025-09-27


@pytest.fixture(scope="module")
def every_release():
    """The releases since 2025-08-20 at a dozen places (tests/hub_places.py)."""
    from pipeline.hub_round.replay import releases_of_time_series

    series = only_places(pd.read_parquet(NHSN / "time-series.parquet"))
    recent = series[pd.to_datetime(series["as_of"]) >= pd.Timestamp("2025-08-20")]
    return releases_of_time_series(recent, "covid")


@pytest.fixture(scope="module")
def releases(every_release):
    """The last three Wednesdays' releases (few rounds: seconds)."""
    return [r for r in every_release if str(r.as_of) >= "2025-09-10"]


def _replay(tmp_path: Path, releases, start: str = DUE,  # noqa: ANN001
            end: str = DUE) -> tuple[Path, dict[str, Any]]:
    import datetime as dt

    from flows.hub_forecast import flow_step
    from pipeline.hub_round import replay as rp
    from pipeline.hub_round.run import HubRunConfig

    run = HubRunConfig.of_preset("tiny")
    config = rp.ReplayConfig(tmp_path / "replay", run, dt.date.fromisoformat(start),
                             dt.date.fromisoformat(end))
    rp.copy_hub_config(run.hub_config_dir(), config.out)
    summary = rp.replay(config, releases, flow_step())
    return config.out, summary


def _checked(out: Path) -> pd.DataFrame:
    """Every round file valid against the hub's tasks.json, and the folder read by hubdata."""
    import hubdata

    from pipeline.outputs.hubverse_validation import load_tasks_config, validate_model_output

    tasks = load_tasks_config(NHSN / "hub-config" / "tasks.json")
    files = sorted((out / "model-output" / "flowcast-nfhub").glob("*.csv"))
    assert files
    for path in files:
        validate_model_output(path, tasks)
    return hubdata.connect_hub(out).get_dataset().to_table().to_pandas()


def _last(summary):  # noqa: ANN001, ANN202
    return summary["rounds"][-1]


def _dropped(summary, what: str) -> dict[tuple[str, str], str]:  # noqa: ANN001
    return {(d["target"], d["name"]): d["why"] for d in _last(summary)["dropped"]
            if d["what"] == what}


def test_members_that_fail_and_a_refit_that_diverges_are_dropped_and_named(
        prefect_harness, tmp_path, releases, monkeypatch):
    """One round meets three failures at once: admissions' two published members both fail
    (nf-context raises, gbqr returns a NaN median), the ED share's other member too (seasonal
    returns a NaN median), and every nf-real fine-tune diverges. The round is still published,
    naming each; its admissions and shares are the hub baseline's (the floor), and the refits
    fall back to the base flow."""
    from pipeline.errors import TrainingDivergedError
    from pipeline.members.base import MemberForecast
    from pipeline.members.boosting import PooledBoostingMember
    from pipeline.members.nf import real
    from pipeline.members.nf.context import ContextFlowMember
    from pipeline.members.seasonal import SeasonalGrowthMember

    def broken(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise RuntimeError("injected failure")

    def diverge(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise TrainingDivergedError("injected: validation NLL 30.64 at iteration 240")

    def nan_median(member_class):  # noqa: ANN001, ANN202
        forecast = member_class.forecast

        def nan(self, cells, horizons, levels):  # noqa: ANN001, ANN202
            count = forecast(self, cells, horizons, levels).count.copy()
            count[:, :, len(levels) // 2] = np.nan         # a numerical blow-up at the median
            return MemberForecast(count)
        return nan

    monkeypatch.setattr(ContextFlowMember, "forecast", broken)
    monkeypatch.setattr(PooledBoostingMember, "forecast", nan_median(PooledBoostingMember))
    monkeypatch.setattr(SeasonalGrowthMember, "forecast", nan_median(SeasonalGrowthMember))
    monkeypatch.setattr(real, "stored_refit", diverge)
    out, summary = _replay(tmp_path, releases)
    last = _last(summary)
    assert summary["rounds_failed"] == 0 and last["state"] == "Completed (degraded)"
    dropped = _dropped(summary, "member")
    assert dropped[(HOSP, "nf-context")] == "raised RuntimeError: injected failure"
    assert dropped[(HOSP, "gbqr")].startswith("non-finite quantiles in ")
    assert dropped[(ED, "nf-context")] == "raised RuntimeError: injected failure"
    assert dropped[(ED, "seasonal")].startswith("non-finite quantiles in ")
    assert "member nf-context (wk inc covid hosp): raised RuntimeError" in last["message"]
    refits = _dropped(summary, "refit")
    assert refits and {t for t, _ in refits} <= {HOSP, ED}
    assert all(name.startswith("nf-real 20") for _, name in refits)
    assert all("injected: validation NLL 30.64" in why and "instead" in why
               for why in refits.values())
    back = _checked(out)
    # every place of the data (Missouri has no ED share)
    assert back.groupby("target")["location"].nunique().to_dict() == {HOSP: 13, ED: 12}
    # without the floor (the hub baseline where every published member failed) admissions
    # would have no forecast at any location from horizon 0 on
    hosp = back[(back["target"] == HOSP) & (back["output_type"] == "quantile")]
    assert hosp.groupby("horizon")["location"].nunique().to_dict() == {
        h: len(PLACES) for h in (-1, 0, 1, 2, 3)}


def _revised(releases, due: str):  # noqa: ANN001, ANN202
    """The admissions release of ``due`` with California's settled weeks ×10."""
    from pipeline.data.hub.nhsn_vintages import canonical_csv

    out = []
    for r in releases:
        if r.target == HOSP and str(r.as_of) == due:
            frame = pd.read_csv(io.BytesIO(r.payload), dtype={"location": str})
            weeks = pd.to_datetime(frame["target_end_date"])
            settled = (frame["location"] == "06") & (weeks < weeks.max() - pd.Timedelta(days=60))
            frame.loc[settled, "value"] *= 10
            r = dataclasses.replace(r, payload=canonical_csv(frame))
        out.append(r)
    return out


def test_a_target_whose_last_release_is_five_weeks_old_is_left_out_and_said(
        prefect_harness, tmp_path, releases, every_release):
    """Admissions from 2025-09-10, the ED share's newest release 2025-08-20's."""
    withheld = ([r for r in releases if r.target == HOSP]
                + [r for r in every_release if r.target == ED and str(r.as_of) == "2025-08-20"])
    out, summary = _replay(tmp_path, withheld)
    last = _last(summary)
    assert last["state"] == "Completed (degraded)" and last["published_targets"] == [HOSP]
    assert _dropped(summary, "target") == {(ED, ED): (
        "no current release: the newest, of 2025-08-20, is 5 weeks old (it serves the round "
        "of 2025-08-23, not 2025-09-27)")}
    assert "5 weeks old" in last["message"]
    back = _checked(out)
    assert set(back["target"]) == {HOSP}
    folder = Path(last["model_output"]).parents[2]
    report = (folder / "report.html").read_text()
    assert "Not in this submission as planned: target wk inc covid prop ed visits" in report
    facts = json.loads((folder / "summary.json").read_text())
    assert facts["degraded"] and facts[ED]["published"] is False
    assert facts[ED]["dropped"][0]["why"].endswith("not 2025-09-27)")


def test_each_wednesday_sees_only_its_releases_and_a_revision_holds_one_location_alone(
        prefect_harness, tmp_path, releases):
    """2025-09-17's round, then a rerun to 2025-09-24 whose admissions release revises
    California's settled weeks tenfold: the rerun replays only the new Wednesday, and that
    round holds California alone while the rest go live: California is still forecast, from
    its accepted series (named as held on page 1 and in summary.json, not left out)."""
    revised = _revised(releases, DUE)
    out, first = _replay(tmp_path, revised, start="2025-09-17", end="2025-09-17")
    assert [r["reference_date"] for r in first["rounds"]] == ["2025-09-20"]
    # the week's data folder travels on the round's config, through the flow whole: the
    # process's own folder ($FLOWCAST_DATA_DIR) is never read or written
    assert not Path(os.environ["FLOWCAST_DATA_DIR"]).exists()
    assert (out / "data" / "models").is_dir() and (out / "data" / "forecast-memo").is_dir()
    # 2025-09-24's releases are not in the cache of 2025-09-17's round
    assert not list((out / "releases").glob("2025-09-24-*"))
    _, again = _replay(tmp_path, revised, start="2025-09-17", end=DUE)
    assert [r["reference_date"] for r in again["rounds"]] == ["2025-09-20", "2025-09-27"]
    assert again["rounds"][0] == first["rounds"][0]           # not replayed
    assert again["rounds_due"] == again["rounds_published"] == 2
    assert sorted(p.name for p in (out / "model-output" / "flowcast-nfhub").iterdir()) == [
        "2025-09-20-flowcast-nfhub.csv", "2025-09-27-flowcast-nfhub.csv"]
    last = _last(again)
    assert last["state"] != "Failed" and HOSP in last["published_targets"]
    assert set(_checked(out)["target"]) == {HOSP, ED}
    assert (HOSP, "06") not in _dropped(again, "location")
    rows = _checked(out)
    september = rows[(rows["reference_date"].astype(str) == "2025-09-27")
                     & (rows["target"] == HOSP)]
    # held, not left out: every location of admissions is in the round, California with it
    assert september["location"].nunique() == len(PLACES) and "06" in set(september["location"])
    folder = Path(last["model_output"]).parents[2]
    summary = json.loads((folder / "summary.json").read_text())
    assert "06" in summary["held"][HOSP]
    assert "forecast from its accepted series" in summary["held"][HOSP]["06"]
    # page 1 says the revision waits for review (the operator's `data accept-revisions`)
    report = (folder / "report.html").read_text()
    assert f"{HOSP}: 06 held: a revision waiting for review" in report
    # each round's seconds per target and member, summed up per target and member
    assert set(last["target_seconds"]) == {HOSP, ED}
    assert "nf-real" in last["target_seconds"][HOSP]         # its refit date 2025-09-06
    for target, seconds in last["target_seconds"].items():
        assert {"total", "nf-context", "nf-weekly", "seasonal", "hub-baseline"} <= set(seconds)
        assert 0 < seconds["total"] and all(0 <= v <= seconds["total"] for v in seconds.values())
        assert again["seconds_by_target"][target]["total"]["first_round"] == \
            first["rounds"][0]["target_seconds"][target]["total"]
