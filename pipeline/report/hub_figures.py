"""Figures of a hub round: every location's last weeks and its forecast fan, as small multiples.

The conventions of :mod:`pipeline.report.figures` (Okabe–Ito colours, the Agg canvas, 50 % and
90 %-or-wider bands); here the wide band is the hub's 95 % interval.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from pipeline.report.content import ReportError
from pipeline.report.figures import OKABE_ITO, _figure, _png

COLUMNS = 6


def small_multiples_figure(names: Sequence[str], week_ends: Sequence[dt.date],
                           observed: NDArray[np.float64], target_ends: Sequence[dt.date],
                           bands: NDArray[np.float64], *, unit: str) -> bytes:
    """One panel per location: the observed weeks ``observed (L, W)`` at ``week_ends`` (black
    dots; the last still being reported) and the forecast at ``target_ends`` as median and
    50 %/95 % bands, ``bands (L, H, 5)`` = (2.5 %, 25 %, 50 %, 75 %, 97.5 %); each panel on its
    own y scale (the US is 100× a small state)."""
    if bands.shape[:2] != (len(names), len(target_ends)) or bands.shape[2] != 5:
        raise ReportError(f"bands of shape {bands.shape} do not fit {len(names)} locations × "
                          f"{len(target_ends)} weeks × 5 levels")
    if observed.shape != (len(names), len(week_ends)):
        raise ReportError(f"observed of shape {observed.shape} do not fit {len(names)} "
                          f"locations × {len(week_ends)} weeks")
    rows = int(np.ceil(len(names) / COLUMNS))
    fig, axes = _figure(1.25 * rows + 0.3, rows, COLUMNS)
    x_obs = np.arange(len(week_ends)) - len(week_ends) + 1
    x_fc = np.array([(end - week_ends[-1]).days // 7 for end in target_ends])
    blue = OKABE_ITO["blue"]
    for i, ax in enumerate(axes.ravel()):
        if i >= len(names):
            ax.set_visible(False)
            continue
        ax.fill_between(x_fc, bands[i, :, 0], bands[i, :, 4], color=blue, alpha=0.2, lw=0)
        ax.fill_between(x_fc, bands[i, :, 1], bands[i, :, 3], color=blue, alpha=0.4, lw=0)
        ax.plot(x_fc, bands[i, :, 2], color=blue, lw=1.2)
        ax.plot(x_obs, observed[i], "o", color="black", ms=2.2)
        ax.set_title(names[i], fontsize=8, pad=2)
        ax.tick_params(labelsize=6.5, pad=1)
        ax.set_ylim(bottom=0)
        ax.set_xticks([x_obs[0], 0, x_fc[-1]])
        ax.set_xticklabels([f"{week_ends[0]:%m-%d}", f"{week_ends[-1]:%m-%d}",
                            f"{target_ends[-1]:%m-%d}"])
    fig.supylabel(unit, fontsize=9)
    return _png(fig)
