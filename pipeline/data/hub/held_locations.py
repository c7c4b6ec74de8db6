"""Revisions waiting per location: the locations of a hub target whose settled history a release
revised beyond the policy, held for review one by one while the other locations go live
(issue 37, item 4; issue 39).

A release is judged location by location (:func:`pipeline.data.hub.nhsn_vintages.
check_weekly_successor`). A location whose settled weeks change beyond the revision policy is
**held**: the release goes live for every other location, and the held one is left out of every
vintage read from then on, and, while it is held, is forecast from its last accepted series:
the weeks the release revised beyond the policy keep their accepted values, the weeks after
them are the release's (named in the vintage's ``held``: "revision held for review …"), so no
forecast is made from the disputed revision and the location is not left out. Its last
accepted series stays in the archive (``vintages/``) and is the reference every later release
is judged against, until

* a later release no longer breaks the policy against that reference (the source took the
  revision back): the hold ends by itself; or
* the next release repeats the revision (its series of the location agrees, within the policy,
  with the release that was held: the source stands by it): the revision is accepted by itself
  for that location, recorded on the hold (``settled``: what changed, when, why), and the
  location reads from the revised series from that release on (issue 49: an unattended
  deployment must not leave a location out for a season because nobody answered); or
* the operator accepts it for that location alone (``flowcast data accept-revisions
  --target T LOCATION``): from the live vintage on, the location reads as released.

FluSight's real releases: the release of 2024-11-20 (the first of the 2024-25 season) revised
Louisiana's week ending 2022-02-19 from 39 to 170 admissions and Ohio's weeks ending 2023-05-20
and 2023-07-29 (11 -> 218, 9 -> 117); the whole release used to be held, and every release
after it (27 of 59). Now those two locations are held and the other 51 go live.

A location **missing** from a newer release altogether (no row at all, and not one the gate
skipped) is held the same way (``kind`` "missing"): it keeps its last accepted series as its
reference, is named in every vintage read from then on ("missing from the release of …"), and
the release goes live for the others; when it is back, it is judged against that reference.
A release missing more than a quarter of the locations is a broken payload, refused whole.

Kept as ``<dataset dir>/held-locations.json`` (written atomically): for each location, its holds
as ``since`` (the release that was held), ``reference`` (the release its accepted series is
from), ``until`` (the release from which it reads again; null while waiting), ``reason`` and ``kind``
("revision" or "missing"; files written before it read as "revision").
"""
from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal

from pipeline.errors import ConfigError
from pipeline.io import atomic_write_text

HOLDS_FILE = "held-locations.json"
# why a location is held: its settled weeks revised beyond the policy, or the location missing
# from a newer release altogether (issue 39: one state missing used to refuse the whole release)
HoldKind = Literal["revision", "missing"]
# More places held at once than this share of the source's places is a broken payload, held (or
# refused) whole: on the real releases at most 4 of 53 hub locations (FluSight) and 1 of 58
# counties (CDPH's four-month step) are held by one release.
MAX_HELD_SHARE = 0.25


@dataclass(frozen=True)
class Hold:
    """One location held from the release of ``since`` (ISO date) until ``until`` (None:
    waiting), judged against its series in the release of ``reference``."""

    location: str
    since: str
    reference: str
    reason: str
    until: str | None = None
    kind: HoldKind = "revision"
    # how the hold ended, in words (None while waiting, and in files written before it)
    settled: str | None = None

    def note(self) -> str:
        """How a vintage read without this place names it (its ``skipped``)."""
        if self.kind == "missing":
            return (f"{self.location}: missing from the release of {self.since} (its series of "
                    f"{self.reference} kept until it is back): {self.reason}")
        return (f"{self.location}: revision held for review since the release of {self.since} "
                f"(its series of {self.reference} kept): {self.reason}")

    def covers(self, as_of: str) -> bool:
        """Is a vintage released on ``as_of`` (ISO date) read without this location?"""
        return self.since <= as_of and (self.until is None or as_of < self.until)


@dataclass(frozen=True)
class Holds:
    """Every hold of one target, in the order they began."""

    entries: tuple[Hold, ...] = ()

    def waiting(self) -> dict[str, Hold]:
        """The locations whose revision waits for review, each with its open hold."""
        return {h.location: h for h in self.entries if h.until is None}

    def at(self, as_of: str) -> dict[str, Hold]:
        """The locations a vintage released on ``as_of`` is read without."""
        return {h.location: h for h in self.entries if h.covers(as_of)}

    def opened(self, found: Mapping[str, str], *, since: str, reference: str,
               missing: Mapping[str, str] | None = None,
               repeated: Mapping[str, str] | None = None) -> Holds:
        """These holds after a release of ``since`` judged ``found`` (location -> why) beyond
        the policy and left ``missing`` (location -> why) out: new holds opened (against
        ``reference``), holds no longer breaking nor missing ended (a location that is back
        and agrees with its reference reads again: the source took the revision back), and
        the revisions the release ``repeated`` (location -> what) accepted: the source stands
        by them, so the location reads from the revised series from this release on."""
        waiting, gone, kept = self.waiting(), dict(missing or {}), dict(repeated or {})
        held = {**found, **gone}

        def settle(h: Hold) -> Hold:
            if h.until is not None or h.location in held:
                return h
            why = (f"accepted on {since}: the release of {since} repeats the revision (the "
                   "source stands by it)" if h.location in kept else
                   f"ended on {since}: the location is back in the release of {since}"
                   if h.kind == "missing" else
                   f"ended on {since}: the release of {since} takes the revision back")
            return replace(h, until=since, settled=why)

        ended = [settle(h) for h in self.entries]
        new = [Hold(loc, since, reference, why, kind="missing" if loc in gone else "revision")
               for loc, why in sorted(held.items()) if loc not in waiting]
        return Holds((*ended, *new))

    def accepted(self, locations: tuple[str, ...], *, live: str) -> Holds:
        """The holds of ``locations`` ended by the operator: read again from the live vintage
        (released on ``live``) on. Every location named must be waiting."""
        waiting = self.waiting()
        unknown = [loc for loc in locations if loc not in waiting]
        if unknown:
            raise ConfigError(f"no revision waits for {', '.join(unknown)}; waiting: "
                              f"{', '.join(sorted(waiting)) or 'none'}")
        return Holds(tuple(replace(h, until=live, settled=f"accepted by the operator from the "
                                                          f"release of {live}")
                           if h.until is None and h.location in locations
                           else h for h in self.entries))


def read_holds(directory: Path) -> Holds:
    """The holds kept in ``directory`` (none when the file is missing)."""
    path = directory / HOLDS_FILE
    if not path.is_file():
        return Holds()
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return Holds(tuple(Hold(**entry) for entry in data["holds"]))
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"damaged {path}: {exc}; delete it to release every held location "
                          f"(they are then judged against the live vintage again)") from exc


def write_holds(directory: Path, holds: Holds) -> None:
    atomic_write_text(directory / HOLDS_FILE,
                      json.dumps({"holds": [asdict(h) for h in holds.entries]}, indent=1) + "\n")


def record_release(directory: Path, holds: Holds, *, as_of: str, accepted: bool,
                   found: Mapping[str, str], missing: Mapping[str, str] | None = None,
                   reference: str | None = None,
                   repeated: Mapping[str, str] | None = None) -> None:
    """The holds after a release of ``as_of`` went live, written when they change: with
    ``accepted`` (the operator took the whole release) every waiting hold ends; otherwise the
    places ``found`` revised and those ``missing`` are held against ``reference`` (the live
    vintage the release was judged against) and the others' holds end (:meth:`Holds.opened`)."""
    after = (holds.accepted(tuple(holds.waiting()), live=as_of) if accepted else
             holds.opened(found, since=as_of, reference=reference or as_of, missing=missing,
                          repeated=repeated))
    if after != holds:
        write_holds(directory, after)
