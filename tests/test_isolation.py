"""Failure isolation in the engine: the guard around every member (an exception, non-finite or
crossing quantiles, a time limit), the combiner averaging the members left (the hub baseline
the floor), and a backtest with a failing member equal, cell for cell, to the backtest without
it; nf-real's refits falling back when one diverges."""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import pandas as pd
import pytest

from pipeline.backtest.config import BacktestConfig

from pipeline.backtest.backtest import OneVintage, run_backtest
from pipeline.combine.combiner import PUBLISHED, UNCALIBRATED, CombineConfig, combine
from pipeline.members.base import MemberForecast
from pipeline.members.isolation import guarded_forecast, invalid_cells
from pipeline.panels.panel import Panel, weekly_origins
from tests.forecasting_helpers import LogNormalMember, random_walk_history

LEVELS = np.array([0.05, 0.25, 0.5, 0.75, 0.95])


@dataclasses.dataclass(frozen=True)
class Broken:
    """A member that fails the way it is told to: ``raise``, ``nan`` (every other cell),
    ``horizon`` (every other cell: no forecast at all at its furthest horizon, which it
    reaches), ``cross`` (every third cell's quantiles reversed) or ``slow``."""

    how: str
    inner: LogNormalMember = LogNormalMember("inner", 0.2)
    name: str = "broken"

    def forecast(self, cells, horizons, levels):  # noqa: ANN001, ANN201
        if self.how == "raise":
            raise ZeroDivisionError("injected")
        if self.how == "slow":
            time.sleep(0.3)
        count = self.inner.forecast(cells, horizons, levels).count.copy()
        if self.how == "nan":
            count[::2, 1, 2] = np.nan
        if self.how == "horizon":
            count[::2, -1, :] = np.nan
        if self.how == "cross":
            count[::3] = count[::3, :, ::-1]
        return MemberForecast(count)


def _cells_of(history, n=6):  # noqa: ANN001, ANN202
    from pipeline.panels.panel import Cells, origin_seed

    origins = list(history.dates[-(7 * n)::7])[:n]
    panel = Panel({"place": history})
    return Cells(tuple(history.up_to(o) for o in origins), ("place",) * n, (panel,) * n,
                 tuple(origin_seed(0, o) for o in origins))


def test_the_guard_names_each_failure_and_keeps_the_good_cells():
    cells = _cells_of(random_walk_history(80, seed=1))
    raised = guarded_forecast(Broken("raise"), cells, (1, 2), LEVELS, None)
    assert raised.forecast is None and raised.failed.all()
    assert raised.why == "raised ZeroDivisionError: injected"
    nan = guarded_forecast(Broken("nan"), cells, (1, 2), LEVELS, None)
    assert nan.failed.tolist() == [True, False] * 3
    assert nan.why == "non-finite quantiles in 3 cell(s)"
    assert nan.forecast is not None and np.isnan(nan.forecast.count[nan.failed]).all()
    good = Broken("ok").forecast(cells, (1, 2), LEVELS).count
    np.testing.assert_array_equal(nan.forecast.count[~nan.failed], good[~nan.failed])
    crossed = guarded_forecast(Broken("cross"), cells, (1, 2), LEVELS, None)
    assert crossed.failed.tolist() == [True, False, False] * 2
    assert crossed.why == "crossing quantiles in 2 cell(s)"
    slow = guarded_forecast(Broken("slow"), cells, (1, 2), LEVELS, 0.05)
    assert slow.forecast is None and slow.why.startswith("raised MemberTimeoutError: ran past "
                                                         "its time limit of 0.05 s")


def test_a_horizon_beyond_reach_is_not_a_failure():
    count = np.tile(np.arange(5.0), (2, 3, 1))
    count[:, 2] = np.nan                          # a flow's horizon beyond its reach
    failed, why = invalid_cells(count)
    assert not failed.any() and why == ""
    count[1, 0, 3] = np.inf
    assert invalid_cells(count)[0].tolist() == [False, True]
    # within the reach the member declares, an all-NaN horizon is a failure, not its reach
    failed, why = invalid_cells(count, np.array([True, True, True]))
    assert failed.tolist() == [True, True] and why == "non-finite quantiles in 2 cell(s)"
    assert not invalid_cells(count[:1], np.array([True, True, False]))[0].any()


def test_a_member_without_a_forecast_at_a_horizon_it_reaches_is_dropped_not_fatal():
    """Issue 49, item 7: the only member returns no forecast (all NaN) at its furthest horizon
    in every other cell. Taken for "beyond reach", the cells had no forecast, and once their
    weeks ended the online calibration's scorer failed the whole run (``ScoringError: quantile
    values contain NaN or inf``, naming no member). Now the member is named as failed there
    and the hub baseline stands in: every published cell is finite."""
    history = random_walk_history(70, seed=3, sigma=0.3)
    origins = weekly_origins(history.dates, scored_only=False)[-12:]
    config = BacktestConfig(horizons=(1, 2, 3), combine=CombineConfig(
        beyond_reach="reachable-members", calibration="aggregated-aci"))
    result = run_backtest(OneVintage(Panel({"place": history})), [Broken("horizon")], origins,
                          config)
    failure = result.failures["broken"]
    assert failure.why == "non-finite quantiles in 6 cell(s)"
    assert failure.cells[0].tolist() == [True, False] * 6
    published = result.forecasts[result.panel.count_target][PUBLISHED].values
    assert published.shape == (1, 12, 3, 23) and np.isfinite(published).all()


def test_the_combiner_averages_the_members_left_and_the_baseline_is_the_floor():
    """Two members, log scale, no recalibration: where one failed the average is the other
    exactly; where both failed, the baseline; nowhere else changed."""
    rng = np.random.default_rng(0)
    shape = (3, 4, 2)                                            # C, O, H
    base = np.sort(rng.uniform(10, 50, (*shape, 5)), axis=-1)
    a, b = base * 1.5, base * 0.7
    truth = np.full(shape, np.nan)
    regimes = np.zeros(shape[:2], dtype=np.intp)
    origins = list(pd.date_range("2025-01-04", periods=4, freq="7D"))
    config = CombineConfig(scale="log", calibration="none")
    dropped_b = np.zeros(shape[:2], dtype=bool)
    dropped_b[0, 1] = dropped_b[2, 3] = True
    b_failed = np.where(dropped_b[..., None, None], np.nan, b)
    a_failed = a.copy()
    a_failed[2, 3] = np.nan
    dropped_a = np.zeros(shape[:2], dtype=bool)
    dropped_a[2, 3] = True
    plain = combine({"a": a, "b": b}, base, truth, regimes, LEVELS, (1, 2), origins, config)
    got = combine({"a": a_failed, "b": b_failed}, base, truth, regimes, LEVELS, (1, 2), origins,
                  config, dropped={"a": dropped_a, "b": dropped_b})
    np.testing.assert_allclose(got.published[0, 1], a[0, 1], rtol=1e-12)   # b left out
    np.testing.assert_allclose(got.published[2, 3], base[2, 3], rtol=1e-12)  # both: the floor
    keep = ~(dropped_a | dropped_b)
    np.testing.assert_allclose(got.published[keep], plain.published[keep], rtol=1e-12)
    # "missing" (a flow's reach) still leaves a cell without a forecast when a member has
    # none there, but not when it failed there
    missing = dataclasses.replace(config, beyond_reach="missing")
    got = combine({"a": a, "b": b_failed}, base, truth, regimes, LEVELS, (1, 2), origins,
                  missing, dropped={"b": dropped_b})
    np.testing.assert_allclose(got.published[0, 1], a[0, 1], rtol=1e-12)
    unreached = combine({"a": a, "b": b_failed}, base, truth, regimes, LEVELS, (1, 2), origins,
                        missing)
    assert np.isnan(unreached.published[0, 1]).all()


@pytest.mark.parametrize("how", ["raise", "nan", "horizon", "cross"])
def test_a_failing_member_leaves_the_backtest_of_the_others_unchanged(how):
    """The published forecast with a failing member is, cell for cell, the one without it
    where it failed (and the failures are named on the result)."""
    history = random_walk_history(70, seed=3, sigma=0.3)
    origins = weekly_origins(history.dates, scored_only=False)[-12:]
    data = OneVintage(Panel({"place": history}))
    config = BacktestConfig(combine=CombineConfig(beyond_reach="reachable-members"))
    good = [LogNormalMember("wide", 0.4), LogNormalMember("narrow", 0.1)]
    alone = run_backtest(data, good, origins, config)
    broken = Broken(how, LogNormalMember("inner", 0.25))
    both = run_backtest(data, [*good, broken], origins, config)
    failure = both.failures["broken"]
    expected = {"raise": "raised ZeroDivisionError: injected",
                "nan": "non-finite quantiles in 6 cell(s)",
                "horizon": "non-finite quantiles in 6 cell(s)",
                "cross": "crossing quantiles in 4 cell(s)"}[how]
    assert failure.why == expected and failure.cells.shape == (1, 12)
    cells = failure.cells[0]
    count = both.panel.count_target
    for name in (PUBLISHED, UNCALIBRATED):
        if how == "raise":                          # left out everywhere: the same backtest
            np.testing.assert_allclose(both.forecasts[count][name].values,
                                       alone.forecasts[count][name].values, rtol=1e-12)
        else:                                       # at the cells it failed, before any score
            first = int(np.flatnonzero(cells)[0])
            np.testing.assert_allclose(both.forecasts[count][name].values[0, first],
                                       alone.forecasts[count][name].values[0, first],
                                       rtol=1e-12)
    assert np.isfinite(both.forecasts[count][PUBLISHED].values).all()


def test_a_diverged_refit_falls_back_to_the_one_before(monkeypatch):
    """nf-real: a refit date whose fine-tuning diverges is left out, recorded, and its origins
    forecast by the previous refit (the base flow before the first)."""
    from pipeline.errors import TrainingDivergedError
    from pipeline.members.nf import real as ft

    calls = []

    def fake(base, train_ds, val_ds, config):  # noqa: ANN001, ANN202
        calls.append(len(calls))
        if len(calls) == 2:
            raise TrainingDivergedError("validation NLL 30.64 at iteration 240 diverged")
        return f"model {len(calls)}"

    monkeypatch.setattr(ft, "refit_copy", fake)
    monkeypatch.setattr(ft, "refit_windows", lambda *a: ("train", "val"))
    dates = list(pd.date_range("2025-01-04", periods=3, freq="28D"))
    member = ft.fit_finetuned_member(_FakeFlow(), None, [], dates,  # type: ignore[arg-type]
                                     ft.FineTuneConfig(), None, known_at=lambda d: [])
    assert list(member.models) == [dates[0], dates[2]]
    assert member.fallbacks == {dates[1]: "validation NLL 30.64 at iteration 240 diverged; "
                                          "forecasts from the refit of 2025-01-04 instead"}
    assert member.refit_for(dates[1] + pd.Timedelta(days=7)) == dates[0]


@dataclasses.dataclass(frozen=True)
class _FakeFlow:
    estimator: object = None


def test_only_what_changes_the_submission_degrades_a_round():
    """A target or a published member left out (or the refit of a published member replaced)
    degrades the round; nf-real's refit replaced while nf-real is scored beside the hub's
    average, or a location the gate left out, is named in ``dropped`` but does not."""
    from pipeline.hub_round.run import HubRun, HubRunConfig
    from pipeline.members.isolation import Dropped

    hosp, ed = "wk inc covid hosp", "wk inc covid prop ed visits"
    config = HubRunConfig.of_preset("tiny")
    assert "nf-real" not in (*config.members.published, *config.members.published_share)

    from pipeline.members.published import published_names

    # the plan each target's members carry (HubMembers.planned): asked once, at build time
    planned = {t: published_names(config.members, t, refitted=True) for t in (hosp, ed)}

    def run(*dropped: Dropped) -> HubRun:
        return HubRun(config, {}, {}, "", True, {}, dropped, planned=planned)

    beside = Dropped("refit", hosp, "nf-real 2025-09-20", "diverged; the refit of 2025-08-23 "
                     "instead")
    gate = Dropped("location", ed, "72", "no week in the last 8")
    # the weekly flow is scored beside admissions' average (nf-context + gbqr), not in it
    flow = Dropped("member", hosp, "nf-weekly", "raised RuntimeError: injected failure")
    quiet = run(beside, gate, flow)
    assert not quiet.degraded and quiet.degraded_message() == ""
    boosting = Dropped("member", hosp, "gbqr", "raised RuntimeError: injected failure")
    stale = Dropped("target", ed, ed, "no current release")
    degraded = run(beside, boosting, gate, stale)
    assert degraded.degraded
    assert degraded.degraded_message() == (
        f"target {ed}: no current release; member gbqr ({hosp}): raised RuntimeError: "
        "injected failure")
