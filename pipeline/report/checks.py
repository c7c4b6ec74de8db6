"""Diagnostics that signal trouble, said in words: stale or old data, a particle filter whose
effective sample size collapsed, β/γ posteriors the data did not update from the prior.

Each check returns a sentence, or None when nothing is wrong. The report shows every sentence at
the top of its section and lists them all on page 1; the data banner is one box, whatever the
number of datasets.
"""
from __future__ import annotations

import datetime as dt
import re
from collections.abc import Sequence

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

ESS_COLLAPSE_FRACTION = 0.05      # ESS below 5 % of the particles: a handful carry the estimate
ROLLOUT_OVERSHOOT = 2.0           # a rollout median this many times the observed peak of I
PRIOR_WIDTH_FRACTION = 0.9        # a 90 % interval this wide, relative to the prior range
OLD_DATA_DAYS = 7

STALE_HEADLINE = ("Stale data: {provider} could not be reached (every retry failed), so this "
                  "forecast was made from the cached data")
# the transport's error notes, left out of the banner (the run log keeps them)
_UNREACHABLE = ("DataSF unreachable", "CHHS portal unreachable")
_URL = re.compile(r"https?://[^\s;,)]+")
# pipeline.data.sf.series' cache note, said shorter (the banner is on page 1)
_CACHE_NOTE = re.compile(r"using cache, fetched (\S+) days ago \(its last day, ([0-9-]+), is "
                         r"[0-9,]+ days before today\)")


# ----------------------------------------------------------------------------- data

def _short(note: str, limit: int = 200) -> str:
    """A note without the transport's nested exception text (the run log keeps it)."""
    note = note.split(" (Caused by", 1)[0].split("; last: ", 1)[0].rstrip(" .;")
    return note if len(note) <= limit else note[: limit - 1] + "…"


def dataset_lines(notes: Sequence[str]) -> list[str]:
    """One line per dataset from the ``"<key>: <note>"`` cache notes: the dataset's own
    resource URL (from its own notes) and what the cache said, the error text left out."""
    by_key: dict[str, list[str]] = {}
    for note in notes:
        key, _, text = str(note).partition(": ")
        by_key.setdefault(key, []).append(text)
    lines = []
    for key, texts in by_key.items():
        urls = [m.group(0) for t in texts for m in _URL.finditer(t)]
        kept = [_CACHE_NOTE.sub(r"cache fetched \1 days ago, last day \2", _short(t))
                for t in texts if not t.startswith(_UNREACHABLE)]
        source = f" ({urls[0]})" if urls else ""
        lines.append(f"{key}{source}: " + ("; ".join(kept) or "from the cache"))
    return lines


def data_banner(*, stale: bool, vintage: str, notes: Sequence[str], last_day: dt.date,
                today: dt.date, source: str, provider: str = "DataSF") -> str | None:
    """The one data banner: stale (live fetch failed, cache used) or old (newest observation
    more than a week before the run date), else None. ``provider``: who publishes the data
    (DataSF, CDPH)."""
    age = (today - last_day).days
    age_text = (f"the newest observation ({last_day}) is {age:,} days before the run date "
                f"({today})")
    if stale:
        per_dataset = dataset_lines(notes)
        return (f"{STALE_HEADLINE.format(provider=provider)} ({vintage.split(';', 1)[0]}); "
                f"{age_text}."
                + (" Per dataset: " + "; ".join(per_dataset) + "." if per_dataset else ""))
    if age > OLD_DATA_DAYS:
        return (f"Old data: {age_text}; this run read {provider} data from the local "
                f"{'cache' if source == 'cache' else source} ({vintage.split(';', 1)[0]}), "
                "as asked. The forecast describes the weeks after the data, not the coming "
                "weeks.")
    return None


# ----------------------------------------------------------------------------- SMC

def ess_collapse(ess: ArrayLike, n_particles: int, dates: pd.DatetimeIndex,
                 fraction: float = ESS_COLLAPSE_FRACTION) -> str | None:
    """Days on which the effective sample size fell below ``fraction`` of the particles."""
    e = np.asarray(ess, dtype=np.float64)
    low = e < fraction * n_particles
    if not low.any():
        return None
    worst = int(np.argmin(e))
    return (f"Particle filter degenerate: effective sample size below {fraction:.0%} of the "
            f"particles on {int(low.sum())} of {len(e)} days; minimum {e[worst]:.0f} of "
            f"{n_particles:,} on {dates[worst].date()}. On those days a handful of particles "
            "carry the filtered estimate, and its bands understate the uncertainty.")


# ----------------------------------------------------------------------------- rollouts

def rollout_overshoot(label: str, median_i: ArrayLike, observed_i: ArrayLike,
                      factor: float = ROLLOUT_OVERSHOOT, *,
                      dates: pd.DatetimeIndex | None = None, anchors: Sequence[int] = (),
                      direction: str = "forward", chained: bool = True) -> str | None:
    """When a rollout's median I exceeds ``factor`` times the highest I ever observed. With the
    ``dates`` of the series and the rolling ``anchors`` (each segment's first predicted index),
    it says where: a segment whose start came before the observed peak and whose overshoot came
    after it extrapolated the rise past a turn it could not see; otherwise its chained
    estimates compounded their errors (``chained``), or the prior's dynamics carried its
    starting estimate too far."""
    median = np.asarray(median_i, dtype=np.float64)
    observed = np.asarray(observed_i, dtype=np.float64)
    peak = float(np.nanmax(observed))
    top = float(np.nanmax(median)) if np.isfinite(median).any() else float("nan")
    if not (peak > 0 and top > factor * peak):
        return None
    where, peak_where = "", ""
    drift = ("chained estimates compound their errors over the window" if chained else
             "the prior's dynamics carry the starting estimate too far over the window")
    why = drift[0].upper() + drift[1:]
    if dates is not None and anchors:
        at, peak_at = int(np.nanargmax(median)), int(np.nanargmax(observed))
        start = (max(a for a in anchors if a <= at) if direction == "forward"
                 else min(a for a in anchors if a >= at))
        where, peak_where = f" on {dates[at].date()}", f" on {dates[peak_at].date()}"
        turn = "rise" if direction == "forward" else "fall"
        why = (f"Its segment starts on {dates[start].date()}, "
               + (f"so the peak lies inside it: the rollout follows the {turn} it started from "
                  "past a turn its starting window could not see"
                  if min(start, at) <= peak_at <= max(start, at) else
                  f"after the peak: {drift}"))
    # page 1 lists each check up to its first "; "
    return (f"The {label} overshoots: its median I reaches {top:.3g}{where}, "
            f"{top / peak:.1f}× the highest I observed ({peak:.3g}{peak_where}). {why}; this is "
            "the paper's reconstruction method shown for reference, not the published forecast "
            "(section 1).")


# ----------------------------------------------------------------------------- β, γ

def prior_not_updated(name: str, lower: ArrayLike, upper: ArrayLike,
                      prior: tuple[float, float] | None, dates: pd.DatetimeIndex,
                      fraction: float = PRIOR_WIDTH_FRACTION) -> str | None:
    """When the 90 % interval spans at least ``fraction`` of the prior range on the latest day:
    the posterior says what the prior said, so the data did not inform the parameter."""
    if prior is None:
        return None
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    width = (hi - lo) / (prior[1] - prior[0])
    wide = width >= fraction
    if not wide[-1]:
        return None
    return (f"{name} not identified by the data: its 90% interval spans {width[-1]:.0%} of "
            f"the training prior's range on {dates[-1].date()}; the prior range is "
            f"{prior[0]:g}–{prior[1]:g} per day, and the interval spans at least "
            f"{fraction:.0%} of it on {int(wide.sum())} of {len(wide)} days. The estimate "
            "restates the prior, not the data.")
