"""CDPH's county file judged county by county against the live vintage (issue 39; issue 37,
item 4, for the hub's locations): the revision policy of :mod:`pipeline.data.california.cdph_source`
and the counties it holds alone.

A new vintage may not end earlier, start later, drop a county, or (same date) make a county fail
the gate that passes in the live copy: refused whole. Then each county's settled days (older
than 28 days before the live vintage's last day) are compared with the live vintage, or, for a
county already held, with its reference (its last accepted series): a county whose ``cases``,
``deaths`` or ``reported_cases`` change there beyond max(100, 50 %) is **held alone** (kept by
:mod:`pipeline.data.hub.held_locations`, the machinery the hub's locations use), the vintage
live for the others. More than :data:`~pipeline.data.hub.held_locations.MAX_HELD_SHARE` of the
counties at once, or the statewide total of the other counties over their common days falling
by more than 2 %, is a whole-file event: the payload is held for review.

Measured on the six real vintages: weekly successors hold no county; the four-month step
2021-04-28 → 2021-09-06 holds Los Angeles alone (2020-06-21, 1,043 → 1,573 cases).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from pipeline.data.california.cdph import COUNT_COLUMNS, CDPHVintage
from pipeline.data.california.chhs import CDPH_COUNTIES as SPEC
from pipeline.data.core.cache import RevisionRefusedError
from pipeline.data.core.revision_policy import (HELD, RevisionPolicy, describe_breaks,
                                                refuse_revisions, settled_breaks)
from pipeline.data.hub.held_locations import MAX_HELD_SHARE, Holds

DEFAULT_POLICY = RevisionPolicy(open_days=28, settled_abs=100, settled_rel=0.5, max_total_drop=0.02)


def check_cdph_successor(new: CDPHVintage, cached: CDPHVintage,
                         policy: RevisionPolicy = DEFAULT_POLICY, *,
                         references: Mapping[str, CDPHVintage] | None = None) -> dict[str, str]:
    """The counties of ``new`` to hold for review (county -> why), judged one by one: each
    against ``cached`` (the live vintage), a county already held against its reference
    vintage (``references``). Raise :class:`RevisionRefusedError` unless ``new`` may replace
    ``cached`` at all (module doc): older, shrinking, a county dropped, a county failing the
    gate in a payload of the same date, the statewide total of the other counties falling
    beyond the policy, or more than a quarter of the counties revised (held whole)."""
    key = SPEC.key
    refs = references or {}
    _refuse_cdph_shape(new, cached)
    held = _counties_revised(new, cached, policy, last=cached.as_of,
                             counties=[c for c in new.counties if c not in refs])
    for county, reference in refs.items():
        if county in new.counties:
            held |= {c: f"{why} (against its series in the vintage of "
                        f"{reference.as_of.date()})" for c, why in _counties_revised(
                            new, reference, policy, last=reference.as_of,
                            counties=[county]).items()}
    if len(held) > MAX_HELD_SHARE * len(cached.counties):
        raise RevisionRefusedError(
            f"{key}: {len(held)} of the {len(cached.counties)} counties revise settled days "
            f"beyond the policy (more than {MAX_HELD_SHARE:.0%}: the vintage is held whole); "
            f"e.g. {next(iter(held.values()))}; {HELD}", hold=True)
    _refuse_statewide_drop(new, cached, policy, judged_alone={*held, *refs})
    return held


def _refuse_cdph_shape(new: CDPHVintage, cached: CDPHVintage) -> None:
    """What no county-by-county judgement can mend (the first lines of
    :func:`check_cdph_successor`)."""
    key = SPEC.key
    if new.as_of < cached.as_of:
        raise RevisionRefusedError(
            f"{key}: last date moves backwards: new vintage ends {new.as_of.date()}, the cached "
            f"copy {cached.as_of.date()} (an older vintage); cached copy kept")
    new_first, old_first = new.frame["date"].min(), cached.frame["date"].min()
    if new_first > old_first:
        raise RevisionRefusedError(
            f"{key}: date range shrinks: new vintage starts {new_first.date()}, the cached copy "
            f"{old_first.date()}; cached copy kept")
    # a county the gate skipped in the new vintage is there, only not usable: not "dropped"
    dropped = sorted(set(cached.counties) - set(new.counties) - set(new.skipped))
    if dropped:
        raise RevisionRefusedError(
            f"{key}: county dropped: {', '.join(dropped)} in the cached vintage of "
            f"{cached.as_of.date()} but not in the new one ({len(new.counties)} counties); "
            f"cached copy kept")
    worse = sorted(set(cached.counties) & set(new.skipped))
    if worse and new.as_of == cached.as_of:
        raise RevisionRefusedError(
            f"{key}: {worse[0]} passes the validation gate in the cached vintage of "
            f"{cached.as_of.date()} but fails it in a new payload of the same date "
            f"({new.skipped[worse[0]]}); cached copy kept")


def _common_days(new: CDPHVintage, reference: CDPHVintage, counties: Sequence[str]
                 ) -> pd.DataFrame:
    """The county-days of ``counties`` both vintages hold, the reference's counts beside the
    new ones (``<column>_new``)."""
    mine = new.frame[new.frame["area"].isin(counties)]
    theirs = reference.frame[reference.frame["area"].isin(counties)]
    return theirs.merge(mine, on=["area", "date"], suffixes=("", "_new"))


def _counties_revised(new: CDPHVintage, reference: CDPHVintage, policy: RevisionPolicy, *,
                      last: pd.Timestamp, counties: Sequence[str]) -> dict[str, str]:
    """Each of ``counties`` whose settled days in ``new`` break ``policy`` against
    ``reference`` (whose last day is ``last``), with why: every column judged over every
    common county-day at once, the counties that break described one by one."""
    common = _common_days(new, reference, counties)
    dates = common["date"].to_numpy()
    breaks = {column: settled_breaks(common[column].to_numpy(np.int64),
                                     common[f"{column}_new"].to_numpy(np.int64), dates,
                                     policy=policy, last=last) for column in COUNT_COLUMNS}
    any_break = np.logical_or.reduce(list(breaks.values()))
    held: dict[str, str] = {}
    areas = common["area"].astype(str).to_numpy()
    for county in sorted(set(areas[any_break].tolist())):    # the few that break
        mine = areas == county
        column = next(c for c in COUNT_COLUMNS if (breaks[c] & mine).any())
        rows = common[mine]
        held[county] = describe_breaks(
            SPEC.key, column, rows[column].to_numpy(np.int64),
            rows[f"{column}_new"].to_numpy(np.int64), breaks[column][mine], policy=policy,
            last=last, cells="county-day",
            example=lambda i, rows=rows: f"{county} {pd.Timestamp(rows['date'].iloc[i]).date()}")
    return held


def _refuse_statewide_drop(new: CDPHVintage, cached: CDPHVintage, policy: RevisionPolicy, *,
                           judged_alone: set[str]) -> None:
    """The statewide total of each column over the common days of the counties not judged
    alone (held, or judged against their own reference) may fall by at most the policy's
    share: a whole-file event, refused whole."""
    others = [c for c in new.counties if c not in judged_alone]
    common = _common_days(new, cached, others)
    for column in COUNT_COLUMNS:
        refuse_revisions(
            SPEC.key, column, common[column].to_numpy(np.int64),
            common[f"{column}_new"].to_numpy(np.int64), common["date"].to_numpy(),
            policy=policy, last=cached.as_of, cells="county-day",
            over="the counties' common days",
            example=lambda i: (f"{common['area'].iloc[i]} "
                               f"{pd.Timestamp(common['date'].iloc[i]).date()}"))


def with_county_holds(vintage: CDPHVintage, holds: Holds) -> CDPHVintage:
    """``vintage`` without the counties held at its date, each named in ``skipped``."""
    held = holds.at(str(vintage.as_of.date()))
    if not held:
        return vintage
    frame = vintage.frame[~vintage.frame["area"].isin(list(held))].reset_index(drop=True)
    skipped = {**vintage.skipped, **{county: h.note() for county, h in held.items()}}
    return dataclasses.replace(vintage, frame=frame, skipped=dict(sorted(skipped.items())))
