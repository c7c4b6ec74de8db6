"""Figure builders for the reports: arrays / DataFrames in, PNG bytes out.

Conventions (readers are epidemiologists who look at the pictures first):

* Matplotlib's object API with the Agg canvas (no pyplot global state; safe in worker threads).
* Okabe–Ito colour-blind-safe palette; S blue, I vermilion, R bluish green, always.
* One panel per compartment where scales differ (S ≈ 1, I ≈ 1e-3): a shared axis would flatten I.
* Dates on the x axis with concise date labels; y axes say what and in which unit.
* Observations are black dots, estimates a line in the compartment colour with a shaded band;
  legends say what the band is (e.g. "mean ± 2σ").
* Figures are 8.5 in wide at 110 dpi: about 935 px, so text stays ≥ 8 pt on an A4 page.

Array conventions: ``dates (T,)``; state arrays ``(T, 3)`` with columns S, I, R; NaN marks a
missing value (e.g. no estimate before the first full context window) and leaves a gap.
"""
from __future__ import annotations

import datetime as dt
import io
from collections.abc import Mapping, Sequence
from typing import Literal

import matplotlib
import matplotlib.dates as mdates
import numpy as np
import pandas as pd
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import ArrayLike, NDArray

from pipeline.report.content import ReportError

DPI = 110
FULL_WIDTH_IN = 8.5

# Okabe & Ito (2008), "Color Universal Design".
OKABE_ITO: Mapping[str, str] = {
    "black": "#000000", "orange": "#E69F00", "sky_blue": "#56B4E9", "green": "#009E73",
    "yellow": "#F0E442", "blue": "#0072B2", "vermilion": "#D55E00", "purple": "#CC79A7",
}
COMPARTMENTS = ("S", "I", "R")
COMPARTMENT_COLORS: Mapping[str, str] = {"S": OKABE_ITO["blue"], "I": OKABE_ITO["vermilion"],
                                         "R": OKABE_ITO["green"]}
COMPARTMENT_NAMES: Mapping[str, str] = {"S": "Susceptible S", "I": "Infectious I",
                                        "R": "Removed R"}
SERIES_CYCLE = (OKABE_ITO["blue"], OKABE_ITO["vermilion"], OKABE_ITO["green"],
                OKABE_ITO["purple"], OKABE_ITO["orange"], OKABE_ITO["sky_blue"], "#000000")

_RC = {
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

def _figure(height_in: float, nrows: int = 1, ncols: int = 1, *, sharex: bool | str = False,
            width_in: float = FULL_WIDTH_IN) -> tuple[Figure, NDArray]:
    with matplotlib.rc_context(_RC):
        fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(nrows, ncols, sharex=sharex, squeeze=False)
    return fig, axes


def _png(fig: Figure) -> bytes:
    buffer = io.BytesIO()
    with matplotlib.rc_context(_RC):
        fig.savefig(buffer, format="png", dpi=DPI, facecolor="white")
    return buffer.getvalue()


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


def _band_panel(ax: Axes, dates: NDArray, observed: NDArray | None, mean: NDArray,
                lower: NDArray, upper: NDArray, compartment: str, band_label: str,
                estimate_label: str) -> None:
    color = COMPARTMENT_COLORS[compartment]
    ax.fill_between(dates, lower, upper, color=color, alpha=0.25, linewidth=0,
                    label=band_label, zorder=1)
    if observed is not None:
        # small, half-transparent dots: on a long series they must not hide the estimate
        ax.plot(dates, observed, linestyle="none", marker="o", markersize=2.0,
                markeredgewidth=0, color="black", alpha=0.55, label="observed", zorder=2)
    ax.plot(dates, mean, color=color, label=estimate_label, zorder=3)
    ax.set_title(COMPARTMENT_NAMES[compartment], loc="left")
    _proportion_axis(ax, compartment)


def _legend_below(fig: Figure, ax: Axes, ncols: int = 4) -> None:
    """One legend for the whole figure, under the panels, so it never covers data."""
    handles, labels = ax.get_legend_handles_labels()
    # grey legend patches for bands: the compartment colour is explained by the panel titles
    fig.legend(handles, labels, loc="outside lower center", ncols=ncols, frameon=False)


def _check_bands(dates: NDArray, mean: ArrayLike, lower: ArrayLike, upper: ArrayLike,
                 observed: ArrayLike | None) -> tuple[NDArray, ...]:
    n = len(dates)
    m, lo, up = (_states(a, n, name) for a, name in ((mean, "mean"), (lower, "lower"),
                                                      (upper, "upper")))
    obs = None if observed is None else _states(observed, n, "observed")
    if np.any(lo > up):
        raise ReportError("band lower bound exceeds its upper bound")
    return m, lo, up, obs


def _shade(ax: Axes, span: tuple[dt.date, dt.date] | None, label: str | None) -> None:
    if span is not None:
        ax.axvspan(pd.Timestamp(span[0]), pd.Timestamp(span[1]), color="#999999", alpha=0.15,
                   linewidth=0, label=label)


# ----------------------------------------------------------------------------- figures

def sir_series_figure(df: pd.DataFrame, vintage: str | None = None) -> bytes:
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
        fig.suptitle(f"San Francisco COVID-19 — {vintage}", fontsize=10, color="#444444")
    return _png(fig)


def estimate_band_figure(dates: Sequence[dt.date] | ArrayLike, observed: ArrayLike | None,
                         mean: ArrayLike, lower: ArrayLike, upper: ArrayLike, *,
                         direction: Literal["forward", "backward"] = "forward",
                         band_label: str = "mean ± 2σ",
                         context: tuple[dt.date, dt.date] | None = None) -> bytes:
    """Estimated S, I, R (mean and band) against observations, one panel per compartment.

    ``context``: optional date span of the conditioning window, shaded grey.
    """
    d = _dates(dates)
    m, lo, up, obs = _check_bands(d, mean, lower, upper, observed)
    fig, axes = _figure(3.3, 1, 3)
    for k, (ax, c) in enumerate(zip(axes[0], COMPARTMENTS)):
        _shade(ax, context, "context window" if k == 0 else None)
        _band_panel(ax, d, None if obs is None else obs[:, k], m[:, k], lo[:, k], up[:, k], c,
                    band_label, f"{direction} estimate (mean)")
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


def rollout_figure(dates: Sequence[dt.date] | ArrayLike, observed: ArrayLike, mean: ArrayLike,
                   lower: ArrayLike, upper: ArrayLike, *, window_days: int,
                   direction: Literal["forward", "backward"],
                   zoom: tuple[dt.date, dt.date] | None = None,
                   band_label: str = "mean ± 2σ") -> bytes:
    """A rollout's full view (left) and a zoomed view (right) for S, I, R (rows).

    ``zoom`` defaults to 60 days around the peak of observed I; the full view shades it.
    """
    d = _dates(dates)
    m, lo, up, obs = _check_bands(d, mean, lower, upper, observed)
    assert obs is not None
    span = zoom or default_zoom(d, obs[:, 1])
    inside = (d >= np.datetime64(pd.Timestamp(span[0]))) & (d <= np.datetime64(pd.Timestamp(span[1])))
    if not inside.any():
        raise ReportError(f"zoom span {span[0]}..{span[1]} contains none of the dates")
    fig, axes = _figure(5.0, 3, 2, sharex="col")
    label = f"{direction} rollout, {window_days}-day window"
    for k, c in enumerate(COMPARTMENTS):
        full, zoomed = axes[k, 0], axes[k, 1]
        _shade(full, span, "zoomed span" if k == 0 else None)
        _band_panel(full, d, obs[:, k], m[:, k], lo[:, k], up[:, k], c, band_label, label)
        _band_panel(zoomed, d[inside], obs[inside, k], m[inside, k], lo[inside, k],
                    up[inside, k], c, band_label, label)
        zoomed.set_ylabel("")
        zoomed.set_title(f"{COMPARTMENT_NAMES[c]} (zoomed)", loc="left")
    for ax in axes[-1]:
        _date_axis(ax, maxticks=6)
    _legend_below(fig, axes[0, 0])
    return _png(fig)


def _quantile_columns(q: ArrayLike, n: int, name: str) -> NDArray[np.float64]:
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (n, 3):
        raise ReportError(f"{name} must have shape ({n}, 3) = (lower, median, upper); "
                          f"got {arr.shape}")
    if np.any(arr[:, 0] > arr[:, 1]) or np.any(arr[:, 1] > arr[:, 2]):
        raise ReportError(f"{name} columns must be ordered lower ≤ median ≤ upper")
    return arr


def parameter_figure(dates: Sequence[dt.date] | ArrayLike, beta_q: ArrayLike, gamma_q: ArrayLike,
                     *, interval_label: str = "95% credible interval",
                     beta_prior: tuple[float, float] | None = None,
                     gamma_prior: tuple[float, float] | None = None) -> bytes:
    """β and γ over time: posterior median and credible interval; optional prior ranges.

    ``beta_q``, ``gamma_q``: arrays (T, 3) with columns lower, median, upper (per day).
    A third panel shows the ratio of medians β/γ (an R0-like summary; not the median of β/γ).
    """
    d = _dates(dates)
    b = _quantile_columns(beta_q, len(d), "beta_q")
    g = _quantile_columns(gamma_q, len(d), "gamma_q")
    fig, axes = _figure(6.4, 3, 1, sharex=True)
    panels = ((axes[0, 0], b, "transmission rate β", "β (per day)", OKABE_ITO["vermilion"],
               beta_prior),
              (axes[1, 0], g, "recovery rate γ", "γ (per day)", OKABE_ITO["blue"], gamma_prior))
    for ax, q, title, ylabel, color, prior in panels:
        ax.fill_between(d, q[:, 0], q[:, 2], color=color, alpha=0.22, linewidth=0,
                        label=interval_label)
        ax.plot(d, q[:, 1], color=color, label="posterior median")
        if prior is not None:
            for bound in prior:
                ax.axhline(bound, color="#555555", linestyle=":", linewidth=1.2)
            ax.plot([], [], color="#555555", linestyle=":", linewidth=1.2,
                    label="prior range (training)")
        ax.set_title(title, loc="left")
        ax.set_ylabel(ylabel)
    ratio = axes[2, 0]
    ratio.plot(d, b[:, 1] / g[:, 1], color=OKABE_ITO["purple"])
    ratio.axhline(1.0, color="#555555", linestyle="--", linewidth=1.0)
    ratio.set_title("ratio of medians β/γ (R0-like; epidemic grows while S·β/γ > 1)",
                    loc="left")
    ratio.set_ylabel("β/γ")
    _date_axis(ratio)
    ratio.set_xlabel("date")
    _legend_below(fig, axes[0, 0], ncols=3)
    return _png(fig)


def smc_band_figure(dates: Sequence[dt.date] | ArrayLike, observed: ArrayLike | None,
                    mean: ArrayLike, lower: ArrayLike, upper: ArrayLike, *,
                    band_label: str = "mean ± 3σ", ess: ArrayLike | None = None,
                    n_particles: int | None = None) -> bytes:
    """Filtered S, I, R of the NF-seeded particle filter; optional effective-sample-size panel."""
    d = _dates(dates)
    m, lo, up, obs = _check_bands(d, mean, lower, upper, observed)
    rows = 4 if ess is not None else 3
    fig, axes = _figure(2.1 * rows + 0.3, rows, 1, sharex=True)
    for k, c in enumerate(COMPARTMENTS):
        _band_panel(axes[k, 0], d, None if obs is None else obs[:, k], m[:, k], lo[:, k],
                    up[:, k], c, band_label, "filtered mean")
    _legend_below(fig, axes[0, 0], ncols=3)
    if ess is not None:
        e = np.asarray(ess, dtype=np.float64)
        if e.shape != (len(d),):
            raise ReportError(f"ess must have shape ({len(d)},), got {e.shape}")
        ax = axes[3, 0]
        ax.plot(d, e, color=OKABE_ITO["black"], linewidth=1.2)
        if n_particles:
            ax.axhline(n_particles, color="#555555", linestyle=":", linewidth=1.0)
            ax.set_ylim(0, n_particles * 1.05)
        ax.set_title("effective sample size (before resampling)", loc="left")
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


def backtest_figure(by_horizon: pd.DataFrame, baseline: str = "persistence") -> bytes:
    """Relative WIS (left, < 1 beats ``baseline``) and 50%/90% interval coverage (right).

    ``by_horizon``: rows (forecaster, horizon) with relative_wis, coverage_50, coverage_90 —
    as :func:`pipeline.backtest.summary_by_horizon` returns.
    """
    needed = ("forecaster", "horizon", "relative_wis", "coverage_50", "coverage_90")
    missing = [c for c in needed if c not in by_horizon.columns]
    if missing:
        raise ReportError(f"backtest summary lacks columns {missing}")
    models = [m for m in dict.fromkeys(by_horizon["forecaster"]) if m != baseline]
    horizons = np.sort(by_horizon["horizon"].unique())
    fig, axes = _figure(4.2, 1, 2)
    rel_ax, cov_ax = axes[0, 0], axes[0, 1]
    width = 0.8 / max(1, len(models))
    colors = dict(zip(models, SERIES_CYCLE))
    colors[baseline] = "#777777"
    for k, model in enumerate(models):
        rows = by_horizon[by_horizon["forecaster"] == model].set_index("horizon").reindex(horizons)
        rel_ax.bar(horizons + (k - (len(models) - 1) / 2) * width, rows["relative_wis"],
                   width=width, color=colors[model], label=model)
    for model in [*models, baseline]:
        rows = by_horizon[by_horizon["forecaster"] == model].set_index("horizon").reindex(horizons)
        if rows["coverage_50"].isna().all():
            continue
        cov_ax.plot(horizons, rows["coverage_50"], color=colors[model], marker="o",
                    label=model)
        cov_ax.plot(horizons, rows["coverage_90"], color=colors[model], marker="s",
                    linestyle="--")
    rel_ax.axhline(1.0, color="black", linewidth=1.0)
    rel_ax.set_title(f"relative WIS vs {baseline}\n(below 1: better than {baseline})", loc="left")
    rel_ax.set_xlabel("horizon (weeks ahead)")
    rel_ax.set_ylabel("relative WIS")
    rel_ax.set_xticks(horizons)

    for nominal in (0.5, 0.9):
        cov_ax.axhline(nominal, color="#555555", linestyle=":", linewidth=1.0)
    cov_ax.set_ylim(0, 1.05)
    cov_ax.set_title("interval coverage\n(dotted: nominal 50% and 90%)", loc="left")
    cov_ax.set_xlabel("horizon (weeks ahead)")
    cov_ax.set_ylabel("fraction of observations inside")
    cov_ax.set_xticks(horizons)
    # one legend entry per model: colour = model, circles/solid = 50%, squares/dashed = 90%
    handles, labels = cov_ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=min(4, len(labels)),
               frameon=False, title="circles/solid: 50% interval, squares/dashed: 90% interval",
               title_fontsize=8.5)
    return _png(fig)


def forecast_fan_figure(history_dates: Sequence[dt.date] | ArrayLike, history: ArrayLike,
                        dates: Sequence[dt.date] | ArrayLike, samples: ArrayLike, *,
                        history_days: int = 56) -> bytes:
    """The next weeks as a fan: median with 50% and 90% intervals of the sample paths,
    after the last ``history_days`` of observations, one panel per compartment.

    ``history (T, 3)`` observed at ``history_dates``; ``samples (n, H, 3)`` at ``dates (H,)``.
    """
    hd = _dates(history_dates, "history_dates")
    obs = _states(history, len(hd), "history")
    fd = _dates(dates)
    paths = np.asarray(samples, dtype=np.float64)
    if paths.ndim != 3 or paths.shape[1:] != (len(fd), 3):
        raise ReportError(f"samples must have shape (n, {len(fd)}, 3); got {paths.shape}")
    q05, q25, q50, q75, q95 = np.quantile(paths, [0.05, 0.25, 0.5, 0.75, 0.95], axis=0)
    keep = slice(max(0, len(hd) - history_days), len(hd))
    fig, axes = _figure(3.3, 1, 3)
    for k, (ax, c) in enumerate(zip(axes[0], COMPARTMENTS)):
        color = COMPARTMENT_COLORS[c]
        ax.fill_between(fd, q05[:, k], q95[:, k], color=color, alpha=0.18, linewidth=0,
                        label="90% interval")
        ax.fill_between(fd, q25[:, k], q75[:, k], color=color, alpha=0.35, linewidth=0,
                        label="50% interval")
        ax.plot(fd, q50[:, k], color=color, label="median forecast")
        ax.plot(hd[keep], obs[keep, k], linestyle="none", marker="o", markersize=2.4,
                markeredgewidth=0, color="black", alpha=0.7, label="observed")
        ax.axvline(hd[-1], color="#555555", linestyle=":", linewidth=1.0)
        ax.set_title(COMPARTMENT_NAMES[c], loc="left")
        _proportion_axis(ax, c)
        _date_axis(ax, maxticks=4)
    _legend_below(fig, axes[0, 0])
    return _png(fig)
