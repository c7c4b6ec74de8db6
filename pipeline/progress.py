"""Progress reporting for long work (simulation, training, SMC) without tying the library to a UI.

Library functions accept an optional ``ProgressReporter``; the CLI passes a rich bar, tests pass
nothing (``SilentProgress``), flows pass a reporter that logs.
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID


class ProgressReporter(Protocol):
    def advance(self, steps: int = 1, **fields: float | str) -> None: ...


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


def _format_fields(fields: dict[str, float | str]) -> str:
    return "  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                     for k, v in fields.items())


class _RichTask:
    def __init__(self, progress: Progress, task_id: TaskID) -> None:
        self._progress, self._task_id = progress, task_id

    def advance(self, steps: int = 1, **fields: float | str) -> None:
        self._progress.update(self._task_id, advance=steps, status=_format_fields(fields))


@contextlib.contextmanager
def rich_progress(description: str, total: int) -> Iterator[ProgressReporter]:
    """A rich progress bar showing count, rate (it/s), ETA and status fields such as the loss."""
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TaskProgressColumn,
                               TextColumn, TimeElapsedColumn, TimeRemainingColumn)

    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TaskProgressColumn(show_speed=True), TimeElapsedColumn(), TimeRemainingColumn(),
               TextColumn("{task.fields[status]}"))
    with Progress(*columns) as progress:
        yield _RichTask(progress, progress.add_task(description, total=total, status=""))
