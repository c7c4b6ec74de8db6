"""Progress bars count against the right total: each phase announces its size."""
from __future__ import annotations

import io
import logging

import pytest
from rich.console import Console
from rich.progress import Progress

from pipeline.backtest.backtest import OneVintage, run_backtest
from pipeline.panels.panel import Panel, weekly_origins
from pipeline.progress import (LogProgress, PhasedProgress, SilentProgress, _RichTask,
                               start_phase)
from tests.forecasting_helpers import LogNormalMember, random_walk_history


class Recorder:
    """A reporter that shows totals: every phase with its announced size and the steps done."""

    def __init__(self) -> None:
        self.phases: list[tuple[str, int | None]] = []
        self.steps: list[int] = []

    def advance(self, steps: int = 1, **fields: float | str) -> None:
        self.steps[-1] += steps

    def phase(self, description: str, total: int | None) -> None:
        self.phases.append((description, total))
        self.steps.append(0)


def test_a_backtest_announces_every_forecast_it_makes_as_its_total():
    """Two places × 6 weekly origins × (2 members + the hub baseline, added as a reference):
    the bar's total is 36, and it ends at 36 (the county backtest's bar read "14712/1")."""
    places = {"a": random_walk_history(14, seed=1), "b": random_walk_history(14, seed=2)}
    panel = Panel(places)
    origins = weekly_origins(panel.dates, scored_only=False)[:6]
    recorder = Recorder()
    assert isinstance(recorder, PhasedProgress)
    run_backtest(OneVintage(panel), [LogNormalMember("sharp", 0.1),
                                     LogNormalMember("wide", 0.6)], origins, progress=recorder)
    assert len(origins) == 6
    assert recorder.phases == [("forecasts", 2 * 6 * 3)]
    assert recorder.steps == [36]


def test_a_rich_bar_opens_one_task_per_phase_and_closes_the_one_before_at_its_count():
    progress = Progress(console=Console(file=io.StringIO()), auto_refresh=False)
    task = _RichTask(progress, progress.add_task("backtest", total=None, status=""), "backtest")
    start_phase(task, "members' models", None)        # nothing counted yet: replaces the first
    task.advance(7, loss=0.5)
    start_phase(task, "forecasts", 12)
    task.advance(12)
    assert [(t.description, t.total, t.completed) for t in progress.tasks] == [
        ("backtest: members' models", 7, 7), ("backtest: forecasts", 12, 12)]


def test_reporters_that_show_no_total_ignore_phases(caplog: pytest.LogCaptureFixture):
    start_phase(SilentProgress(), "forecasts", 3)       # no phase method: nothing happens
    log = LogProgress(logging.getLogger("test-progress"), "rounds", every=2)
    with caplog.at_level(logging.INFO, logger="test-progress"):
        log.advance(3)
        start_phase(log, "forecasts", 4)
        log.advance(2)
    assert [r.getMessage() for r in caplog.records] == [
        "rounds: 3 steps ", "rounds: forecasts, 4 steps", "rounds: 2 steps "]
