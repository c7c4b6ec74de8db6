"""Figure builders for the reports: arrays / DataFrames in, PNG bytes out.

Conventions (readers are epidemiologists who look at the pictures first):

* Matplotlib's object API with the Agg canvas (no pyplot global state; safe in worker threads).
* Okabe–Ito colour-blind-safe palette; S blue, I vermilion, R bluish green, always.
* One panel per compartment where scales differ (S ≈ 1, I ≈ 1e-3): a shared axis would flatten I.
* Dates on the x axis with concise date labels; y axes say what and in which unit.
* Observations are black dots, estimates a line in the compartment colour with two shaded
  bands: every band in every figure is a 50 % (darker) or 90 % (lighter) central interval.
* Figures are 8.5 in wide at 110 dpi: about 935 px, so text stays ≥ 8 pt on an A4 page.

Array conventions: ``dates (T,)``; state arrays ``(T, 3)`` with columns S, I, R; NaN marks a
missing value (e.g. no estimate before the first full context window) and leaves a gap.
"""
from __future__ import annotations

import datetime as dt
import io
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, Literal, cast

import matplotlib
import matplotlib.dates as mdates
import matplotlib.ticker as mticker
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import ArrayLike, NDArray

from pipeline.names import COMPARTMENTS
from pipeline.report.content import ReportError
from pipeline.evaluation.scoring import CENTRAL_LEVELS

if TYPE_CHECKING:
    from matplotlib.typing import RcKeyType

DPI = 110
FULL_WIDTH_IN = 8.5

# Okabe & Ito (2008), "Color Universal Design".
OKABE_ITO: Mapping[str, str] = {
    "black": "#000000", "orange": "#E69F00", "sky_blue": "#56B4E9", "green": "#009E73",
    "yellow": "#F0E442", "blue": "#0072B2", "vermilion": "#D55E00", "purple": "#CC79A7",
}
COMPARTMENT_COLORS: Mapping[str, str] = {"S": OKABE_ITO["blue"], "I": OKABE_ITO["vermilion"],
                                         "R": OKABE_ITO["green"]}
COMPARTMENT_NAMES: Mapping[str, str] = {"S": "Susceptible S", "I": "Infectious I",
                                        "R": "Removed R"}
SERIES_CYCLE = (OKABE_ITO["blue"], OKABE_ITO["vermilion"], OKABE_ITO["green"],
                OKABE_ITO["purple"], OKABE_ITO["orange"], OKABE_ITO["sky_blue"], "#000000")

_RC: dict[RcKeyType, Any] = {
    "font.family": "DejaVu Sans",
    "font.size": 10.5,
    "axes.titlesize": 11.5,
    "axes.labelsize": 10.5,
    "xtick.labelsize": 9.5,
    "ytick.labelsize": 9.5,
    "legend.fontsize": 9.5,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "grid.linewidth": 0.6,
    "lines.linewidth": 1.8,
}


# ----------------------------------------------------------------------------- helpers

def _figure(height_in: float, nrows: int = 1, ncols: int = 1, *,
            sharex: bool | Literal["none", "all", "row", "col"] = False,
            width_in: float = FULL_WIDTH_IN,
            layout: Literal["constrained"] | None = "constrained") -> tuple[Figure, NDArray]:
    with matplotlib.rc_context(_RC):
        fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout=layout)
        FigureCanvasAgg(fig)
        axes = fig.subplots(nrows, ncols, sharex=sharex, squeeze=False)
    return fig, axes


def _png(fig: Figure) -> bytes:
    buffer = io.BytesIO()
    with matplotlib.rc_context(_RC):
        _freeze_ticks(fig)
        fig.savefig(buffer, format="png", dpi=DPI, facecolor="white")
    return buffer.getvalue()


def _freeze_ticks(fig: Figure) -> None:
    """Fix every axis' ticks, labels and offset text at what its locator and formatter give
    now, before the layout. Constrained layout measures each axis twice before the figure is
    drawn, and each measure ran the date locators and the formatters again: a fifth of the
    report's drawing time. The pictures are the same, except that a linear axis keeps the ticks
    chosen for its height before the layout shrank it (e.g. steps of 0.2, not 0.25)."""
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            major = _frozen(axis.get_majorticklocs(), axis.get_major_formatter())
            minor = _frozen(axis.get_minorticklocs(), axis.get_minor_formatter())
            axis.set_major_locator(major[0])
            axis.set_major_formatter(major[1])
            axis.set_minor_locator(minor[0])
            axis.set_minor_formatter(minor[1])


def _frozen(locs: NDArray, formatter: mticker.Formatter
            ) -> tuple[mticker.FixedLocator, mticker.FixedFormatter]:
    values = [float(v) for v in locs]
    fixed = mticker.FixedFormatter(formatter.format_ticks(values))
    fixed.set_offset_string(formatter.get_offset())
    return mticker.FixedLocator(values), fixed


def _dates(dates: Sequence[dt.date] | ArrayLike, name: str = "dates") -> NDArray:
    index = pd.DatetimeIndex(pd.to_datetime(np.asarray(dates)))
    if index.hasnans:
        raise ReportError(f"{name} contain missing dates")
    return index.to_numpy()


def _states(values: ArrayLike, n: int, name: str) -> NDArray[np.float64]:
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (n, 3):
        raise ReportError(f"{name} must have shape ({n}, 3) for S, I, R; got {arr.shape}")
    return arr


def _date_axis(ax: Axes, maxticks: int = 8) -> None:
    """Concise date ticks; narrow panels (a third of the width) ask for at most 4."""
    locator = mdates.AutoDateLocator(minticks=2, maxticks=maxticks)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator, show_offset=False))


def _proportion_axis(ax: Axes, compartment: str) -> None:
    ax.set_ylabel(f"{compartment} (fraction)")
    ax.ticklabel_format(axis="y", style="sci", scilimits=(-3, 3), useMathText=True)


# The report's one interval convention: median with 50 % and 90 % central intervals.
LEVELS = CENTRAL_LEVELS
BAND_LABELS = ("90% interval", "50% interval")


def _band_panel(ax: Axes, dates: NDArray, observed: NDArray | None, q: NDArray,
                compartment: str, estimate_label: str) -> None:
    """``q (5, T)``: quantiles at :data:`LEVELS`; 90 % band, 50 % band, median line."""
    color = COMPARTMENT_COLORS[compartment]
    ax.fill_between(dates, q[0], q[4], color=color, alpha=0.18, linewidth=0,
                    label=BAND_LABELS[0], zorder=1)
    ax.fill_between(dates, q[1], q[3], color=color, alpha=0.35, linewidth=0,
                    label=BAND_LABELS[1], zorder=1)
    if observed is not None:
        # small, half-transparent dots: on a long series they must not hide the estimate
        ax.plot(dates, observed, linestyle="none", marker="o", markersize=2.0,
                markeredgewidth=0, color="black", alpha=0.55, label="observed", zorder=2)
    ax.plot(dates, q[2], color=color, label=estimate_label, zorder=3)
    ax.set_title(COMPARTMENT_NAMES[compartment], loc="left")
    _proportion_axis(ax, compartment)


def _legend_below(fig: Figure, ax: Axes, ncols: int = 4) -> None:
    """One legend for the whole figure, under the panels, so it never covers data."""
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=ncols, frameon=False)


def _check_quantiles(dates: NDArray, q: ArrayLike, observed: ArrayLike | None
                     ) -> tuple[NDArray, NDArray | None]:
    """``q (5, T, 3)`` at :data:`LEVELS`, ordered along the levels (NaN allowed: a gap)."""
    n = len(dates)
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (len(LEVELS), n, 3):
        raise ReportError(f"quantiles must have shape ({len(LEVELS)}, {n}, 3) for levels "
                          f"{LEVELS} × dates × S, I, R; got {arr.shape}")
    with np.errstate(invalid="ignore"):
        if np.any(np.diff(arr, axis=0) < 0):
            raise ReportError("band quantiles decrease along the levels (lower bound exceeds "
                              "its upper bound)")
    obs = None if observed is None else _states(observed, n, "observed")
    return arr, obs


def _shade(ax: Axes, span: tuple[dt.date, dt.date] | None, label: str | None) -> None:
    if span is not None:
        # matplotlib's stubs say float, but axvspan converts dates through the axis units.
        start, end = cast(float, pd.Timestamp(span[0])), cast(float, pd.Timestamp(span[1]))
        ax.axvspan(start, end, color="#999999", alpha=0.15, linewidth=0, label=label)


# ----------------------------------------------------------------------------- figures

def sir_series_figure(df: pd.DataFrame, vintage: str | None = None,
                      place: str = "San Francisco") -> bytes:
    """The observed S, I, R proportions over time: three stacked panels sharing the date axis.

    ``df`` has columns date, S, I, R (proportions of the population).
    """
    missing = [c for c in ("date", *COMPARTMENTS) if c not in df.columns]
    if missing:
        raise ReportError(f"S/I/R frame lacks columns {missing}")
    dates = _dates(df["date"])
    fig, axes = _figure(6.4, 3, 1, sharex=True)
    for ax, c in zip(axes[:, 0], COMPARTMENTS):
        ax.plot(dates, df[c].to_numpy(dtype=float), color=COMPARTMENT_COLORS[c])
        ax.set_title(COMPARTMENT_NAMES[c], loc="left")
        _proportion_axis(ax, c)
    _date_axis(axes[-1, 0])
    axes[-1, 0].set_xlabel("date")
    if vintage:
        fig.suptitle(f"{place} COVID-19 — {vintage}", fontsize=10, color="#444444")
    return _png(fig)


def estimate_band_figure(dates: Sequence[dt.date] | ArrayLike, observed: ArrayLike | None,
                         quantiles: ArrayLike, *,
                         direction: Literal["forward", "backward"] = "forward",
                         context: tuple[dt.date, dt.date] | None = None) -> bytes:
    """Estimated S, I, R (median, 50 % and 90 % bands) against observations, one panel per
    compartment. ``quantiles (5, T, 3)`` at :data:`LEVELS`.

    ``context``: optional date span of the conditioning window, shaded grey.
    """
    d = _dates(dates)
    q, obs = _check_quantiles(d, quantiles, observed)
    fig, axes = _figure(3.3, 1, 3)
    for k, (ax, c) in enumerate(zip(axes[0], COMPARTMENTS)):
        _shade(ax, context, "context window" if k == 0 else None)
        _band_panel(ax, d, None if obs is None else obs[:, k], q[:, :, k], c,
                    f"{direction} estimate (median)")
        _date_axis(ax, maxticks=4)
        ax.set_xlabel("date of the estimated state")
    _legend_below(fig, axes[0, 0])
    return _png(fig)


def default_zoom(dates: NDArray, observed_i: NDArray, days: int = 60) -> tuple[dt.date, dt.date]:
    """A ``days``-long span centred on the peak of observed I (clipped to the data)."""
    finite = np.isfinite(observed_i)
    if not finite.any():
        centre = len(dates) // 2
    else:
        centre = int(np.nanargmax(np.where(finite, observed_i, -np.inf)))
    start = int(np.clip(centre - days // 2, 0, max(0, len(dates) - days)))
    stop = min(len(dates) - 1, start + days - 1)
    return (pd.Timestamp(dates[start]).date(), pd.Timestamp(dates[stop]).date())


def rollout_figure(dates: Sequence[dt.date] | ArrayLike, observed: ArrayLike,
                   quantiles: ArrayLike, *, window_days: int,
                   direction: Literal["forward", "backward"],
                   zoom: tuple[dt.date, dt.date] | None = None) -> bytes:
    """A rollout's full view (left) and a zoomed view (right) for S, I, R (rows): median, 50 %
    and 90 % bands of the sample paths (``quantiles (5, T, 3)`` at :data:`LEVELS`).

    ``zoom`` defaults to 60 days around the peak of observed I; the full view shades it.
    """
    d = _dates(dates)
    q, obs = _check_quantiles(d, quantiles, observed)
    assert obs is not None
    span = zoom or default_zoom(d, obs[:, 1])
    inside = (d >= np.datetime64(pd.Timestamp(span[0]))) & (d <= np.datetime64(pd.Timestamp(span[1])))
    if not inside.any():
        raise ReportError(f"zoom span {span[0]}..{span[1]} contains none of the dates")
    fig, axes = _figure(5.0, 3, 2, sharex="col")
    label = f"{direction} rollout, {window_days}-day window (median)"
    for k, c in enumerate(COMPARTMENTS):
        full, zoomed = axes[k, 0], axes[k, 1]
        _shade(full, span, "zoomed span" if k == 0 else None)
        _band_panel(full, d, obs[:, k], q[:, :, k], c, label)
        _band_panel(zoomed, d[inside], obs[inside, k], q[:, inside, k], c, label)
        zoomed.set_ylabel("")
        zoomed.set_title(f"{COMPARTMENT_NAMES[c]} (zoomed)", loc="left")
    for ax in axes[-1]:
        _date_axis(ax, maxticks=6)
    _legend_below(fig, axes[0, 0], ncols=3)
    return _png(fig)


def _quantile_columns(q: ArrayLike, n: int, name: str) -> NDArray[np.float64]:
    """``(n, 5)`` quantiles at :data:`LEVELS` per day, ordered along the levels."""
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (n, len(LEVELS)):
        raise ReportError(f"{name} must have shape ({n}, {len(LEVELS)}) = quantiles at "
                          f"{LEVELS}; got {arr.shape}")
    if np.any(np.diff(arr, axis=1) < 0):
        raise ReportError(f"{name} columns must be ordered along the levels "
                          "(5% ≤ 25% ≤ median ≤ 75% ≤ 95%)")
    return arr


def _quantile_panel(ax: Axes, d: NDArray, q: NDArray, color: str) -> None:
    ax.fill_between(d, q[:, 0], q[:, 4], color=color, alpha=0.18, linewidth=0,
                    label=BAND_LABELS[0])
    ax.fill_between(d, q[:, 1], q[:, 3], color=color, alpha=0.35, linewidth=0,
                    label=BAND_LABELS[1])
    ax.plot(d, q[:, 2], color=color, label="posterior median")


def parameter_figure(dates: Sequence[dt.date] | ArrayLike, beta_q: ArrayLike, gamma_q: ArrayLike,
                     rt_q: ArrayLike | None = None, *,
                     beta_prior: tuple[float, float] | None = None,
                     gamma_prior: tuple[float, float] | None = None,
                     gamma_fixed: float | None = None) -> bytes:
    """β, γ and R_t = β·S/γ over time: posterior median, 50 % and 90 % intervals; optional
    prior ranges. Each ``*_q`` is ``(T, 5)`` at :data:`LEVELS`; ``rt_q`` is the posterior of the
    ratio (per joint sample), not a ratio of medians. ``gamma_fixed``: γ is a stated constant
    (its panel says so and draws the line).
    """
    d = _dates(dates)
    b = _quantile_columns(beta_q, len(d), "beta_q")
    g = _quantile_columns(gamma_q, len(d), "gamma_q")
    rows = 3 if rt_q is not None else 2
    fig, axes = _figure(2.15 * rows, rows, 1, sharex=True)
    panels = ((axes[0, 0], b, "transmission rate β", "β (per day)", OKABE_ITO["vermilion"],
               beta_prior),
              (axes[1, 0], g, "recovery rate γ" if gamma_fixed is None else
               f"recovery rate γ = {gamma_fixed:.4g} per day (fixed by the conversion's window)",
               "γ (per day)", OKABE_ITO["blue"], gamma_prior))
    for ax, q, title, ylabel, color, prior in panels:
        _quantile_panel(ax, d, q, color)
        if prior is not None:
            for bound in prior:
                ax.axhline(bound, color="#555555", linestyle=":", linewidth=1.2)
            ax.plot([], [], color="#555555", linestyle=":", linewidth=1.2,
                    label="prior range (training)")
        ax.set_title(title, loc="left")
        ax.set_ylabel(ylabel)
    if rt_q is not None:
        ax = axes[2, 0]
        _quantile_panel(ax, d, _quantile_columns(rt_q, len(d), "rt_q"), OKABE_ITO["purple"])
        ax.axhline(1.0, color="#555555", linestyle="--", linewidth=1.0)
        ax.set_title("effective reproduction number R_t = β·S/γ (grows while above 1)",
                     loc="left")
        ax.set_ylabel("R_t")
    _date_axis(axes[-1, 0])
    axes[-1, 0].set_xlabel("date")
    _legend_below(fig, axes[0, 0], ncols=4)
    return _png(fig)


def smc_band_figure(dates: Sequence[dt.date] | ArrayLike, observed: ArrayLike | None,
                    quantiles: ArrayLike, *, ess: ArrayLike | None = None,
                    n_particles: int | None = None, collapse_fraction: float = 0.05) -> bytes:
    """Filtered S, I, R of the NF-seeded particle filter (median, 50 % and 90 % weighted
    quantile bands, ``quantiles (5, T, 3)``); optional effective-sample-size panel with the
    collapse threshold (``collapse_fraction`` of the particles) drawn and the days below it
    marked."""
    d = _dates(dates)
    q, obs = _check_quantiles(d, quantiles, observed)
    rows = 4 if ess is not None else 3
    fig, axes = _figure(1.9 * rows + 0.4, rows, 1, sharex=True)
    for k, c in enumerate(COMPARTMENTS):
        _band_panel(axes[k, 0], d, None if obs is None else obs[:, k], q[:, :, k], c,
                    "filtered median")
    _legend_below(fig, axes[0, 0], ncols=4)
    if ess is not None:
        e = np.asarray(ess, dtype=np.float64)
        if e.shape != (len(d),):
            raise ReportError(f"ess must have shape ({len(d)},), got {e.shape}")
        ax = axes[3, 0]
        ax.plot(d, e, color=OKABE_ITO["black"], linewidth=1.2)
        if n_particles:
            limit = collapse_fraction * n_particles
            ax.axhline(n_particles, color="#555555", linestyle=":", linewidth=1.0)
            ax.axhline(limit, color=OKABE_ITO["vermilion"], linestyle="--", linewidth=1.0)
            low = e < limit
            ax.plot(d[low], e[low], linestyle="none", marker="o", markersize=4,
                    color=OKABE_ITO["vermilion"])
            ax.set_ylim(0, n_particles * 1.05)
        ax.set_title(f"effective sample size (dashed: {collapse_fraction:.0%} of the "
                     "particles; red dots: days below it)", loc="left")
        ax.set_ylabel("particles")
    _date_axis(axes[-1, 0])
    axes[-1, 0].set_xlabel("date")
    return _png(fig)


def loss_curve_figure(history: pd.DataFrame, *, x: str = "step",
                      ylabel: str = "loss (mean NLL, nats)") -> bytes:
    """Training (solid) and validation (dashed) loss; one colour per model variant.

    ``history``: columns ``x`` (step or epoch), ``train``, ``validation`` (NaN where not
    evaluated) and optionally ``variant``.
    """
    missing = [c for c in (x, "train", "validation") if c not in history.columns]
    if missing:
        raise ReportError(f"loss history lacks columns {missing}")
    frame = history if "variant" in history.columns else history.assign(variant="model")
    fig, axes = _figure(3.8, 1, 1)
    ax = axes[0, 0]
    for color, (variant, group) in zip(SERIES_CYCLE, frame.groupby("variant", sort=False)):
        ax.plot(group[x], group["train"], color=color, label=f"{variant} — training")
        val = group.dropna(subset=["validation"])
        ax.plot(val[x], val["validation"], color=color, linestyle="--", marker="o",
                markersize=3, label=f"{variant} — validation")
    ax.set_xlabel(x)
    ax.set_ylabel(ylabel)
    ax.legend(loc="upper right", frameon=False, ncols=2 if frame["variant"].nunique() > 1 else 1)
    return _png(fig)


def _count_axis(ax: Axes, log: bool, share: bool = False) -> None:
    """Plain numbers on a (log) axis: 1,000 rather than 10³; shares in percent."""
    from matplotlib import ticker

    if log:
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_minor_locator(ticker.NullLocator())
    fmt = ((lambda v, _pos: f"{100 * v:.2g}%") if share else (lambda v, _pos: f"{v:,.0f}"))
    ax.yaxis.set_major_formatter(ticker.FuncFormatter(fmt))


def _fan(ax: Axes, x: NDArray, q: NDArray, color: str, label: str,
         start: tuple[NDArray, float] | None = None) -> None:
    """Forecast fan from ``q (H, 5)`` at :data:`LEVELS`, joined to the last observation."""
    if start is not None:
        x = np.concatenate([[start[0]], x])
        q = np.vstack([np.full(len(LEVELS), start[1]), q])
    ax.fill_between(x, q[:, 0], q[:, 4], color=color, alpha=0.18, linewidth=0,
                    label=BAND_LABELS[0])
    ax.fill_between(x, q[:, 1], q[:, 3], color=color, alpha=0.35, linewidth=0,
                    label=BAND_LABELS[1])
    ax.plot(x, q[:, 2], color=color, marker="o", markersize=3.5, label=label)


def published_forecast_figure(week_ends: Sequence[dt.date] | ArrayLike, weekly_cases: ArrayLike,
                              weekly_i: ArrayLike, target_ends: Sequence[dt.date] | ArrayLike,
                              cases_q: ArrayLike, i_q: ArrayLike, population: int, *,
                              log: bool = True) -> bytes:
    """The published forecast after the last weeks observed: weekly reported cases (left) and I
    (right, share with people on the right axis). ``weekly_*`` at ``week_ends`` (observed, the
    last one = the origin); ``*_q (H, 5)`` at :data:`LEVELS` at ``target_ends``. The y axes are
    set by what is drawn (the weeks shown and the forecast's 90 % intervals) only."""
    wd, td = _dates(week_ends, "week_ends"), _dates(target_ends, "target_ends")
    cases, share = (np.asarray(a, dtype=np.float64) for a in (weekly_cases, weekly_i))
    cq, iq = (_quantile_columns(q, len(td), name) for q, name in ((cases_q, "cases_q"),
                                                                    (i_q, "i_q")))
    fig, axes = _figure(3.6, 1, 2)
    panels = ((axes[0, 0], cases, cq, "weekly reported cases", "cases per week", False),
              (axes[0, 1], share, iq, "infectious I (share of the population)",
               "I (% of population)", True))
    for ax, obs, q, title, ylabel, is_share in panels:
        ax.plot(wd, obs, color="black", marker="o", markersize=3.5, linewidth=1.0,
                label="observed (week ending)")
        _fan(ax, td, q, OKABE_ITO["vermilion"], "published forecast (median)",
             start=(wd[-1], float(obs[-1])))
        ax.axvline(wd[-1], color="#555555", linestyle=":", linewidth=1.0)
        ax.set_title(title, loc="left")
        ax.set_ylabel(ylabel + (" (log scale)" if log else ""))
        _count_axis(ax, log, share=is_share)
        _date_axis(ax, maxticks=5)
    people = axes[0, 1].secondary_yaxis("right", functions=(lambda x: x * population,
                                                            lambda p: p / population))
    people.set_ylabel("people")
    _count_axis(people, False)
    _legend_below(fig, axes[0, 0], ncols=4)
    return _png(fig)


def past_forecasts_figure(panels: Mapping[str, pd.DataFrame], horizons: Sequence[int] = (1, 4),
                          *, log: bool = True) -> bytes:
    """Past published forecasts against what was observed: one column per target, one row per
    horizon. ``panels[target]``: rows per (origin, horizon) with ``target_end_date``,
    ``horizon``, ``q0.05 … q0.95`` (:data:`LEVELS`) and ``observed`` (NaN: not yet known)."""
    targets = list(panels)
    fig, axes = _figure(2.3 * len(horizons) + 0.5, len(horizons), len(targets), sharex=True)
    for j, target in enumerate(targets):
        frame = panels[target]
        for i, h in enumerate(horizons):
            ax = axes[i, j]
            part = frame[frame["horizon"] == h].sort_values("target_end_date")
            x = _dates(part["target_end_date"])
            q = part[[f"q{lv:g}" for lv in LEVELS]].to_numpy(dtype=np.float64)
            ax.fill_between(x, q[:, 0], q[:, 4], color=OKABE_ITO["vermilion"], alpha=0.18,
                            linewidth=0, label=BAND_LABELS[0])
            ax.fill_between(x, q[:, 1], q[:, 3], color=OKABE_ITO["vermilion"], alpha=0.35,
                            linewidth=0, label=BAND_LABELS[1])
            ax.plot(x, q[:, 2], color=OKABE_ITO["vermilion"], linewidth=1.2,
                    label="published median")
            ax.plot(x, part["observed"], color="black", marker="o", markersize=1.8,
                    linewidth=0.8, label="observed")
            ax.set_title(f"{target}, {h} week{'s' if h > 1 else ''} ahead", loc="left")
            _count_axis(ax, log, share=target.startswith("I"))
            _date_axis(ax, maxticks=5)
    _legend_below(fig, axes[0, 0], ncols=4)
    return _png(fig)


def pit_figure(histograms: Mapping[str, Mapping[str, Sequence[int]]]) -> bytes:
    """PIT histograms per target (panels), one bar series per forecaster, as densities (a
    calibrated forecast is flat at 1; a U shape: intervals too narrow; a hump: too wide)."""
    targets = list(histograms)
    fig, axes = _figure(3.0, 1, len(targets))
    for ax, target in zip(axes[0], targets):
        series = histograms[target]
        width = 0.1 / max(1, len(series))
        for k, (name, counts) in enumerate(series.items()):
            c = np.asarray(counts, dtype=np.float64)
            bins = len(c)
            density = c / max(1.0, c.sum()) * bins
            centres = (np.arange(bins) + 0.5) / bins
            ax.bar(centres + (k - (len(series) - 1) / 2) * width, density, width=width,
                   color=SERIES_CYCLE[k % len(SERIES_CYCLE)], label=name)
        ax.axhline(1.0, color="black", linestyle="--", linewidth=1.0)
        ax.set_xlim(0, 1)
        ax.set_title(f"PIT, {target}", loc="left")
        ax.set_xlabel("probability integral transform")
        ax.set_ylabel("density")
    _legend_below(fig, axes[0, 0], ncols=3)
    return _png(fig)
