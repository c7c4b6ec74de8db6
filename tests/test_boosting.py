"""The pooled gradient-boosted quantile member (``gbqr``) against known answers: its scale is
exactly invertible, its local fit recovers a quadratic, it extrapolates a panel whose fourth-root
rates rise in straight lines, and on random walks its quantiles are the walk's normal ones."""
from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.stats import norm

from pipeline.members.boosting import (BoostingConfig, PooledBoostingMember, _local_fit,
                                       counts_of, last_finite, scaled)
from pipeline.panels.history import WeeklyHistory
from pipeline.panels.panel import Panel, panel_cells

CONFIG = BoostingConfig()


def _panel(counts: np.ndarray, population: np.ndarray) -> Panel:
    dates = pd.date_range("2022-01-08", periods=counts.shape[1], freq="7D")
    return Panel({f"p{i}": WeeklyHistory(dates, c, int(n), "wk inc flu hosp")
                  for i, (c, n) in enumerate(zip(counts, population))}, name="synthetic")


def _counts_of_z(z: np.ndarray, population: np.ndarray) -> np.ndarray:
    return (z ** 4 - CONFIG.rate_offset) * population[:, None] / 1e5


def test_the_scale_is_inverted_exactly() -> None:
    rng = np.random.default_rng(0)
    counts = rng.gamma(2.0, 300.0, size=(5, 40))
    population = np.array([5e5, 1e6, 3e6, 2e7, 3.3e8])
    block = scaled(counts, population, CONFIG)
    np.testing.assert_allclose(counts_of(block.u, block, CONFIG), counts, rtol=1e-12)
    # each place's 95th percentile of z is 1 on its own scale
    np.testing.assert_allclose(np.quantile(block.u, 0.95, axis=1), 1.0, rtol=1e-12)


def test_the_local_fit_recovers_a_quadratic_and_the_last_finite_value() -> None:
    t = np.arange(20, dtype=np.float64)
    u = np.stack([0.3 + 0.02 * t - 0.001 * t ** 2, np.full(20, 0.5)])
    fit = _local_fit(u, 6)
    # at week t the slope is the derivative there and the curvature the quadratic coefficient
    np.testing.assert_allclose(fit[0, 5:, 0], 0.02 - 0.002 * t[5:], atol=1e-12)
    np.testing.assert_allclose(fit[0, 5:, 1], -0.001, atol=1e-12)
    np.testing.assert_allclose(fit[1, 5:], 0.0, atol=1e-12)
    assert np.isnan(fit[:, :5]).all()
    values = np.array([[1.0, 2.0, np.nan], [np.nan, np.nan, np.nan], [4.0, np.nan, 5.0]])
    np.testing.assert_array_equal(last_finite(values), [2.0, 0.0, 5.0])


def test_straight_lines_on_the_fourth_root_scale_are_extrapolated() -> None:
    """Forty places whose z rises by a place's own slope each week: the median forecast is the
    line continued (the trees see every slope in training), within 3 % of the count."""
    n_p, n_w = 40, 80
    population = np.geomspace(5e5, 4e7, n_p)
    slope = np.linspace(0.002, 0.02, n_p)
    z = 0.8 + slope[:, None] * np.arange(n_w + 4)
    counts = _counts_of_z(z, population)
    panel = _panel(counts[:, :n_w], population)
    cells = panel_cells(panel, [panel.last_date], seed=0)
    levels = np.array([0.25, 0.5, 0.75])
    q = PooledBoostingMember(BoostingConfig(n_estimators=200)).forecast(
        cells, (1, 2, 3, 4), levels).count
    truth = counts[:, n_w:]
    np.testing.assert_allclose(q[..., 1], truth, rtol=0.03)


def test_random_walks_give_the_walks_normal_quantiles() -> None:
    """u = z / s a Gaussian random walk (σ = 0.02 a week) in 60 places: the 10 % and 90 %
    quantiles of the change over h weeks are ±1.2816 σ √h, within 15 % of the spread."""
    rng = np.random.default_rng(1)
    n_p, n_w, sigma = 60, 150, 0.02
    population = np.geomspace(1e6, 1e7, n_p)
    z = 1.0 + np.cumsum(rng.normal(0.0, sigma, size=(n_p, n_w)), axis=1)
    panel = _panel(_counts_of_z(z, population), population)
    cells = panel_cells(panel, [panel.last_date], seed=0)
    levels = np.array([0.1, 0.5, 0.9])
    member = PooledBoostingMember(BoostingConfig(n_estimators=200))
    horizons = (1, 4)
    q = member.forecast(cells, horizons, levels).count
    block = scaled(panel.pool("p0", panel.last_date, n_w), population, member.config)
    # the member's quantiles back on its scale: the change of u, multiplied back by s
    z_q = (q / population[:, None, None] * 1e5 + CONFIG.rate_offset) ** 0.25
    change = z_q - z[:, -1][:, None, None]
    for k, h in enumerate(horizons):
        expected = norm.ppf(0.9) * sigma * np.sqrt(h)
        half_width = (np.median(change[:, k, 2]) - np.median(change[:, k, 0])) / 2
        np.testing.assert_allclose(half_width, expected, rtol=0.15)
        assert abs(np.median(change[:, k, 1])) < 0.25 * expected
    assert block.u.shape == (n_p, n_w)
