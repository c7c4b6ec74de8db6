"""The flow-based forecast member: its multi-wave prior, its coordinates, validity, real time."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.outputs.hubverse import HUB_QUANTILE_LEVELS
from pipeline.members.nf.flow import decode_paths, stored_flow
from pipeline.members.nf.growth import (GrowthModelConfig, NFGrowthMember, build_growth_dataset,
                                        growth_targets, trailing_week_sums)
from pipeline.panels.history import EpiHistory
from tests.forecasting_helpers import forecast_one
from pipeline.systems.waves import WavePrior, simulate_waves

TINY = GrowthModelConfig(n_trajectories=120, iterations=30, batch_size=256,
                         prior=WavePrior(days=140))


def test_trailing_week_sums_by_hand() -> None:
    cases = np.arange(1, 11)                      # 1..10
    sums = trailing_week_sums(cases)
    assert np.isnan(sums[:6]).all()
    np.testing.assert_array_equal(sums[6:], [28, 35, 42, 49])   # 1+..+7, 2+..+8, ...


def test_prior_is_reproducible_and_conserves_population() -> None:
    a = simulate_waves(WavePrior(days=120), 50, seed=3)
    b = simulate_waves(WavePrior(days=120), 50, seed=3)
    np.testing.assert_array_equal(a.cases, b.cases)
    assert (a.infections >= 0).all() and (a.infections <= a.susceptible + 1e-15).all()
    assert ((a.susceptible > 0) & (a.susceptible <= 1)).all()


def test_prior_has_several_waves_at_every_level() -> None:
    """Weekly growth changes sign within trajectories, and low levels grow as often as they fall
    (the single-wave prior's "low I late means decline" is absent)."""
    ensemble = simulate_waves(WavePrior(days=400), 300, seed=0)
    weekly = trailing_week_sums(ensemble.cases)[:, 6::7]
    growth = np.diff(np.log(weekly + 0.5), axis=1)
    sign_changes = (np.diff(np.sign(growth), axis=1) != 0).sum(axis=1)
    assert np.median(sign_changes) >= 4
    level = weekly[:, :-1]
    low = (level > 50) & (level < 500)
    assert 0.35 < (growth[low] > 0).mean() < 0.65


def test_targets_decode_back_to_the_weekly_counts() -> None:
    """decode(encode(x)) = x: the coordinates lose nothing, week by week."""
    rng = np.random.default_rng(0)
    n_days, population = 120, 10_000
    cases = rng.poisson(40, size=n_days).astype(np.float64)
    susceptible = 0.9 - np.concatenate([[0.0], np.cumsum(cases)[:-1]]) / population
    sums = trailing_week_sums(cases)[None]
    origin = np.array([60])
    z = growth_targets(sums, susceptible[None], origin, population).astype(np.float64)
    paths = decode_paths(z, float(sums[0, 60]), float(susceptible[53]), float(susceptible[60]),
                         population)
    expected = sums[0, 60 + 7 * np.arange(1, 5)]
    np.testing.assert_allclose(paths[0, :, 1] * population, expected + 0.5, rtol=1e-5)


def _history(cases: np.ndarray, population: int = 873_965) -> EpiHistory:
    cumulative = np.cumsum(cases)
    infectious = trailing_week_sums(cases)
    infectious = np.where(np.isnan(infectious), cumulative, infectious) / population
    removed = (cumulative / population) - infectious
    dates = pd.date_range("2021-01-01", periods=len(cases), freq="D")
    return EpiHistory(dates, cases.astype(np.int64), 1.0 - infectious - removed, infectious,
                      removed, population)


@pytest.fixture(scope="module")
def member(tmp_path_factory: pytest.TempPathFactory) -> NFGrowthMember:
    stored = stored_flow(TINY, tmp_path_factory.mktemp("store"))
    return NFGrowthMember(stored.estimator, TINY, n_samples=400)


def test_sampled_paths_are_valid_by_construction(member: NFGrowthMember) -> None:
    rng = np.random.default_rng(1)
    cases = rng.poisson(np.linspace(50, 3000, 90)).astype(np.int64)   # a steep rise
    history = _history(cases)
    paths = member.sample_paths([history], [0])[0]
    s, i, r = paths[..., 0], paths[..., 1], paths[..., 2]
    assert paths.shape == (400, 4, 3)
    assert (s >= 0).all() and (i > 0).all() and (r >= 0).all()
    np.testing.assert_allclose(paths.sum(-1), 1.0, atol=1e-12)
    s_path = np.concatenate([np.full((400, 1), history.S[-1]), s], axis=1)
    r_path = np.concatenate([np.full((400, 1), history.R[-1]), r], axis=1)
    assert (np.diff(s_path, axis=1) <= 0).all()
    assert (np.diff(r_path, axis=1) >= -1e-15).all()


def test_forecast_sees_only_its_past(member: NFGrowthMember) -> None:
    rng = np.random.default_rng(2)
    cases = rng.poisson(np.linspace(200, 600, 120)).astype(np.int64)
    full = _history(cases)
    altered = cases.copy()
    altered[100:] *= 10
    origin = full.dates[99]
    levels = np.asarray(HUB_QUANTILE_LEVELS)
    a = forecast_one(member, full.up_to(origin), seed=5, levels=levels)
    b = forecast_one(member, _history(altered).up_to(origin), seed=5, levels=levels)
    for target in ("I", "cases"):
        np.testing.assert_array_equal(a.values[target], b.values[target])
    np.testing.assert_allclose(a.values["cases"], a.values["I"] * full.population, rtol=1e-12)
    # a cell's draws are its own: the same cell in a batch with others is the same forecast
    other = full.up_to(full.dates[80])
    both = member.sample_paths([other, full.up_to(origin)], [9, 5])
    np.testing.assert_allclose(both[1], member.sample_paths([full.up_to(origin)], [5])[0],
                               rtol=1e-5)


def test_model_store_reuses_the_trained_member(tmp_path) -> None:  # type: ignore[no-untyped-def]
    first = stored_flow(TINY, tmp_path)
    second = stored_flow(TINY, tmp_path)
    assert not first.reused and second.reused and first.key == second.key


def test_dataset_windows_are_finite_and_scale_free() -> None:
    ensemble = simulate_waves(TINY.prior, 40, seed=0)
    ds = build_growth_dataset(ensemble, TINY)
    assert bool(ds.context.isfinite().all()) and bool(ds.target.isfinite().all())
    assert float(ds.context[:, -1, 0].abs().max()) == 0.0   # the latest row is the reference
