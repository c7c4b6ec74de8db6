"""The CDC COVID-19 Forecast Hub's panels: weekly NHSN admissions (or the NSSP ED share) of the
US, the 50 states, DC and Puerto Rico, one panel per data vintage, and the hub's rounds.

A **vintage** is the hub's target data as released on one day (``as_of``, a Wednesday): for
every location the weekly values up to the last week then reported. Its panel holds one
:class:`~pipeline.panels.history.WeeklyHistory` per location on one calendar of Saturdays
(NaN where a week was not reported).

The **ED share** is a proportion of visits. The members forecast counts (log growth, negative
binomial noise, values ≥ 0), so the share enters as a rate per :data:`ED_VISITS_SCALE` visits
with that many "people" and no depletion (its S is 1: the flows' bound is a share of 100 %);
forecasts are divided back to a proportion for the hub file.

A **round** (:class:`HubRound`) is named by its reference date R, a Saturday; its forecast is
due the Wednesday before (R − 3) and uses the newest vintage released by then; its horizons
−1 … 3 are the weeks ending R − 7 … R + 21. Weeks after the vintage's last week are forecast,
steps ``(end − origin) / 7`` after the origin (the vintage's last week); the vintage's last week
itself (hub horizon −1 when the data are a week behind) is still being reported and is nowcast
(:mod:`pipeline.nowcast.revisions`).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from pipeline.data.hub.locations import POPULATION, US
from pipeline.data.hub.nhsn_vintages import ED_COVID, HOSP_COVID, WeeklyVintage
from pipeline.panels.history import WeeklyHistory
from pipeline.panels.panel import Panel
from pipeline.panels.targets import DAYS_PER_WEEK, SATURDAY, TargetError

__all__ = ["ED_COVID", "HOSP_COVID", "US"]
ED_VISITS_SCALE = 100_000          # the ED share as a rate per 100,000 visits
HUB_HORIZONS: tuple[int, ...] = (-1, 0, 1, 2, 3)
DUE_DAYS_BEFORE_REFERENCE = 3      # due Wednesday, named by the Saturday after


def is_share(target: str) -> bool:
    """Whether the hub target is a proportion (the ED share) rather than a count."""
    return "prop" in target


def target_scale(target: str) -> float:
    """Counts per unit of the hub's value: 1 for a count, :data:`ED_VISITS_SCALE` for a share."""
    return float(ED_VISITS_SCALE) if is_share(target) else 1.0


def vintage_panel(frame: pd.DataFrame, target: str, populations: Mapping[str, int],
                  as_of: pd.Timestamp, *, skipped: Mapping[str, str] | None = None) -> Panel:
    """The panel of one vintage: ``frame`` has ``target_end_date``, ``location`` and ``value``
    (the hub's units); every location of ``populations`` that the vintage reports, on the
    vintage's calendar of Saturdays (NaN where a week is missing)."""
    missing = {"target_end_date", "location", "value"} - set(frame.columns)
    if missing:
        raise TargetError(f"{target} vintage of {pd.Timestamp(as_of).date()} lacks columns "
                          f"{sorted(missing)}")
    dates = pd.to_datetime(frame["target_end_date"])
    if len(dates) and (dates.dt.weekday != SATURDAY).any():
        bad = dates[dates.dt.weekday != SATURDAY].iloc[0]
        raise TargetError(f"{target}: week {bad.date()} does not end on a Saturday")
    wide = (frame.assign(target_end_date=dates)
            .pivot_table(index="location", columns="target_end_date", values="value",
                         aggfunc="last"))
    if wide.empty:
        raise TargetError(f"{target} vintage of {pd.Timestamp(as_of).date()} has no rows")
    calendar = pd.date_range(wide.columns.min(), wide.columns.max(), freq="7D")
    wide = wide.reindex(columns=calendar)
    scale = target_scale(target)
    histories = {}
    for place, population in populations.items():
        if place not in wide.index:
            continue
        values = wide.loc[place].to_numpy(np.float64) * scale
        last = int(np.flatnonzero(np.isfinite(values))[-1]) if np.isfinite(values).any() else -1
        if last < 0:
            continue
        histories[place] = WeeklyHistory(calendar[:last + 1], values[:last + 1],
                                         ED_VISITS_SCALE if is_share(target) else int(population),
                                         target, depletes=not is_share(target))
    unknown = sorted(set(wide.index) - set(populations))
    gate = dict(skipped or {})
    gate.update({p: "not one of the hub's locations" for p in unknown if p not in gate})
    newest = max((h.origin for h in histories.values()), default=None)
    for place in [p for p, h in histories.items() if h.origin != newest]:
        gate[place] = (f"no value for the week ending {newest.date()} (last reported "
                       f"{histories[place].origin.date()})") if newest is not None else ""
        del histories[place]
    return Panel(histories, skipped=gate, name=f"hub {target} as of {pd.Timestamp(as_of).date()}",
                 as_of=pd.Timestamp(as_of))


def panel_of(vintage: WeeklyVintage, populations: Mapping[str, int] = POPULATION) -> Panel:
    """The panel of a cached hub vintage (:mod:`pipeline.data.hub.nhsn_vintages`), the locations
    its gate skipped named on it."""
    return vintage_panel(vintage.frame, vintage.target, populations, vintage.as_of,
                         skipped=vintage.skipped)


def reference_date_for(as_of: pd.Timestamp) -> pd.Timestamp:
    """The round a vintage released on ``as_of`` serves: the first Saturday at least
    :data:`DUE_DAYS_BEFORE_REFERENCE` days after it (a Wednesday release serves that
    Saturday's round; a holiday's Thursday release the same round, a day late)."""
    day = pd.Timestamp(as_of).normalize()
    saturday = day + pd.Timedelta(days=(SATURDAY - day.weekday()) % DAYS_PER_WEEK)
    return saturday if (saturday - day).days >= DUE_DAYS_BEFORE_REFERENCE - 1 else \
        saturday + pd.Timedelta(days=DAYS_PER_WEEK)


@dataclass(frozen=True, eq=False)
class HubRound:
    """A round: its reference date, the vintage it was made from (``as_of`` and its panel) and
    the forecast origin (the vintage's last week)."""

    reference: pd.Timestamp
    as_of: pd.Timestamp
    panel: Panel

    @property
    def origin(self) -> pd.Timestamp:
        return self.panel.last_date

    @property
    def lag_weeks(self) -> int:
        """Weeks between the origin and the reference date (1 when the data are a week behind,
        as the hub's are on a Wednesday)."""
        return int((self.reference - self.origin).days // DAYS_PER_WEEK)

    def steps(self, horizons: Sequence[int] = HUB_HORIZONS) -> tuple[int, ...]:
        """Weeks after the origin of each hub horizon (≤ 0: a week in the data, nowcast)."""
        return tuple(h + self.lag_weeks for h in horizons)

    def target_end(self, horizon: int) -> pd.Timestamp:
        return self.reference + pd.Timedelta(days=DAYS_PER_WEEK * horizon)


def hub_rounds(vintages: Sequence[tuple[pd.Timestamp, Panel]],
               serving: Callable[[pd.Timestamp], pd.Timestamp] = reference_date_for
               ) -> list[HubRound]:
    """One round per vintage (the newest vintage released by a round's due date serves it),
    oldest first; ``serving`` maps a release date to the round it serves (the hub's calendar,
    :meth:`pipeline.outputs.hub_calendar.HubCalendar.serving`; by default the weekly rule)."""
    by_round: dict[pd.Timestamp, tuple[pd.Timestamp, Panel]] = {}
    for as_of, panel in sorted(vintages, key=lambda v: v[0]):
        by_round[pd.Timestamp(serving(as_of))] = (as_of, panel)
    return [HubRound(ref, as_of, panel) for ref, (as_of, panel) in sorted(by_round.items())]
