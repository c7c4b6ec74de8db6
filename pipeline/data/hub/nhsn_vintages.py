"""The weekly hub targets (NHSN admissions, NSSP ED-visit shares) as vintages: what a vintage is,
the validation gate and revision policy it passes, and the cache that keeps every one.

A target's payload (Socrata rows as received, or the canonical target CSV an import writes)
becomes long rows for the validation gate (:mod:`pipeline.data.core.gate`): locations only the hub's
53 (territories and HHS regions dropped as known non-hub places), weeks on Saturday and not after
the vintage's date, one row per week, no gap, admissions whole, not negative, at most 0.5 % of the
location's population in a week and plausible against the location's previous weeks
(:data:`WEEKLY`), ED shares within 0 … 0.5. A location that fails is skipped and named
(:attr:`WeeklyVintage.skipped`); a vintage is committed under the cache lock
(:mod:`pipeline.data.core.vintages`) against the revision policy (:class:`RevisionPolicy`).

Cache: ``<data dir>/nhsn/<target, slugged>/`` (manifest, live payload, ``vintages/``, ``held/``).
The live source and the loader are :mod:`pipeline.data.hub.nhsn`; imports of a hub's target data
:mod:`pipeline.data.hub.target_import`.
"""
from __future__ import annotations

import bisect
import logging
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import date, datetime
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from pipeline.data.core.cache import (CachedPayload, CacheManifest, DatasetCache, SourceKind,
                                      RevisionRefusedError, utc_now)
from pipeline.data.core.revision_policy import (HELD, RevisionPolicy, describe_breaks,
                                                settled_breaks)
from pipeline.data.core.decoding import decode_csv_frame, decode_json_records
from pipeline.data.core.fallback import DEFAULT_LOCK_TIMEOUT_S
from pipeline.data.core.gate import GateRules, Places, ShareBound, admissions_bound, gate
from pipeline.data.hub.held_locations import (MAX_HELD_SHARE, Hold, Holds, read_holds,
                                                record_release, write_holds)
from pipeline.data.hub.locations import (JURISDICTION_LOCATION, NAME_LOCATION,
                                         NOT_HUB_JURISDICTIONS, POPULATION, US, hub_location)
from pipeline.data.hub.release import refuse_future, refuse_implausible
from pipeline.data.core.plausibility import JumpRule
from pipeline.data.core.vintages import Committed, Older, VintageArchive, manifest_as_of
from pipeline.errors import ConfigError, DataSourceError, ValidationError
from pipeline.io import sha256_bytes

log = logging.getLogger(__name__)

HOSP_COVID = "wk inc covid hosp"
HOSP_FLU = "wk inc flu hosp"
HOSP_RSV = "wk inc rsv hosp"
ED_COVID = "wk inc covid prop ed visits"
ED_FLU = "wk inc flu prop ed visits"
ED_RSV = "wk inc rsv prop ed visits"
Disease = Literal["covid", "flu", "rsv"]
DISEASES: tuple[Disease, ...] = ("covid", "flu", "rsv")
CACHE_FOLDER = "nhsn"
SATURDAY = 5
HRD_OFFICIAL, HRD_PRELIMINARY, NSSP = "ua7e-t2fy", "mpgq-jmmr", "rdmq-nq56"
FIRST_WEEK = date(2024, 11, 9)   # the first week of the hub's target data

# Admissions against the location's own previous weeks (pipeline.data.core.plausibility): on the hub's
# 44 real vintages the largest ratio of a week to this bound is 0.69 (Pennsylvania's 6,124 for
# the week ending 2024-11-16 in the release of 2024-11-20, after 868; revised to 1,005 a week
# later); every other vintage stays below 0.23.
WEEKLY = JumpRule(window=8, jump_factor=10.0, floor=20, growth_factor=6.0, growth_window=2,
                  unit="week")
ED_SHARE_MAX = 0.5   # the largest real share in the hub's data: 0.0614


@dataclass(frozen=True)
class TargetSpec:
    """One hub target: what it counts, where it is read live and where it is cached."""

    target: str
    disease: Disease
    kind: Literal["admissions", "ed-share"]
    live_column: str          # HRD count column, or NSSP percent column

    @property
    def key(self) -> str:
        return self.target

    @property
    def dataset_id(self) -> str:
        return re.sub(r"[^a-z0-9]+", "-", self.target.lower()).strip("-")

    @property
    def cache_folder(self) -> str:
        return CACHE_FOLDER


TARGETS: dict[str, TargetSpec] = {s.target: s for s in (
    TargetSpec(HOSP_COVID, "covid", "admissions", "totalconfc19newadm"),
    TargetSpec(HOSP_FLU, "flu", "admissions", "totalconfflunewadm"),
    TargetSpec(HOSP_RSV, "rsv", "admissions", "totalconfrsvnewadm"),
    TargetSpec(ED_COVID, "covid", "ed-share", "percent_visits_covid"),
    TargetSpec(ED_FLU, "flu", "ed-share", "percent_visits_influenza"),
    TargetSpec(ED_RSV, "rsv", "ed-share", "percent_visits_rsv"))}


def target_spec(target: str) -> TargetSpec:
    spec = TARGETS.get(target.strip())
    if spec is None:
        raise ConfigError(f"unknown hub target {target!r}; known: {', '.join(TARGETS)}")
    return spec


def disease_targets(disease: str) -> tuple[str, str]:
    """The admissions and ED-share targets of ``disease`` (covid, flu or rsv)."""
    if disease not in DISEASES:
        raise ConfigError(f"disease must be one of {', '.join(DISEASES)}, got {disease!r}")
    return (next(t for t, s in TARGETS.items() if s.disease == disease and s.kind == "admissions"),
            next(t for t, s in TARGETS.items() if s.disease == disease and s.kind == "ed-share"))


@dataclass(frozen=True, eq=False)
class WeeklyVintage:
    """One release of one target: ``frame`` has ``target_end_date`` (datetime64[ns], Saturdays),
    ``location`` (str: ``US`` or two-digit FIPS) and ``value`` (float64), sorted by week and
    location; ``skipped`` names each location the gate dropped, with why."""

    target: str
    as_of: pd.Timestamp
    frame: pd.DataFrame
    skipped: Mapping[str, str] = field(default_factory=dict)
    source: str = ""
    derived: Mapping[str, str] = field(default_factory=dict)   # location -> how it was made
    missing: Mapping[str, tuple[str, ...]] = field(default_factory=dict)  # NA weeks, by place
    # locations forecast from their accepted series while a revision is held, with why
    held: Mapping[str, str] = field(default_factory=dict)

    @property
    def locations(self) -> tuple[str, ...]:
        return tuple(sorted(self.frame["location"].unique()))

    @property
    def last_week(self) -> pd.Timestamp:
        return pd.Timestamp(self.frame["target_end_date"].max())


# ------------------------------------------------------------------------------ the gate

HUB_PLACES = Places("hub location", POPULATION, "hub locations.csv")


def gate_rules(spec: TargetSpec, column: str, *, percent: bool = False) -> GateRules:
    """The gate of a target whose values are in ``column`` (NSSP's raw percent: ``percent``)."""
    if spec.kind == "admissions":
        return GateRules(source=f"NHSN {spec.target}", places=HUB_PLACES,
                         counts=(admissions_bound(column),), step_days=7, weekday=SATURDAY,
                         jump=WEEKLY, missing_weeks=True)
    return GateRules(source=f"NSSP {spec.target}", places=HUB_PLACES,
                     shares=(ShareBound(column, ED_SHARE_MAX * (100.0 if percent else 1.0)),),
                     step_days=7, weekday=SATURDAY, missing_weeks=True)


def _weeks(text: pd.Series) -> pd.Series:
    """Dates as the hub and Socrata write them (``2024-11-09``, ``2024-11-09T00:00:00.000``)."""
    return pd.to_datetime(text.astype("string").str.strip().str[:10], format="%Y-%m-%d",
                          errors="coerce")


def rows_of_payload(spec: TargetSpec, data: bytes, *, suffix: str, source: str
                    ) -> tuple[pd.DataFrame, GateRules, float]:
    """A payload as the gate's long rows (``place``, ``date``, the value column), its rules and
    the factor that turns the gated values into the target's unit. ``csv``: the canonical
    target CSV (``target_end_date, location, value``); ``json``: Socrata rows as received."""
    if suffix == "csv":
        raw = decode_csv_frame(data, source=source, max_bytes=MAX_CSV_BYTES)
        missing = [c for c in ("target_end_date", "location", "value") if c not in raw.columns]
        if missing:
            raise ValidationError(f"{source}: missing column(s) {missing} of a hub target CSV; "
                                  f"columns present: {list(raw.columns)[:10]}")
        rows = pd.DataFrame({"place": raw["location"].astype("string").str.strip(),
                             "date": _weeks(raw["target_end_date"]), "value": raw["value"]})
        return rows, gate_rules(spec, "value"), 1.0
    records = pd.DataFrame.from_records(decode_json_records(data, source=source,
                                                            max_bytes=MAX_JSON_BYTES))
    if records.empty:
        raise ValidationError(f"{source}: empty payload (no rows) for {spec.target}")
    if spec.kind == "admissions":
        needed = ("weekendingdate", "jurisdiction", spec.live_column)
        _need(records, needed, source)
        names = records["jurisdiction"].astype("string").str.strip()
        records, names = records[~names.isin(list(NOT_HUB_JURISDICTIONS))], names.str.upper()
        places = names[records.index].map(JURISDICTION_LOCATION).fillna(names[records.index])
        dates = records["weekendingdate"]
    else:
        needed = ("week_end", "geography", "county", spec.live_column)
        _need(records, needed, source)
        records = records[records["county"].astype("string").str.strip() == "All"]
        names = records["geography"].astype("string").str.strip()
        places = names.str.casefold().map(NAME_LOCATION).fillna(names)
        dates = records["week_end"]
    rows = pd.DataFrame({"place": places.to_numpy(), "date": _weeks(dates).to_numpy(),
                         spec.live_column: records[spec.live_column].to_numpy()})
    percent = spec.kind == "ed-share"
    return rows, gate_rules(spec, spec.live_column, percent=percent), 0.01 if percent else 1.0


def _need(records: pd.DataFrame, columns: Sequence[str], source: str) -> None:
    missing = [c for c in columns if c not in records.columns]
    if missing:
        raise ValidationError(f"{source}: missing field(s) {missing}; fields present: "
                              f"{sorted(map(str, records.columns))[:12]}")


# Genuine sizes (docs/data.md): a vintage as the canonical CSV is at most 196,811 bytes in the
# hub's design data (ED shares since 2022-10-01; admissions 47,291); one Socrata page of 1,000
# rows 98 KB (HRD) or 116 KB (NSSP).
MAX_CSV_BYTES = 16 << 20
MAX_JSON_BYTES = 16 << 20
_PARSED: dict[tuple[str, str], WeeklyVintage] = {}
_PARSED_LIMIT = 256


def parse_vintage(spec: TargetSpec, data: bytes, *, suffix: str, as_of: date,
                  source: str) -> WeeklyVintage:
    """A payload of ``spec`` through the gate, as a :class:`WeeklyVintage` (parsed once per
    process for the same bytes and date)."""
    key = (sha256_bytes(data), f"{spec.target}|{suffix}|{as_of}")
    if key not in _PARSED:
        rows, rules, scale = rows_of_payload(spec, data, suffix=suffix, source=source)
        gated = gate(rows, rules, source=source, as_of=pd.Timestamp(as_of))
        value = gated.frame[rules.columns[0]].to_numpy(np.float64) * scale
        frame = pd.DataFrame({"target_end_date": gated.frame["date"].to_numpy("datetime64[ns]"),
                              "location": gated.frame["place"].astype(str).to_numpy(),
                              "value": value}).sort_values(
            ["target_end_date", "location"], ignore_index=True)
        frame, derived, left_out = _national_from_states(frame, spec, dict(gated.skipped))
        if len(_PARSED) >= _PARSED_LIMIT:
            _PARSED.pop(next(iter(_PARSED)))
        _PARSED[key] = WeeklyVintage(spec.target, pd.Timestamp(as_of), frame,
                                     {**gated.skipped, **left_out},
                                     derived=derived, missing=dict(gated.missing))
    parsed = _PARSED[key]
    return WeeklyVintage(parsed.target, parsed.as_of, parsed.frame, parsed.skipped, source,
                         parsed.derived, parsed.missing)


def _national_from_states(frame: pd.DataFrame, spec: TargetSpec, skipped: Mapping[str, str]
                          ) -> tuple[pd.DataFrame, dict[str, str], dict[str, str]]:
    """A release of admissions without a national row (or whose national row the gate
    skipped): the US is the sum of the 52 states, on every week all of them report (issue 39,
    problem 6: every round failed). On the real releases the states sum to the US row within
    0.2 % (COVID-19, every week of the release of 2025-09-24; median 0.03 %). A share (the ED
    visits) cannot be summed, nor a week with a state missing: the US is then left out and
    named (the third value: location -> why, for the vintage's ``skipped``), the states' release
    goes live and the round publishes them without a national forecast."""
    states = [loc for loc in POPULATION if loc != US]
    if US in set(frame["location"]):
        return frame, {}, {}
    wide = frame.pivot_table(index="target_end_date", columns="location", values="value")
    absent = [loc for loc in states if loc not in wide.columns]
    total = wide[states].dropna().sum(axis=1) if not absent else pd.Series(dtype=np.float64)
    if spec.kind != "admissions" or total.empty:
        why = ("a share cannot be summed from the states" if spec.kind != "admissions" else
               f"the states do not all report ({len(absent)} missing, e.g. "
               f"{', '.join(absent[:3])})" if absent else "no week on which every state reports")
        gate_note = skipped.get(US)
        return frame, {}, {US: f"{gate_note or 'US: no national row in the release'}; {why}: "
                               f"the national forecast is left out"}
    national = pd.DataFrame({"target_end_date": total.index.to_numpy("datetime64[ns]"),
                             "location": US, "value": total.to_numpy(np.float64)})
    why = skipped.get(US, "no national row in the release")
    note = f"{why}: the national value is the sum of the 52 states ({len(total)} weeks)"
    return (pd.concat([frame, national], ignore_index=True).sort_values(
        ["target_end_date", "location"], ignore_index=True), {US: note}, {})


def canonical_csv(frame: pd.DataFrame) -> bytes:
    """A vintage's rows as the canonical target CSV the cache keeps for imports."""
    out = frame[["target_end_date", "location", "value"]].sort_values(
        ["target_end_date", "location"], kind="stable")
    out = out.assign(target_end_date=pd.to_datetime(out["target_end_date"]).dt.strftime(
        "%Y-%m-%d"))
    return out.to_csv(index=False, lineterminator="\n").encode()


# ------------------------------------------------------------------------------ revisions


# A new vintage against the live one: weeks ending more than 4 weeks before the live vintage's
# last week are settled. On the hub's 44 real vintages the largest settled revisions are
# Arizona's, down to 0.37× and back up 2.7× a fortnight later (516 → 191 → 516 for the week
# ending 2024-11-09), and Puerto Rico's 13 → 107 (lag 74 days): a revision of a settled week
# beyond 3× its value (or 100 admissions) is held for review. Totals are not checked: a state's
# settled week may legitimately fall by more than any small share.
# Judged location by location (check_weekly_successor); a settled week that read 0 and becomes
# positive is a backfill, not a revision (backfill_ok): FluSight's real releases have 6 such
# settled weeks (at most 0 -> 9), the COVID-19 hub's none; settled non-zero weeks changing beyond
# the policy: Ohio (11 -> 218, 9 -> 117) and Louisiana (39 -> 170) on 2024-11-20, Arizona
# (48 -> 187) on 2025-02-05, Puerto Rico (30 -> 655, 79 -> 342) on 2025-03-19: each held alone.
ADMISSIONS_POLICY = RevisionPolicy(open_days=28, settled_abs=100.0, settled_rel=2.0,
                                   max_total_drop=None, backfill_ok=True)
# NSSP shares: the largest settled revision in the 15 real vintages is 0.0008 (0.08 points)
ED_POLICY = RevisionPolicy(open_days=28, settled_abs=0.005, settled_rel=0.5, max_total_drop=None,
                           backfill_ok=True)


def policy_of(spec: TargetSpec) -> RevisionPolicy:
    return ADMISSIONS_POLICY if spec.kind == "admissions" else ED_POLICY


@dataclass(frozen=True)
class Successor:
    """A newer release judged location by location against the live one: the locations whose
    settled weeks it revises beyond the policy, and those it leaves out altogether (each
    location -> why); both are held alone, the release live for the others."""

    revised: Mapping[str, str] = field(default_factory=dict)
    missing: Mapping[str, str] = field(default_factory=dict)
    # held locations whose revision this release repeats (the source stands by it): accepted
    repeated: Mapping[str, str] = field(default_factory=dict)


def check_weekly_successor(new: WeeklyVintage, cached: WeeklyVintage, policy: RevisionPolicy,
                           *, references: Mapping[str, WeeklyVintage] | None = None
                           ) -> Successor:
    """The locations of ``new`` to hold for review, judged one by one: each against ``cached``
    (the live vintage), or a held location against its reference vintage (``references``);
    a location of either that ``new`` lacks (and the gate did not skip) is missing. Raise
    :class:`RevisionRefusedError` unless ``new`` may replace ``cached`` at all: older,
    shrinking, a location dropped or failing the gate in a payload of the same date, more than
    a quarter of the locations missing (a broken payload, refused) or revised beyond
    ``policy`` (held whole)."""
    refs = references or {}
    _refuse_shape(new, cached)
    missing = _missing_locations(new, cached, refs)
    against_live = _revised_locations(new, cached, policy)
    judged = {loc: why for loc, why in (_location_revised(new, refs.get(loc, cached), loc, policy)
                                        for loc in new.locations
                                        if loc in refs or loc in against_live)
              if why is not None}
    repeated = {loc: why for loc, why in judged.items() if loc in refs and loc not in against_live}
    held = {loc: why for loc, why in judged.items() if loc not in repeated}
    if len(held) > MAX_HELD_SHARE * len(POPULATION):
        first = next(iter(held.values()))
        raise RevisionRefusedError(f"{new.target}: {len(held)} of the {len(POPULATION)} "
                                   f"locations revise settled weeks beyond the policy (more than "
                                   f"{MAX_HELD_SHARE:.0%}: the release is held whole); e.g. "
                                   f"{first}; {HELD}", hold=True)
    return Successor(held, missing, repeated)


def _missing_locations(new: WeeklyVintage, cached: WeeklyVintage,
                       references: Mapping[str, WeeklyVintage]) -> dict[str, str]:
    """The locations of the live vintage (or held, with a reference) that ``new`` lacks
    altogether, each with why: held alone. One missing from a payload of the same date, or
    more than :data:`MAX_HELD_SHARE` of the locations missing, refuses ``new``."""
    known = set(cached.locations) | set(references)
    gone = sorted(known - set(new.locations) - set(new.skipped))
    if not gone:
        return {}
    t, day = new.target, new.as_of.date()
    if new.as_of == cached.as_of:
        raise RevisionRefusedError(f"{t}: location dropped: {', '.join(gone)} in the cached "
                                   f"vintage of {cached.as_of.date()} but not in a new payload "
                                   f"of the same date; cached copy kept")
    if len(gone) > MAX_HELD_SHARE * len(POPULATION):
        raise RevisionRefusedError(f"{t}: {len(gone)} of the {len(POPULATION)} locations are "
                                   f"missing from the release of {day} (more than "
                                   f"{MAX_HELD_SHARE:.0%}: a broken payload, refused), e.g. "
                                   f"{', '.join(gone[:5])}; cached copy kept")
    return {loc: f"{t}: no row of {loc} in the release of {day}" for loc in gone}


def _refuse_shape(new: WeeklyVintage, cached: WeeklyVintage) -> None:
    """What no location-by-location judgement can mend (the first lines of
    :func:`check_weekly_successor`)."""
    t = new.target
    if new.as_of < cached.as_of:
        raise RevisionRefusedError(f"{t}: vintage date moves backwards: new {new.as_of.date()}, "
                                   f"the cached copy {cached.as_of.date()}; cached copy kept")
    new_first, old_first = new.frame["target_end_date"].min(), cached.frame["target_end_date"].min()
    if new_first > old_first:
        raise RevisionRefusedError(f"{t}: payload shrinks: new vintage starts "
                                   f"{pd.Timestamp(new_first).date()}, the cached copy "
                                   f"{pd.Timestamp(old_first).date()}; cached copy kept")
    if new.last_week < cached.last_week:
        raise RevisionRefusedError(f"{t}: last week moves backwards: new vintage ends "
                                   f"{new.last_week.date()}, the cached copy "
                                   f"{cached.last_week.date()}; cached copy kept")
    worse = sorted(set(cached.locations) & set(new.skipped))
    if worse and new.as_of == cached.as_of:
        raise RevisionRefusedError(f"{t}: {worse[0]} passes the validation gate in the cached "
                                   f"vintage of {cached.as_of.date()} but fails it in a new "
                                   f"payload of the same date ({new.skipped[worse[0]]}); cached "
                                   f"copy kept")


def _revised_locations(new: WeeklyVintage, reference: WeeklyVintage, policy: RevisionPolicy
                       ) -> set[str]:
    """The locations whose settled weeks in ``new`` break ``policy`` against ``reference``,
    every location's weeks judged at once (what :func:`_location_revised` says of one)."""
    columns = ["location", "target_end_date", "value"]
    common = reference.frame[columns].merge(new.frame[columns], on=["location", "target_end_date"],
                                            suffixes=("", "_new"))
    breaks = settled_breaks(common["value"].to_numpy(), common["value_new"].to_numpy(),
                            common["target_end_date"].to_numpy(), policy=policy,
                            last=reference.last_week)
    return set(common.loc[breaks, "location"])


def _location_revised(new: WeeklyVintage, reference: WeeklyVintage, location: str,
                      policy: RevisionPolicy) -> tuple[str, str | None]:
    """(``location``, why its settled weeks in ``new`` break ``policy`` against
    ``reference``, or None)."""
    mine = new.frame[new.frame["location"] == location]
    theirs = reference.frame[reference.frame["location"] == location]
    common = theirs.merge(mine, on="target_end_date", suffixes=("", "_new"))
    before, after = common["value"].to_numpy(), common["value_new"].to_numpy()
    breaks = settled_breaks(before, after, common["target_end_date"].to_numpy(), policy=policy,
                            last=reference.last_week)
    if not breaks.any():
        return location, None
    return location, describe_breaks(
        new.target, "value", before, after, breaks, policy=policy, last=reference.last_week,
        cells="week", example=lambda i: (f"{location} week ending "
                                         f"{pd.Timestamp(common['target_end_date'].iloc[i]).date()}"
                                         )) + (f" (against its series in the release of "
                                               f"{reference.as_of.date()})")


def with_holds(vintage: WeeklyVintage, holds: Holds,
               references: Mapping[str, WeeklyVintage] | None = None) -> WeeklyVintage:
    """``vintage`` as read while locations are held at its release date: a held revision is
    forecast from its accepted series (``references``: the release each hold's accepted
    series is from; the weeks it revised beyond the policy take their accepted values back,
    named in ``held``); a location missing from the release, or whose reference is not at
    hand, is left out (named in ``skipped``)."""
    held = holds.at(str(vintage.as_of.date()))
    if not held:
        return vintage
    refs = references or {}
    kept = {loc: h for loc, h in held.items() if h.kind == "revision" and h.reference in refs
            and loc in vintage.locations}
    frame = vintage.frame[~vintage.frame["location"].isin([loc for loc in held
                                                           if loc not in kept])]
    frame = _accepted_values(frame, {loc: refs[h.reference] for loc, h in kept.items()},
                             policy_of(target_spec(vintage.target)))
    skipped = {**vintage.skipped, **{loc: h.note() for loc, h in held.items() if loc not in kept}}
    return WeeklyVintage(vintage.target, vintage.as_of, frame, dict(sorted(skipped.items())),
                         vintage.source, vintage.derived, vintage.missing,
                         {loc: h.note() for loc, h in sorted(kept.items())})


def _accepted_values(frame: pd.DataFrame, references: Mapping[str, WeeklyVintage],
                     policy: RevisionPolicy) -> pd.DataFrame:
    """``frame`` with each location of ``references`` given back its accepted value on every
    week its release revised beyond ``policy`` against that reference."""
    out = frame.reset_index(drop=True).copy()
    for location, reference in references.items():
        theirs = reference.frame[reference.frame["location"] == location]
        mine = out[out["location"] == location]
        common = mine.reset_index().merge(theirs, on="target_end_date", suffixes=("", "_ref"))
        breaks = settled_breaks(common["value_ref"].to_numpy(), common["value"].to_numpy(),
                                common["target_end_date"].to_numpy(), policy=policy,
                                last=reference.last_week)
        rows = common["index"].to_numpy()[breaks]
        out.loc[rows, "value"] = common["value_ref"].to_numpy()[breaks]
    return out


# ------------------------------------------------------------------------------ the cache


def archive(cache: DatasetCache, spec: TargetSpec) -> VintageArchive:
    return VintageArchive(cache, spec)


def _cached(cache: DatasetCache, spec: TargetSpec, live: CachedPayload) -> WeeklyVintage | None:
    try:
        return parse_vintage(spec, live.payload, suffix=live.path.suffix.lstrip("."),
                             as_of=date.fromisoformat(str(live.manifest.data_as_of)[:10]),
                             source=str(live.path))
    except (DataSourceError, ValueError) as exc:
        log.warning("cached %s vintage no longer passes (%s); replacing it", spec.target, exc)
        return None


def commit_weekly(cache: DatasetCache, vintage: WeeklyVintage, payload: bytes, *,
                  suffix: str, source_kind: SourceKind, source: str, older: Older,
                  final_url: str | None = None, accept_revisions: bool = False,
                  lock_timeout_s: float = DEFAULT_LOCK_TIMEOUT_S,
                  today: date | None = None) -> Committed:
    """Store a gated vintage: live, archived (older, imports) or refused/held (module doc). A
    release dated after ``today`` is refused; a stale or implausible one held; locations
    revised beyond the policy held one by one (:mod:`pipeline.data.hub.held_locations`), the
    release live for the others."""
    spec = target_spec(vintage.target)
    day = today or utc_now().date()
    refuse_future(vintage.as_of.date(), day, source=source)
    folder = cache.directory(spec)
    holds = read_holds(folder)
    found: list[Successor] = []
    reference: list[str] = []

    def check(live: CachedPayload | None) -> None:
        if accept_revisions:
            return
        refuse_implausible(vintage.frame, vintage.as_of, vintage.last_week,
                           target=vintage.target, counts=spec.kind == "admissions")
        if live is None:
            return
        cached = _cached(cache, spec, live)
        if cached is not None and cached.as_of.date() > day:
            log.warning("the cached %s vintage is dated %s, after today: no reference, replaced",
                        spec.target, cached.as_of.date())   # stored by an older flowcast
            cached = None
        if cached is not None:
            found.append(check_weekly_successor(vintage, cached, policy_of(spec),
                                                references=_references(cache, spec, holds)))
            reference.append(str(cached.as_of.date()))

    frame = vintage.frame
    committed = archive(cache, spec).commit(
        payload, as_of=vintage.as_of.date(), suffix=suffix,
        older=older if not accept_revisions else "refuse", check=check,
        accept_hint="`flowcast data fetch --source nhsn --accept-revisions` (or `flowcast data "
                    "import --accept-revisions FILE`)",
        source_kind=source_kind, source=source, row_count=len(frame),
        first_date=str(frame["target_end_date"].min().date()),
        last_date=str(vintage.last_week.date()), data_as_of=str(vintage.as_of.date()),
        final_cumulative=None, final_url=final_url, lock_timeout_s=lock_timeout_s)
    if committed.action == "live":
        judged = found[0] if found else Successor()
        record_release(folder, holds, as_of=str(vintage.as_of.date()), accepted=accept_revisions,
                       found=judged.revised, missing=judged.missing,
                       reference=reference[0] if reference else None,
                       repeated=judged.repeated)
        for location, what in judged.repeated.items():
            log.warning("%s: the revision of %s held for review is repeated by the release of "
                        "%s: accepted (%s)", spec.target, location, vintage.as_of.date(), what)
    return committed


def _references(cache: DatasetCache, spec: TargetSpec, holds: Holds) -> dict[str, WeeklyVintage]:
    """Each waiting location's reference vintage (its last accepted series), from the
    archive."""
    waiting = holds.waiting()
    if not waiting:
        return {}
    kept = archive(cache, spec)
    by_date = {str(as_of): path for as_of, path in kept.listing()}
    out = {}
    for loc, hold in waiting.items():
        path = by_date.get(hold.reference)
        if path is not None:
            out[loc] = parse_vintage(spec, kept.read(path), suffix=path.suffix.lstrip("."),
                                     as_of=date.fromisoformat(hold.reference), source=str(path))
    return out


def read_with_holds(cache: DatasetCache, spec: TargetSpec, vintage: WeeklyVintage
                    ) -> WeeklyVintage:
    """``vintage`` as the round reads it (:func:`with_holds`), its held locations' accepted
    series from the archive."""
    holds = read_holds(cache.directory(spec))
    wanted = {h.reference for h in holds.at(str(vintage.as_of.date())).values()}
    if not wanted:
        return vintage
    kept = archive(cache, spec)
    references = {str(as_of): parse_vintage(spec, kept.read(path),
                                            suffix=path.suffix.lstrip("."), as_of=as_of,
                                            source=str(path))
                  for as_of, path in kept.listing() if str(as_of) in wanted}
    return with_holds(vintage, holds, references)


def revisions_waiting(target: str, data_dir: str | os.PathLike[str] | None = None
                      ) -> dict[str, Hold]:
    """The locations of ``target`` whose revision waits for review (what the report shows),
    each with its hold (since, reference, reason)."""
    return read_holds(DatasetCache.default(data_dir).directory(target_spec(target))).waiting()


def accept_location_revisions(target: str, locations: Sequence[str],
                              data_dir: str | os.PathLike[str] | None = None) -> dict[str, Hold]:
    """The operator accepts the waiting revision of each of ``locations`` (hub codes or postal
    abbreviations) alone: from the live vintage on, they read from the revised series. Returns
    the holds ended."""
    spec = target_spec(target)
    cache = DatasetCache.default(data_dir)
    manifest = cache.read_manifest(spec)
    if manifest is None:
        raise ConfigError(f"no cached {target} vintage: nothing to accept")
    codes = tuple(hub_location(loc).location for loc in locations)
    folder = cache.directory(spec)
    holds = read_holds(folder)
    write_holds(folder, holds.accepted(codes, live=str(manifest_as_of(manifest))))
    return {c: holds.waiting()[c] for c in codes}


def skipped_note(vintage: WeeklyVintage) -> tuple[str, ...]:
    derived = tuple(f"{vintage.target} vintage of {vintage.as_of.date()}: {loc}: {how}"
                    for loc, how in vintage.derived.items())
    if vintage.missing:
        derived += (f"{vintage.target} vintage of {vintage.as_of.date()}: weeks without a value "
                    f"(those weeks left out, the locations kept): "
                    + "; ".join(f"{loc} {len(d)} week(s) from {d[0]}"
                                for loc, d in vintage.missing.items()),)
    if vintage.held:
        derived += (f"{len(vintage.held)} location(s) of the {vintage.target} vintage of "
                    f"{vintage.as_of.date()} forecast from their accepted series while a "
                    "revision is held: " + "; ".join(vintage.held.values()),)
    if not vintage.skipped:
        return derived
    return derived + (f"{len(vintage.skipped)} location(s) left out of the {vintage.target} "
                      f"vintage of {vintage.as_of.date()} (each with why: the validation gate, "
                      "a revision held or the location missing): "
                      + "; ".join(vintage.skipped.values()),)


def cached_weekly_vintages(target: str, data_dir: str | os.PathLike[str] | None = None
                           ) -> list[WeeklyVintage]:
    """Every vintage of ``target`` the cache holds, oldest first (one per date), each through
    the gate (its skipped locations named on it); each file checked against its hash."""
    spec = target_spec(target)
    cache = DatasetCache.default(data_dir)
    kept, holds = archive(cache, spec), read_holds(cache.directory(spec))
    vintages = [parse_vintage(spec, kept.read(path), suffix=path.suffix.lstrip("."),
                              as_of=as_of, source=str(path)) for as_of, path in kept.listing()]
    by_date = {str(v.as_of.date()): v for v in vintages}
    return [with_holds(v, holds, by_date) for v in vintages]


def vintage_as_of(vintages: Sequence[WeeklyVintage], when: date | datetime | str | pd.Timestamp
                  ) -> WeeklyVintage | None:
    """The newest of ``vintages`` (oldest first) released on or before ``when``; None if none."""
    cut = pd.Timestamp(when).normalize()
    k = bisect.bisect_right([v.as_of for v in vintages], cut)
    return vintages[k - 1] if k else None


def live_manifest(target: str, data_dir: str | os.PathLike[str] | None = None
                  ) -> CacheManifest | None:
    return DatasetCache.default(data_dir).read_manifest(target_spec(target))


def held_count(target: str, data_dir: str | os.PathLike[str] | None = None) -> int:
    held = DatasetCache.default(data_dir).directory(target_spec(target)) / "held"
    return len(list(held.glob("payload-*.reason.json"))) if held.is_dir() else 0


def vintages_folder(target: str, data_dir: str | os.PathLike[str] | None = None) -> Path:
    return archive(DatasetCache.default(data_dir), target_spec(target)).folder
