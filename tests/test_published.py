"""The published ensemble for many histories of one vintage (``pipeline.ensemble.published``):
the batched pooled growth regression against one series at a time, the log average of the
members within and beyond the flows' reach against its closed form, completions mixed per member
before the members are averaged (the weekly run's order), and the drop-N baseline batched over
places against one place at a time. Real data: the shared CDPH vintage of 2021-11-04."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from numpy.typing import NDArray
from scipy import stats

from pipeline.data.cdph import read_cdph_csv
from pipeline.ensemble.backtest import origin_seed
from pipeline.ensemble.growth_regression import (PooledGrowthMember,
                                                 pooled_growth_forecast_batch)
from pipeline.ensemble.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.ensemble.nf_finetune import REFIT_EPOCH, latest_refit_date, refit_dates
from pipeline.ensemble.nowcast import Nowcast, complete_histories
from pipeline.ensemble.nowcast_forecast import (MemberForecaster, floor_current_week, hub_weeks,
                                                mix_quantiles,
                                                nowcast_then_forecast_places,
                                                truncated_forecast, truncated_forecasts,
                                                week_sums)
from pipeline.ensemble.published import PublishedEnsemble
from pipeline.ensemble.targets import HUB_QUANTILE_LEVELS, EpiHistory, history_from_county

REPO = Path(__file__).resolve().parents[1]
LATEST = (REPO.parent / "shared" / "data" / "cdph" / "ofaye98__CSC508_Mentor_Class"
          / "covid19cases_test.csv")
COUNTIES = ("Alameda", "Fresno", "Los Angeles", "Sacramento", "San Francisco")
LEVELS = np.asarray(HUB_QUANTILE_LEVELS)
SEED = 7


@pytest.fixture(scope="module")
def pool() -> dict[str, EpiHistory]:
    """Five counties of the real vintage, less its last 14 days (as the run pools them)."""
    if not LATEST.is_file():
        pytest.fail(f"the real CDPH vintage of 2021-11-04 is expected at {LATEST}")
    vintage = read_cdph_csv(LATEST)
    last = vintage.as_of - pd.Timedelta(days=14)
    return {c: history_from_county(vintage.county(c)).up_to(last) for c in COUNTIES}


@dataclass(frozen=True)
class LogNormalFlow:
    """A four-week member with a known answer: log-normal weekly cases, median the last week's
    count × 1.1^h, log sd 0.2."""

    name: str = "flow"

    @property
    def max_horizon(self) -> int:
        return 4

    def forecast_batch(self, histories: Sequence[EpiHistory], horizons: tuple[int, ...],
                       levels: NDArray[np.float64], seed: int) -> NDArray[np.float64]:
        if max(horizons) > self.max_horizon:
            raise AssertionError(f"asked for {horizons} beyond the reach of {self.name}")
        last = np.array([h.weekly_cases()[-1] for h in histories])
        median = last[:, None] * 1.1 ** np.asarray(horizons)[None, :]
        return median[..., None] * np.exp(0.2 * stats.norm.ppf(levels))[None, None, :]


def test_batched_growth_regression_equals_one_series_at_a_time(pool):
    """Every county at three origins (the first too early for a fit: the zero-growth fallback),
    each pooled with the others but not itself, in one batch: the member's own forecasts."""
    names = list(pool)
    origins = [pd.Timestamp("2020-03-14"), pd.Timestamp("2020-06-06"), pd.Timestamp("2021-06-26")]
    cells = [(pool[c].up_to(o), i) for o in origins for i, c in enumerate(names)]
    horizons = (1, 2, 3, 4, 5, 6)
    got = pooled_growth_forecast_batch([h for h, _ in cells], list(pool.values()), horizons,
                                       LEVELS, excluded=[i for _, i in cells])
    for (history, i), batched in zip(cells, got, strict=True):
        others = tuple(pool[c] for c in names if c != names[i])
        alone = PooledGrowthMember(others).forecast(history, horizons, LEVELS, 0)
        np.testing.assert_allclose(batched, alone.values["cases"], rtol=1e-9)
    # nothing left out: the member pooled with all five (its own series twice)
    member = PooledGrowthMember(tuple(pool.values()))
    history = pool["Fresno"].up_to(origins[-1])
    np.testing.assert_allclose(member.forecast_batch([history], horizons, LEVELS, 0)[0],
                               member.forecast(history, horizons, LEVELS, 0).values["cases"],
                               rtol=1e-9)


def _members_by_hand(pool: dict[str, EpiHistory], histories: list[EpiHistory],
                     places: list[str], horizons: tuple[int, ...], baseline: HubBaseline
                     ) -> dict[str, NDArray[np.float64]]:
    growth = np.stack([PooledGrowthMember(tuple(h for c, h in pool.items() if c != p))
                       .forecast(history, horizons, LEVELS, 0).values["cases"]
                       for history, p in zip(histories, places, strict=True)])
    hub = np.stack([baseline.forecast(h, horizons, LEVELS, origin_seed(SEED, h.origin))
                    .values["cases"] for h in histories])
    return {"growth": growth, "hub": hub}


def test_published_is_the_log_average_of_its_members_within_their_reach(pool):
    """Horizons 1–6 with a four-week flow: weeks 1–4 the geometric mean of the three members'
    quantiles + 1; weeks 5–6 missing, or (reachable members) the mean of the other two."""
    origin = pd.Timestamp("2021-07-31")
    places = ["Fresno", "Alameda", "Los Angeles"]
    histories = [pool[p].up_to(origin) for p in places]
    horizons = (1, 2, 3, 4, 5, 6)
    baseline = HubBaseline(HubBaselineConfig(n_samples=2_000))
    ensemble = PublishedEnsemble((baseline, LogNormalFlow()), pool)
    assert ensemble.member_names == ("growth-qr", "hub-baseline", "flow")
    assert ensemble.full_reach == 4
    got = ensemble(histories, horizons, LEVELS, SEED, places)
    by_hand = _members_by_hand(pool, histories, places, horizons, baseline)
    flow = LogNormalFlow().forecast_batch(histories, (1, 2, 3, 4), LEVELS, 0)
    three = np.expm1((np.log1p(by_hand["growth"][:, :4]) + np.log1p(by_hand["hub"][:, :4])
                      + np.log1p(flow)) / 3)
    np.testing.assert_allclose(got[:, :4], three, rtol=1e-9)
    assert np.isnan(got[:, 4:]).all()
    wider = PublishedEnsemble((baseline, LogNormalFlow()), pool,
                              beyond_reach="reachable-members")(histories, horizons, LEVELS,
                                                                SEED, places)
    two = np.expm1((np.log1p(by_hand["growth"][:, 4:]) + np.log1p(by_hand["hub"][:, 4:])) / 2)
    np.testing.assert_allclose(wider[:, 4:], two, rtol=1e-9)
    np.testing.assert_allclose(wider[:, :4], got[:, :4], rtol=1e-12)


def _completed(history: EpiHistory, k: int, seed: int):
    """``history`` with its last 10 days completed K times (reported + Poisson(40 %))."""
    rng = np.random.default_rng(seed)
    dates = history.dates[-10:]
    observed = history.cases[-10:].astype(np.int64)
    samples = observed[None, :] + rng.poisson(0.4 * observed[None, :] + 1.0, (k, 10))
    nowcast = Nowcast(dates, observed, samples, np.full((k, 10), 0.7), history.origin)
    return complete_histories(history, nowcast)


def test_completions_are_mixed_per_member_then_averaged(pool):
    """Two counties' completions in one call: each forecast week is the log average of each
    member's mixture over that county's completions; the nowcast week the mixture of the
    completions' own counts."""
    data_date = pd.Timestamp("2021-08-04")                   # a Wednesday: origin 07-31
    completed = {p: _completed(pool[p].up_to(data_date), 12, i)
                 for i, p in enumerate(("Fresno", "Sacramento"))}
    ensemble = PublishedEnsemble((HubBaseline(HubBaselineConfig(n_samples=2_000)),
                                  LogNormalFlow()), pool)
    got = nowcast_then_forecast_places(completed, data_date, ensemble, LEVELS, SEED)
    weeks = hub_weeks(data_date)
    for place, histories in completed.items():
        members = ensemble.member_quantiles(histories.histories(up_to=weeks.origin), (1, 2, 3, 4),
                                            LEVELS, SEED, [place] * len(histories))
        # the current week (Sunday..Wednesday in the data) floored at its 4 reported days
        floored = np.stack([floor_current_week(m, histories, weeks.origin, (1, 2, 3, 4))
                            for m in members])
        mixed = np.stack([mix_quantiles(m, LEVELS) for m in floored])
        expected = np.expm1(np.log1p(np.maximum(mixed, 0.0)).mean(axis=0))
        np.testing.assert_allclose(got[place].quantiles[1:], expected, rtol=1e-9)
        if histories.reported is not None:
            assert got[place].quantiles[1, 0] >= histories.reported[-4:].sum() - 1e-6
        # the nowcast week: the mixture of the K completions' counts (point masses), whose
        # median lies between the 6th and 7th of the 12 sorted counts
        sums = np.sort(week_sums(histories, [weeks.origin])[:, 0])
        assert sums[5] <= got[place].quantiles[0, 11] <= sums[6]
        assert sums[0] - 1e-6 <= got[place].quantiles[0, 0]
        assert got[place].quantiles[0, -1] <= sums[-1] + 1e-6
    # one place alone gives the same numbers as with the other in the batch (the flow and the
    # baseline see each history alone; growth-qr's pool is the same)
    alone = nowcast_then_forecast_places({"Fresno": completed["Fresno"]}, data_date, ensemble,
                                         LEVELS, SEED)["Fresno"]
    np.testing.assert_allclose(alone.quantiles, got["Fresno"].quantiles, rtol=1e-12)


def test_drop_n_baseline_batched_over_places_equals_one_at_a_time(pool):
    data_date = pd.Timestamp("2021-09-22")
    histories = {p: pool[p].up_to(data_date) for p in ("Alameda", "Fresno", "Sacramento")}
    forecaster = MemberForecaster(HubBaseline(HubBaselineConfig(n_samples=2_000)))
    together = truncated_forecasts(histories, data_date, forecaster, LEVELS, SEED, drop_days=14)
    for place, history in histories.items():
        alone = truncated_forecast(history, data_date, forecaster, LEVELS, SEED, drop_days=14)
        np.testing.assert_allclose(together[place], alone, rtol=1e-12)
        # the hub weeks are 2..6 weeks after the drop-14 origin (Saturday 2021-09-04)
        assert together[place].shape == (5, len(LEVELS))


def test_latest_refit_date_is_the_refit_a_forecast_uses():
    for origin in pd.date_range("2021-04-03", "2021-10-02", freq="7D"):
        refit = latest_refit_date(origin, 4)
        assert refit_dates([refit], 4) == [refit]
        assert refit <= origin < refit + pd.Timedelta(days=28)
    assert latest_refit_date(REFIT_EPOCH + pd.Timedelta(days=55), 4) == \
        REFIT_EPOCH + pd.Timedelta(days=28)
