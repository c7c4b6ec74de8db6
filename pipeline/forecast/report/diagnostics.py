"""The weekly report's model diagnostics: the epidemic model's sections, each drawn from the
run's :class:`~pipeline.forecast.results.ModelOutputs` — the S/I/R series, β/γ/R_t, the state
estimates, rollouts, the NF-seeded SMC, the NLL table (paper Table 5) and the training curves.

A section whose inputs are malformed (a :class:`ReportError` from its builder) is left out and
named in the report's warnings; anything else fails the report, so a test notices. Some are
drawn in a forked child while the rest of the report is written (:func:`start_diagnostics`).
The report around them: :mod:`pipeline.forecast.report.weekly`.
"""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from pipeline.forked import ChildBuild, start_in_child
from pipeline.names import COMPARTMENTS, DIRECTIONS
from pipeline.report import checks, figures
from pipeline.report.content import (FigureItem, ReportError, Section, SectionKey, TableItem,
                                     nll_table)
from pipeline.forecast.report.headline import as_numpy, fmt_range

if TYPE_CHECKING:
    from pipeline.forecast.results import ModelOutputs
    from pipeline.inference.smc import SMCResult

log = logging.getLogger(__name__)
STATES = COMPARTMENTS
LEVELS = figures.LEVELS
Q_COLUMNS = tuple(f"q{level:g}" for level in LEVELS)


def observed_at(sir: pd.DataFrame, dates: pd.DatetimeIndex) -> NDArray[np.float64]:
    frame = sir.assign(date=pd.to_datetime(sir["date"]).dt.normalize()).set_index("date")
    return frame.reindex(dates.normalize())[list(STATES)].to_numpy(dtype=np.float64)


def figure_item(png: bytes, caption: str, alt: str) -> FigureItem:
    return FigureItem(png=png, caption=caption, alt=alt)


def component_indices(names: Sequence[str], wanted: Sequence[str], what: str) -> list[int]:
    missing = [n for n in wanted if n not in names]
    if missing:
        raise ReportError(f"{what} lacks components {missing} (has {list(names)})")
    return [list(names).index(n) for n in wanted]


# ----------------------------------------------------------------------------- diagnostics

def series_section(results: ModelOutputs) -> Section:
    sir = results.sir_frame
    last = pd.to_datetime(sir["date"]).max().date()
    place = results.config.data.place
    png = figures.sir_series_figure(sir, vintage=str(results.vintage).split(";", 1)[0],
                                    place=place)
    counts = ("DataSF cases, tests and deaths" if results.config.data.county is None
              else "CDPH cases (by episode date) and deaths")
    return Section.weekly(SectionKey.SIR_SERIES, [figure_item(
        png, f"S, I and R as fractions of the {place} population, derived from {counts}; "
             f"last day {last}. Data: {results.vintage}.",
        "Three stacked time series: susceptible, infectious and removed fractions")],
        title=f"{place} S/I/R series")


def _long_to_arrays(frame: pd.DataFrame, direction: str
                    ) -> tuple[pd.DatetimeIndex, dict[str, pd.DataFrame]]:
    part = frame[frame["direction"] == direction]
    wide = {c: part[part["component"] == c].assign(date=lambda d: pd.to_datetime(d["date"]))
            .set_index("date").sort_index() for c in part["component"].unique()}
    if "S" not in wide:
        raise ReportError(f"parameter table has no {direction} S rows")
    dates = wide["S"].index
    return pd.DatetimeIndex(dates), {c: w.reindex(dates) for c, w in wide.items()}


def _q(wide: pd.DataFrame) -> NDArray[np.float64]:
    """(T, 5) quantiles at :data:`LEVELS` of one component's rows."""
    missing = [c for c in Q_COLUMNS if c not in wide.columns]
    if missing:
        raise ReportError(f"parameter table lacks quantile columns {missing}")
    return wide[list(Q_COLUMNS)].to_numpy(dtype=np.float64)


def estimates_section(results: ModelOutputs) -> Section:
    items = []
    for direction in DIRECTIONS:
        dates, wide = _long_to_arrays(results.parameters, direction)
        q = np.stack([_q(wide[c]) for c in STATES], axis=-1).transpose(1, 0, 2)   # (5, T, 3)
        png = figures.estimate_band_figure(dates, observed_at(results.sir_frame, dates), q,
                                           direction=direction)
        side = "before" if direction == "forward" else "after"
        items.append(figure_item(
            png, f"{direction.capitalize()} estimates of each day's state from the "
                 f"{results.config.resolved.window} observations {side} it: median, 50% and 90% "
                 "intervals of the flow's samples; dots: observed.",
            f"{direction} state estimates of S, I, R with 50% and 90% bands"))
    return Section.weekly(SectionKey.STATE_ESTIMATES, items)


def _path_quantiles(samples: NDArray[np.float64]) -> NDArray[np.float64]:
    """Quantiles at :data:`LEVELS` over the paths of ``samples (n, T, C)``, as
    ``np.nanquantile`` gives them: NaN where nothing was predicted (days before the first
    window: the band leaves a gap). Days predicted on every path go through ``np.quantile``
    (the same values; ``nanquantile`` loops over the days in Python, seconds per rollout)."""
    missing = np.isnan(samples)
    everywhere = ~missing.any(axis=0)                                               # (T, C)
    somewhere = ~everywhere & ~missing.all(axis=0)
    out = np.full((len(LEVELS), *samples.shape[1:]), np.nan)
    out[:, everywhere] = np.quantile(samples[:, everywhere], LEVELS, axis=0)
    if somewhere.any():
        out[:, somewhere] = np.nanquantile(samples[:, somewhere], LEVELS, axis=0)
    return out


def rollout_section(results: ModelOutputs) -> Section:
    sir = results.sir_frame
    start = pd.to_datetime(sir["date"]).min()
    items = []
    alerts: list[str] = []
    for (direction, every), roll in sorted(results.rollouts.items(),
                                           key=lambda kv: (kv[0][1], kv[0][0])):
        dates = pd.DatetimeIndex(start + pd.to_timedelta(np.asarray(roll.times, dtype=float),
                                                         unit="D"))
        idx = component_indices(roll.names, STATES, f"{direction} {every}-day rollout")
        q = _path_quantiles(as_numpy(roll.samples)[..., idx])                      # (5, T, 3)
        png = figures.rollout_figure(dates, observed_at(sir, dates), q,
                                     window_days=int(every), direction=direction)
        seeded = direction == "forward" and results.config.rollouts.forward == "flow-seeded-prior"
        alert = checks.rollout_overshoot(f"{direction} {every}-day rollout",
                                         q[LEVELS.index(0.5), :, STATES.index("I")],
                                         sir["I"].to_numpy(),
                                         dates=pd.DatetimeIndex(pd.to_datetime(sir["date"])),
                                         anchors=roll.anchors, direction=direction,
                                         chained=not seeded)
        if alert:
            alerts.append(alert)
        how = (f"the forward flow's estimate of S, I, R and β from the {results.config.resolved.window} "
               "days before each anchor, carried on by the multi-wave prior's own dynamics (I as "
               "it would be reported)" if seeded else
               "the flow's one-day estimates chained, each path fed its own draws")
        items.append(figure_item(
            png, f"{direction.capitalize()} rollout re-anchored on observations every {every} "
                 f"days: {how}. Median, 50% and 90% intervals of the sample paths; full series "
                 "(left) and 60 days around the peak of I (right).",
            f"{direction} {every}-day rollout of S, I, R, full and zoomed"))
    return Section.weekly(SectionKey.ROLLOUTS, items, alerts=alerts)


ONE_MODEL = (
    "One model of the epidemic: the forward and backward joint flows behind β, R_t, the state "
    "estimates and the rollouts are trained on the multi-wave prior that also trains the "
    "published forecast's flow member (SIRS with a drifting, jumping transmission rate, seen "
    "through the same 7-day S/I/R conversion as the forecast's data), and the NF-seeded SMC "
    "filters that prior's own dynamics from the flow's draws. γ = 1/7 per day is not "
    "estimated: the conversion removes every case after exactly 7 days. R_t = β·S/γ on page 1 is the forward "
    "flow's; the SMC's four-week forecast is scored in the backtest beside the members "
    "(“nf-smc”) and enters the published forecast only if it earns weight there.")


def parameter_section(results: ModelOutputs) -> Section:
    dates, wide = _long_to_arrays(results.parameters, "forward")
    resolved = results.config.resolved
    gamma = resolved.gamma
    beta_prior = resolved.prior.beta_range
    rt = _q(wide["Rt"]) if "Rt" in wide else None
    png = figures.parameter_figure(dates, _q(wide["beta"]), _q(wide["gamma"]), rt,
                                   beta_prior=beta_prior, gamma_fixed=gamma)
    names = {"beta": "β (per day)", "gamma": "γ (per day)", "Rt": "R_t = β·S/γ"}
    rows = {names[c]: [wide[c]["q0.5"].iloc[-1],
                       fmt_range(wide[c]["q0.25"].iloc[-1], wide[c]["q0.75"].iloc[-1], _g3),
                       fmt_range(wide[c]["q0.05"].iloc[-1], wide[c]["q0.95"].iloc[-1], _g3),
                       fmt_range(*beta_prior, _g3) if c == "beta" else "—"]
            for c in names if c in wide and c != "gamma"}
    rows[names["gamma"]] = [gamma, "fixed", f"1/{resolved.prior.window_days} (the window)", "—"]
    table = pd.DataFrame(list(rows.values()), index=pd.Index(list(rows), name="parameter"),
                         columns=["median", "50% interval", "90% interval", "prior range"])
    alert = checks.prior_not_updated("β", wide["beta"]["q0.05"].to_numpy(),
                                     wide["beta"]["q0.95"].to_numpy(), beta_prior, dates)
    return Section.weekly(SectionKey.PARAMETERS, [
        figure_item(
            png, "Joint estimates of the transmission rate β (per observed susceptible) and "
                 f"R_t = β·S/γ (per joint sample) from the {resolved.window} days of S/I/R "
                 "before each day: median, 50% and 90% intervals; dotted lines: the prior's "
                 "starting range of β (β drifts in the prior, and the estimate is the β in "
                 "effect on the day). γ = 1/7 per day is fixed by the conversion's window.",
            "Time series of beta and R_t with 50% and 90% intervals, gamma fixed"),
        TableItem(table, f"β, γ and R_t on {dates[-1].date()} (latest estimated day).",
                  decimals=4)], intro=ONE_MODEL, alerts=[alert] if alert else [])


def _g3(x: float) -> str:
    return f"{x:.3g}"


def _smc_quantiles(res: SMCResult, idx: list[int]) -> NDArray[np.float64]:
    """(5, T, 3) weighted quantiles at :data:`LEVELS` of the (first) filter."""
    recorded = np.asarray(res.quantile_levels, dtype=np.float64)
    picks = []
    for level in LEVELS:
        hits = np.flatnonzero(np.isclose(recorded, level, rtol=0, atol=1e-9))
        if hits.size == 0:
            raise ReportError(f"the SMC run did not record the {level} quantile (recorded "
                              f"{recorded.tolist()}); SMCConfig.quantiles must include "
                              f"{list(LEVELS)}")
        picks.append(as_numpy(res.quantiles[0, :, hits[0]])[:, idx])
    return np.stack(picks)


def smc_section(results: ModelOutputs) -> Section:
    res = results.smc.result
    idx = component_indices(res.state_names, STATES, "the SMC result")
    q = _smc_quantiles(res, idx)
    dates = pd.DatetimeIndex(results.smc.dates)
    ess = as_numpy(res.ess)[0]
    n = results.config.smc.particles
    png = figures.smc_band_figure(dates, observed_at(results.sir_frame, dates), q,
                                  ess=ess, n_particles=n,
                                  collapse_fraction=checks.ESS_COLLAPSE_FRACTION)
    alert = checks.ess_collapse(ess, n, dates)
    return Section.weekly(SectionKey.SMC, [figure_item(
        png, f"Particle filter ({n:,} particles) on the multi-wave prior's renewal dynamics, "
             f"seeded with the forward joint flow's (S, I, R, β) draws at {dates[0].date()} and "
             "following the cases reported in each 7-day window: filtered median, 50% and 90% "
             "weighted-quantile bands; bottom: effective sample size. The same filter, run at "
             "every past Saturday, is the backtest's “nf-smc” forecaster.",
        "Particle filter estimates of S, I, R with 50% and 90% bands and effective sample "
        "size")], alerts=[alert] if alert else [])


# The paper's Table 5 columns, then any other variant this store holds (e.g. MLP).
_PAPER_VARIANTS = ("Transformer", "Transformer + KE", "Mamba-SSM")


def nll_section(results: ModelOutputs) -> Section:
    frame = results.nll
    short = {"forward": "fw", "backward": "bw"}
    ours = list(dict.fromkeys(frame["variant"].astype(str)))
    variants = [*_PAPER_VARIANTS, *(v for v in ours if v not in _PAPER_VARIANTS)]
    values = {(short.get(str(d), str(d)), str(v)): float(x)
              for d, v, x in zip(frame["direction"], frame["variant"], frame["mean_nll"])}
    table = nll_table(values, variants=variants)
    n = int(frame["locations"].max()) if "locations" in frame else None
    where = f" at {n} random days" if n else ""
    missing = [v for v in _PAPER_VARIANTS if v not in ours]
    absent = (f" “—”: no trained {', '.join(missing)} model in the model store for this "
              "configuration (train them with `python -m flows.scale_out`; the next weekly run "
              "scores every cached variant)." if missing else "")
    return Section.weekly(SectionKey.NLL, [TableItem(
        table, f"Mean negative log-likelihood of the observed (S, I, R){where} under the "
               "estimated conditional density, forward (fw) and backward (bw), aggregated "
               "across compartments (layout of the paper's Table 5; lower is better)." + absent,
        highlight="row-min")])


def training_section(results: ModelOutputs) -> Section:
    frames = []
    for direction, history in results.models.histories.items():
        h = pd.DataFrame(list(history))
        if h.empty:
            continue
        frames.append(pd.DataFrame({"step": h["iteration"], "train": h["train_loss"],
                                    "validation": h["val_nll"], "variant": f"{direction} flow"}))
    if not frames:
        raise ReportError("no training history in the model store entry")
    png = figures.loss_curve_figure(pd.concat(frames, ignore_index=True),
                                    ylabel="loss (standardized NLL)")
    reused = "reused from the model cache" if results.models.reused else "trained in this run"
    return Section.weekly(SectionKey.TRAINING, [figure_item(
        png, f"Training loss (mean since the previous evaluation) and validation NLL of the "
             f"forward and backward {results.models.encoder} joint flows ({reused}).",
        "Training and validation loss curves")], new_page=False)


# Diagnostics: a malformed input (ReportError) leaves the section out, named in the warnings.
_DIAGNOSTICS: Sequence[tuple[str, Callable[[ModelOutputs], Section]]] = (
    ("S/I/R series", series_section), ("β, γ, R_t", parameter_section),
    ("state estimates", estimates_section), ("rollouts", rollout_section),
    ("SMC", smc_section), ("NLL table", nll_section), ("loss curves", training_section))


# About half the report's drawing (3.9 of 7.5 s here: 6 of the 13 figures): a child process
# draws these while this one writes the tables and the other sections (publish).
FORKED_DIAGNOSTICS = ("S/I/R series", "rollouts", "loss curves")
DIAGNOSTICS = tuple(name for name, _ in _DIAGNOSTICS)
Drawn = dict[str, "Section | str"]          # a diagnostic's section, or why it is missing


@dataclasses.dataclass(frozen=True)
class DiagnosticsUnderWay:
    """Diagnostic sections ``names`` being drawn in a child process (:func:`start_diagnostics`)."""

    names: tuple[str, ...]
    build: ChildBuild[Drawn]


def diagnostic_sections(outputs: ModelOutputs, names: Sequence[str] | None = None) -> Drawn:
    """The report's diagnostic sections named ``names`` (default: all, :data:`DIAGNOSTICS`);
    a section that cannot be drawn is replaced by a note saying so (the rest is published)."""
    drawn: Drawn = {}
    for name, build in _DIAGNOSTICS:
        if names is not None and name not in names:
            continue
        try:
            drawn[name] = build(outputs)
        except ReportError as exc:   # malformed inputs: publish the rest, say what is missing
            log.exception("report section %s failed", name)
            drawn[name] = f"The {name} section could not be drawn: {exc}"
    return drawn


def start_diagnostics(outputs: ModelOutputs, names: Sequence[str] = DIAGNOSTICS
                      ) -> DiagnosticsUnderWay:
    """The diagnostic sections ``names`` started in a forked child process
    (:mod:`pipeline.forked`): drawn while this process goes on (the weekly forecast, or the
    rest of the report)."""
    chosen = tuple(names)
    return DiagnosticsUnderWay(chosen, start_in_child(lambda: diagnostic_sections(outputs,
                                                                                  chosen)))
