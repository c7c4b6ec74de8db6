"""The hub's calendar: which round a release serves, and which round is due on a day.

A hub names its rounds by reference date (a Saturday) in its ``tasks.json``; a round's files
are due by its deadline, the Wednesday before the reference date (23:59 in the hub's
timezone), except where the hub moved it for a holiday. The round a release serves is the
first round of the calendar whose deadline is on or after the release's date: a release on a
holiday's Monday after the reference date (the COVID-19 hub's round of 2025-12-27, due Monday
2025-12-29) serves that round, not the next one, and a Wednesday release the round of that
week. A date the calendar has no round for (FluSight off season; before or after the hub's
listed rounds) serves none.

Before the hub's first round (design periods: the RSV hub's rounds begin 2025-09-20, its data
in 2024-11) a release serves the weekly round of :func:`pipeline.panels.hub.reference_date_for`
(the first Saturday at least two days after it): :meth:`HubCalendar.serving`, which the track
record's rounds use.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import pandas as pd

from pipeline.errors import ConfigError
from pipeline.outputs.hub_tasks import hub_round_ids
from pipeline.panels.hub import reference_date_for

DAYS_BEFORE_REFERENCE = 3        # Wednesday's deadline before Saturday's reference date

# Deadlines the hubs moved for holidays (their announcements). NHSN released on Thursday in the
# weeks of Christmas and New Year 2024 (both Wednesdays holidays), and the COVID-19 hub moved
# its deadlines with it; for the round of 2025-12-27 it moved the deadline to Monday 2025-12-29,
# the day NHSN released. The RSV hub is run by the same CDC team on the same NHSN release and
# moved its deadline with the COVID-19 hub's; FluSight released on the Wednesdays themselves.
DEADLINE_SHIFTS: Mapping[str, Mapping[dt.date, dt.date]] = {
    "covid": {dt.date(2024, 12, 28): dt.date(2024, 12, 26),
              dt.date(2025, 1, 4): dt.date(2025, 1, 2),
              dt.date(2025, 12, 27): dt.date(2025, 12, 29)},
    "rsv": {dt.date(2025, 12, 27): dt.date(2025, 12, 29)},
    "flu": {},
}


@dataclass(frozen=True)
class HubCalendar:
    """A hub's rounds (their reference dates, oldest first) and their deadlines
    (``shifts``: reference date -> the day it is due, where it is not the Wednesday before)."""

    references: tuple[dt.date, ...]
    shifts: Mapping[dt.date, dt.date] = field(default_factory=dict)
    hub: str = "the hub"

    def __post_init__(self) -> None:
        if list(self.references) != sorted(set(self.references)):
            raise ConfigError(f"{self.hub}'s rounds must be distinct and in order")
        unknown = sorted(set(self.shifts) - set(self.references))
        if unknown and self.references:
            raise ConfigError(f"{self.hub}: a deadline is moved for {unknown[0]}, which is no "
                              f"round of its tasks.json")

    @classmethod
    def of_tasks(cls, tasks: Mapping[str, Any], disease: str, hub: str = "the hub"
                 ) -> HubCalendar:
        """The calendar of a hub's ``tasks.json`` (its round ids, reference dates) with the
        disease's known deadline shifts (:data:`DEADLINE_SHIFTS`) that fall on its rounds."""
        try:
            references = tuple(dt.date.fromisoformat(r) for r in hub_round_ids(tasks))
        except ValueError as error:
            raise ConfigError(f"{hub}'s tasks.json names a round that is no date: {error}"
                              ) from error
        shifts = {r: d for r, d in DEADLINE_SHIFTS.get(disease, {}).items() if r in references}
        return cls(references, shifts, hub)

    def deadline(self, reference: dt.date) -> dt.date:
        """The day a round's files are due (the hub's timezone)."""
        return self.shifts.get(reference,
                               reference - dt.timedelta(days=DAYS_BEFORE_REFERENCE))

    def round_for(self, release: dt.date) -> dt.date | None:
        """The round a release of ``release`` serves (module docstring); None where the hub
        has no round open then (off season, or outside its listed rounds)."""
        for reference in self.references:
            if self.deadline(reference) >= release:
                return reference if self._open(reference, release) else None
        return None

    def _open(self, reference: dt.date, day: dt.date) -> bool:
        """Is ``day`` within the round's window: after the previous round's deadline, and no
        more than a week before its own (a round after an off-season gap opens a week before
        its deadline, not at the end of the last season)?"""
        earlier = [r for r in self.references if r < reference]
        start = (self.deadline(earlier[-1]) if earlier and
                 (reference - earlier[-1]).days <= 7 else
                 self.deadline(reference) - dt.timedelta(days=7))
        return start < day <= self.deadline(reference)

    def due_on(self, day: dt.date) -> dt.date | None:
        """The round whose deadline is ``day`` (None: no round is due that day)."""
        return next((r for r in self.references if self.deadline(r) == day), None)

    def serving(self, release: pd.Timestamp) -> pd.Timestamp:
        """The round a release serves for the track record: the hub's (:meth:`round_for`), or
        before the hub's first round and off season, the weekly round
        (:func:`reference_date_for`)."""
        found = self.round_for(pd.Timestamp(release).date())
        return pd.Timestamp(found) if found is not None else reference_date_for(release)

    def rounds_between(self, first: dt.date, last: dt.date) -> list[dt.date]:
        """The hub's rounds due within ``first`` … ``last`` (their deadlines, inclusive)."""
        return [r for r in self.references if first <= self.deadline(r) <= last]

    def describe(self) -> str:
        if not self.references:
            return f"{self.hub} lists no round"
        return (f"{self.hub}'s {len(self.references)} rounds, {self.references[0]} … "
                f"{self.references[-1]}")


def weekly_calendar(references: Sequence[dt.date]) -> HubCalendar:
    """A calendar of the given Saturdays with Wednesday deadlines (tests, design panels)."""
    return HubCalendar(tuple(sorted(references)))


__all__ = ["DEADLINE_SHIFTS", "HubCalendar", "weekly_calendar"]
