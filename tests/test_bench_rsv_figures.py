"""The RSV bench's figures from a round's track record (``bench.replay_hubs``): coverage with
its bootstrap interval and the online calibration's cost per window, on a record whose answers
are known by construction."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest


def _record(n_rounds: int) -> pd.DataFrame:
    """Two locations × ``n_rounds`` rounds × horizons 0-1: the published forecast covers its 50 %
    interval at every other round and its 95 % always; its WIS is 2 where the uncalibrated
    average's is 1 in the first five rounds, and equal to it afterwards."""
    rows = []
    dates = pd.date_range("2025-01-04", periods=n_rounds, freq="7D").strftime("%Y-%m-%d")
    for j, date in enumerate(dates):
        for place in ("01", "02"):
            for horizon in (0, 1):
                rows.append({"model_id": "published", "reference_date": date,
                             "target": "wk inc rsv hosp", "horizon": horizon,
                             "location": place, "wis": 2.0 if j < 5 else 1.0,
                             "coverage_50": float(j % 2 == 0), "coverage_95": 1.0})
                rows.append({"model_id": "ensemble-uncalibrated", "reference_date": date,
                             "target": "wk inc rsv hosp", "horizon": horizon,
                             "location": place, "wis": 1.0, "coverage_50": 0.0,
                             "coverage_95": 0.0})
    return pd.DataFrame(rows)


def test_coverage_and_the_calibrations_cost_per_window_from_a_track_record():
    from bench.replay_hubs import _coverage_and_cost

    figures = _coverage_and_cost(_record(20))
    assert figures["coverage50"] == pytest.approx(0.5)
    assert figures["coverage95"] == 1.0
    low, high = figures["coverage50_interval"]
    assert low <= 0.5 <= high
    cost = figures["calibration_cost_by_window"]
    # every round: (5 × 2 + 15 × 1) / 20; the worst window of 15 starts at the first round
    assert cost["all"] == pytest.approx(25 / 20, abs=1e-4)
    assert cost["worst_window"] == pytest.approx(20 / 15, abs=1e-4)
    assert cost["n_windows"] == 6
    assert cost["worst_window_origins"] == ["2025-01-04", "2025-04-12"]


def test_a_record_shorter_than_a_window_has_no_worst_window():
    from bench.replay_hubs import _coverage_and_cost

    cost = _coverage_and_cost(_record(10))["calibration_cost_by_window"]
    assert cost["all"] == pytest.approx(15 / 10, abs=1e-4)
    assert cost["worst_window"] is None and cost["n_windows"] == 0
    assert np.isfinite(_coverage_and_cost(_record(10))["coverage95"])
