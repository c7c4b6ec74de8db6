"""Is a hub release plausible as a whole, for its release date? (issue 39)

The gate judges each location's rows; a release can pass it location by location and still be
no release anyone should forecast from. Before a release may go live:

* **its date**: readable (:func:`release_date`: an unreadable ``as_of`` in a parquet or
  ``--as-of notadate`` is one named error) and not after today (:func:`refuse_future`: an
  import dated 2031-01-01 used to go live and refuse every later fetch);
* **its newest week** not older than the source's usual lag (:func:`stale_reason`). Measured
  on the real releases (``../shared/data/nhsn``, ``../shared/data/flusight``): the newest week
  ends 4 or 5 days before the release for admissions (44 COVID-19 and 59 influenza releases),
  4 to 11 days for the ED share (15 releases). A release whose newest week ends more than
  :data:`MAX_LAG_DAYS` (21: the largest real lag, 11, plus ten days) before its date is
  **stale**: held (``held/``, named), not live, and the loader says so (a release whose newest
  week was 62 weeks old used to become this week's round, ``"stale": false``);
* **no implausible whole-release event** (:func:`implausible_event`): every location reading 0
  in the newest week after a week with admissions, or the national row falling by more than
  :data:`MAX_NATIONAL_FALL` in one week. The largest real fall of the national row from one
  week to the next, over every week of every real release: 49 % (influenza, week ending
  2023-01-14: 14,077 -> 7,184 after the holiday peak); in a release's newest week 36 %
  (influenza, release of 2025-04-16); COVID-19 admissions 22 % (2025-01-11), the ED share 23 %.
  So a fall of more than 75 % in a week is held for review, named. (A nationwide drop to 0, the
  US at 7,897 the week before, used to be published as a median of 0 at every horizon.)
"""
from __future__ import annotations

from datetime import date

import numpy as np
import pandas as pd

from pipeline.data.core.cache import RevisionRefusedError
from pipeline.errors import ValidationError

MAX_LAG_DAYS = 21
MAX_NATIONAL_FALL = 0.75
NATIONAL = "US"


class ReleaseDateError(ValidationError):
    """A release date that cannot be read, or lies after today: the release is refused."""


def release_date(value: object, *, where: str) -> date:
    """``value`` (a date, a timestamp or ``YYYY-MM-DD`` text) as a date; anything else is a
    :class:`ReleaseDateError` naming ``where`` it was read and the value."""
    if isinstance(value, date):
        return value if not isinstance(value, pd.Timestamp) else value.date()
    text = str(value).strip()[:10]
    try:
        return date.fromisoformat(text)
    except ValueError:
        raise ReleaseDateError(f"{where}: release date {str(value)!r} is not a date "
                               f"(YYYY-MM-DD)") from None


def refuse_future(as_of: date, today: date, *, source: str) -> None:
    """A release dated after ``today`` is refused by name."""
    if as_of > today:
        raise ReleaseDateError(f"{source}: the release is dated {as_of}, after today ({today}); "
                               f"refused (a release from the future would refuse every later "
                               f"one as older)")


def stale_reason(as_of: pd.Timestamp, last_week: pd.Timestamp, *,
                 max_lag_days: int = MAX_LAG_DAYS) -> str | None:
    """Why a release of ``as_of`` whose newest week ends ``last_week`` is stale, or None."""
    lag = int((pd.Timestamp(as_of) - pd.Timestamp(last_week)).days)
    if lag <= max_lag_days:
        return None
    return (f"stale release: its newest week ends {pd.Timestamp(last_week).date()}, {lag} days "
            f"({lag // 7} weeks) before its date {pd.Timestamp(as_of).date()}; the source's "
            f"usual lag is 4-11 days (at most {max_lag_days} accepted)")


def implausible_event(frame: pd.DataFrame, *, counts: bool,
                      max_fall: float = MAX_NATIONAL_FALL) -> str | None:
    """Why the newest week of a release (``target_end_date``, ``location``, ``value``) is no
    plausible news as a whole, or None (module doc). ``counts``: the values are counts (a
    nationwide 0 is checked on counts only; a share of 0 everywhere is as implausible, and
    the national fall catches it)."""
    weeks = np.sort(frame["target_end_date"].unique())
    if len(weeks) < 2:
        return None
    newest, before = frame[frame["target_end_date"] == weeks[-1]], \
        frame[frame["target_end_date"] == weeks[-2]]
    day = pd.Timestamp(weeks[-1]).date()
    if counts and len(newest) > 1 and (newest["value"] == 0).all() and before["value"].sum() > 0:
        return (f"implausible release: every one of the {len(newest)} locations reads 0 for the "
                f"week ending {day}, after {before['value'].sum():,.0f} the week before; held "
                f"for review")
    now = newest.loc[newest["location"] == NATIONAL, "value"]
    then = before.loc[before["location"] == NATIONAL, "value"]
    if len(now) and len(then) and float(then.iloc[0]) > 0:
        fall = 1.0 - float(now.iloc[0]) / float(then.iloc[0])
        if fall > max_fall:
            return (f"implausible release: the national value falls {fall:.0%} in the week "
                    f"ending {day} ({float(then.iloc[0]):,.6g} -> {float(now.iloc[0]):,.6g}), "
                    f"more than the {max_fall:.0%} a week the real releases allow (largest "
                    f"real fall 49%); held for review")
    return None


def refuse_implausible(frame: pd.DataFrame, as_of: pd.Timestamp, last_week: pd.Timestamp, *,
                       target: str, counts: bool) -> None:
    """Hold a stale or implausible release (a :class:`RevisionRefusedError` with ``hold``:
    the vintage archive keeps it under ``held/`` and the cache stays as it is)."""
    why = stale_reason(as_of, last_week) or implausible_event(frame, counts=counts)
    if why is not None:
        raise RevisionRefusedError(f"{target}: {why}; cached copy kept", hold=True)
