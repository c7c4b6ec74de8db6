"""Labelled quantiles (pipeline/panels/quantiles.py) and the one way a level is found
(pipeline/evaluation/quantile_function.level_index): values worked out by hand."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.evaluation.quantile_function import CalibrationError, level_index, median_index
from pipeline.panels.quantiles import Observed, Quantiles, long_frame
from pipeline.panels.targets import TargetError

ORIGINS = (pd.Timestamp("2024-01-06"), pd.Timestamp("2024-01-13"))
LEVELS = np.array([0.25, 0.5, 0.75])


def _quantiles() -> Quantiles:
    # value = 1000·place + 100·origin + 10·horizon + level position: each cell names itself
    c, o, h, q = np.meshgrid(np.arange(3), np.arange(2), np.arange(2), np.arange(3),
                             indexing="ij")
    return Quantiles((1000 * c + 100 * o + 10 * h + q).astype(np.float64), ("CA", "NY", "US"),
                     ORIGINS, (1, 2), LEVELS)


def test_long_frame_is_every_element_in_array_order_with_its_labels() -> None:
    frame = long_frame(np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]),
                       {"location": ["a", "b"], "horizon": [0, 1, 2]})
    assert frame["location"].tolist() == ["a", "a", "a", "b", "b", "b"]
    assert frame["horizon"].tolist() == [0, 1, 2, 0, 1, 2]
    assert frame["value"].tolist() == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    with pytest.raises(TargetError, match="do not fit the axes"):
        long_frame(np.zeros((2, 3)), {"location": ["a", "b"], "horizon": [0, 1]})


def test_at_and_select_find_cells_by_label() -> None:
    q = _quantiles()
    assert q.at(place="NY", origin="2024-01-13", horizon=2, level=0.75) == 1112.0
    assert q.at(place="US", horizon=1).tolist() == [[2000.0, 2001.0, 2002.0],
                                                  [2100.0, 2101.0, 2102.0]]
    assert q.median()[0, 1].tolist() == [101.0, 111.0]
    sub = q.select(places=["US", "CA"], origins=np.array([False, True]), horizons=[2])
    assert sub.places == ("US", "CA") and sub.origins == (ORIGINS[1],) and sub.horizons == (2,)
    assert sub.values[:, 0, 0, 1].tolist() == [2111.0, 111.0]
    with pytest.raises(TargetError, match="place"):
        q.at(place="TX")
    with pytest.raises(CalibrationError, match="0.1 is not among"):
        q.at(level=0.1)


def test_frame_keeps_only_forecasts_made() -> None:
    q = _quantiles()
    values = q.values.copy()
    values[1] = np.nan                                   # NY not forecast
    frame = Quantiles(values, q.places, q.origins, q.horizons, q.levels).frame()
    assert len(frame) == 2 * 2 * 2 * 3
    assert set(frame["place"]) == {"CA", "US"}
    row = frame[(frame["place"] == "US") & (frame["origin"] == ORIGINS[1])
                & (frame["horizon"] == 1) & (frame["level"] == 0.75)]
    assert row["value"].tolist() == [2102.0]


def test_a_shape_that_does_not_fit_its_labels_is_refused() -> None:
    with pytest.raises(TargetError, match="do not fit 3 places"):
        Quantiles(np.zeros((3, 2, 2, 2)), ("CA", "NY", "US"), ORIGINS, (1, 2), LEVELS)


def test_a_forecast_is_scored_against_the_truth_of_its_own_cells_only() -> None:
    # quantiles 1, 2, 3 at levels 0.25, 0.5, 0.75: WIS = (|y − m| / 2 + α/2 · IS_α) / 1.5 with
    # α = 0.5; y = 2: (0 + 0.25 · 2) / 1.5 = 1/3; y = 5: (1.5 + 0.25 · (2 + 4 · 2)) / 1.5 = 8/3
    q = Quantiles(np.tile([1.0, 2.0, 3.0], (2, 1, 1, 1)), ("CA", "NY"), ORIGINS[:1], (1,), LEVELS)
    truth = Observed(np.array([[[2.0]], [[5.0]]]), ("CA", "NY"), ORIGINS[:1], (1,))
    scores = q.score(truth)
    np.testing.assert_allclose(scores.wis[:, 0, 0], [1 / 3, 8 / 3], rtol=1e-12)
    assert scores.covered[0.5][:, 0, 0].tolist() == [1.0, 0.0]
    assert truth.select(places=["NY"]).values.tolist() == [[[5.0]]]
    # the same numbers labelled as other places are refused, not scored against the wrong cells
    with pytest.raises(TargetError, match="place"):
        q.score(Observed(truth.values, ("NY", "CA"), ORIGINS[:1], (1,)))
    with pytest.raises(TargetError, match="horizon"):
        q.score(Observed(truth.values, ("CA", "NY"), ORIGINS[:1], (2,)))
    with pytest.raises(TargetError, match=r"horizon \[2\] not in"):
        truth.select(horizons=[2])
    with pytest.raises(TargetError, match="do not fit 2 places"):
        Observed(np.zeros((2, 1, 2)), ("CA", "NY"), ORIGINS[:1], (1,))


def test_level_index_is_exact_never_the_nearest_level() -> None:
    hub = np.array([0.01, 0.025, *np.arange(0.05, 0.951, 0.05), 0.975, 0.99])
    assert median_index(hub) == 11
    assert level_index(hub, 0.975) == 21
    with pytest.raises(CalibrationError):
        level_index(hub, 0.97)
