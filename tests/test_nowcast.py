"""Nowcasting: revision pairs, the delay model on synthetic truncation with a known delay
distribution, the nowcast (never below what was reported), hub weeks, mixing, hubverse rows."""
from __future__ import annotations

import dataclasses
import datetime as dt
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import optimize, stats

from pipeline.data.california.cdph import CDPHVintage
from pipeline.data.california.delays import (DelayModelConfig, fit_delay_model, load_delay_model,
                                             save_delay_model)
from pipeline.data.california.vintage_pairs import VintagePairError, revision_pairs
from pipeline.backtest.result import QuantileForecast
from pipeline.combine.average import mix_quantiles
from pipeline.members.base import MemberForecast
from pipeline.nowcast.completions import (CompletedHistories, NowcastConfig, complete_histories,
                                          nowcast_history, week_sums)
from pipeline.nowcast.hub_weeks import hub_weeks
from pipeline.nowcast.mixture import CompletionMixture, floor_current_week, median_history
from pipeline.panels.history import EpiHistory
from pipeline.panels.targets import HUB_QUANTILE_LEVELS
from tests.forecasting_helpers import forecast_one
from pipeline.outputs.hubverse import NowcastWeek, write_model_output
from pipeline.outputs.hubverse_validation import load_tasks_config

LEVELS = np.asarray(HUB_QUANTILE_LEVELS)
MAX_LAG = 21
# the known delay distribution: P(reported at lag l), lags 0..21 (geometric-like, 3-day mean;
# the model's final count is the one at lag MAX_LAG)
TRUE_PMF = np.exp(-np.arange(MAX_LAG + 1) / 3.0)
TRUE_PMF /= TRUE_PMF.sum()
TRUE_F = np.cumsum(TRUE_PMF)
CONFIG = DelayModelConfig(max_lag=MAX_LAG, bin_edges=(*range(8), 8, 11, 14),
                          max_iterations=300)


def _synthetic_vintages(n_counties: int = 6, seed: int = 3) -> list[CDPHVintage]:
    """Counties with Poisson(400) final cases a day, each case reported after a lag drawn from
    TRUE_PMF; six vintages on different weekdays (as the real ones: else the report weekday is
    confounded with the lag) count what had arrived by their date."""
    rng = np.random.default_rng(seed)
    days = pd.date_range("2021-06-01", "2021-09-30")
    as_of = [pd.Timestamp("2021-08-20") + pd.Timedelta(days=k) for k in (0, 6, 13, 17, 24, 30)]
    final = rng.poisson(400, (n_counties, len(days)))
    arrivals = np.stack([rng.multinomial(n, TRUE_PMF) for n in final.ravel()])
    arrivals = arrivals.reshape(n_counties, len(days), MAX_LAG + 1)
    out = []
    for v in as_of:
        keep = days <= v
        lag = (v - days[keep]).days.to_numpy()
        known = np.cumsum(arrivals[:, keep], axis=2)[:, np.arange(keep.sum()),
                                                      np.minimum(lag, MAX_LAG)]
        frame = pd.DataFrame({
            "date": np.tile(days[keep], n_counties),
            "area": np.repeat([f"county {c}" for c in range(n_counties)], keep.sum()),
            "population": 500_000, "cases": known.ravel(), "deaths": 0,
            "reported_cases": 0})
        out.append(CDPHVintage(frame=frame, as_of=v, source="synthetic"))
    return out


@pytest.fixture(scope="module")
def synthetic():
    vintages = _synthetic_vintages()
    model = fit_delay_model(revision_pairs(vintages, max_lag=MAX_LAG, consecutive=True), CONFIG)
    return vintages, model


def test_revision_pairs_by_hand():
    def vintage(as_of: str, cases: list[int]) -> CDPHVintage:
        dates = pd.date_range(end=as_of, periods=len(cases))
        return CDPHVintage(pd.DataFrame({"date": dates, "area": "A", "population": 10,
                                         "cases": cases, "deaths": 0, "reported_cases": 0}),
                           pd.Timestamp(as_of), "hand")
    early = vintage("2021-01-03", [5, 3, 1])
    late = vintage("2021-01-05", [6, 2, 4, 7, 1])      # the 2nd day fell from 3 to 2
    pairs = revision_pairs([late, early], max_lag=2)
    assert pairs.lag_early.tolist() == [2, 1, 0]
    assert pairs.lag_late.tolist() == [4, 3, 2]
    assert pairs.early.tolist() == [5, 2, 1] and pairs.late.tolist() == [6, 2, 4]
    assert pairs.capped == 1
    with pytest.raises(VintagePairError, match="at least two vintages"):
        revision_pairs([early])


def test_delay_model_recovers_a_known_delay_distribution(synthetic):
    _, model = synthetic
    truth = TRUE_F[:MAX_LAG]
    # the pooled curve (a typical county, uncertain by the spread of six counties' effects)
    pooled = model.pooled_curve(300, seed=0)[:, :MAX_LAG]
    lo, hi = np.quantile(pooled, [0.05, 0.95], axis=0)
    assert ((lo <= truth) & (truth <= hi)).all(), (lo, truth, hi)
    # one county's own curve (weekday-averaged) follows that county's realised arrivals: close
    # to the generating distribution (within 0.02 at every lag; one realisation of arrivals
    # differs from the generating shares, so its interval need not hold them) and narrow
    own = model.completeness_draws(300, at=model.eras[-1], county="county 0",
                                   seed=1).mean(axis=1)[:, :MAX_LAG]
    lo, hi = np.quantile(own, [0.05, 0.95], axis=0)
    assert (hi - lo)[:7].max() < 0.08
    assert np.abs(np.median(own, axis=0) - truth).max() < 0.02


def test_delay_model_round_trips_and_refuses_another_config(synthetic, tmp_path: Path):
    _, model = synthetic
    save_delay_model(model, tmp_path / "m.npz")
    again = load_delay_model(tmp_path / "m.npz", CONFIG)
    np.testing.assert_array_equal(again.mode, model.mode)
    np.testing.assert_array_equal(again.covariance, model.covariance)
    with pytest.raises(Exception, match="another config"):
        load_delay_model(tmp_path / "m.npz", DelayModelConfig())


def _history(vintage: CDPHVintage, county: str = "county 0") -> EpiHistory:
    rows = vintage.frame[vintage.frame["area"] == county]
    cases = rows["cases"].to_numpy(np.int64)
    n = 500_000
    cumulative = np.cumsum(cases)
    week = cumulative - np.concatenate([np.zeros(7, np.int64), cumulative[:-7]])
    s = 1 - cumulative / n
    i = week / n
    return EpiHistory(pd.DatetimeIndex(rows["date"]), cases, s, i, 1 - s - i, n)


def test_nowcast_is_never_below_what_was_reported(synthetic):
    vintages, model = synthetic
    history = _history(vintages[2])
    nowcast = nowcast_history(history, model, county="county 0",
                              config=NowcastConfig(n_completions=200), seed=1)
    assert (nowcast.samples >= nowcast.observed[None, :]).all()
    # the last days were truncated, and the nowcast raises them
    assert nowcast.samples[:, -3:].mean() > 2 * nowcast.observed[-3:].mean()
    completed = complete_histories(history, nowcast)
    assert (completed.cases >= history.cases[None, :]).all()
    assert (np.diff(completed.S, axis=1) <= 1e-15).all()          # S never rises
    np.testing.assert_allclose(completed.S + completed.I + completed.R, 1.0)
    # I·N is the trailing 7-day case count, as the conversion defines it
    np.testing.assert_allclose(completed.I[:, -1] * history.population,
                               completed.cases[:, -7:].sum(axis=1))
    median = median_history(history, nowcast)
    assert (median.cases >= history.cases).all()


def test_nowcast_covers_the_final_week_count(synthetic):
    """The week ending on the vintage's last day: the final count (the latest vintage) lies
    inside the nowcast's 90 % interval for most counties."""
    vintages, model = synthetic
    inside = []
    for c in range(6):
        history = _history(vintages[2], f"county {c}")
        truth = _history(vintages[-1], f"county {c}").up_to(history.origin)
        nowcast = nowcast_history(history, model, county=f"county {c}",
                                  config=NowcastConfig(n_completions=200), seed=c)
        sums = week_sums(complete_histories(history, nowcast), [history.origin])[:, 0]
        lo, hi = np.quantile(sums, [0.05, 0.95])
        inside.append(lo <= truth.cases[-7:].sum() <= hi)
    assert np.mean(inside) >= 5 / 6


def test_hub_weeks_count_from_the_data_date():
    wednesday = hub_weeks(pd.Timestamp("2022-03-16"))
    assert wednesday.origin == pd.Timestamp("2022-03-12")
    assert wednesday.reference == pd.Timestamp("2022-03-19")
    assert [(w.horizon, w.kind, w.step) for w in wednesday.weeks] == [
        (-1, "nowcast", 0), (0, "forecast", 1), (1, "forecast", 2), (2, "forecast", 3),
        (3, "forecast", 4)]
    assert wednesday.known_days_after_origin == 4
    saturday = hub_weeks(pd.Timestamp("2022-03-19"))
    assert saturday.origin == saturday.reference == pd.Timestamp("2022-03-19")
    assert [w.kind for w in saturday.weeks] == ["nowcast", "nowcast", "forecast", "forecast",
                                                "forecast"]
    assert saturday.forecast_steps == (1, 2, 3)


def test_mixture_is_the_average_of_cdfs():
    """Two log-normal forecasts: the mixed quantiles are those of their equal mixture."""
    parts = [stats.lognorm(s=0.2, scale=100.0), stats.lognorm(s=0.3, scale=300.0)]
    q = np.stack([p.ppf(LEVELS) for p in parts])[:, None, :]           # (K=2, H=1, Q)
    mixed = mix_quantiles(q, LEVELS, n_levels=2000)[0]
    for level, value in zip(LEVELS[2:-2], mixed[2:-2], strict=True):
        exact = optimize.brentq(lambda x: np.mean([p.cdf(x) for p in parts]) - level, 1, 1e4)
        assert value == pytest.approx(exact, rel=0.02), level
    # not the average of the quantiles (Vincentization), which has no mass between the modes
    assert not np.allclose(mixed, q.mean(axis=0)[0], rtol=0.05)


def test_hub_file_fills_the_nowcast_week(tmp_path: Path):
    origin = pd.Timestamp("2022-03-12")
    rng = np.random.default_rng(0)
    cases = np.sort(rng.lognormal(6, 0.3, (200, 4)), axis=0)
    paths = np.stack([1 - cases / 1e6, cases / 1e6, np.zeros_like(cases)], axis=-1)
    forecast = QuantileForecast("published", origin, (1, 2, 3, 4), LEVELS,
                                {"cases": np.quantile(cases, LEVELS, axis=0).T,
                                 "I": np.quantile(cases, LEVELS, axis=0).T / 1e6}, paths=paths)
    week = NowcastWeek(dt.date(2022, 3, 12), np.linspace(500, 700, len(LEVELS)),
                       np.linspace(500, 700, 200))
    tasks = load_tasks_config(Path(__file__).resolve().parents[1] / "hub-config" / "tasks.json")
    submission = write_model_output(forecast, population=1e6, run_date=dt.date(2022, 3, 16),
                                    hub_dir=tmp_path, tasks=tasks, nowcasts=[week])
    assert submission.horizons == (-1, 0, 1, 2, 3)
    rows = submission.frame
    median = rows[(rows["horizon"] == -1) & (rows["output_type"] == "quantile")
                  & (rows["target"] == "wk inc case") & (rows["output_type_id"] == "0.5")]
    assert float(median["value"].iloc[0]) == pytest.approx(week.quantiles[11])
    assert not submission.omitted


def _completed(cases: np.ndarray, reported: np.ndarray,
               end: str = "2022-03-16") -> CompletedHistories:
    """K completions of a daily series ending ``end`` (S, I, R consistent enough for a member)
    and the counts as reported."""
    dates = pd.date_range(end=end, periods=cases.shape[1])
    n = 1_000_000
    cumulative = np.cumsum(cases, axis=1) / n
    return CompletedHistories(dates=dates, cases=cases.astype(np.int64), S=1.0 - cumulative,
                              I=np.full(cases.shape, 1e-4), R=cumulative - 1e-4, population=n,
                              first_nowcast_day=dates[-5], reported=reported.astype(np.int64))


def test_the_current_week_never_ends_below_what_was_reported_of_it():
    # data to Wednesday 2022-03-16; the round's origin is Saturday 2022-03-12: 4 days reported
    reported = np.array([10] * 20 + [40, 50, 30, 10])                   # 130 in the 4 days
    cases = np.stack([reported + np.array([0] * 20 + [5, 10, 20, 40]), reported])
    completed = _completed(cases, reported)
    low = np.tile(np.array([0.0, 100.0, 300.0]), (2, 4, 1))                   # (K, H, Q)
    floored = floor_current_week(low, completed, pd.Timestamp("2022-03-12"), (1, 2, 3, 4))
    np.testing.assert_array_equal(floored[:, 0], [[130.0, 130.0, 300.0]] * 2)
    np.testing.assert_array_equal(floored[:, 1:], low[:, 1:])               # later weeks as they were
    # a backtest origin a week earlier sees nothing after itself: unchanged
    np.testing.assert_array_equal(
        floor_current_week(low, completed, pd.Timestamp("2022-03-05"), (1, 2, 3, 4)), low)
    # without the reported counts there is nothing to floor at
    bare = dataclasses.replace(completed, reported=None)
    np.testing.assert_array_equal(
        floor_current_week(low, bare, pd.Timestamp("2022-03-12"), (1, 2, 3, 4)), low)


def test_the_published_current_week_is_floored_through_the_completion_mixture():
    class Zero:
        name = "zero"

        def forecast(self, cells, horizons, levels):
            return MemberForecast(np.zeros((len(cells), len(horizons), len(levels))))

    reported = np.array([10] * 20 + [50, 60, 70, 80])
    completed = _completed(np.stack([reported] * 3), reported)
    mixture = CompletionMixture(Zero(), completed, pd.Timestamp("2022-03-05"), n_mixed=3)
    latest = forecast_one(mixture, completed.history(0).up_to(pd.Timestamp("2022-03-12")),
                          (1, 2))
    np.testing.assert_allclose(latest.values["cases"][0], 260.0)
    np.testing.assert_allclose(latest.values["I"][0], 260.0 / completed.population)
    np.testing.assert_allclose(latest.values["cases"][1], 0.0)
    earlier = forecast_one(mixture, completed.history(0).up_to(pd.Timestamp("2022-03-05")),
                           (1, 2))
    np.testing.assert_allclose(earlier.values["cases"], 0.0)
