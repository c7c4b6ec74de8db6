"""The nowcast of the weeks a weekly source is still revising, from the revision pattern of its
earlier vintages (NHSN admissions, the NSSP ED share).

A hub vintage's newest week is incomplete: hospitals report late, so its count rises in later
releases (NHSN admissions, 44 vintages: the first report of a week is 7 % below the latest
in the median, 45 % below at the 90th percentile; a week's second report is final in the median).
The delay model of the daily CDPH series (:mod:`pipeline.data.california.delays`, by day) becomes, by
week: for lag k (0: the vintage's newest week), the log ratio g(now) − g(reported) between a
week's value as known at the round and as an earlier vintage reported it at lag k, over every
earlier vintage and location (the US apart from the states: its aggregate revises more
smoothly), g = log(1 + x). The nowcast of a week at lag k is its reported value × those ratios'
quantiles; its median replaces the reported value in the history the members forecast from.

Real time: at a round only the vintages released by then enter, and "now" is that round's own
vintage, never a later one.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.evaluation.quantile_function import median_index
from pipeline.panels.history import WeeklyHistory
from pipeline.panels.hub import US
from pipeline.panels.panel import Panel, weeks_ending
from pipeline.panels.targets import DAYS_PER_WEEK, TargetError


@dataclass(frozen=True)
class RevisionNowcastConfig:
    """``lags``: the newest weeks nowcast (0 … lags − 1); ``min_pairs``: fewer revision pairs than
    this leave a week as reported; ``separate_us``: the US's own ratios."""

    lags: int = 2
    min_pairs: int = 10
    separate_us: bool = True

    def __post_init__(self) -> None:
        if self.lags < 1 or self.min_pairs < 2:
            raise TargetError(f"invalid RevisionNowcastConfig {self}: lags >= 1, min_pairs >= 2")


@dataclass(frozen=True, eq=False)
class WeekNowcast:
    """``quantiles[place]`` ``(lags, Q)``: the final value of the weeks at lags 0 … lags − 1 of
    the panel (newest first); ``panel``: the panel with each nowcast week at its median."""

    levels: NDArray[np.float64]
    ends: tuple[pd.Timestamp, ...]
    quantiles: dict[str, NDArray[np.float64]]
    panel: Panel
    n_pairs: dict[int, int]


def _g(x: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.log1p(np.maximum(x, 0.0))


def revision_log_ratios(earlier: Sequence[Panel], now: Panel, lag: int
                        ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """(g(now) − g(reported), is the US) of every earlier vintage's week at ``lag`` and every
    location both hold."""
    ratios, us = [], []
    for old in earlier:
        end = old.last_date - pd.Timedelta(days=DAYS_PER_WEEK * lag)
        places = [p for p in old.histories if p in now.histories]
        if not places:
            continue
        reported = np.array([weeks_ending(old.histories[p], end, 1)[0] for p in places])
        current = np.array([weeks_ending(now.histories[p], end, 1)[0] for p in places])
        ok = np.isfinite(reported) & np.isfinite(current)
        ratios.append((_g(current) - _g(reported))[ok])
        us.append(np.array([p == US for p in places])[ok])
    if not ratios:
        return np.empty(0), np.empty(0, dtype=bool)
    return np.concatenate(ratios), np.concatenate(us)


def nowcast_weeks(panel: Panel, earlier: Sequence[Panel], levels: NDArray[np.float64],
                  config: RevisionNowcastConfig = RevisionNowcastConfig()) -> WeekNowcast:
    """The nowcast of ``panel``'s newest weeks from the vintages released before it
    (``earlier``; module docstring)."""
    levels = np.asarray(levels, dtype=np.float64)
    ends = tuple(panel.last_date - pd.Timedelta(days=DAYS_PER_WEEK * k)
                 for k in range(config.lags))
    mid = median_index(levels)
    out: dict[str, NDArray[np.float64]] = {}
    corrected: dict[str, WeeklyHistory] = {}
    pairs: dict[int, int] = {}
    spread = {}
    for lag in range(config.lags):
        ratios, us = revision_log_ratios(earlier, panel, lag)
        pairs[lag] = int(ratios.size)
        pooled = (np.quantile(ratios, levels) if ratios.size >= config.min_pairs
                  else np.zeros(levels.size))
        spread[lag] = {group: (np.quantile(ratios[pick], levels)
                               if config.separate_us and pick.sum() >= config.min_pairs
                               else pooled)
                       for group, pick in (("US", us), ("states", ~us))}
    for place, history in panel.histories.items():
        if not isinstance(history, WeeklyHistory):
            raise TargetError(f"{place}: the revision nowcast is of weekly series")
        group = "US" if place == US else "states"
        values = history.cases.copy()
        q = np.empty((config.lags, levels.size))
        for lag, end in enumerate(ends):
            reported = weeks_ending(history, end, 1)[0]
            # a week's final value is at most what it is counted in: a share at most every
            # visit (a week first released as 0 has revision ratios that reach far beyond it)
            q[lag] = (np.clip(np.expm1(_g(np.array(reported)) + spread[lag][group]), 0.0,
                              float(history.population))
                      if np.isfinite(reported) else np.nan)
            index = len(history) - 1 - lag
            if index >= 0 and history.dates[index] == end and np.isfinite(q[lag, mid]):
                values[index] = q[lag, mid]
        out[place] = q
        corrected[place] = dataclasses.replace(history, cases=values)
    return WeekNowcast(levels, ends, out, dataclasses.replace(panel, histories=corrected), pairs)
