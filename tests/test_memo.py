"""The forecast memo (pipeline.ensemble.memo): a forecast read back is the forecast made, bit for
bit, and anything it depends on changes its key."""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pytest

from pipeline.ensemble.backtest import BacktestConfig, run_realtime_backtest
from pipeline.ensemble.growth_regression import PooledGrowthMember
from pipeline.ensemble.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.ensemble.memo import ForecastMemo
from pipeline.fingerprint import fingerprint
from pipeline.ensemble.nf_member import GrowthModelConfig, NFGrowthMember, \
    train_or_reuse_growth_model
from pipeline.ensemble.targets import EpiHistory, HUB_QUANTILE_LEVELS
from tests.forecasting_helpers import LogNormalMember, random_walk_history

LEVELS = np.asarray(HUB_QUANTILE_LEVELS)
TINY_FLOW = GrowthModelConfig(n_trajectories=120, iterations=30, batch_size=256,
                              hidden_features=16, flow_layers=2, flow_hidden=16)


@dataclasses.dataclass(frozen=True)
class CountingMember:
    """LogNormalMember that counts its forecasts (a hit must not reach it); the private
    counter is not part of the member's fingerprint."""

    inner: LogNormalMember
    _calls: list[int] = dataclasses.field(default_factory=list, compare=False)

    @property
    def calls(self) -> list[int]:
        return self._calls

    @property
    def name(self) -> str:
        return self.inner.name

    def forecast(self, history, horizons, levels, seed):
        self.calls.append(1)
        return self.inner.forecast(history, horizons, levels, seed)


def _revised(history: EpiHistory, day: int, delta: int) -> EpiHistory:
    cases = history.cases.copy()
    cases[day] += delta
    return dataclasses.replace(history, cases=cases)


def test_a_hit_returns_the_stored_forecast_and_skips_the_member(tmp_path: Path) -> None:
    history = random_walk_history(30, seed=1)
    member = CountingMember(LogNormalMember("lognormal", 0.3))
    first = ForecastMemo.load(tmp_path / "memo.npz")
    made = first.wrap(member).forecast(history, (1, 2, 3, 4), LEVELS, 7)
    first.save()
    again = ForecastMemo.load(tmp_path / "memo.npz")
    read = again.wrap(member).forecast(history, (1, 2, 3, 4), LEVELS, 7)
    assert len(member.calls) == 1 and (again.hits, again.misses) == (1, 0)
    assert read.forecaster == made.forecaster and read.origin == made.origin
    assert read.horizons == made.horizons and np.array_equal(read.levels, made.levels)
    for target in ("I", "cases"):
        assert np.array_equal(read.values[target], made.values[target])


@pytest.mark.parametrize("change", ["revised count", "one more day", "seed", "member setting",
                                    "levels"])
def test_whatever_the_forecast_depends_on_changes_the_key(tmp_path: Path, change: str) -> None:
    history = random_walk_history(30, seed=2)
    member = CountingMember(LogNormalMember("lognormal", 0.3))
    memo = ForecastMemo.load(tmp_path / "memo.npz")
    memo.wrap(member).forecast(history, (1, 2), LEVELS, 7)
    other_member, other_history, seed, levels = member, history, 7, LEVELS
    if change == "revised count":
        other_history = _revised(history, len(history) - 20, 1)
    elif change == "one more day":
        other_history = random_walk_history(31, seed=2).up_to(history.dates[-1]
                                                               + np.timedelta64(1, "D"))
    elif change == "seed":
        seed = 8
    elif change == "member setting":
        other_member = CountingMember(LogNormalMember("lognormal", 0.31), member.calls)
    else:
        levels = LEVELS[1:-1]
    memo.wrap(other_member).forecast(other_history, (1, 2), levels, seed)
    assert (memo.hits, memo.misses) == (0, 2) and len(member.calls) == 2


def test_the_code_is_part_of_the_key(tmp_path: Path, monkeypatch) -> None:
    import pipeline.ensemble.memo as memo_module

    member = LogNormalMember("lognormal", 0.3)
    before = ForecastMemo.load(tmp_path / "m.npz").wrap(member).member_key
    monkeypatch.setattr(memo_module, "code_fingerprint", lambda: "another version")
    assert ForecastMemo.load(tmp_path / "m.npz").wrap(member).member_key != before


def test_model_weights_are_part_of_the_key(tmp_path: Path) -> None:
    stored = train_or_reuse_growth_model(TINY_FLOW, tmp_path / "store")
    member = NFGrowthMember(stored.estimator, TINY_FLOW, n_samples=50)
    key = fingerprint(member)
    with np.errstate(all="ignore"):
        first = next(stored.estimator.parameters())
        first.data[(0,) * first.dim()] += 1e-6
    assert fingerprint(member) != key


def test_an_unreadable_memo_is_reported_and_replaced(tmp_path: Path, caplog) -> None:
    path = tmp_path / "memo.npz"
    path.write_bytes(b"not an npz file")
    with caplog.at_level(logging.WARNING):
        memo = ForecastMemo.load(path)
    assert "unreadable" in caplog.text and len(memo) == 0
    memo.wrap(LogNormalMember("lognormal", 0.3)).forecast(random_walk_history(20, 3), (1,),
                                                          LEVELS, 0)
    memo.save()
    assert len(ForecastMemo.load(path)._stored) == 1


def test_the_file_keeps_only_what_the_last_run_used(tmp_path: Path) -> None:
    path = tmp_path / "memo.npz"
    member = LogNormalMember("lognormal", 0.3)
    history = random_walk_history(30, seed=4)
    memo = ForecastMemo.load(path)
    for n_days in (150, 200):
        memo.wrap(member).forecast(history.up_to(history.dates[n_days]), (1,), LEVELS, 0)
    memo.save()
    later = ForecastMemo.load(path)
    later.wrap(member).forecast(history.up_to(history.dates[200]), (1,), LEVELS, 0)
    assert later.changed
    later.save()
    assert len(ForecastMemo.load(path)._stored) == 1


def test_a_memoized_backtest_equals_the_plain_one_bit_for_bit(tmp_path: Path) -> None:
    """Hub baseline (its own random draws), growth-qr pooled over other places, and a flow
    with sample paths: the backtest with a cold memo, with a warm one and without one agree in
    every quantile and path; the warm run forecasts nothing."""
    history = random_walk_history(26, seed=5)
    reference = tuple(random_walk_history(26, seed=s) for s in (6, 7, 8))
    stored = train_or_reuse_growth_model(TINY_FLOW, tmp_path / "store")
    members = [HubBaseline(HubBaselineConfig(n_samples=2000)),
               PooledGrowthMember(reference),
               NFGrowthMember(stored.estimator, TINY_FLOW, n_samples=100)]
    config = BacktestConfig(min_history_weeks=8, scored_only=False, n_paths=50)
    plain = run_realtime_backtest(history, members, config)
    results = []
    for _ in range(2):
        memo = ForecastMemo.load(tmp_path / "memo.npz")
        results.append(run_realtime_backtest(history, [memo.wrap(m) for m in members], config))
        memo.save()
    assert memo.misses == 0 and memo.hits == len(plain.origins) * len(members)
    for result in results:
        for origin, made in plain.forecasts.items():
            for name, forecast in made.items():
                other = result.forecasts[origin][name]
                for target in ("I", "cases"):
                    assert np.array_equal(other.values[target], forecast.values[target])
                assert (forecast.paths is None) == (other.paths is None)
                if forecast.paths is not None:
                    assert np.array_equal(other.paths, forecast.paths)
