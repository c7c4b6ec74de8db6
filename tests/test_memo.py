"""The forecast memo (pipeline.backtest.memo): a forecast read back is the forecast made, bit for
bit, and anything it depends on changes its key."""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.backtest.config import BacktestConfig

from pipeline.backtest.backtest import OneVintage, run_backtest
from pipeline.backtest.memo import ForecastMemo
from pipeline.fingerprint import fingerprint
from pipeline.members.nf.growth import NFGrowthMember
from pipeline.members.nf.flow import stored_flow
from pipeline.members.nf.growth import GrowthModelConfig
from pipeline.members.growth_regression import PooledGrowthMember
from pipeline.members.hub_baseline import HubBaseline, HubBaselineConfig
from pipeline.members.seasonal import SeasonalGrowthMember
from pipeline.panels.history import EpiHistory, WeeklyHistory
from pipeline.panels.panel import Cells, Panel, weekly_origins
from pipeline.panels.targets import HUB_QUANTILE_LEVELS
from tests.forecasting_helpers import LogNormalMember, forecast_one, random_walk_history

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

    def forecast(self, cells, horizons, levels):
        self.calls.extend([1] * len(cells))
        return self.inner.forecast(cells, horizons, levels)


def _revised(history: EpiHistory, day: int, delta: int) -> EpiHistory:
    cases = history.cases.copy()
    cases[day] += delta
    return dataclasses.replace(history, cases=cases)


def test_a_hit_returns_the_stored_forecast_and_skips_the_member(tmp_path: Path) -> None:
    history = random_walk_history(30, seed=1)
    member = CountingMember(LogNormalMember("lognormal", 0.3))
    first = ForecastMemo.load(tmp_path / "memo.npz")
    made = forecast_one(first.wrap(member), history, seed=7)
    first.save()
    again = ForecastMemo.load(tmp_path / "memo.npz")
    read = forecast_one(again.wrap(member), history, seed=7)
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
    forecast_one(memo.wrap(member), history, (1, 2), 7)
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
    forecast_one(memo.wrap(other_member), other_history, (1, 2), seed, levels)
    assert (memo.hits, memo.misses) == (0, 2) and len(member.calls) == 2


def test_the_code_is_part_of_the_key(tmp_path: Path, monkeypatch) -> None:
    import pipeline.backtest.memo as memo_module

    member = LogNormalMember("lognormal", 0.3)
    before = ForecastMemo.load(tmp_path / "m.npz").wrap(member).member_key
    monkeypatch.setattr(memo_module, "code_fingerprint", lambda: "another version")
    assert ForecastMemo.load(tmp_path / "m.npz").wrap(member).member_key != before


def test_model_weights_are_part_of_the_key(tmp_path: Path) -> None:
    stored = stored_flow(TINY_FLOW, tmp_path / "store")
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
    forecast_one(memo.wrap(LogNormalMember("lognormal", 0.3)), random_walk_history(20, 3), (1,))
    memo.save()
    assert len(ForecastMemo.load(path)._stored) == 1


def test_the_file_keeps_only_what_the_last_run_used(tmp_path: Path) -> None:
    path = tmp_path / "memo.npz"
    member = LogNormalMember("lognormal", 0.3)
    history = random_walk_history(30, seed=4)
    memo = ForecastMemo.load(path)
    for n_days in (150, 200):
        forecast_one(memo.wrap(member), history.up_to(history.dates[n_days]), (1,))
    memo.save()
    later = ForecastMemo.load(path)
    forecast_one(later.wrap(member), history.up_to(history.dates[200]), (1,))
    assert later.changed
    later.save()
    assert len(ForecastMemo.load(path)._stored) == 1


def test_a_pooling_member_is_keyed_by_its_panel(tmp_path: Path) -> None:
    """growth-qr learns from every place of the cell's panel: another reference place's data
    is another key; the flow of the same cell is not keyed by the panel."""
    history = random_walk_history(30, seed=2)
    panel = Panel({"place": history}, {"other": random_walk_history(30, seed=3)})
    revised = Panel({"place": history}, {"other": random_walk_history(30, seed=4)})
    memo = ForecastMemo.load(tmp_path / "memo.npz")
    growth = memo.wrap(PooledGrowthMember())
    forecast_one(growth, history, panel=panel)
    forecast_one(growth, history, panel=revised)
    assert (memo.hits, memo.misses) == (0, 2)
    lognormal = memo.wrap(LogNormalMember("lognormal", 0.3))
    forecast_one(lognormal, history, panel=panel)
    forecast_one(lognormal, history, panel=revised)
    assert (memo.hits, memo.misses) == (1, 3)


def test_a_memoized_backtest_equals_the_plain_one_bit_for_bit(tmp_path: Path) -> None:
    """Hub baseline (its own random draws), growth-qr pooled over other places, and a flow
    with sample paths: the backtest with a cold memo, with a warm one and without one agree in
    every quantile and path; the warm run forecasts nothing."""
    history = random_walk_history(26, seed=5)
    reference = {f"ref{s}": random_walk_history(26, seed=s) for s in (6, 7, 8)}
    data = OneVintage(Panel({"place": history}, reference))
    origins = weekly_origins(history.dates, scored_only=False)
    stored = stored_flow(TINY_FLOW, tmp_path / "store")
    members = [HubBaseline(HubBaselineConfig(n_samples=2000)), PooledGrowthMember(),
               NFGrowthMember(stored.estimator, TINY_FLOW, n_samples=100)]
    config = BacktestConfig(n_paths=50)
    plain = run_backtest(data, members, origins, config)
    results, memos = [], []
    for _ in range(2):
        memos.append(ForecastMemo.load(tmp_path / "memo.npz"))
        results.append(run_backtest(data, [memos[-1].wrap(m, config.n_paths) for m in members],
                                    origins, config))
        memos[-1].save()
    assert memos[-1].misses == 0 and memos[-1].hits == len(plain.origins) * len(members)
    # only the 50 paths the backtest uses are kept of the flow's 100
    kept = {f.paths.shape for f in ForecastMemo.load(tmp_path / "memo.npz")._stored.values()
            if f.paths is not None}
    assert kept == {(50, 4, 3)}
    for result in results:
        for target, made in plain.forecasts.items():
            for name, q in made.items():
                assert np.array_equal(result.forecasts[target][name].values, q.values), name
        assert plain.paths is not None and result.paths is not None
        assert np.array_equal(result.paths, plain.paths)


def _weekly_panel(seed: int, as_of: str, weeks: int = 130) -> Panel:
    """Two places' weekly counts (a yearly wave), released ``as_of``."""
    rng = np.random.default_rng(seed)
    dates = pd.date_range("2022-10-01", periods=weeks, freq="7D")
    wave = 200 + 150 * np.sin(2 * np.pi * np.arange(weeks) / 52)
    return Panel({p: WeeklyHistory(dates, np.round(wave * rng.uniform(0.8, 1.2, weeks)),
                                   1_000_000, "wk inc covid hosp") for p in ("01", "02")},
                 name="hub", as_of=pd.Timestamp(as_of))


def test_a_member_keyed_by_cell_keeps_its_past_cells_keys_when_a_later_release_comes(
        tmp_path: Path) -> None:
    """The seasonal member reads the climatology released by the cell's vintage: a later
    release of it leaves last week's cells as they were (read back), while a revision of the
    release the cell read is another key."""
    cell = _weekly_panel(1, "2025-03-05")
    history = cell.histories["01"].up_to(pd.Timestamp("2025-03-01"))
    first = (pd.Timestamp("2025-03-05"), _weekly_panel(2, "2025-03-05"))
    later = (pd.Timestamp("2025-03-12"), _weekly_panel(3, "2025-03-12"))
    revised = (first[0], _weekly_panel(4, "2025-03-05"))
    memo = ForecastMemo.load(tmp_path / "memo.npz")
    made = forecast_one(memo.wrap(SeasonalGrowthMember((first,))), history, panel=cell)
    read = forecast_one(memo.wrap(SeasonalGrowthMember((first, later))), history, panel=cell)
    assert (memo.hits, memo.misses) == (1, 1)
    assert np.array_equal(read.values["wk inc covid hosp"], made.values["wk inc covid hosp"])
    forecast_one(memo.wrap(SeasonalGrowthMember((revised, later))), history, panel=cell)
    assert (memo.hits, memo.misses) == (1, 2)
