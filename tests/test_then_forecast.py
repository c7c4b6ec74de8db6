"""Forecasting many histories of one vintage at once (``pipeline.nowcast.then_forecast``,
``pipeline.combine.combiner.Ensemble``): the batched pooled growth regression against one series
at a time, the log average of the members within and beyond the flows' reach against its closed
form, completions mixed per member before the members are averaged (the weekly run's order), and
the drop-N baseline batched over places against one place at a time. Real data: the shared CDPH
vintage of 2021-11-04."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from numpy.typing import NDArray
from scipy import stats

from pipeline.data.california.cdph import read_cdph_csv
from pipeline.combine.average import mix_quantiles
from pipeline.combine.combiner import LOG_AVERAGE, Ensemble
from pipeline.members.base import MemberForecast
from pipeline.members.nf.refit import REFIT_EPOCH, latest_refit_date, refit_dates
from pipeline.members.growth_regression import PooledGrowthMember
from pipeline.members.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.nowcast.completions import Nowcast, complete_histories, week_sums
from pipeline.nowcast.hub_weeks import hub_weeks
from pipeline.nowcast.mixture import floor_current_week
from pipeline.nowcast.then_forecast import (forecast_cells, nowcast_then_forecast_places,
                                            truncated_forecast, truncated_forecasts)
from pipeline.panels.history import EpiHistory, history_from_county
from pipeline.panels.panel import Cells, Panel, origin_seed
from pipeline.panels.targets import HUB_QUANTILE_LEVELS

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

    def forecast(self, cells: Cells, horizons: tuple[int, ...],
                 levels: NDArray[np.float64]) -> MemberForecast:
        if max(horizons) > self.max_horizon:
            raise AssertionError(f"asked for {horizons} beyond the reach of {self.name}")
        last = np.array([h.weekly_cases()[-1] for h in cells.histories])
        median = last[:, None] * 1.1 ** np.asarray(horizons)[None, :]
        return MemberForecast(median[..., None]
                              * np.exp(0.2 * stats.norm.ppf(levels))[None, None, :])


def _alone(member: PooledGrowthMember, pool: dict[str, EpiHistory], place: str,
           history: EpiHistory, horizons: tuple[int, ...]) -> NDArray[np.float64]:
    """``place`` forecast on its own, the other counties its references."""
    panel = Panel({place: history}, {c: h for c, h in pool.items() if c != place})
    return member.forecast(Cells.of([history], [0], [place], [panel]), horizons, LEVELS).count[0]


def test_batched_growth_regression_equals_one_series_at_a_time(pool):
    """Every county at three origins (the first too early for a fit: the zero-growth fallback),
    in one call with the five counties as the pool: the same forecasts as each county alone
    with the others as references — through the shared regression of a panel's own rows, and
    through the batched one of cells holding their own version of a place's data (a nowcast's
    completions)."""
    names = list(pool)
    panel = Panel(pool)
    member = PooledGrowthMember()
    origins = [pd.Timestamp("2020-03-14"), pd.Timestamp("2020-06-06"), pd.Timestamp("2021-06-26")]
    horizons = (1, 2, 3, 4, 5, 6)
    histories = [pool[c].up_to(o) for o in origins for c in names]
    places = [c for _ in origins for c in names]
    shared = member.forecast(Cells.of(histories, [0] * len(histories), places,
                                      [panel] * len(histories)), horizons, LEVELS).count
    own = [dataclasses.replace(h, cases=h.cases + 3) for h in histories]      # other versions
    batched = member.forecast(Cells.of(own, [0] * len(own), places, [panel] * len(own)),
                              horizons, LEVELS).count
    for b, (place, history) in enumerate(zip(places, histories, strict=True)):
        np.testing.assert_allclose(shared[b], _alone(member, pool, place, history, horizons),
                                   rtol=1e-9)
        np.testing.assert_allclose(batched[b], _alone(member, pool, place, own[b], horizons),
                                   rtol=1e-9)


def _members_by_hand(pool: dict[str, EpiHistory], histories: list[EpiHistory],
                     places: list[str], horizons: tuple[int, ...], baseline: HubBaseline
                     ) -> dict[str, NDArray[np.float64]]:
    growth = np.stack([_alone(PooledGrowthMember(), pool, p, history, horizons)
                       for history, p in zip(histories, places, strict=True)])
    hub = baseline.forecast(Cells.of(histories, [origin_seed(SEED, h.origin) for h in histories]),
                            horizons, LEVELS).count
    return {"growth": growth, "hub": hub}


def test_published_is_the_log_average_of_its_members_within_their_reach(pool):
    """Horizons 1–6 with a four-week flow: weeks 1–4 the geometric mean of the three members'
    quantiles + 1; weeks 5–6 missing, or (reachable members) the mean of the other two."""
    origin = pd.Timestamp("2021-07-31")
    places = ["Fresno", "Alameda", "Los Angeles"]
    histories = [pool[p].up_to(origin) for p in places]
    horizons = (1, 2, 3, 4, 5, 6)
    baseline = HubBaseline(HubBaselineConfig(n_samples=2_000))
    ensemble = Ensemble((PooledGrowthMember(), baseline, LogNormalFlow()), LOG_AVERAGE)
    assert ensemble.member_names == ("growth-qr", "hub-baseline", "flow")
    members = forecast_cells(ensemble, histories, places, horizons, LEVELS, SEED, Panel(pool))
    got = ensemble.combine(members)
    by_hand = _members_by_hand(pool, histories, places, horizons, baseline)
    flow = LogNormalFlow().forecast(Cells.of(histories, [0] * 3), (1, 2, 3, 4), LEVELS).count
    three = np.expm1((np.log1p(by_hand["growth"][:, :4]) + np.log1p(by_hand["hub"][:, :4])
                      + np.log1p(flow)) / 3)
    np.testing.assert_allclose(got[:, :4], three, rtol=1e-9)
    assert np.isnan(got[:, 4:]).all()
    wider = Ensemble(ensemble.members, dataclasses.replace(LOG_AVERAGE,
                                                           beyond_reach="reachable-members"))
    two = np.expm1((np.log1p(by_hand["growth"][:, 4:]) + np.log1p(by_hand["hub"][:, 4:])) / 2)
    np.testing.assert_allclose(wider.combine(members)[:, 4:], two, rtol=1e-9)
    np.testing.assert_allclose(wider.combine(members)[:, :4], got[:, :4], rtol=1e-12)


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
    ensemble = Ensemble((PooledGrowthMember(), HubBaseline(HubBaselineConfig(n_samples=2_000)),
                         LogNormalFlow()), LOG_AVERAGE)
    panel = Panel(pool)
    got = nowcast_then_forecast_places(completed, data_date, ensemble, LEVELS, SEED, panel=panel)
    weeks = hub_weeks(data_date)
    for place, histories in completed.items():
        members = forecast_cells(ensemble, histories.histories(up_to=weeks.origin),
                                 [place] * len(histories), (1, 2, 3, 4), LEVELS, SEED, panel)
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
                                         LEVELS, SEED, panel=panel)["Fresno"]
    np.testing.assert_allclose(alone.quantiles, got["Fresno"].quantiles, rtol=1e-12)


def test_drop_n_baseline_batched_over_places_equals_one_at_a_time(pool):
    data_date = pd.Timestamp("2021-09-22")
    histories = {p: pool[p].up_to(data_date) for p in ("Alameda", "Fresno", "Sacramento")}
    forecaster = HubBaseline(HubBaselineConfig(n_samples=2_000))
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
