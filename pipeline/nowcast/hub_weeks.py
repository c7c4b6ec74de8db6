"""The weeks of a hub round: which are nowcast, which are forecast, and how far ahead.

The data date D is the last day in the data. The hub round's reference date is the Saturday
ending D's epiweek (D itself on a Saturday); the origin is the last Saturday ≤ D. Hub horizon h is
the epiweek ending ``reference + 7h``: a week ending on or before the origin lies wholly in the
data and is **nowcast** (its final count from the nowcast's samples); a later week is
**forecast**, ``(end − origin)/7`` weeks after the origin (1..4 for hub horizons 0..3 when the
data end in the reference week, the four weeks the flow member forecasts).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import pandas as pd

from pipeline.panels.targets import DAYS_PER_WEEK, SATURDAY

HUB_HORIZONS: tuple[int, ...] = (-1, 0, 1, 2, 3)
WeekKind = Literal["nowcast", "forecast"]


def last_saturday(date: pd.Timestamp) -> pd.Timestamp:
    """The last Saturday on or before ``date``."""
    d = pd.Timestamp(date).normalize()
    return d - pd.Timedelta(days=(d.weekday() - SATURDAY) % DAYS_PER_WEEK)


def reference_date(data_date: pd.Timestamp) -> pd.Timestamp:
    """The Saturday ending the epiweek (Sunday–Saturday) that holds ``data_date``."""
    d = pd.Timestamp(data_date).normalize()
    return d + pd.Timedelta(days=(SATURDAY - d.weekday()) % DAYS_PER_WEEK)


@dataclass(frozen=True)
class HubWeek:
    """One hub horizon: its week's last day, nowcast or forecast, and (forecast) the step in
    weeks after the origin."""

    horizon: int
    end: pd.Timestamp
    kind: WeekKind
    step: int            # weeks after the origin (≤ 0: a nowcast week)


@dataclass(frozen=True)
class HubWeeks:
    """The weeks of a round with data up to ``data_date`` (module docstring)."""

    data_date: pd.Timestamp
    origin: pd.Timestamp
    reference: pd.Timestamp
    weeks: tuple[HubWeek, ...]

    @property
    def forecast_steps(self) -> tuple[int, ...]:
        return tuple(w.step for w in self.weeks if w.kind == "forecast")

    @property
    def known_days_after_origin(self) -> int:
        """Days of the current week in the data (0 when the data end on a Saturday)."""
        return int((self.data_date - self.origin).days)


def hub_weeks(data_date: pd.Timestamp, horizons: tuple[int, ...] = HUB_HORIZONS) -> HubWeeks:
    """Nowcast and forecast weeks of the round whose data end on ``data_date``."""
    d = pd.Timestamp(data_date).normalize()
    origin, ref = last_saturday(d), reference_date(d)
    weeks = []
    for h in horizons:
        end = ref + pd.Timedelta(days=DAYS_PER_WEEK * h)
        step = int((end - origin).days // DAYS_PER_WEEK)
        weeks.append(HubWeek(h, end, "nowcast" if step <= 0 else "forecast", step))
    return HubWeeks(d, origin, ref, tuple(weeks))
