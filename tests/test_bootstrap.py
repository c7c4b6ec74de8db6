"""The moving-block bootstrap of a backtest's coverage against known answers."""
import numpy as np
import pytest

from pipeline.errors import ConfigError
from pipeline.evaluation.bootstrap import BlockBootstrap, coverage_interval, ratio_interval


def test_independent_origins_give_the_binomial_interval():
    rng = np.random.default_rng(1)
    hits = (rng.random(4000) < 0.3).astype(float)
    low, high = ratio_interval(hits, np.ones(4000), block=1)
    p = hits.mean()
    half = 1.959964 * np.sqrt(p * (1 - p) / 4000)          # the normal approximation
    assert low < p < high
    assert (high - low) == pytest.approx(2 * half, rel=0.1)


def test_runs_of_equal_outcomes_widen_the_interval():
    # 400 runs of L = 10 origins that all miss or all hold. A block of L consecutive origins
    # starts at a uniform offset u into a run, so it sums L·u of one run and L·(1−u) of the
    # next: E[u² + (1−u)²] = 2/3, the resampled total's variance is 2L/3 times an independent
    # sample's, and the interval √(2L/3) ≈ 2.58 times wider than block = 1 gives
    rng = np.random.default_rng(2)
    hits = np.repeat((rng.random(400) < 0.5).astype(float), 10)
    ones = np.ones_like(hits)
    low, high = ratio_interval(hits, ones, block=1)
    low_l, high_l = ratio_interval(hits, ones, block=10)
    assert (high_l - low_l) / (high - low) == pytest.approx(np.sqrt(20 / 3), rel=0.1)


def test_origins_with_the_same_share_leave_no_uncertainty():
    # every origin covers 3 of its 4 cells: every resample's share is 0.75
    assert ratio_interval(np.full(30, 3.0), np.full(30, 4.0), block=4) == (0.75, 0.75)


def test_coverage_interval_counts_only_the_masked_scored_cells():
    # (C=2, O=3, H=2): per origin the kept, scored cells hold 1 of 3 (a NaN dropped), 1 of 2
    # and 2 of 2
    covered = np.array([[[1, 0], [1, 1], [0, 1]],
                        [[np.nan, 0], [0, 0], [1, 1]]], dtype=float)
    mask = np.array([[[True, True], [True, False], [False, True]],
                     [[True, True], [False, True], [True, False]]])
    config = BlockBootstrap(block=1, draws=4000)
    interval = coverage_interval(covered, mask, config)
    assert interval == ratio_interval(np.array([1.0, 1, 2]), np.array([3.0, 2, 2]), 1, config)
    assert 1 / 3 <= interval[0] < 4 / 7 < interval[1] <= 1.0
    same = np.array([[[1, 0]] * 5], dtype=float)
    assert coverage_interval(same, np.ones_like(same, dtype=bool)) == (0.5, 0.5)


def test_reproducible_from_the_seed_and_named_errors():
    hits = np.arange(20) % 3 == 0
    a = ratio_interval(hits.astype(float), np.ones(20), 4, BlockBootstrap(seed=5))
    assert a == ratio_interval(hits.astype(float), np.ones(20), 4, BlockBootstrap(seed=5))
    assert ratio_interval(np.zeros(3), np.zeros(3), 2) is None
    assert coverage_interval(np.full((1, 2, 1), np.nan), np.ones((1, 2, 1), bool)) is None
    for bad in ({"block": 0}, {"draws": 1}, {"level": 1.0}):
        with pytest.raises(ConfigError, match="invalid BlockBootstrap"):
            BlockBootstrap(**bad)
