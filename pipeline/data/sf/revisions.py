"""Is a new DataSF payload a plausible successor of the cached one? (issue 15, "silent shrinkage")

A payload that passes :func:`pipeline.data.sf.validation.validate_frame` can still be wrong as a
*replacement*: a valid but short series (60 of 744 rows), a series whose last date moves
backwards, an older vintage, or one that rewrites settled history. Each used to replace (and
delete) the good cache. :func:`check_successor` compares the new payload with the live cached copy
and raises :class:`RevisionRefusedError` naming the problem; the caller keeps the cache.

Revision policy (docs/data.md, "Revision policy"). DataSF revises recent days as late reports
arrive: two vintages of the cases series differ on 215 of 744 days, median |difference| 1, 90th
percentile 9, largest 50, mostly at the trailing edge. So:

* the last ``open_days`` (default 28) days of the *cached* series are open: they may change by
  any amount (backfill);
* an older ("settled") day may change by at most ``max(settled_abs, settled_rel × cached value)``
  (default max(50, 25 %)) in every count column;
* over the days both copies hold, the total of each count column may fall by at most
  ``max_total_drop`` (default 2 %): revisions add late reports, they rarely remove many.

A payload breaking the policy is *held for review* (kept under the cache's ``held/`` folder) and
not used; after a person has looked at it, ``flowcast data fetch --accept-revisions`` (or
``data import --accept-revisions FILE``) takes it.
"""
from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pandas as pd

from pipeline.data.core.cache import (CachedPayload, CommitCheck, DatasetCache,
                                      RevisionRefusedError, SourceKind)
from pipeline.data.core.revision_policy import RevisionPolicy, refuse_revisions
from pipeline.data.sf.datasf import check_gate
from pipeline.data.sf.payloads import decode_cached
from pipeline.data.core.plausibility import DAILY, JumpRule
from pipeline.data.sf.validation import GapPolicy, ValidatedFrame, validate_frame
from pipeline.errors import DataSourceError
from pipeline.io import LOCK_TIMEOUT_S

log = logging.getLogger(__name__)


DEFAULT_POLICY = RevisionPolicy(open_days=28, settled_abs=50, settled_rel=0.25, max_total_drop=0.02)


def check_successor(new: ValidatedFrame, cached: ValidatedFrame,
                    policy: RevisionPolicy = DEFAULT_POLICY) -> None:
    """Raise :class:`RevisionRefusedError` unless ``new`` may replace ``cached``."""
    key = new.spec.key
    _check_coverage(new, cached, key)
    _check_vintage(new, cached, key)
    _check_revisions(new, cached, key, policy)


def _span(v: ValidatedFrame) -> str:
    return f"{v.report.row_count} rows, {v.report.first_date.date()}…{v.report.last_date.date()}"


def _check_coverage(new: ValidatedFrame, cached: ValidatedFrame, key: str) -> None:
    if new.report.last_date < cached.report.last_date:
        raise RevisionRefusedError(
            f"{key}: last date moves backwards: new payload ends {new.report.last_date.date()}, "
            f"the cached copy {cached.report.last_date.date()}; cached copy kept")
    if new.report.first_date > cached.report.first_date or len(new.frame) < len(cached.frame):
        raise RevisionRefusedError(
            f"{key}: payload shrinks: new {_span(new)} against cached {_span(cached)}; cached "
            f"copy kept")


def _check_vintage(new: ValidatedFrame, cached: ValidatedFrame, key: str) -> None:
    old_stamp, new_stamp = cached.report.data_as_of, new.report.data_as_of
    if old_stamp is not None and new_stamp is not None and new_stamp < old_stamp:
        raise RevisionRefusedError(
            f"{key}: 'data as of' moves backwards: new payload {new_stamp}, cached copy "
            f"{old_stamp} (an older vintage); cached copy kept")


def _check_revisions(new: ValidatedFrame, cached: ValidatedFrame, key: str,
                     policy: RevisionPolicy) -> None:
    columns = list(new.spec.count_columns)
    old = cached.frame.set_index("date")[columns]
    common = old.join(new.frame.set_index("date")[columns], how="inner", rsuffix="_new")
    for column in columns:
        refuse_revisions(key, column, common[column].to_numpy(dtype=np.int64),
                         common[f"{column}_new"].to_numpy(dtype=np.int64),
                         common.index.to_numpy(), policy=policy, last=cached.report.last_date,
                         cells="day", over=f"the {len(common)} common days",
                         example=lambda i: str(common.index[i].date()))


def successor_check(new: ValidatedFrame, *, gap_policy: GapPolicy,
                    policy: RevisionPolicy = DEFAULT_POLICY,
                    jump: JumpRule = DAILY) -> CommitCheck:
    """A :meth:`DatasetCache.store` check: refuse ``new`` unless it may replace the live copy.

    A live copy that no longer validates or is implausible (damaged, or stored by an older
    flowcast with weaker checks, e.g. a poisoned count) is no reference: the new payload repairs
    it instead of being held as a revision of it.
    """
    def check(live: CachedPayload | None) -> None:
        if live is None:
            return
        try:
            cached = validate_frame(decode_cached(live), new.spec, source=str(live.path),
                                    gap_policy=gap_policy)
            check_gate(cached.frame, new.spec, source=str(live.path), jump=jump)
        except DataSourceError as exc:
            log.warning("cached %s no longer validates (%s); replacing it", new.spec.key, exc)
            return
        check_successor(new, cached, policy)

    return check


def commit_validated(cache: DatasetCache, validated: ValidatedFrame, payload: bytes, *,
                     suffix: str, source_kind: SourceKind, source: str,
                     final_url: str | None = None, gap_policy: GapPolicy,
                     accept_revisions: bool = False,
                     policy: RevisionPolicy = DEFAULT_POLICY,
                     jump: JumpRule = DAILY,
                     lock_timeout_s: float = LOCK_TIMEOUT_S) -> Any:
    """Store a validated payload unless it fails the validation gate (refused, even with
    ``accept_revisions``: no review makes 1e8 cases in a day true) or it may not replace the
    live copy (shrinks, goes back, breaks the revision policy: then it is held for review and
    the error says where)."""
    report = validated.report
    check_gate(validated.frame, validated.spec, source=report.source, jump=jump)
    check = None if accept_revisions else successor_check(
        validated, gap_policy=gap_policy, policy=policy, jump=jump)
    try:
        return cache.store(
            validated.spec, payload, suffix=suffix, source_kind=source_kind, source=source,
            row_count=report.row_count, first_date=str(report.first_date.date()),
            last_date=str(report.last_date.date()),
            data_as_of=report.data_as_of.isoformat() if report.data_as_of is not None else None,
            final_cumulative=report.final_cumulative, final_url=final_url, check=check,
            lock_timeout_s=lock_timeout_s)
    except RevisionRefusedError as exc:
        if not exc.hold:
            raise
        held = cache.hold(validated.spec, payload, suffix=suffix, reason=str(exc))
        raise RevisionRefusedError(f"{exc} (payload held in {held}; after review accept it "
                                   "with `flowcast data fetch --accept-revisions` (or `flowcast data import --accept-revisions FILE`))", hold=True) from exc
