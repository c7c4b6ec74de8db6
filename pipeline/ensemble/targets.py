"""What the weekly forecast predicts, and the history a forecaster may see.

Targets, at weekly horizons h = 1..4 after an origin t (the last day a forecaster sees):

* ``I``: the infectious share I(t + 7h) of the S/I/R conversion (:mod:`pipeline.data.sir_transform`:
  cases reported in the last L days over the population).
* ``cases``: weekly incident reported cases, the count of cases reported on days
  t + 7(h-1) + 1 … t + 7h. From S/I/R sample paths this is N·(S(t+7h-7) − S(t+7h)) less the
  week's deaths; forecasters here forecast it from the case counts directly.

With the product's L = 7 days, N·I(t) is the trailing 7-day case count, so the two targets carry
the same week of cases; they are still scored separately because the baselines see different
histories (the daily I series against the weekly case series), and because the targets must stay
separate if L changes.

:class:`EpiHistory` is the only thing a forecaster receives: the daily series up to and including
its origin. ``up_to`` is how the backtest enforces real-time discipline.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.data.cdph import CountySeries, county_sir
from pipeline.errors import FlowcastError

# The COVID-19 Forecast Hub's 23 quantile levels, which every forecast here reports.
HUB_QUANTILE_LEVELS: tuple[float, ...] = (
    0.01, 0.025, 0.05, 0.10, 0.15, 0.20, 0.25, 0.30, 0.35, 0.40, 0.45, 0.50,
    0.55, 0.60, 0.65, 0.70, 0.75, 0.80, 0.85, 0.90, 0.95, 0.975, 0.99,
)


def format_level(level: float) -> str:
    """A quantile level as hub files write it: ``0.025``, ``0.5``, ``0.1``."""
    return f"{level:.3f}".rstrip("0").rstrip(".")

TARGETS: tuple[str, ...] = ("I", "cases")
HORIZONS_WEEKS: tuple[int, ...] = (1, 2, 3, 4)
DAYS_PER_WEEK = 7


class TargetError(FlowcastError):
    """A history or forecast that does not fit the weekly targets (gaps, lengths, shapes)."""


@dataclass(frozen=True, eq=False)
class EpiHistory:
    """The daily SF series up to and including the origin (its last date).

    ``cases`` are the daily reported case counts the conversion used (ascertainment-adjusted when
    that is on); ``S``, ``I``, ``R`` the proportions; ``population`` N. Dates are consecutive days.
    """

    dates: pd.DatetimeIndex
    cases: NDArray[np.int64]
    S: NDArray[np.float64]
    I: NDArray[np.float64]  # noqa: E741 - the compartment's name
    R: NDArray[np.float64]
    population: int

    def __post_init__(self) -> None:
        # nanosecond dates: ``up_to``/``observed_targets`` compare the dates as int64 with
        # Timestamp.value (ns); pandas 2 reads dates as datetime64[us], which would silently
        # shift every lookup
        object.__setattr__(self, "dates", pd.DatetimeIndex(self.dates).as_unit("ns"))
        n = len(self.dates)
        if n == 0:
            raise TargetError("empty history")
        for name in ("cases", "S", "I", "R"):
            if len(getattr(self, name)) != n:
                raise TargetError(f"history column {name} has {len(getattr(self, name))} rows, "
                                  f"dates {n}")
        steps = np.diff(self.dates.to_numpy(dtype=np.int64))
        if n > 1 and not (steps == pd.Timedelta(days=1).value).all():
            raise TargetError("history dates must be consecutive days")

    @property
    def origin(self) -> pd.Timestamp:
        return self.dates[-1]

    def __len__(self) -> int:
        return len(self.dates)

    def up_to(self, date: pd.Timestamp) -> EpiHistory:
        """The history a forecaster at origin ``date`` would have seen (nothing after it)."""
        keep = history_length_up_to(self.dates, date)
        if keep == 0:
            raise TargetError(f"no history on or before {pd.Timestamp(date).date()}")
        # The first days of a checked history need no new checks (the backtest cuts thousands).
        head = object.__new__(EpiHistory)
        for name, value in (("dates", self.dates[:keep]), ("cases", self.cases[:keep]),
                            ("S", self.S[:keep]), ("I", self.I[:keep]), ("R", self.R[:keep]),
                            ("population", self.population)):
            object.__setattr__(head, name, value)
        return head

    def weekly_cases(self) -> NDArray[np.float64]:
        """Case counts of the complete 7-day weeks ending at the origin, origin − 7, … (oldest
        first); the incomplete week at the start is dropped."""
        n_weeks = len(self) // DAYS_PER_WEEK
        tail = self.cases[len(self) - n_weeks * DAYS_PER_WEEK:].astype(np.float64)
        return tail.reshape(n_weeks, DAYS_PER_WEEK).sum(axis=1)

    def weekly_I(self) -> NDArray[np.float64]:  # noqa: N802 - the compartment's name
        """I at the origin, origin − 7, … (oldest first), aligned with :meth:`weekly_cases`."""
        n_weeks = len(self) // DAYS_PER_WEEK
        return self.I[len(self) - 1 - DAYS_PER_WEEK * np.arange(n_weeks)[::-1]]

    def target_history(self, target: str) -> NDArray[np.float64]:
        """The weekly series of ``target`` ending at the origin (what a weekly model fits)."""
        if target == "I":
            return self.weekly_I()
        if target == "cases":
            return self.weekly_cases()
        raise TargetError(f"unknown target {target!r}; known: {TARGETS}")


def history_length_up_to(dates: pd.DatetimeIndex, date: pd.Timestamp) -> int:
    """How many of ``dates`` (ascending, nanosecond unit) fall on or before ``date``."""
    return int(np.searchsorted(dates.as_unit("ns").to_numpy(dtype=np.int64),
                               pd.Timestamp(date).as_unit("ns").value, side="right"))


def history_from_frames(sir_frame: pd.DataFrame, cases: NDArray[np.int64] | pd.Series,
                        population: int) -> EpiHistory:
    """An :class:`EpiHistory` from the S/I/R proportions frame (date, S, I, R) and the daily
    case counts on the same dates."""
    missing = [c for c in ("date", "S", "I", "R") if c not in sir_frame.columns]
    if missing:
        raise TargetError(f"S/I/R frame lacks columns {missing}")
    case_counts = np.asarray(cases, dtype=np.int64)
    if len(case_counts) != len(sir_frame):
        raise TargetError(f"{len(case_counts)} case counts for {len(sir_frame)} S/I/R days")
    return EpiHistory(pd.DatetimeIndex(pd.to_datetime(sir_frame["date"])).normalize(),
                      case_counts, sir_frame["S"].to_numpy(np.float64),
                      sir_frame["I"].to_numpy(np.float64), sir_frame["R"].to_numpy(np.float64),
                      int(population))


def history_from_county(series: CountySeries) -> EpiHistory:
    """A California county's :class:`EpiHistory` (CDPH episode-date cases, its own population)."""
    s, i, r = county_sir(series)
    return EpiHistory(series.dates, series.cases, s, i, r, series.population)


def observed_targets(history: EpiHistory, origin: pd.Timestamp,
                     horizons: tuple[int, ...] = HORIZONS_WEEKS) -> dict[str, NDArray[np.float64]]:
    """Truth of each target at ``origin`` + 7h, from a (later) history; NaN where not observed."""
    pos = int(np.searchsorted(history.dates.to_numpy(dtype=np.int64),
                              pd.Timestamp(origin).value))
    if pos >= len(history) or history.dates[pos] != pd.Timestamp(origin):
        raise TargetError(f"origin {pd.Timestamp(origin).date()} is not a date of the history")
    out = {t: np.full(len(horizons), np.nan) for t in TARGETS}
    cumulative = np.concatenate([[0], np.cumsum(history.cases, dtype=np.int64)])
    for k, h in enumerate(horizons):
        end = pos + DAYS_PER_WEEK * h
        if end < len(history):
            out["I"][k] = history.I[end]
            out["cases"][k] = float(cumulative[end + 1] - cumulative[end + 1 - DAYS_PER_WEEK])
    return out


@dataclass(frozen=True, eq=False)
class QuantileForecast:
    """One forecaster's forecast from one origin: quantiles per target and horizon.

    ``values[target]`` has shape (H, Q): horizons × ``levels`` (ascending, the 23 hub levels by
    default); values are non-decreasing along the levels. ``paths``: optional weekly S/I/R sample
    paths (n, H, 3) at origin + 7h, for members that simulate them (validity checks, the hub's
    sample output).
    """

    forecaster: str
    origin: pd.Timestamp
    horizons: tuple[int, ...]
    levels: NDArray[np.float64]
    values: dict[str, NDArray[np.float64]]
    paths: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        shape = (len(self.horizons), len(self.levels))
        for target, arr in self.values.items():
            if target not in TARGETS:
                raise TargetError(f"{self.forecaster}: unknown target {target!r}")
            if arr.shape != shape:
                raise TargetError(f"{self.forecaster} at {self.origin.date()}: {target} quantiles "
                                  f"have shape {arr.shape}, expected {shape}")
            if not np.isfinite(arr).all():
                raise TargetError(f"{self.forecaster} at {self.origin.date()}: {target} "
                                  "quantiles are not finite")
            if (np.diff(arr, axis=-1) < -1e-12 * np.abs(arr[..., 1:]).max(initial=1.0)).any():
                raise TargetError(f"{self.forecaster} at {self.origin.date()}: {target} "
                                  "quantiles decrease along the levels")
