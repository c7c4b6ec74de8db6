"""The revision policy every source applies before a new payload may replace the cached one.

Each source settles its cells differently (DataSF's days, CDPH's county-days, NHSN's
location-weeks) but judges a revision the same way: a **settled** cell (older than the source's
open window) may change by at most max(``settled_abs``, ``settled_rel`` × |before|), and the
total of a count over the cells both payloads hold may not fall by more than
``max_total_drop``. A payload beyond either is refused and held for review
(:class:`~pipeline.data.core.cache.RevisionRefusedError` with ``hold=True``): the cached copy is
kept, and ``--accept-revisions`` takes it after review.

A source of many places (the hub's 53 locations) judges each place on its own
(:func:`settled_breaks`, per cell; the caller holds the places that break, issue 39), and with
``backfill_ok`` a settled cell that read 0 and becomes positive is a **backfill** (late reports
of a week first published empty), not a revision: the gate still bounds the value against the
place's population and history, the policy does not. A settled count that changes tenfold is a
revision and is held.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.core.cache import RevisionRefusedError
from pipeline.errors import ConfigError

HELD = "held for review, cached copy kept"


@dataclass(frozen=True)
class RevisionPolicy:
    """What a new payload may revise: cells dated within ``open_days`` of the cached copy's last
    date are open (late reports); an older, settled cell may change by at most
    max(``settled_abs``, ``settled_rel`` × |cached value|); the total of a count over the cells
    both copies hold may fall by at most ``max_total_drop`` (None: a source whose values are
    not counts, or whose totals legitimately fall, is not checked)."""

    open_days: int = 28
    settled_abs: float = 50.0
    settled_rel: float = 0.25
    max_total_drop: float | None = 0.02
    backfill_ok: bool = False

    def __post_init__(self) -> None:
        if (self.open_days < 0 or self.settled_abs < 0 or self.settled_rel < 0
                or (self.max_total_drop is not None and not 0 <= self.max_total_drop <= 1)):
            raise ConfigError(f"invalid {self}: open_days, settled_abs and settled_rel must be "
                              ">= 0, max_total_drop in [0, 1] or None")

    def settled_until(self, last: pd.Timestamp) -> pd.Timestamp:
        """The newest date of a settled cell when the cached copy ends on ``last``."""
        return pd.Timestamp(last) - pd.Timedelta(days=self.open_days)


def settled_breaks(before: NDArray[np.number], after: NDArray[np.number],
                   dates: NDArray[np.datetime64], *, policy: RevisionPolicy,
                   last: pd.Timestamp) -> NDArray[np.bool_]:
    """Per cell both copies hold: does it break ``policy`` (a settled cell changed beyond
    max(``settled_abs``, ``settled_rel`` × |before|); with ``backfill_ok`` a cell that read 0
    may become anything)? ``last``: the cached copy's last date."""
    before, after = np.asarray(before, np.float64), np.asarray(after, np.float64)
    settled = np.asarray(dates, dtype="datetime64[ns]") <= \
        policy.settled_until(last).to_datetime64()
    allowed = np.maximum(policy.settled_abs, policy.settled_rel * np.abs(before))
    if policy.backfill_ok:
        allowed = np.where((before == 0) & (after > 0), np.inf, allowed)
    return settled & (np.abs(after - before) > allowed)


def describe_breaks(key: str, label: str, before: NDArray[np.number],
                    after: NDArray[np.number], breaks: NDArray[np.bool_], *,
                    policy: RevisionPolicy, last: pd.Timestamp, cells: str,
                    example: Callable[[int], str]) -> str:
    """The policy's message for the cells ``breaks`` marks (as :func:`refuse_revisions` says
    it, without the consequence)."""
    i = int(np.flatnonzero(breaks)[0])
    until = policy.settled_until(last)
    return (f"{key}: revision beyond policy: '{label}' changed on {int(breaks.sum())} settled "
            f"{cells}(s) (on or before {until.date()}) by more than max({policy.settled_abs:g}, "
            f"{policy.settled_rel:.0%}), e.g. {example(i)} {_number(before[i])} -> "
            f"{_number(after[i])}")


def refuse_revisions(key: str, label: str, before: NDArray[np.number],
                     after: NDArray[np.number], dates: NDArray[np.datetime64], *,
                     policy: RevisionPolicy, last: pd.Timestamp, cells: str, over: str,
                     example: Callable[[int], str]) -> None:
    """Both checks of ``policy`` on one column of the cells both copies hold (their ``dates``;
    ``last``: the cached copy's last date). ``cells`` (what a cell is: ``day``, ``county-day``, ``week``), ``over`` and ``example`` (cell
    ``i`` named): as in :func:`describe_breaks` and :func:`_refuse_total_drop`."""
    breaks = settled_breaks(before, after, dates, policy=policy, last=last)
    if breaks.any():
        raise RevisionRefusedError(describe_breaks(key, label, before, after, breaks,
                                                   policy=policy, last=last, cells=cells,
                                                   example=example) + f"; {HELD}", hold=True)
    if policy.max_total_drop is not None:
        _refuse_total_drop(key, label, before, after, max_total_drop=policy.max_total_drop,
                          over=over)


def _refuse_total_drop(key: str, label: str, before: NDArray[np.number],
                      after: NDArray[np.number], *, max_total_drop: float, over: str) -> None:
    """Refuse when the total of ``label`` over the common cells (``over``, in words) falls by
    more than ``max_total_drop``."""
    total_before, total_after = float(before.sum()), float(after.sum())
    if total_before > 0 and total_after < (1.0 - max_total_drop) * total_before:
        raise RevisionRefusedError(
            f"{key}: revision beyond policy: total '{label}' over {over} falls from "
            f"{total_before:,.0f} to {total_after:,.0f} (more than {max_total_drop:.0%}); "
            f"{HELD}", hold=True)


def _number(x: float) -> str:
    """A count with thousands separators, a share as it is."""
    return f"{int(x):,}" if float(x).is_integer() else f"{float(x):g}"
