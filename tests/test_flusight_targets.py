"""FluSight's derived targets by its own definition, and the scores of a pmf, against known
answers: the rate-change bins against FluSight's own count thresholds (its ``locations.csv``),
half-open intervals and the 10-admission floor, a pmf from joint paths, the peak joined from
observed weeks and paths, and RPS / log score in closed form."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.evaluation.categorical import (CategoricalScoreError, log_score,
                                             ranked_probability_score)
from pipeline.outputs.derived_targets import (RATE_CHANGE_RULES, SEASON_WEEKS, SeasonTails,
                                              categorize, category_edges, observed_peak,
                                              peak_draws, peak_week_pmf, rate_change_pmf,
                                              rate_change_rule, season_weeks)

FLUSIGHT = Path(__file__).resolve().parents[2] / "shared" / "data" / "flusight"
RULE_2024 = RATE_CHANGE_RULES[1]


def test_rps_and_log_score_in_closed_form():
    sure = np.eye(5)[2]
    assert ranked_probability_score(sure, 2) == 0.0 and log_score(sure, 2) == 0.0
    uniform = np.full(5, 0.2)
    # F = .2 .4 .6 .8 against 1[2 <= k] = 0 0 1 1: .04 + .16 + .16 + .04
    assert ranked_probability_score(uniform, 2) == pytest.approx(0.4)
    assert log_score(uniform, 2) == pytest.approx(np.log(5))
    # one category off costs less than two (the RPS is ordinal)
    assert ranked_probability_score(sure, 3) == pytest.approx(1.0)
    assert ranked_probability_score(sure, 4) == pytest.approx(2.0)
    assert np.isinf(log_score(sure, 4))
    assert np.isnan(ranked_probability_score(np.stack([sure, sure]), [2, -1])[1])
    with pytest.raises(CategoricalScoreError, match="sum to 1"):
        ranked_probability_score(np.full(5, 0.3), 1)


def test_rate_change_bins_are_flusights_own_counts():
    """Every location's stable and large bounds of 2024-25 (and after) equal the counts
    FluSight lists in its locations.csv (``count_rate0p3`` … ``count_rate5``), to rounding."""
    table = pd.read_csv(FLUSIGHT / "locations.csv", dtype={"location": str})
    columns = {0: ("count_rate0p3", "count_rate1p7"), 1: ("count_rate0p5", "count_rate3"),
               2: ("count_rate0p7", "count_rate4"), 3: ("count_rate1", "count_rate5")}
    pop = table.population.to_numpy(dtype=float)
    for h, (stable, large) in columns.items():
        edges = category_edges(np.zeros(len(pop)), pop, h, RULE_2024)
        np.testing.assert_allclose(edges[:, 2], np.maximum(table[stable], 9.5), atol=0.5)
        np.testing.assert_allclose(edges[:, 3], np.maximum(table[large], 9.5), atol=0.5)
        np.testing.assert_allclose(edges[:, 0], -edges[:, 3])
    assert rate_change_rule(pd.Timestamp("2026-01-10")) is RULE_2024
    assert rate_change_rule(pd.Timestamp("2023-12-02")).multipliers[0] == (1.0, 2.0)


def test_categories_are_half_open_with_the_ten_admission_floor():
    # Alaska (740,133 people): 0.3/100k is 2.2 admissions, under the floor of 9.5; 1.7/100k 12.6
    edges = category_edges(np.array(100.0), np.array(740_133.0), 0, RULE_2024)
    np.testing.assert_allclose(edges, [100 - 12.582261, 90.5, 109.5, 100 + 12.582261])
    values = np.array([80.0, 87.0, 90.5, 91.0, 109.0, 110.0, 112.0, 113.0, np.nan])
    assert categorize(values, np.broadcast_to(edges, (9, 4))).tolist() == \
        [0, 0, 1, 2, 2, 3, 3, 4, -1]


def test_the_pmf_comes_from_joint_paths():
    """Paths whose base and later weeks move together: every path rises by 30, so the pmf is
    sure of 'increase' though the weeks' marginals overlap widely."""
    rng = np.random.default_rng(1)
    base = rng.uniform(100, 400, size=500)
    paths = np.stack([base, base + 10, base + 30, base + 30, base + 30], axis=1)[None]
    pmf = rate_change_pmf(paths, (-1, 0, 1, 2, 3), np.array([740_133.0]), RULE_2024,
                          pseudo_count=0.0)
    assert pmf.shape == (1, 4, 5)
    np.testing.assert_array_equal(pmf[0, 0], [0, 0, 0, 1, 0])        # +10 ≥ 10: increase
    np.testing.assert_array_equal(pmf[0, 1], [0, 0, 0, 0, 1])        # +30 > 22.2 (3/100k)
    np.testing.assert_array_equal(pmf[0, 3], [0, 0, 0, 1, 0])        # +30 < 37 (5/100k)
    assert np.isclose(pmf.sum(axis=-1), 1.0).all()
    # a half path of every category (Jeffreys): no category at 0, the sure one at 500.5/502.5
    smoothed = rate_change_pmf(paths, (-1, 0, 1, 2, 3), np.array([740_133.0]), RULE_2024)
    np.testing.assert_allclose(smoothed[0, 0], np.array([0.5, 0.5, 0.5, 500.5, 0.5]) / 502.5)


def test_peak_joins_the_observed_weeks_the_paths_and_the_tail():
    days = season_weeks(pd.Timestamp("2025-12-06"))
    assert (str(days[0].date()), str(days[-1].date()), len(days)) == \
        ("2025-11-22", "2026-05-23", SEASON_WEEKS)
    known = np.full(SEASON_WEEKS, np.nan)
    known[:3] = [50.0, 400.0, 60.0]                 # the vintage's weeks, a peak of 400 at week 1
    paths = np.array([[70.0, 80.0, 90.0, 100.0, 110.0],
                      [70.0, 300.0, 500.0, 200.0, 100.0]])
    rng = np.random.default_rng(0)
    draws = peak_draws(known, paths, [3, 4, 5, 6, 7], None, 1e6, rng)
    np.testing.assert_array_equal(draws.intensity, [400.0, 500.0])
    np.testing.assert_array_equal(draws.week, [1, 5])
    # beyond the paths, an earlier season's rest: 60 per 100k (600 here) at week 20
    rate = np.zeros((1, SEASON_WEEKS))
    rate[0, :21] = 60.0
    week = np.full((1, SEASON_WEEKS), 20)
    with_tail = peak_draws(known, paths, [3, 4, 5, 6, 7], SeasonTails(rate, week), 1e6, rng)
    np.testing.assert_array_equal(with_tail.intensity, [600.0, 600.0])
    np.testing.assert_array_equal(with_tail.week, [20, 20])
    pmf = peak_week_pmf(np.array([5, 5, 20, 20]), pseudo_count=0.1)
    assert pmf.sum() == pytest.approx(1.0)
    assert pmf[5] == pytest.approx(2.1 / (4 + 0.1 * SEASON_WEEKS))
    assert observed_peak(np.r_[known[:3], np.zeros(SEASON_WEEKS - 3)]) == (400.0, 1)
    assert observed_peak(known)[1] == -1


def test_a_share_nowcast_stays_a_share():
    """A week first released as 0 and revised to 90 % (the issue's ED share whose newest weeks
    were released as 0): the revision ratios reach far beyond 1, the nowcast's quantiles of a
    share never do."""
    from pipeline.nowcast.revisions import nowcast_weeks
    from pipeline.panels.history import WeeklyHistory
    from pipeline.panels.hub import ED_VISITS_SCALE
    from pipeline.panels.panel import Panel
    from pipeline.panels.targets import HUB_QUANTILE_LEVELS

    weeks = pd.date_range("2025-01-04", periods=30, freq="7D")
    final = np.full(30, 0.9 * ED_VISITS_SCALE)

    def vintage(n: int, newest: float) -> Panel:
        values = final[:n].copy()
        values[-1] = newest
        return Panel({p: WeeklyHistory(weeks[:n], values, ED_VISITS_SCALE, "wk inc flu prop ed "
                                       "visits", depletes=False) for p in ("06", "36")},
                     name="share", as_of=weeks[n - 1] + pd.Timedelta(days=4))

    earlier = [vintage(n, 0.0) for n in range(10, 29)]          # every newest week a 0
    now = vintage(30, 0.5 * ED_VISITS_SCALE)
    nowcast = nowcast_weeks(now, earlier, np.asarray(HUB_QUANTILE_LEVELS))
    q = nowcast.quantiles["06"]
    assert np.isfinite(q).all() and q.max() == ED_VISITS_SCALE      # a share of at most 1
    assert (nowcast.panel.histories["06"].cases <= ED_VISITS_SCALE).all()
