"""Quantile functions, PIT, recalibration, weights, the combiner and the published sample paths."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import norm

import pandas as pd

from pipeline.combine.average import (EnsembleError, fit_weights, mix_quantiles, scored_wis,
                                      vincentize)
from pipeline.combine.combiner import (LOG_AVERAGE, CombineConfig, Ensemble, combine,
                                       scored_before)
from pipeline.combine.paths import count_invalid, sample_paths
from pipeline.combine.recalibration import (AggregatedTracker, IntervalTracker, calibrated_levels,
                                            fit_recalibration)
from pipeline.evaluation.quantile_function import pit_from_quantiles, quantiles_at
from pipeline.panels.targets import HUB_QUANTILE_LEVELS
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


def test_recalibration_hand_computed():
    """Φ⁻¹(τ') = μ + σΦ⁻¹(τ): bias-scale shrinks (mean, sd) of the PITs' probits towards (0, 1)
    by λ = n/(n + n0); scale uses their root mean square; widen-only never narrows."""
    probits = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])                # mean 0, sd √2.5, rms √2
    pits = norm.cdf(probits)
    regimes = np.ones(5, dtype=np.intp)
    lam = 5 / 15
    fit = fit_recalibration("bias-scale", pits, regimes, shrinkage_pits=10, min_level=1e-4)
    np.testing.assert_allclose(fit, np.tile([0.0, lam * np.sqrt(2.5) + 1 - lam], (3, 1)),
                               atol=1e-12)
    scale = fit_recalibration("scale", pits, regimes, shrinkage_pits=10, min_level=1e-4)
    assert scale[0, 1] == pytest.approx(lam * np.sqrt(2.0) + 1 - lam)
    got = calibrated_levels(LEVELS, fit[0], 1e-4)
    np.testing.assert_allclose(got, norm.cdf(fit[0, 1] * norm.ppf(LEVELS)), rtol=1e-9)
    # over-dispersed past forecasts (every PIT 0.5): widen-only keeps the levels ...
    half = np.full(10, 0.5)
    widen = fit_recalibration("widen-only", half, np.ones(10, np.intp), shrinkage_pits=10,
                              min_level=1e-4)
    np.testing.assert_allclose(calibrated_levels(LEVELS, widen[1], 1e-4), LEVELS, rtol=1e-12)
    # ... while the two-sided map narrows (towards the median)
    narrow = fit_recalibration("bias-scale", half, np.ones(10, np.intp), shrinkage_pits=10,
                               min_level=1e-4)
    narrowed = calibrated_levels(LEVELS, narrow[1], 1e-4)
    assert narrowed[0] > LEVELS[0] and narrowed[-1] < LEVELS[-1]
    # per regime: each regime's own fit, shrunk towards the pooled one
    split = fit_recalibration("bias-scale-regime", np.concatenate([pits, half]),
                              np.repeat([0, 2], [5, 10]).astype(np.intp), shrinkage_pits=0,
                              min_level=1e-4)
    assert split[0, 1] == pytest.approx(np.sqrt(2.5)) and split[2, 1] == pytest.approx(0.0)


def test_recalibration_widens_an_over_confident_forecast_and_restores_coverage():
    rng = np.random.default_rng(0)
    sigma_true, sigma_claimed = 0.5, 0.15        # the member is 3.3× too confident
    forecast = _lognormal(5.0, sigma_claimed, LEVELS)
    past_y = _lognormal(5.0, sigma_true, rng.uniform(size=200))
    past_pits = pit_from_quantiles(LEVELS, np.tile(forecast, (200, 1)), past_y)
    new_y = _lognormal(5.0, sigma_true, rng.uniform(size=2000))
    # levels may go far into the tails: σ ≈ 3.3 maps the 5 % level to Φ(−5.4)
    fit = fit_recalibration("widen-only", past_pits, np.ones(200, np.intp), shrinkage_pits=10,
                            min_level=1e-9)
    fixed = quantiles_at(LEVELS, forecast, calibrated_levels(LEVELS, fit[1], 1e-9))

    def cover90(q):
        return np.mean((q[2] <= new_y) & (new_y <= q[20]))

    assert cover90(forecast) == pytest.approx(2 * norm.cdf(1.645 * 0.3) - 1, abs=0.03)  # ≈ 0.38
    assert 0.82 <= cover90(fixed) <= 0.95
    assert (np.diff(fixed) >= 0).all()


def test_weights_hand_computed_and_equal_without_past_scores():
    one = np.array([[[[0.0, 10.0, 20.0]]], [[[0.0, 5.0, 40.0]]]])      # (M, C, n, Q) at 3 levels
    levels = np.array([0.05, 0.5, 0.95])
    truth = np.array([[10.0]])
    base_wis = scored_wis(levels, np.array([[[0.0, 20.0, 40.0]]]), truth)
    kw = dict(scale="log", shrinkage_origins=2.0, stacking_step=0.5)
    np.testing.assert_allclose(fit_weights("inverse-wis", one, truth, base_wis, levels, 0, **kw),
                               [0.5, 0.5])
    np.testing.assert_allclose(fit_weights("equal", one, truth, base_wis, levels, 5, **kw),
                               [0.5, 0.5])
    wis = scored_wis(levels, one, np.broadcast_to(truth, one.shape[:-1]))[:, 0, 0]
    skill = (base_wis[0, 0] / wis) / (base_wis[0, 0] / wis).sum()     # ∝ 1 / relative WIS
    lam = 1 / (1 + 2.0)
    np.testing.assert_allclose(fit_weights("inverse-wis", one, truth, base_wis, levels, 1, **kw),
                               lam * skill + (1 - lam) * 0.5)
    np.testing.assert_allclose(vincentize(np.array([[[1.0, 3.0]], [[3.0, 7.0]]]),
                                          np.array([0.75, 0.25])), [[1.5, 4.0]])


def test_a_cell_without_a_forecast_is_unscored_not_fatal():
    """A cell with a non-finite quantile (no member's forecast there) scores NaN, like an
    unobserved one; the other cells' WIS are unchanged (issue 49, item 7)."""
    levels = np.array([0.05, 0.5, 0.95])
    q = np.array([[0.0, 10.0, 20.0], [np.nan, np.nan, np.nan], [0.0, 5.0, np.inf],
                  [0.0, 20.0, 40.0]])
    y = np.array([10.0, 10.0, 10.0, np.nan])
    wis = scored_wis(levels, q, y)
    assert np.isnan(wis[1:]).all()
    np.testing.assert_allclose(wis[0], scored_wis(levels, q[:1], y[:1])[0])
    # by hand: (½·|10 − 10| + (0.1 / 2)·IS of the 90 % interval [0, 20], i.e. 20) / (K + ½)
    np.testing.assert_allclose(wis[0], (0.0 + 0.05 * 20.0) / 1.5)


def test_scored_before_is_the_real_time_mask_by_dates():
    """A forecast from origin o at horizon h is scored at origin t only when o + 7h ≤ t — by
    dates, so a missing week (a hub round without a vintage) counts as it should."""
    origins = pd.to_datetime(["2025-01-04", "2025-01-11", "2025-01-25", "2025-02-01"])
    known = scored_before(origins, (1, 2))
    assert known[1, :, 0].tolist() == [True, False, False, False]          # 01-04 + 7 ≤ 01-11
    assert known[2, :, 0].tolist() == [True, True, False, False]
    assert known[2, :, 1].tolist() == [True, True, False, False]           # 01-11 + 14 ≤ 01-25
    assert known[3, :, 1].tolist() == [True, True, False, False]           # 01-25 + 14 > 02-01


def test_combiner_learns_only_from_the_past_and_averages_in_logs():
    """Changing the truth of forecasts not yet scored at an origin changes nothing there."""
    rng = np.random.default_rng(3)
    levels = LEVELS
    n_o = 12
    origins = pd.date_range("2021-01-02", periods=n_o, freq="7D")
    members = {m: np.sort(np.exp(rng.normal(5 + s, 0.4, (3, n_o, 2, levels.size))), axis=-1)
               for m, s in (("a", 0.0), ("b", 0.3))}
    baseline = np.sort(np.exp(rng.normal(5.2, 0.5, (3, n_o, 2, levels.size))), axis=-1)
    truth = np.exp(rng.normal(5.1, 0.4, (3, n_o, 2)))
    regimes = np.ones((3, n_o), dtype=np.intp)
    config = CombineConfig(weights="inverse-wis", calibration="bias-scale")
    full = combine(members, baseline, truth, regimes, levels, (1, 2), origins, config)
    later = truth.copy()
    later[:, 6:] *= 3.0                  # origins 6.. are scored at origin 7 at the earliest
    changed = combine(members, baseline, later, regimes, levels, (1, 2), origins, config)
    np.testing.assert_array_equal(full.published[:, :7], changed.published[:, :7])
    assert not np.array_equal(full.published[:, 7:], changed.published[:, 7:])
    equal = combine(members, baseline, truth, regimes, levels, (1, 2), origins, LOG_AVERAGE)
    np.testing.assert_allclose(equal.published, np.expm1(
        0.5 * np.log1p(members["a"]) + 0.5 * np.log1p(members["b"])), rtol=1e-12)
    # a member missing in a cell: no published forecast there, unless the others are asked for
    gap = dict(members, b=members["b"].copy())
    gap["b"][0, 3] = np.nan
    missing = combine(gap, baseline, truth, regimes, levels, (1, 2), origins, LOG_AVERAGE)
    assert np.isnan(missing.published[0, 3]).all() and np.isfinite(missing.published[1]).all()
    reach = combine(gap, baseline, truth, regimes, levels, (1, 2), origins,
                    dataclasses.replace(LOG_AVERAGE, beyond_reach="reachable-members"))
    np.testing.assert_allclose(reach.published[0, 3], members["a"][0, 3], rtol=1e-12)


def test_stacking_reads_each_past_average_once_and_chooses_as_from_scratch():
    """The stacking's store of past averages (GridAverages) gives, at every origin, the weights
    that averaging the window's cells afresh gives (fit_weights without the store), on the
    log-mixture where a member misses some cells."""
    rng = np.random.default_rng(11)
    levels = np.asarray(HUB_QUANTILE_LEVELS)
    n_c, n_o, horizons = 4, 10, (1, 2)
    origins = pd.date_range("2021-01-02", periods=n_o, freq="7D")
    members = {m: np.sort(np.exp(rng.normal(4 + s, 0.5, (n_c, n_o, 2, levels.size))), axis=-1)
               for m, s in (("a", 0.0), ("b", 0.4), ("c", -0.3))}
    members["c"][1, 2] = np.nan                    # a cell one member did not forecast
    baseline = np.sort(np.exp(rng.normal(4.2, 0.6, (n_c, n_o, 2, levels.size))), axis=-1)
    truth = np.exp(rng.normal(4.1, 0.5, (n_c, n_o, 2)))
    config = CombineConfig(weights="stacking", stacking_step=0.25, window_origins=4,
                           beyond_reach="reachable-members")
    stored = combine(members, baseline, truth, np.ones((n_c, n_o), np.intp), levels, horizons,
                     origins, config)
    values = np.stack(list(members.values()))
    base_wis = scored_wis(levels, baseline, truth)
    known = scored_before(origins, horizons)
    for j in range(n_o):
        for k in range(len(horizons)):
            fit = np.flatnonzero(known[j, :, k])[-config.window_origins:]
            afresh = fit_weights("stacking", values[:, :, fit, k], truth[:, fit, k],
                                 base_wis[:, fit, k], levels, len(fit), scale=config.scale,
                                 shrinkage_origins=config.shrinkage_origins,
                                 stacking_step=config.stacking_step)
            np.testing.assert_allclose(stored.weights[j, k], afresh, rtol=0, atol=1e-12)
    assert (stored.weights[-1].max(axis=-1) > 1 / 3 + 0.05).all()     # it did choose


def test_mixture_of_forecasts_averages_their_cdfs():
    a, b = _lognormal(4.0, 0.3, LEVELS), _lognormal(6.0, 0.3, LEVELS)
    mixed = mix_quantiles(np.stack([a, b]), LEVELS)
    # the median of an equal mixture of two well-separated log-normals lies between them
    # in the tails one component has (almost) all the mass: F_mix = F_a / 2 there
    assert a[11] < mixed[11] < b[11]
    assert mixed[0] == pytest.approx(_lognormal(4.0, 0.3, 0.02), rel=0.03)
    assert mixed[-1] == pytest.approx(_lognormal(6.0, 0.3, 0.98), rel=0.03)


def test_an_ensemble_refuses_rules_that_need_past_scores():
    from pipeline.combine.average import EnsembleError
    from tests.forecasting_helpers import LogNormalMember

    with pytest.raises(EnsembleError, match="learn from past scores"):
        Ensemble((LogNormalMember("a", 0.3),), CombineConfig(weights="stacking"))


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


@pytest.mark.parametrize("step", ["pooled", "per-regime"])
def test_interval_tracker_moves_each_phase_by_its_misses_and_never_the_median(step: str) -> None:
    """Nine covered forecasts of one phase and one missed forecast of another, hand-computed:
    φ[r, e] += η Σ_r (miss − α_e) / N, N all ten forecasts (pooled) or the phase's own."""
    levels = np.array([0.05, 0.25, 0.5, 0.75, 0.95])
    tracker = IntervalTracker(levels, rate=0.2, outer=0.9, step=step)  # type: ignore[arg-type]
    published = np.tile([1.0, 2.0, 3.0, 4.0, 5.0], (10, 1))
    truth = np.array([3.0] * 9 + [10.0])
    regimes = np.array([0] * 9 + [2])
    tracker.update(published, truth, regimes)
    alpha = np.array([0.5, 0.1])
    n_covered, n_missed = (10, 10) if step == "pooled" else (9, 1)
    np.testing.assert_allclose(tracker.stretch[0], 0.2 * 9 * -alpha / n_covered)
    np.testing.assert_allclose(tracker.stretch[1], 0.0)
    np.testing.assert_allclose(tracker.stretch[2], 0.2 * (1 - alpha) / n_missed)
    moved = tracker.apply(published[:3], np.array([0, 1, 2]))
    np.testing.assert_allclose(moved[:, 2], 3.0)                     # the median stays
    assert moved[2, 4] > 5.0 and moved[2, 0] < 1.0                   # the missed phase widens
    assert moved[0, 4] < 5.0 and moved[0, 0] > 1.0                   # the covered one narrows
    np.testing.assert_allclose(moved[1], published[1])               # an unseen phase is kept


def test_a_standardized_tracker_moves_each_interval_in_units_of_its_own_misses() -> None:
    """The same ten forecasts as above, pooled: the inner interval (α = 0.5) moves as before,
    the outer (α = 0.1) by 0.5 / √(0.1 · 0.9) = 5/3 times as much."""
    levels = np.array([0.05, 0.25, 0.5, 0.75, 0.95])
    published = np.tile([1.0, 2.0, 3.0, 4.0, 5.0], (10, 1))
    truth = np.array([3.0] * 9 + [10.0])
    regimes = np.array([0] * 9 + [2])
    plain = IntervalTracker(levels, rate=0.2, outer=0.9)
    standard = IntervalTracker(levels, rate=0.2, outer=0.9, standardized=True)
    for tracker in (plain, standard):
        tracker.update(published, truth, regimes)
    np.testing.assert_allclose(standard.stretch[:, 0], plain.stretch[:, 0])
    np.testing.assert_allclose(standard.stretch[:, 1], plain.stretch[:, 1] * 5.0 / 3.0)
    assert plain.stretch[2, 1] == pytest.approx(0.2 * 0.9 / 10)


def test_aggregated_tracker_weighs_by_relative_wis_among_the_experts_that_cover() -> None:
    """Hand-computed: ten outcomes, three experts. The first expert's 50 % interval missed them
    all (against 50 %: beyond the 5 points allowed), so it weighs nothing however good its WIS;
    the others missed half of their 50 % and one in ten of their 90 % intervals, and weigh
    exp(−(L_e / min L − 1) / 0.01), L_e the Σ of each outcome's WIS over the experts' mean."""
    levels = np.array([0.05, 0.25, 0.5, 0.75, 0.95])
    experts = tuple(IntervalTracker(levels, rate=r, outer=0.9) for r in (0.0, 0.1, 0.2))
    agg = AggregatedTracker(experts)
    np.testing.assert_allclose(agg.weights, 1 / 3)                    # nothing known yet
    truth = np.array([3.5] * 5 + [4.5] * 4 + [7.0])
    quantiles = np.stack([np.tile(q, (10, 1)) for q in ([2.9, 2.95, 3.0, 3.05, 3.1],
                                                        [1.0, 2.0, 3.0, 4.0, 5.0],
                                                        [0.0, 1.5, 3.0, 4.4, 6.0])])
    wis = np.stack([np.full(10, 1.0), np.full(10, 1.2), np.linspace(1.1, 1.4, 10)])
    agg.update(quantiles, truth, np.zeros(10, dtype=np.intp), wis)
    loss = (wis / wis.mean(axis=0)).sum(axis=1)
    np.testing.assert_allclose(agg.loss, loss)
    assert agg.admissible.tolist() == [False, True, True]
    w = np.exp(-(loss[1:] / loss[1:].min() - 1) / 0.01)
    np.testing.assert_allclose(agg.weights, [0.0, *(w / w.sum())])
    np.testing.assert_allclose(agg.combine(quantiles[:, :1])[0], agg.weights @ quantiles[:, 0])
    # η = 0 learns nothing: its next forecast is the average's own
    np.testing.assert_allclose(agg.expert_quantiles(quantiles[1, :1], np.zeros(1, np.intp))[0],
                               quantiles[1, :1])


def test_a_calibration_that_forgets_halves_old_losses_and_lets_a_stretch_fade() -> None:
    """Hand-computed: with a half-life of 2 origins, an origin's losses and misses count half
    two origins later, and the choice among the experts is the same as if the older outcomes
    had been seen half as often; a stretch leaking 10 % an origin is 0.9ⁿ of itself after n
    origins without outcomes, and a stretch without leak stays."""
    levels = np.array([0.05, 0.25, 0.5, 0.75, 0.95])
    truth = np.array([3.5] * 5 + [4.5] * 4 + [7.0])
    quantiles = np.stack([np.tile(q, (10, 1)) for q in ([1.0, 2.0, 3.0, 4.0, 5.0],
                                                        [0.0, 1.5, 3.0, 4.4, 6.0])])
    wis = np.stack([np.full(10, 1.2), np.linspace(1.1, 1.4, 10)])
    regimes = np.zeros(10, dtype=np.intp)
    nothing = np.full(10, np.nan)
    forgets = AggregatedTracker(tuple(IntervalTracker(levels, r, 0.9) for r in (0.0, 0.1)),
                                memory_origins=2.0)
    forgets.update(quantiles, truth, regimes, wis)
    loss, missed, scored = forgets.loss.copy(), forgets.missed.copy(), forgets.scored
    for _ in range(2):
        forgets.update(quantiles, nothing, regimes, np.full_like(wis, np.nan))
    np.testing.assert_allclose(forgets.loss, loss / 2)
    np.testing.assert_allclose(forgets.missed, missed / 2)
    assert forgets.scored == pytest.approx(scored / 2)
    for leak, expected in ((0.1, 0.9 ** 3), (0.0, 1.0)):
        tracker = IntervalTracker(levels, 0.1, 0.9, leak=leak)
        tracker.stretch[:] = 0.5
        for _ in range(3):
            tracker.update(quantiles[0], nothing, regimes)
        np.testing.assert_allclose(tracker.stretch, 0.5 * expected)


def test_the_published_weights_follow_the_rules_with_a_half_life() -> None:
    """Hand-computed: two experts that both cover (half of their 50 % and one in ten of their
    90 % intervals missed). The first origin's WIS favours the first, the second origin's the
    second: with a half-life of one origin the published weights move half way from the first
    rule's weights to the second's, and three quarters of the rest of the way after two more
    origins without outcomes; without smoothing they are the rule's at once."""
    levels = np.array([0.05, 0.25, 0.5, 0.75, 0.95])
    truth = np.array([3.5] * 5 + [4.5] * 4 + [7.0])
    quantiles = np.stack([np.tile(q, (10, 1)) for q in ([1.0, 2.0, 3.0, 4.0, 5.0],
                                                        [0.0, 1.5, 3.0, 4.4, 6.0])])
    regimes = np.zeros(10, dtype=np.intp)
    first_wins = np.stack([np.full(10, 1.0), np.full(10, 1.01)])
    second_wins = np.stack([np.full(10, 1.3), np.full(10, 1.0)])

    def tracker(half_life: float | None) -> AggregatedTracker:
        return AggregatedTracker(tuple(IntervalTracker(levels, r, 0.9) for r in (0.0, 0.1)),
                                 smoothing_origins=half_life)
    followed, at_once = tracker(1.0), tracker(None)
    for agg in (followed, at_once):
        agg.update(quantiles, truth, regimes, first_wins)
    before = followed.rule_weights
    assert before[0] > 0.6                                   # the first expert leads
    np.testing.assert_allclose(followed.weights, before)     # the first weights: the rule's
    for agg in (followed, at_once):
        agg.update(quantiles, truth, regimes, second_wins)
    after = followed.rule_weights
    assert after[1] > 0.99                                   # the second leads now
    np.testing.assert_allclose(at_once.weights, after)
    np.testing.assert_allclose(followed.weights, (before + after) / 2)
    for _ in range(2):
        followed.update(quantiles, np.full(10, np.nan), regimes, np.full((2, 10), np.nan))
    np.testing.assert_allclose(followed.weights, after + (before - after) / 8)
    np.testing.assert_allclose(followed.combine(quantiles[:, :1])[0],
                               followed.weights @ quantiles[:, 0])


def test_a_stretch_in_value_space_scales_the_distances_from_the_median() -> None:
    """Hand-computed: an inner stretch of log 2 and an outer one of log 3. In value space each
    quantile's distance from the median is multiplied by e^f: 2 within the 50 % interval, 3 at
    and beyond the 90 % one, the median kept; in level space the same stretch reads the quantile
    function at other levels instead (beyond 95 %: its extrapolated tail), which on this long
    right tail moves the upper end from 30 to over 500. The published reading ("lesser") moves
    each quantile by the lesser of the two. An unknown space is refused by name."""
    levels = np.array([0.05, 0.25, 0.5, 0.75, 0.95])
    quantiles = np.array([[8.0, 9.0, 10.0, 12.0, 30.0]])
    regimes = np.zeros(1, dtype=np.intp)
    values = IntervalTracker(levels, 0.1, 0.9, space="values")
    values.stretch[:] = np.log([2.0, 3.0])
    np.testing.assert_allclose(values.apply(quantiles, regimes), [[4.0, 8.0, 10.0, 14.0, 70.0]])
    on_levels = IntervalTracker(levels, 0.1, 0.9)
    on_levels.stretch[:] = np.log([2.0, 3.0])
    stretched = on_levels.apply(quantiles, regimes)[0]
    assert stretched[2] == pytest.approx(10.0)
    assert stretched[4] > 500.0 and 5.0 < stretched[0] < 8.0
    lesser = IntervalTracker(levels, 0.1, 0.9, space="lesser")
    lesser.stretch[:] = np.log([2.0, 3.0])
    # each quantile moved by the lesser of the two: on this long right tail the upper side by
    # values (12 → 14 and 30 → 70, where levels give about 23 and 589), the lower side by levels
    # (9 → 8.29 and 8 → 5.30, where values give 8 and 4), the median kept
    np.testing.assert_allclose(lesser.apply(quantiles, regimes),
                               [[stretched[0], stretched[1], 10.0, 14.0, 70.0]])
    assert stretched[1] == pytest.approx(8.29, abs=0.01)
    with pytest.raises(EnsembleError, match="tracking_space"):
        CombineConfig(tracking_space="quantiles")  # type: ignore[arg-type]


def test_while_no_expert_covers_the_nearest_to_covering_are_published() -> None:
    """Every outcome far outside every interval: no expert is within the tolerance, and the
    published forecast is the one whose intervals missed least (in units of the tolerance: the
    wide one misses the 50 % interval always and the 90 % never), not the one with the best WIS."""
    levels = np.array([0.05, 0.25, 0.5, 0.75, 0.95])
    agg = AggregatedTracker(tuple(IntervalTracker(levels, rate=r, outer=0.9) for r in (0.0, 0.1)))
    truth = np.full(4, 20.0)
    quantiles = np.stack([np.tile([1.0, 2.0, 3.0, 4.0, 5.0], (4, 1)),
                          np.tile([1.0, 2.0, 3.0, 4.0, 25.0], (4, 1))])
    agg.update(quantiles, truth, np.zeros(4, dtype=np.intp), np.array([[1.0] * 4, [2.0] * 4]))
    # misses: narrow 100 % / 100 % (off 0.5 / 0.05 and 0.9 / 0.025), wide 100 % / 0 %
    assert agg.admissible.tolist() == [False, True]
    np.testing.assert_allclose(agg.weights, [0.0, 1.0])


@pytest.mark.parametrize("claimed", [0.4, 0.2])
def test_aggregated_calibration_keeps_a_calibrated_average_and_widens_an_overconfident_one(
        claimed: float) -> None:
    """60 places × 40 weeks of log-normal outcomes (σ = 0.4). A forecast that claims σ = 0.4
    is calibrated: the aggregate costs it under 1 % of WIS. One that claims σ = 0.2 covers its
    50 % interval about 26 % of the time: the published forecast gains WIS and coverage (its
    experts' coverage is counted from the first week, so the cold start is slow to forget)."""
    rng = np.random.default_rng(11)
    n_c, n_o = 60, 40
    origins = pd.date_range("2022-01-01", periods=n_o, freq="7D")
    centre = rng.normal(6.0, 1.0, (n_c, n_o, 1))
    member = np.expm1(centre[..., None] + claimed * norm.ppf(LEVELS))
    truth = np.expm1(centre + 0.4 * rng.standard_normal((n_c, n_o, 1)))
    regimes = np.ones((n_c, n_o), dtype=np.intp)
    config = CombineConfig(calibration="aggregated-aci", outer_interval=0.95)
    out = combine({"m": member}, member, truth, regimes, LEVELS, (1,), origins, config)
    late = slice(10, None)
    wis = {k: np.nansum(scored_wis(LEVELS, q[:, late], truth[:, late]))
           for k, q in (("published", out.published), ("uncalibrated", out.uncalibrated))}

    def cover50(q):
        y = truth[:, late]
        return np.mean((q[:, late, :, 6] <= y) & (y <= q[:, late, :, 16]))

    if claimed == 0.4:
        assert wis["published"] <= 1.01 * wis["uncalibrated"]
        assert abs(cover50(out.published) - 0.5) < 0.05
    else:
        assert cover50(out.uncalibrated) == pytest.approx(0.26, abs=0.04)
        assert wis["published"] < 0.97 * wis["uncalibrated"]
        assert cover50(out.published) > cover50(out.uncalibrated) + 0.04
