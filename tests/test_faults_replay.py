"""Issue 49's replay cases (bench/faults_replay.py): ``flowcast replay`` and ``forecast --hub``
judge their input before any work, each fault one named error line with 0 bytes lost; two
replays of different Wednesdays into one folder keep both rounds in ``replay.json``."""
from __future__ import annotations

import json

import pytest

from bench.faults_replay import concurrent_replays, replay_faults, run_replay_fault
from pipeline.errors import FlowcastError
from pipeline.io import json_depth, read_bounded_json


@pytest.mark.parametrize("fault", replay_faults(), ids=lambda f: f.name)
def test_a_replay_input_fault_is_one_named_error_and_loses_nothing(fault, tmp_path):
    result = run_replay_fault(fault, tmp_path)
    assert result.passed, result.note
    assert result.bytes_lost == 0
    assert result.seconds < 30          # judged from metadata and sizes, never read whole


def test_two_replays_into_one_folder_keep_both_rounds(tmp_path):
    result = concurrent_replays(tmp_path)
    assert result.passed, result.note
    summary = json.loads((tmp_path / "out" / "replay.json").read_text())
    assert [r["state"] for r in summary["rounds"]] == ["Completed", "Failed"]
    assert "injected" in summary["failed"][0]["message"]


def test_json_depth_counts_brackets_outside_strings_only():
    assert json_depth(b'{"a": [1, {"b": [[]]}]}') == 5
    assert json_depth(b'{"a": "[[[{{{", "b": "\\"[[", "c": "\\\\"}') == 1
    assert json_depth(b"3") == 0


def test_a_bounded_json_is_parsed_within_its_bounds_and_refused_past_them(tmp_path):
    path = tmp_path / "x.json"
    path.write_text('{"rounds": [[1, 2], {"a": "]]]"}]}')
    assert read_bounded_json(path, max_bytes=100, max_depth=3) == {
        "rounds": [[1, 2], {"a": "]]]"}]}
    with pytest.raises(FlowcastError, match="nested 3 levels deep, more than the 2"):
        read_bounded_json(path, max_bytes=100, max_depth=2)
    with pytest.raises(FlowcastError, match="more than 10 bytes; refused unread"):
        read_bounded_json(path, max_bytes=10, max_depth=3)
