"""The revision policy every source applies before a new payload may replace the cached one.

Each source settles its cells differently (DataSF's days, CDPH's county-days, NHSN's
location-weeks) but judges a revision the same way: a **settled** cell (older than the source's
open window) may change by at most max(``settled_abs``, ``settled_rel`` × |before|), and the
total of a count over the cells both payloads hold may not fall by more than
``max_total_drop``. A payload beyond either is refused and held for review
(:class:`~pipeline.data.core.cache.RevisionRefusedError` with ``hold=True``): the cached copy is
kept, and ``--accept-revisions`` takes it after review.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from pipeline.data.core.cache import RevisionRefusedError

HELD = "held for review, cached copy kept"


def refuse_settled_changes(key: str, label: str, before: NDArray[np.number],
                           after: NDArray[np.number], settled: NDArray[np.bool_], *,
                           settled_abs: float, settled_rel: float, cells: str, until: str,
                           example: Callable[[int], str]) -> None:
    """Refuse when a settled cell of ``label`` changed beyond the policy. ``cells``: what a
    cell is (``day``, ``county-day``, ``week``); ``until``: the settled span in words;
    ``example(i)``: cell ``i`` named, for the message."""
    allowed = np.maximum(settled_abs, settled_rel * np.abs(before))
    breaks = settled & (np.abs(after - before) > allowed)
    if breaks.any():
        i = int(np.flatnonzero(breaks)[0])
        raise RevisionRefusedError(
            f"{key}: revision beyond policy: '{label}' changed on {int(breaks.sum())} settled "
            f"{cells}(s) ({until}) by more than max({settled_abs:g}, {settled_rel:.0%}), e.g. "
            f"{example(i)} {_number(before[i])} -> {_number(after[i])}; {HELD}", hold=True)


def refuse_total_drop(key: str, label: str, before: NDArray[np.number],
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
