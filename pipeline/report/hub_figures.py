"""Figures of a hub round: every location's last weeks and its forecast fan, as small multiples;
the tile-grid map of the states by P(rising) (:func:`tile_map_figure`); the track record by
round (:func:`relative_wis_by_round_figure`).

The conventions of :mod:`pipeline.report.figures` (Okabe–Ito colours, the Agg canvas, 50 % and
90 %-or-wider bands); here the wide band is the hub's 95 % interval.
"""
from __future__ import annotations

import datetime as dt
from collections.abc import Sequence

import matplotlib
import matplotlib.dates as mdates
import matplotlib.ticker as mticker
import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.colors import TwoSlopeNorm
from matplotlib.patches import Rectangle
from numpy.typing import NDArray

from pipeline.report.content import ReportError
from pipeline.report.figures import OKABE_ITO, _figure, _png

COLUMNS = 6
# The tile grid of US public-health dashboards (NPR's layout): (row, column) of each state, DC
# and Puerto Rico; every tile the same size, so that small states are as readable as large ones.
TILE_GRID: dict[str, tuple[int, int]] = {
    "AK": (0, 0), "ME": (0, 10), "VT": (1, 9), "NH": (1, 10),
    **{a: (2, c) for c, a in enumerate("WA ID MT ND MN IL WI MI NY RI MA".split())},
    **{a: (3, c) for c, a in enumerate("OR NV WY SD IA IN OH PA NJ CT".split())},
    **{a: (4, c) for c, a in enumerate("CA UT CO NE MO KY WV VA MD DE".split())},
    **{a: (5, c + 1) for c, a in enumerate("AZ NM KS AR TN NC SC DC".split())},
    **{a: (6, c + 3) for c, a in enumerate("OK LA MS AL GA".split())},
    "HI": (7, 0), "TX": (7, 3), "FL": (7, 8), "PR": (7, 10),
}
RISING_CMAP = "PuOr_r"          # colour-blind safe, diverging at 50 %: purple falling, orange rising


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
    height = 1.25 * rows + 0.3
    # fixed margins, not the constrained layout: solving it for 54 axes was most of the
    # figure's drawing time (half of a hub report's), and a regular grid needs no solver
    fig, axes = _figure(height, rows, COLUMNS, layout=None)
    fig.subplots_adjust(left=0.075, right=0.99, bottom=0.35 / height, top=1 - 0.25 / height,
                        wspace=0.42, hspace=0.62)
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


def _ink_on(rgba: tuple[float, float, float, float]) -> str:
    """Black or white text, whichever reads on the tile's colour (relative luminance)."""
    r, g, b = rgba[:3]
    return "black" if 0.2126 * r + 0.7152 * g + 0.0722 * b > 0.45 else "white"


def tile_map_figure(abbreviations: Sequence[str], p_rising: NDArray[np.float64], *,
                    title: str = "", width_in: float = 3.7) -> bytes:
    """The states, DC and Puerto Rico as a tile grid coloured by ``p_rising`` (one per
    abbreviation; NaN or not given: grey), each tile labelled with its abbreviation and its P in
    percent."""
    p = np.asarray(p_rising, dtype=np.float64)
    if p.shape != (len(abbreviations),):
        raise ReportError(f"{p.size} probabilities for {len(abbreviations)} locations")
    unknown = [a for a in abbreviations if a not in TILE_GRID]
    if unknown:
        raise ReportError(f"no tile for {unknown}; the grid holds {sorted(TILE_GRID)}")
    rows = 1 + max(r for r, _ in TILE_GRID.values())
    cols = 1 + max(c for _, c in TILE_GRID.values())
    fig, axes = _figure(width_in * (rows + 1.3) / cols, width_in=width_in)
    ax = axes[0, 0]
    cmap = matplotlib.colormaps[RISING_CMAP]
    norm = TwoSlopeNorm(vmin=0.0, vcenter=0.5, vmax=1.0)
    given = dict(zip(abbreviations, p))
    # every tile is drawn: a place left out of the round is grey with a dash, never missing
    for abbreviation in TILE_GRID:
        value = given.get(abbreviation, np.nan)
        r, c = TILE_GRID[abbreviation]
        colour = cmap(norm(value)) if np.isfinite(value) else (0.85, 0.85, 0.85, 1.0)
        ax.add_patch(Rectangle((c, -r), 0.94, 0.94, color=colour, lw=0))
        ink = _ink_on(colour)
        ax.text(c + 0.47, -r + 0.66, abbreviation, ha="center", va="center", fontsize=6.5,
                fontweight="bold", color=ink)
        ax.text(c + 0.47, -r + 0.28, f"{100 * value:.0f}" if np.isfinite(value) else "—",
                ha="center", va="center", fontsize=6.5, color=ink)
    ax.set_xlim(-0.1, cols)
    ax.set_ylim(-rows + 0.9, 1.0)
    ax.set_aspect("equal")
    ax.axis("off")
    if title:
        ax.set_title(title, fontsize=9.5, loc="left")
    bar = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax,
                       orientation="horizontal", fraction=0.05, pad=0.02, aspect=40)
    bar.set_ticks([0, 0.3, 0.5, 0.7, 1.0], labels=["0%", "30%", "50%", "70%", "100%"])
    bar.ax.tick_params(labelsize=6.5)
    bar.set_label("P(rising), %: 2 weeks ahead above last week", fontsize=7)
    return _png(fig)


def relative_wis_by_round_figure(references: Sequence[dt.date],
                                 series: dict[str, NDArray[np.float64]]) -> bytes:
    """The track record over time: each series (label → ``(R,)`` relative WIS of the
    published forecast against the hub's baseline at each round) on a log axis around 1."""
    if not series:
        raise ReportError("no relative WIS to draw")
    x = np.asarray(references, dtype="datetime64[D]")
    fig, axes = _figure(3.0)
    ax = axes[0, 0]
    colours = (OKABE_ITO["blue"], OKABE_ITO["vermilion"], OKABE_ITO["green"],
               OKABE_ITO["purple"])
    for (label, values), colour in zip(series.items(), colours):
        v = np.asarray(values, dtype=np.float64)
        if v.shape != x.shape:
            raise ReportError(f"{label}: {v.shape} values for {len(x)} rounds")
        ok = np.isfinite(v) & (v > 0)
        ax.plot(x[ok], v[ok], "-o", ms=3.5, color=colour, label=label)
    ax.axhline(1.0, color="black", lw=0.9, ls="--")
    ax.set_yscale("log")
    # plain ratios (0.5, 1, 2), not powers of ten: the axis spans a factor of a few
    ax.yaxis.set_major_locator(mticker.FixedLocator([0.125, 0.25, 0.5, 0.75, 1, 1.5, 2, 4, 8]))
    ax.yaxis.set_major_formatter(mticker.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(mticker.NullFormatter())
    ax.set_ylabel("relative WIS (log scale)")
    ax.text(0.995, 0.02, "below 1: better than the hub's baseline", transform=ax.transAxes,
            ha="right", va="bottom", fontsize=8, color="#5a6370")
    locator = mdates.AutoDateLocator(maxticks=8)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator))
    fig.legend(loc="outside lower center", fontsize=8.5, frameon=False, ncols=len(series))
    return _png(fig)
