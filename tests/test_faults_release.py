"""Issue 39's catalogue (bench/faults_release.py): faults arriving as a release newer than the
cached one, through the live fetch from a fake data.cdc.gov on 127.0.0.1 and through the
import; every case must pass with 0 bytes of good cache lost. FluSight's whole import is
tests/test_release_judgement.py's. A round after a release that revises one location (held,
still forecast from its accepted series) is tests/test_replay.py's each-Wednesday test; the
bench's own case of it is in bench/results/faults.json."""
from __future__ import annotations

import pytest

from bench.faults_release import import_cases, newer_faults, run_newer
from pipeline.data.hub.nhsn import HOSP_COVID
from tests.hub_places import PLACES


@pytest.mark.parametrize("fault", newer_faults(), ids=lambda f: f.name)
def test_a_fault_in_a_newer_release(fault, tmp_path):
    result = run_newer(fault, tmp_path)
    assert result.passed, result.note
    assert result.bytes_lost == 0


@pytest.mark.parametrize("case", import_cases()[:8], ids=lambda c: c.__name__)
def test_an_import_fault(case, tmp_path):
    result = case(tmp_path)
    assert result.passed, f"{result.name}: {result.note}"


@pytest.mark.slow
def test_a_round_after_an_ed_share_release_without_the_us_row_publishes_the_states(tmp_path):
    """The hub round (tiny preset, from the cache, at the dozen places of tests/hub_places.py)
    after an ED-share release of 2025-09-24 without its national row: published with the
    states' shares (Missouri has none) and the US's admissions; the ED share's US left out,
    named in the panel's skipped and in ``HubRun.dropped`` (reconciliation neither spreads nor
    needs a national total for a share). The bench runs it at all 53 locations."""
    from bench.faults_round import round_faults, run_round_fault
    from pipeline.data.hub.nhsn import ED_COVID
    fault = next(f for f in round_faults() if f.name == "round-ed-no-national-row")
    result = run_round_fault(fault, tmp_path / "round", tmp_path / "models", places=PLACES)
    assert result.passed, result.note
    dropped = result.detail["dropped"]
    assert isinstance(dropped, dict) and list(dropped[ED_COVID]) == ["US"]
    assert dropped[HOSP_COVID] == {}
    states_with_ed_share = set(PLACES) - {"US", "29"}
    assert result.detail["locations"] == {HOSP_COVID: len(PLACES),
                                          ED_COVID: len(states_with_ed_share)}
