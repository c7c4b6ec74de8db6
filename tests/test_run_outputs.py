"""Staged outputs: promote atomically, index past runs, never let a failed run replace a good one."""
from __future__ import annotations

import json
import os

import pytest

from pipeline.errors import ConfigError
from pipeline.outputs.run_folders import (INDEX_HTML, INDEX_JSON, RUN_RECORD, RunOutputs, RunRecord,
                                  recover_interrupted_promotions)


def record(date: str, run_id: str, **kw) -> RunRecord:
    base = dict(reference_date=date, run_id=run_id, finished_at=f"{date}T06:00:00+00:00",
                data_stale=False, data_vintage="2022-03-21", model_key="k" * 64, seed=0,
                preset="tiny", files=("report.html",), summary={"beta_mean": 0.03})
    return RunRecord(**{**base, **kw})


def write_report(folder, text):
    (folder / "report.html").write_text(text)


def test_promote_moves_staging_into_place_and_indexes(tmp_path):
    outputs = RunOutputs(tmp_path / "reports")
    staging = outputs.begin("2022-03-07", "run-a")
    assert staging.name.startswith(".staging-2022-03-07-")
    write_report(staging, "week 1")
    final = outputs.promote(staging, record("2022-03-07", "run-a"))
    assert final == tmp_path / "reports" / "2022-03-07"
    assert not staging.exists()
    assert (final / "report.html").read_text() == "week 1"
    assert json.loads((final / RUN_RECORD).read_text())["run_id"] == "run-a"
    index = json.loads((tmp_path / "reports" / INDEX_JSON).read_text())
    assert [r["reference_date"] for r in index["runs"]] == ["2022-03-07"]
    assert 'href="2022-03-07/report.html"' in (tmp_path / "reports" / INDEX_HTML).read_text()


def test_index_lists_runs_newest_first_and_rerun_replaces_its_date(tmp_path):
    outputs = RunOutputs(tmp_path)
    for date, run_id, text in [("2022-03-07", "a", "w1"), ("2022-03-14", "b", "w2"),
                               ("2022-03-07", "c", "w1 again")]:
        staging = outputs.begin(date, run_id)
        write_report(staging, text)
        outputs.promote(staging, record(date, run_id))
    runs = outputs.runs()
    assert [(r.reference_date, r.run_id) for r in runs] == [("2022-03-14", "b"), ("2022-03-07", "c")]
    assert outputs.latest().run_id == "b"
    assert (tmp_path / "2022-03-07" / "report.html").read_text() == "w1 again"
    # no leftovers of the replaced output (the run lock, .run.lock + .owner, is not output)
    assert sorted(p.name for p in tmp_path.iterdir()
                  if not p.name.startswith(".run.lock")) == ["2022-03-07", "2022-03-14",
                                                             INDEX_HTML, INDEX_JSON]


def test_failed_run_keeps_last_good_output_and_index(tmp_path):
    outputs = RunOutputs(tmp_path)
    staging = outputs.begin("2022-03-07", "good")
    write_report(staging, "good report")
    outputs.promote(staging, record("2022-03-07", "good"))
    index_before = (tmp_path / INDEX_JSON).read_bytes()

    with pytest.raises(RuntimeError, match="SMC blew up"):
        with outputs.staged("2022-03-07", "bad") as staging:
            write_report(staging, "half-written")
            raise RuntimeError("SMC blew up")

    assert (tmp_path / "2022-03-07" / "report.html").read_text() == "good report"
    assert (tmp_path / INDEX_JSON).read_bytes() == index_before
    assert not any(p.name.startswith(".staging") for p in tmp_path.iterdir())


def test_interrupted_promotion_is_recovered(tmp_path):
    """A crash between 'move old aside' and 'move new in' must not lose the old output."""
    outputs = RunOutputs(tmp_path)
    staging = outputs.begin("2022-03-07", "good")
    write_report(staging, "good report")
    outputs.promote(staging, record("2022-03-07", "good"))
    os.replace(tmp_path / "2022-03-07", tmp_path / ".previous-2022-03-07-next")  # simulated crash
    assert recover_interrupted_promotions(tmp_path) == [tmp_path / "2022-03-07"]
    assert (tmp_path / "2022-03-07" / "report.html").read_text() == "good report"


@pytest.mark.parametrize("bad", ["2022-3-7", "latest", "2022-02-30", "../etc"])
def test_bad_reference_date_is_rejected(tmp_path, bad):
    with pytest.raises((ConfigError, ValueError)):
        RunOutputs(tmp_path).begin(bad)


def test_damaged_index_names_the_file(tmp_path):
    (tmp_path / INDEX_JSON).write_text("{not json")
    with pytest.raises(ConfigError, match="index.json"):
        RunOutputs(tmp_path).runs()
