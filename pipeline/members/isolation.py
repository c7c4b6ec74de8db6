"""Failure isolation: what a run could not publish, and the one guard around every member.

A round publishes whatever can be published and says what it could not (:class:`Dropped`):

* a **member** that raises, returns non-finite or crossing quantiles, or runs past its time
  limit is left out of the cells it failed (all of them when it raised or ran too long); the
  combiner averages the others there, and where no member is left the hub baseline stands in
  (:func:`pipeline.combine.combiner.combine`, ``dropped``);
* a **location** the validation gate skipped is left out alone (the gate names it);
* a **target** with no current release is left out of the file;
* a **refit** that diverged: its forecasts come from the previous refit (or the base flow).

The guard is applied once, in the engine (:func:`pipeline.backtest.backtest.run_backtest`), so
every panel — San Francisco's weekly run, the counties, the hub's rounds — follows the same rule.
"""
from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from pipeline.errors import FlowcastError
from pipeline.members.base import Member, MemberForecast, forecast_within_reach, reach
from pipeline.panels.panel import Cells

log = logging.getLogger(__name__)
DroppedKind = Literal["member", "location", "target", "refit"]
# Quantiles may tie; a decrease larger than this share of the cell's scale is a crossing.
_CROSSING_TOLERANCE = 1e-9


@dataclass(frozen=True)
class Dropped:
    """One thing a run left out (or replaced): ``what`` kind, the ``target`` it concerns, its
    ``name`` (the member, the location's code, the target, the refit), and ``why`` in words."""

    what: DroppedKind
    target: str
    name: str
    why: str

    def line(self) -> str:
        about = "" if self.name == self.target else f" ({self.target})"
        return f"{self.what} {self.name}{about}: {self.why}"


class MemberTimeoutError(FlowcastError):
    """A member ran past its time limit."""


@dataclass(frozen=True, eq=False)
class GuardedForecast:
    """A member's forecast through the guard: ``forecast`` (None when the member failed as a
    whole), ``failed`` ``(B,)`` the cells it failed, and ``why`` in words ('' when none)."""

    forecast: MemberForecast | None
    failed: NDArray[np.bool_]
    why: str


def invalid_cells(count: NDArray[np.float64], within: NDArray[np.bool_] | None = None
                  ) -> tuple[NDArray[np.bool_], str]:
    """``(B,)`` the cells whose quantiles ``(B, H, Q)`` within reach hold a non-finite value or
    cross, and why. ``within`` ``(H,)``: the horizons the member declares it reaches
    (:func:`~pipeline.members.base.reach`); an all-NaN horizon there is a failure. None: a
    horizon that is all NaN is taken as beyond reach (for forecasts of unknown reach)."""
    reached = (~np.isnan(count).all(axis=-1, keepdims=True) if within is None
               else np.asarray(within, dtype=bool)[None, :, None])         # (B, H, 1)
    nonfinite = np.asarray((reached & ~np.isfinite(count)).any(axis=(1, 2)), dtype=bool)
    scale = np.nanmax(np.abs(count), axis=(1, 2), initial=1.0) if count.size else np.ones(0)
    steps = np.diff(np.where(np.isfinite(count), count, 0.0), axis=-1)
    crossing = np.asarray((steps < -_CROSSING_TOLERANCE * scale[:, None, None]).any(
        axis=(1, 2)), dtype=bool)
    reasons = [f"non-finite quantiles in {int(nonfinite.sum())} cell(s)" if nonfinite.any()
               else "", f"crossing quantiles in {int((crossing & ~nonfinite).sum())} cell(s)"
               if (crossing & ~nonfinite).any() else ""]
    return nonfinite | crossing, "; ".join(r for r in reasons if r)


@contextlib.contextmanager
def _time_limit(seconds: float | None) -> Iterator[None]:
    """Interrupt the block after ``seconds`` (SIGALRM: only in the main thread; elsewhere the
    guard checks the time after the member returns)."""
    if seconds is None or threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: object) -> None:
        raise MemberTimeoutError(f"ran past its time limit of {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, interrupt)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def guarded_forecast(member: Member, cells: Cells, horizons: tuple[int, ...],
                     levels: NDArray[np.float64], time_limit_s: float | None
                     ) -> GuardedForecast:
    """``member``'s forecast within reach (:func:`forecast_within_reach`), its failures
    contained: an exception or a run past ``time_limit_s`` fails every cell (a programming
    error is a failure too: one member's bug must not stop the round; the log keeps it); the
    cells with non-finite or crossing quantiles fail alone, set to NaN."""
    started = time.perf_counter()
    try:
        with _time_limit(time_limit_s):
            made = forecast_within_reach(member, cells, horizons, levels)
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as error:  # noqa: BLE001 - isolation: any failure drops this member only
        log.warning("member %s failed and is left out: %s: %s", member.name,
                    type(error).__name__, error, exc_info=True)
        return GuardedForecast(None, np.ones(len(cells), dtype=bool),
                               f"raised {type(error).__name__}: {error}")
    elapsed = time.perf_counter() - started
    if time_limit_s is not None and elapsed > time_limit_s:
        return GuardedForecast(None, np.ones(len(cells), dtype=bool),
                               f"ran {elapsed:.0f} s, past its time limit of {time_limit_s:g} s")
    # judged on the horizons the member declares it reaches, not on where it returned NaN: a
    # member that returned no forecast at a horizon it reaches (a stale origin's extra step)
    # once passed as "beyond reach", and the NaN failed the whole round in the scorer
    failed, why = invalid_cells(made.count, np.isin(horizons, reach(member, horizons)))
    if not failed.any():
        return GuardedForecast(made, failed, "")
    log.warning("member %s: %s; those cells are left out", member.name, why)
    gone = failed[:, None, None]
    extra = {t: np.where(gone, np.nan, v) for t, v in made.extra.items()}
    paths = None if made.paths is None else np.where(
        failed.reshape(-1, *([1] * (made.paths.ndim - 1))), np.nan, made.paths)
    return GuardedForecast(MemberForecast(np.where(gone, np.nan, made.count), extra, paths),
                           failed, why)


@dataclass(frozen=True, eq=False)
class MemberFailure:
    """Where a member failed in a backtest: ``cells`` ``(C, O)`` and ``why``."""

    cells: NDArray[np.bool_]
    why: str
