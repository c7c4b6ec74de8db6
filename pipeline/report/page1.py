"""Page 1 of every report (the weekly county report, a hub round of any disease): what a
forecaster reads in thirty seconds.

* **One figure that carries the forecast** (:func:`fan_chart_figure`): the last observed weeks
  and the forecast fan of the next ones (median, 50 % and the report's wide interval: 90 % for
  the county report, the hub's 95 %), the weeks still being reported drawn as a nowcast, marked
  as such — never as if they were data. A hub round adds its map of the states
  (:mod:`pipeline.report.hub_figures`).
* **The headline** in one or two sentences.
* **The table of the forecast.**
* **What the round left out or held** (:class:`~pipeline.report.content.Notice`): places or targets left out, data that
  are stale or held for review, sections of the report that could not be drawn. The builders fill
  them from what the run knows; other sources (revisions waiting, members dropped) are added as
  further notices, with no change here.

Page 1 stays short (:data:`MAX_WORDS` words of text on the PDF's first page): everything else —
the long lead, key facts, checks, contents — follows on page 2.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Sequence

import matplotlib.dates as mdates
import matplotlib.ticker as mticker
import numpy as np
from numpy.typing import NDArray

from pipeline.report.content import Notice, NoticeKind, ReportError
from pipeline.report.figures import OKABE_ITO, _figure, _png

MAX_WORDS = 150                 # words of text on the PDF's first page
BAND_COLUMNS = 5                # (wide lower, 25 %, 50 %, 75 %, wide upper)


def word_count(text: str) -> int:
    """Words as a reader counts them: whitespace-separated tokens holding a letter or digit."""
    return sum(1 for token in text.split() if any(ch.isalnum() for ch in token))


def notices_from(texts: Sequence[str], kind: NoticeKind) -> tuple[Notice, ...]:
    """Plain strings (warnings, skipped places) as notices of one kind; blanks dropped."""
    return tuple(Notice(kind, t) for t in texts if t and t.strip())


# ----------------------------------------------------------------------------- the fan chart

def _check_fan(week_ends: Sequence[dt.date], observed: NDArray[np.float64],
               target_ends: Sequence[dt.date], bands: NDArray[np.float64],
               nowcast: NDArray[np.bool_]) -> None:
    if observed.shape != (len(week_ends),):
        raise ReportError(f"observed of shape {observed.shape} do not fit {len(week_ends)} weeks")
    if bands.shape != (len(target_ends), BAND_COLUMNS):
        raise ReportError(f"bands of shape {bands.shape} do not fit {len(target_ends)} weeks × "
                          f"{BAND_COLUMNS} levels")
    if nowcast.shape != (len(target_ends),):
        raise ReportError(f"the nowcast mask of shape {nowcast.shape} does not fit "
                          f"{len(target_ends)} weeks")
    finite = bands[np.isfinite(bands).all(axis=1)]
    if (np.diff(finite, axis=1) < 0).any():
        raise ReportError("the fan's quantiles are not increasing in the level")


def fan_chart_figure(week_ends: Sequence[dt.date], observed: NDArray[np.float64],
                     target_ends: Sequence[dt.date], bands: NDArray[np.float64], *,
                     nowcast: NDArray[np.bool_], unit: str, wide: str,
                     incomplete: NDArray[np.bool_] | None = None, title: str = "",
                     log: bool = False, width_in: float = 8.5, height_in: float = 3.4) -> bytes:
    """The forecast over the last observed weeks.

    ``observed (W,)`` at ``week_ends`` (black dots; ``incomplete`` weeks, still being
    reported, hollow: their count will grow); ``bands (H, 5)`` at ``target_ends`` = (wide lower,
    25 %, median, 75 %, wide upper) — ``wide`` names the wide interval ("90%", "95%");
    ``nowcast (H,)`` marks the target weeks that are in the data but still being reported: drawn
    in their own colour over a shaded span labelled "nowcast", so that no one reads them as
    forecast or as data. ``log``: a log axis (counts that fell tenfold in the weeks shown)."""
    observed = np.asarray(observed, dtype=np.float64)
    bands = np.asarray(bands, dtype=np.float64)
    nowcast = np.asarray(nowcast, dtype=bool)
    _check_fan(week_ends, observed, target_ends, bands, nowcast)
    hollow = (np.zeros(len(week_ends), dtype=bool) if incomplete is None
              else np.asarray(incomplete, dtype=bool))
    fig, axes = _figure(height_in, width_in=width_in)
    ax = axes[0, 0]
    x_obs = np.asarray(week_ends, dtype="datetime64[D]")
    x_fc = np.asarray(target_ends, dtype="datetime64[D]")
    blue, orange = OKABE_ITO["blue"], OKABE_ITO["orange"]
    if nowcast.any():
        half = np.timedelta64(3, "D")
        ax.axvspan(x_fc[nowcast].min() - half, x_fc[nowcast].max() + half, color=orange,
                   alpha=0.12, lw=0)
        ax.text(x_fc[nowcast].min() - half, 1.0, " nowcast", transform=ax.get_xaxis_transform(),
                va="top", ha="left", fontsize=9, color="#8a5a00")
    # the fan: forecast weeks, joined to the nowcast weeks before them so the fan is continuous
    ax.fill_between(x_fc, bands[:, 0], bands[:, 4], color=blue, alpha=0.18, lw=0,
                    label=f"{wide} interval")
    ax.fill_between(x_fc, bands[:, 1], bands[:, 3], color=blue, alpha=0.38, lw=0,
                    label="50% interval")
    ax.plot(x_fc[~nowcast], bands[~nowcast, 2], "-o", color=blue, ms=3.5, lw=1.8,
            label="forecast median")
    if nowcast.any():
        ax.errorbar(x_fc[nowcast], bands[nowcast, 2],
                    yerr=[bands[nowcast, 2] - bands[nowcast, 0],
                          bands[nowcast, 4] - bands[nowcast, 2]],
                    fmt="D", color=orange, ms=5, lw=1.4, capsize=3,
                    label=f"nowcast, {wide}")
    ax.plot(x_obs[~hollow], observed[~hollow], "o", color="black", ms=4, label="reported")
    if hollow.any():
        ax.plot(x_obs[hollow], observed[hollow], "o", mfc="white", mec="black", ms=4,
                label="reported so far")
    if log:
        ax.set_yscale("log")
    else:
        ax.set_ylim(bottom=0)
    # counts with thousands separators, as in the table (shares keep their decimals)
    ax.yaxis.set_major_formatter(mticker.FuncFormatter(
        lambda v, _: f"{v:,.0f}" if abs(v) >= 10 or v == 0 else f"{v:g}"))
    ax.set_ylabel(unit + (" (log scale)" if log else ""))
    if title:
        ax.set_title(title, loc="left")
    locator = mdates.AutoDateLocator(maxticks=7)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))
    # below the axes: inside, it would hide the weeks it explains
    fig.legend(loc="outside lower center", fontsize=7.5, frameon=False, ncols=3,
               columnspacing=1.0, handletextpad=0.4)
    return _png(fig)
