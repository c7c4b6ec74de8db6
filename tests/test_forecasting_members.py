"""Hub baseline against hand-computed quantiles; AutoETS quantiles; I from the count."""
from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.stats import norm

from pipeline.members.autoets import AutoETSMember, interval_levels
from pipeline.members.base import MemberForecast, with_share
from pipeline.members.hub_baseline import HubBaseline, HubBaselineConfig, baseline_quantiles
from pipeline.panels.targets import HUB_QUANTILE_LEVELS, TargetError
from tests.forecasting_helpers import (POPULATION, forecast_one, history_from_cases,
                                       random_walk_history)

LEVELS = np.asarray(HUB_QUANTILE_LEVELS)


def _weekly_history(weekly: list[int]):
    # each week's cases all on its last day, so the weekly sums are exactly ``weekly``
    daily = np.zeros(7 * len(weekly), dtype=np.int64)
    daily[6::7] = weekly
    return history_from_cases(daily)


def test_hub_baseline_h1_is_last_value_plus_type7_quantiles_of_symmetrized_differences():
    # weekly cases 10, 14, 12, 20: differences 4, -2, 8; symmetrized, sorted: -8 -4 -2 2 4 8.
    # type 7 on 6 points: position 5τ. τ=.01: -8+.05·4=-7.8; τ=.25: -4+.25·2=-3.5; τ=.5: 0;
    # τ=.75: 2+.75·2=3.5; τ=.99: 4+.95·4=7.8 → quantiles = 20 + those.
    fc = forecast_one(HubBaseline(), _weekly_history([10, 14, 12, 20]), (1,))
    q = dict(zip(HUB_QUANTILE_LEVELS, fc.values["cases"][0]))
    assert q[0.01] == pytest.approx(12.2) and q[0.25] == pytest.approx(16.5)
    assert q[0.5] == pytest.approx(20.0) and q[0.75] == pytest.approx(23.5)
    assert q[0.99] == pytest.approx(27.8)
    # clipped at 0: last value 5 with the same differences
    low = baseline_quantiles(5.0, np.array([4.0, -2.0, 8.0]), (1,), LEVELS, seed=0)[0]
    assert low[0] == 0.0 and low[list(HUB_QUANTILE_LEVELS).index(0.25)] == pytest.approx(1.5)


def test_hub_baseline_I_uses_one_week_differences_of_the_daily_series():
    history = random_walk_history(10, seed=3)
    fc = forecast_one(HubBaseline(), history, (1,))
    d = history.I[7:] - history.I[:-7]
    expected = np.maximum(history.I[-1] + np.quantile(np.concatenate([d, -d]), LEVELS), 0.0)
    np.testing.assert_allclose(fc.values["I"][0], expected, rtol=0, atol=1e-15)
    assert fc.values["I"][0][11] == history.I[-1]                   # median = last value


def test_hub_baseline_h2_sum_of_two_uniform_draws_is_triangular():
    # one difference 1 → symmetrized {-1, 1}: its type-7 quantile function is U(-1, 1); the sum
    # of two draws is triangular on [-2, 2]: F⁻¹(p) = -2 + 2√(2p) (p ≤ ½), 2 - 2√(2(1-p)).
    q = baseline_quantiles(100.0, np.array([1.0]), (1, 2), LEVELS, seed=7)
    p = LEVELS
    tri = np.where(p <= 0.5, -2 + 2 * np.sqrt(2 * p), 2 - 2 * np.sqrt(2 * (1 - p)))
    np.testing.assert_allclose(q[0], 100.0 + (-1 + 2 * p), atol=1e-12)
    np.testing.assert_allclose(q[1], 100.0 + tri, atol=0.02)
    assert q[1][11] == pytest.approx(100.0, abs=1e-12)              # median forced to last


def test_hub_baseline_h2_matches_exact_enumeration_on_a_tiny_difference_set():
    diffs = np.array([1.0, 3.0])                                    # symmetrized: -3 -1 1 3
    q = baseline_quantiles(50.0, diffs, (2,), LEVELS, seed=11)[0]
    u = (np.arange(2001) + 0.5) / 2001                             # exact grid enumeration
    x = np.quantile(np.concatenate([diffs, -diffs]), u)
    sums = (x[:, None] + x[None, :]).ravel()
    exact = 50.0 + np.quantile(sums - np.median(sums), LEVELS)
    np.testing.assert_allclose(q, exact, atol=0.05)
    # deterministic given the seed, different with another seed (it resamples)
    again = baseline_quantiles(50.0, diffs, (2,), LEVELS, seed=11)[0]
    other = baseline_quantiles(50.0, diffs, (2,), LEVELS, seed=12)[0]
    assert np.array_equal(q, again) and not np.array_equal(q, other)


def test_hub_baseline_rows_are_drawn_in_chunks_that_change_nothing(monkeypatch):
    """A batch drawn 3 rows at a time (memory) equals the batch drawn at once, bit for bit:
    each row has its own seed and data; row 4 alone equals its row in the batch."""
    import pipeline.members.hub_baseline as hb

    rng = np.random.default_rng(5)
    diffs = [rng.normal(0, 10, size=n) for n in (3, 9, 5, 12, 7, 4, 8)]
    last, seeds = rng.uniform(50, 500, size=7), list(range(100, 107))
    config = HubBaselineConfig(n_samples=2000)
    once = hb.baseline_quantiles_batch(last, diffs, (1, 2, 4), LEVELS, seeds, config)
    monkeypatch.setattr(hb, "CHUNK_ROWS", 3)
    chunked = hb.baseline_quantiles_batch(last, diffs, (1, 2, 4), LEVELS, seeds, config)
    assert once.shape == (7, 3, len(LEVELS))
    np.testing.assert_array_equal(chunked, once)
    np.testing.assert_array_equal(baseline_quantiles(last[4], diffs[4], (1, 2, 4), LEVELS,
                                                     seeds[4], config), once[4])


def test_hub_baseline_refuses_a_one_week_history():
    with pytest.raises(TargetError, match="needs two reported weeks"):
        forecast_one(HubBaseline(), history_from_cases(np.ones(7, dtype=np.int64)), (1,))
    with pytest.raises(TargetError, match="n_samples"):
        HubBaselineConfig(n_samples=1)


def test_autoets_quantiles_monotone_positive_and_the_model_s_own_intervals():
    from statsforecast.models import AutoETS

    history = random_walk_history(60, seed=1)
    member = AutoETSMember()
    forecast_one(member, history)                                   # imports / JIT warm-up
    t0 = time.perf_counter()
    fc = forecast_one(member, history)
    seconds = time.perf_counter() - t0
    cases = fc.values["cases"]
    assert (cases > 0).all() and (np.diff(cases, axis=1) >= 0).all()
    np.testing.assert_array_equal(fc.values["I"], cases / POPULATION)
    assert interval_levels(LEVELS) == [10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 90.0,
                                       95.0, 98.0]
    ref = AutoETS(season_length=1).forecast(y=np.log(history.weekly_cases()), h=4, level=[90])
    np.testing.assert_allclose(cases[:, 11], np.exp(ref["mean"]), rtol=1e-10)
    np.testing.assert_allclose(cases[:, 2], np.exp(ref["lo-90"]), rtol=1e-10)   # τ = 0.05
    np.testing.assert_allclose(cases[:, 20], np.exp(ref["hi-90"]), rtol=1e-10)  # τ = 0.95
    assert seconds < 0.1                  # measured ~0.006 s per origin on 2 cores


def test_a_count_forecast_gives_I_as_the_count_over_N_and_checks_its_shape():
    history = history_from_cases(np.ones(14, int), population=1000)
    count = np.tile(np.arange(23.0), (1, 2, 1))
    values = with_share(count, (history,))
    assert values["I"][0, 1, 22] == pytest.approx(0.022)
    assert np.array_equal(values["cases"], count)
    with pytest.raises(TargetError, match="cells, horizons, levels"):
        MemberForecast(np.zeros((2, 23)))
