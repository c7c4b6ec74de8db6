"""Progress reporting for long work (simulation, training, SMC) without tying the library to a UI.

Library functions accept an optional ``ProgressReporter``; the CLI passes a rich bar, tests pass
nothing (``SilentProgress``), flows pass a reporter that logs. Work that comes in phases of
different units (training iterations, then forecasts of cells) announces each phase and its size
with :func:`start_phase`, so that a bar counts against the right total (a reporter that shows no
total needs no ``phase`` method).
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID


class ProgressReporter(Protocol):
    def advance(self, steps: int = 1, **fields: float | str) -> None: ...


@runtime_checkable
class PhasedProgress(ProgressReporter, Protocol):
    """A reporter that shows a total: told when a new phase of work starts and how many steps
    it holds (``None``: not known in advance, e.g. training that may stop early)."""

    def phase(self, description: str, total: int | None) -> None: ...


def start_phase(progress: ProgressReporter, description: str, total: int | None) -> None:
    """Announce a phase of ``total`` steps to a reporter that shows totals (others ignore it)."""
    if isinstance(progress, PhasedProgress):
        progress.phase(description, total)


class SilentProgress:
    def advance(self, steps: int = 1, **fields: float | str) -> None:
        return None


class LogProgress:
    """Logs ``label: N steps k=v ...`` every ``every`` steps (for flows and background
    processes, which have no terminal bar)."""

    def __init__(self, logger: logging.Logger | logging.LoggerAdapter[Any], label: str,
                 every: int) -> None:
        self.logger, self.label, self.every, self.done = logger, label, max(1, every), 0

    def advance(self, steps: int = 1, **fields: float | str) -> None:
        before, self.done = self.done, self.done + steps
        if before // self.every != self.done // self.every:
            self.logger.info("%s: %d steps %s", self.label, self.done, _format_fields(fields))

    def phase(self, description: str, total: int | None) -> None:
        self.done = 0
        self.logger.info("%s: %s, %s steps", self.label, description,
                         "?" if total is None else total)


def _format_fields(fields: dict[str, float | str]) -> str:
    return "  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                     for k, v in fields.items())


class _RichTask:
    """One bar per phase: a new phase closes the bar before it at the count it reached."""

    def __init__(self, progress: Progress, task_id: TaskID, description: str) -> None:
        self._progress, self._task_id, self._description = progress, task_id, description
        self._done = 0

    def advance(self, steps: int = 1, **fields: float | str) -> None:
        self._done += steps
        self._progress.update(self._task_id, advance=steps, status=_format_fields(fields))

    def phase(self, description: str, total: int | None) -> None:
        if self._done:
            self._progress.update(self._task_id, total=self._done)
        else:   # nothing counted yet: the new phase's bar replaces it
            self._progress.remove_task(self._task_id)
        self._task_id = self._progress.add_task(f"{self._description}: {description}",
                                                total=total, status="")
        self._done = 0


@contextlib.contextmanager
def rich_progress(description: str, total: int | None = None) -> Iterator[ProgressReporter]:
    """A rich progress bar showing count, rate (it/s), ETA and status fields such as the loss;
    ``total`` None: counted without a total until a phase announces one."""
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TaskProgressColumn,
                               TextColumn, TimeElapsedColumn, TimeRemainingColumn)

    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TaskProgressColumn(show_speed=True), TimeElapsedColumn(), TimeRemainingColumn(),
               TextColumn("{task.fields[status]}"))
    with Progress(*columns) as progress:
        yield _RichTask(progress, progress.add_task(description, total=total, status=""),
                        description)
