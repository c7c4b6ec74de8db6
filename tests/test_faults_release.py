"""Issue 39's catalogue (bench/faults_release.py): faults arriving as a release newer than the
cached one, through the live fetch from a fake data.cdc.gov on 127.0.0.1 and through the
import; every case must pass with 0 bytes of good cache lost. FluSight's whole import is
tests/test_release_judgement.py's."""
from __future__ import annotations

import pytest

from bench.faults_release import import_cases, newer_faults, run_newer

@pytest.mark.parametrize("fault", newer_faults(), ids=lambda f: f.name)
def test_a_fault_in_a_newer_release(fault, tmp_path):
    result = run_newer(fault, tmp_path)
    assert result.passed, result.note
    assert result.bytes_lost == 0


@pytest.mark.parametrize("case", import_cases()[:8], ids=lambda c: c.__name__)
def test_an_import_fault(case, tmp_path):
    result = case(tmp_path)
    assert result.passed, f"{result.name}: {result.note}"
