"""Scores against hand-computed values, the pinball-loss form of WIS, and the normal CRPS."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from pipeline.evaluation.scoring import (ScoringError, interval_coverage, interval_score, pit_values,
                              quantile_score, quantiles_from_samples, weighted_interval_score)

# K = 2 central intervals: (0.1, 0.9) has α = 0.2, (0.25, 0.75) has α = 0.5; median 0.5.
LEVELS = np.array([0.1, 0.25, 0.5, 0.75, 0.9])
VALUES = np.array([1.0, 2.0, 3.0, 4.0, 5.0])


def test_wis_observation_above_every_quantile_by_hand():
    # y = 6, all quantiles below it: everything is underprediction.
    #   median term      w0 |y - m|       = 0.5 * |6 - 3|           = 1.5   (under)
    #   α=0.5, [2, 4]:   α/2 (u - l)      = 0.25 * 2                = 0.5   (dispersion)
    #                    (y - u)          = 6 - 4                   = 2.0   (under)
    #   α=0.2, [1, 5]:   α/2 (u - l)      = 0.1 * 4                 = 0.4   (dispersion)
    #                    (y - u)          = 6 - 5                   = 1.0   (under)
    #   sum = 5.4; scale 1/(K + 1/2) = 1/2.5 -> WIS = 2.16, dispersion 0.36, under 1.8, over 0.
    parts = weighted_interval_score(LEVELS, VALUES, 6.0)
    assert parts.wis == pytest.approx(2.16)
    assert parts.dispersion == pytest.approx(0.36)
    assert parts.underprediction == pytest.approx(1.8)
    assert parts.overprediction == pytest.approx(0.0)


def test_wis_observation_inside_intervals_below_median_by_hand():
    # y = 2.5: inside both intervals, below the median.
    #   median term  0.5 * |2.5 - 3| = 0.25 (over)
    #   dispersion   0.25 * 2 + 0.1 * 4 = 0.9
    #   WIS = (0.25 + 0.9) / 2.5 = 0.46; over = 0.1; dispersion = 0.36.
    parts = weighted_interval_score(LEVELS, VALUES, 2.5)
    assert parts.wis == pytest.approx(0.46)
    assert parts.overprediction == pytest.approx(0.1)
    assert parts.dispersion == pytest.approx(0.36)
    assert parts.underprediction == pytest.approx(0.0)


def test_wis_observation_below_lower_quantiles_by_hand():
    # y = 0: below everything.  over: 0.5*3 + (2-0) + (1-0) = 4.5; dispersion 0.9.
    # WIS = 5.4 / 2.5 = 2.16 (mirror image of y = 6), over = 1.8.
    parts = weighted_interval_score(LEVELS, VALUES, 0.0)
    assert parts.wis == pytest.approx(2.16)
    assert parts.overprediction == pytest.approx(1.8)


def test_wis_equals_sum_of_parts_and_pinball_form_vectorized():
    rng = np.random.default_rng(3)
    levels = np.array([0.01, 0.025, *np.round(np.arange(0.05, 0.951, 0.05), 2), 0.975, 0.99])
    assert levels.size == 23
    centers = rng.normal(size=(40, 4))
    spread = rng.uniform(0.1, 2.0, size=(40, 4, 1))
    values = centers[..., None] + spread * stats.norm.ppf(levels)
    y = rng.normal(size=(40, 4)) * 1.5
    parts = weighted_interval_score(levels, values, y)
    assert parts.wis.shape == (40, 4)
    np.testing.assert_allclose(parts.wis, parts.dispersion + parts.overprediction
                               + parts.underprediction, rtol=1e-12)
    # Pinball form: WIS = 2/(2K+1) Σ_τ QS_τ, with 2K+1 = 23 levels.
    np.testing.assert_allclose(parts.wis, 2.0 * quantile_score(levels, values, y).mean(axis=-1),
                               rtol=1e-12)
    # Unweighted IS of each pair, weighted by α/2, plus |y - m|/2, reproduces WIS.
    k = levels.size // 2
    manual = 0.5 * np.abs(y - values[..., k])
    for i in range(k):
        alpha = 2 * levels[i]
        manual = manual + alpha / 2 * interval_score(values[..., i], values[..., -1 - i], y, alpha)
    np.testing.assert_allclose(parts.wis, manual / (k + 0.5), rtol=1e-12)


def test_wis_with_many_levels_approaches_normal_crps():
    # CRPS(N(0, σ²), y) = σ [z(2Φ(z) - 1) + 2φ(z) - 1/√π], z = y/σ (Gneiting & Raftery 2007).
    sigma, y = 1.3, np.array([-2.0, 0.0, 0.4, 3.1])
    k = 400
    levels = np.arange(1, 2 * k + 2) / (2 * k + 2)
    values = np.broadcast_to(sigma * stats.norm.ppf(levels), (4, levels.size))
    z = y / sigma
    crps = sigma * (z * (2 * stats.norm.cdf(z) - 1) + 2 * stats.norm.pdf(z) - 1 / np.sqrt(np.pi))
    wis = weighted_interval_score(levels, values, y).wis
    np.testing.assert_allclose(wis, crps, rtol=0.01)


def test_interval_coverage_closed_interval_by_hand():
    levels = np.array([0.05, 0.25, 0.5, 0.75, 0.95])
    q = np.array([[0.0, 1.0, 2.0, 3.0, 4.0]] * 5)
    y = np.array([0.5, 1.0, 3.0, 3.5, 4.5])
    # 50%: [1, 3] -> 0.5 out, 1.0 in (closed), 3.0 in, 3.5 out, 4.5 out
    np.testing.assert_array_equal(interval_coverage(levels, q, y, 0.5),
                                  [False, True, True, False, False])
    # 90%: [0, 4] -> all in except 4.5
    np.testing.assert_array_equal(interval_coverage(levels, q, y, 0.9),
                                  [True, True, True, True, False])
    with pytest.raises(ScoringError, match="0.1"):
        interval_coverage(levels, q, y, 0.8)


def test_pit_by_hand_with_and_without_ties():
    samples = np.arange(10.0)  # 0..9
    # y = 4.5: 5 samples below, none equal -> F(y-) = F(y) = 0.5 for both methods.
    assert pit_values(samples, 4.5, method="mid") == pytest.approx(0.5)
    assert pit_values(samples, 4.5, method="randomized") == pytest.approx(0.5)
    tied = np.array([1.0, 2.0, 2.0, 2.0, 3.0])
    # y = 2: F(y-) = 1/5, F(y) = 4/5 -> mid 0.5; randomized lies in [0.2, 0.8].
    assert pit_values(tied, 2.0, method="mid") == pytest.approx(0.5)
    draws = pit_values(np.broadcast_to(tied, (2000, 5)), np.full(2000, 2.0), seed=1)
    assert draws.min() >= 0.2 and draws.max() <= 0.8
    assert draws.mean() == pytest.approx(0.5, abs=0.02)
    # reproducible from the seed
    np.testing.assert_array_equal(draws, pit_values(np.broadcast_to(tied, (2000, 5)),
                                                    np.full(2000, 2.0), seed=1))


def test_pit_is_uniform_for_a_calibrated_ensemble():
    rng = np.random.default_rng(7)
    samples = rng.normal(size=(3000, 200))
    y = rng.normal(size=3000)
    pit = pit_values(samples, y, seed=2)
    assert stats.kstest(pit, "uniform").pvalue > 0.01
    # an over-confident ensemble (σ = 0.5 for N(0, 1) data) piles PIT at both ends
    pit_narrow = pit_values(0.5 * samples, y, seed=2)
    assert np.mean((pit_narrow < 0.1) | (pit_narrow > 0.9)) > 0.4


def test_quantiles_from_samples_linear_interpolation():
    samples = np.arange(101.0)  # type-7 quantile at τ is exactly 100 τ
    levels = np.array([0.01, 0.25, 0.5, 0.975])
    np.testing.assert_allclose(quantiles_from_samples(samples, levels), [1.0, 25.0, 50.0, 97.5])
    batch = np.stack([samples, 2 * samples])
    assert quantiles_from_samples(batch, levels).shape == (2, 4)


@pytest.mark.parametrize("levels, values, y, match", [
    ([0.25, 0.5, 0.8], [1.0, 2.0, 3.0], 1.0, "symmetric"),
    ([0.25, 0.75], [1.0, 2.0], 1.0, "odd number"),
    ([0.25, 0.5, 0.75], [1.0, np.nan, 3.0], 1.0, "NaN"),
    ([0.25, 0.5, 0.75], [3.0, 2.0, 1.0], 1.0, "crossing"),
    ([0.25, 0.5, 0.75], [1.0, 2.0], 1.0, "levels on the last axis"),
    ([0.0, 0.5, 1.0], [1.0, 2.0, 3.0], 1.0, "strictly in"),
])
def test_bad_inputs_raise_named_errors(levels, values, y, match):
    with pytest.raises(ScoringError, match=match):
        weighted_interval_score(levels, values, y)
