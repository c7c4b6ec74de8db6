"""Quantile functions, PIT, recalibration, ensemble weights and the published sample paths."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm

from pipeline.outputs.hubverse import HUB_QUANTILE_LEVELS
from pipeline.ensemble.calibration import (CalibrationConfig, pit_from_quantiles, quantiles_at,
                                              recalibrated_levels, recalibrate)
from pipeline.ensemble.combine import (EnsembleConfig, count_invalid, sample_paths,
                                           skill_weights, vincentize)
from tests.forecasting_helpers import POPULATION, random_walk_history

LEVELS = np.asarray(HUB_QUANTILE_LEVELS)


def _lognormal(mu: float, sigma: float, p) -> np.ndarray:
    return np.expm1(mu + sigma * norm.ppf(p))


def test_quantile_function_and_pit_are_exact_for_a_log_normal_in_log1p():
    q = _lognormal(6.0, 0.4, LEVELS)
    far = np.array([0.001, 0.3, 0.5, 0.999])
    np.testing.assert_allclose(quantiles_at(LEVELS, q, far), _lognormal(6.0, 0.4, far),
                               rtol=1e-10)
    y = _lognormal(6.0, 0.4, far)
    np.testing.assert_allclose(pit_from_quantiles(LEVELS, np.tile(q, (4, 1)), y), far,
                               rtol=1e-9)
    # the same forecast of I = cases/N gives the same PIT with unit N
    np.testing.assert_allclose(pit_from_quantiles(LEVELS, np.tile(q, (4, 1)) / POPULATION,
                                                  y / POPULATION, unit=POPULATION), far,
                               rtol=1e-9)
    # ties (quantiles clipped at 0): the middle of the tied levels
    tied = np.maximum(q - q[5], 0.0)              # levels 0.01 .. 0.20 are 0
    assert pit_from_quantiles(LEVELS, tied, np.array(0.0)) == pytest.approx((0.01 + 0.20) / 2)


def test_recalibrated_levels_hand_computed():
    np.testing.assert_array_equal(recalibrated_levels(LEVELS, []), LEVELS)
    # 10 PITs all 0.5, n0 = 10 → λ = ½; R⁻¹ is linear from (0, 0) to (1/11, 0.5), flat at 0.5
    # up to 10/11, then linear to (1, 1). τ = 0.05: R⁻¹ = 0.275 → Φ(½Φ⁻¹(0.275) + ½Φ⁻¹(0.05));
    # τ = 0.25: R⁻¹ = 0.5 → Φ(½·0 + ½Φ⁻¹(0.25)).
    empirical = CalibrationConfig(method="empirical", window=None, widen_only=False)
    got = recalibrated_levels(LEVELS, np.full(10, 0.5), empirical)
    assert got[2] == pytest.approx(norm.cdf(0.5 * norm.ppf(0.275) + 0.5 * norm.ppf(0.05)))
    assert got[11] == pytest.approx(0.5)
    assert got[6] == pytest.approx(norm.cdf(0.5 * norm.ppf(0.25)))
    assert (np.diff(got) > 0).all()               # strictly increasing: quantiles never cross


def test_probit_normal_recalibration_hand_computed():
    """Φ⁻¹(τ') = λσΦ⁻¹(τ) + (1 − λ)Φ⁻¹(τ), σ the sd of the PITs' probits, λ = n/(n + n0)."""
    pits = norm.cdf(np.array([-2.0, -1.0, 0.0, 1.0, 2.0]))      # probit sd = √2.5
    lam = 5 / 15
    sigma = np.sqrt(2.5)
    got = recalibrated_levels(LEVELS, pits)
    expected = norm.cdf((lam * sigma + 1 - lam) * norm.ppf(LEVELS))
    np.testing.assert_allclose(got, expected, rtol=1e-9)
    # over-dispersed past forecasts (every PIT 0.5): the default never narrows ...
    np.testing.assert_allclose(recalibrated_levels(LEVELS, np.full(10, 0.5)), LEVELS, rtol=1e-12)
    # ... while the two-sided map would (towards the median), bias term included
    both = CalibrationConfig(widen_only=False)
    narrowed = recalibrated_levels(LEVELS, np.full(10, 0.5), both)
    assert narrowed[0] > LEVELS[0] and narrowed[-1] < LEVELS[-1]
    # only the last ``window`` PITs count
    recent = recalibrated_levels(LEVELS, np.concatenate([np.full(60, 0.5), pits]),
                                 CalibrationConfig(window=5))
    np.testing.assert_allclose(recent, expected, rtol=1e-9)


def test_recalibration_widens_an_over_confident_forecast_and_restores_coverage():
    rng = np.random.default_rng(0)
    sigma_true, sigma_claimed = 0.5, 0.15        # the member is 3.3× too confident
    forecast = _lognormal(5.0, sigma_claimed, LEVELS)
    past_y = _lognormal(5.0, sigma_true, rng.uniform(size=200))
    past_pits = pit_from_quantiles(LEVELS, np.tile(forecast, (200, 1)), past_y)
    new_y = _lognormal(5.0, sigma_true, rng.uniform(size=2000))
    fixed = recalibrate(LEVELS, forecast, past_pits)

    def cover90(q):
        return np.mean((q[2] <= new_y) & (new_y <= q[20]))

    assert cover90(forecast) == pytest.approx(2 * norm.cdf(1.645 * 0.3) - 1, abs=0.03)  # ≈ 0.38
    assert 0.82 <= cover90(fixed) <= 0.95
    assert (np.diff(fixed) >= 0).all()


def test_skill_weights_hand_computed_and_equal_without_past_scores():
    np.testing.assert_allclose(skill_weights(np.empty((0, 3))), [1 / 3] * 3)
    # WIS 1 and 2 at two past origins: inverse-WIS weights 2/3, 1/3; n = 2, n0 = 4 → λ = 1/3:
    # w = 1/3·(2/3, 1/3) + 2/3·(1/2, 1/2) = (5/9, 4/9)
    w = skill_weights(np.array([[1.0, 2.0], [1.0, 2.0]]),
                      EnsembleConfig(weighting="skill", shrinkage_origins=4))
    np.testing.assert_allclose(w, [5 / 9, 4 / 9])
    # the published weighting is equal whatever the past scores
    np.testing.assert_allclose(skill_weights(np.array([[1.0, 2.0], [1.0, 2.0]])), [0.5, 0.5])
    # rows with a missing member are ignored; only the last ``window`` rows count
    w2 = skill_weights(np.array([[9.0, 1.0], [np.nan, 1.0], [1.0, 2.0], [1.0, 2.0]]),
                       EnsembleConfig(weighting="skill", window=2, shrinkage_origins=4))
    np.testing.assert_allclose(w2, [5 / 9, 4 / 9])
    np.testing.assert_allclose(vincentize(np.array([[[1.0, 3.0]], [[3.0, 7.0]]]),
                                          np.array([0.75, 0.25])), [[1.5, 4.0]])


def test_published_paths_are_valid_by_construction_and_invalid_ones_are_counted():
    history = random_walk_history(12, seed=5)
    cases = np.stack([_lognormal(np.log(300 * k), 0.6, LEVELS) for k in (1, 2, 4, 8)])
    paths = sample_paths(history, LEVELS, cases, 400)
    start = np.array([history.S[-1], history.I[-1], history.R[-1]])
    assert count_invalid(paths, start).total == 0
    np.testing.assert_allclose(paths.sum(axis=-1), 1.0, atol=1e-12)
    # comonotone: the path with the k-th smallest case count is the k-th at every horizon
    order = np.argsort(paths[:, :, 1], axis=0)
    assert (order == order[:, :1]).all()
    # a forecast far beyond the population exhausts S exactly: S = 0, still valid
    huge = np.full((4, LEVELS.size), 10.0 * POPULATION)
    burnt = sample_paths(history, LEVELS, huge, 10)
    assert (burnt[:, :, 0] == 0).all() and count_invalid(burnt, start).total == 0
    # ensemble copula coupling follows a template's ranks
    template = np.random.default_rng(1).uniform(size=(400, 4, 3))
    ecc = sample_paths(history, LEVELS, cases, 400, template_paths=template)
    assert (np.argsort(ecc[:, 0, 1]) == np.argsort(template[:, 0, 1])).all()
    assert count_invalid(ecc, start).total == 0
    # the counter itself: one S increase, one R decrease, one negative fraction
    bad = paths[:2].copy()
    bad[0, 2, 0] = bad[0, 1, 0] + 1e-3
    bad[1, 3, 2] = bad[1, 2, 2] - 1e-3
    bad[1, 0, 1] = -1e-6
    counts = count_invalid(bad, start, rates=np.array([0.2, -0.1]))
    assert counts.to_dict() == {"negative_fractions": 1, "s_increases": 1, "r_decreases": 1,
                                "negative_rates": 1, "total": 4}
