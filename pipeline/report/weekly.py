"""The weekly report of one run's :class:`pipeline.forecast.results.ForecastResults`.

:func:`forecast_report_content` is what :func:`pipeline.forecast.publish.publish` renders (with
:func:`pipeline.report.render.start_report`). It is annotated against ``ForecastResults``
(imported for type checking only: the forecast package imports this module), turns arrays into
figures and frames into tables; ``report.html`` + ``report.pdf`` are written by
:mod:`pipeline.report.render`.

A decision document: page 1 is the headline (:mod:`pipeline.report.headline`, the published
forecast ``results.weekly.latest`` and its backtest), then the forecast and its track record, then
the model diagnostics (S/I/R series, β/γ/R_t, state estimates, rollouts, SMC, NLL, training), then
the provenance appendix. Every band is a 50 % or 90 % central interval. Diagnostics that signal
trouble (:mod:`pipeline.report.checks`) are said in words in their section and listed on page 1.

A diagnostic section whose inputs are malformed (a :class:`ReportError` from its builder) is
left out and named in the report's warnings; anything else (a renamed field, a bug) fails the
report, so a test notices.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import platform
from collections.abc import Callable, Sequence
from importlib import metadata
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import NDArray
from torch import Tensor

from pipeline import __version__
from pipeline.io import sha256_bytes, sha256_file
from pipeline.report import checks, figures
from pipeline.forked import ChildBuild, start_in_child
from pipeline.report.content import (FigureItem, Provenance, ReportContent, ReportError, Section,
                                     SectionKey, TableItem, nll_table)
from pipeline.report.headline import (PUBLISHED, daily_history, Headline, as_numpy, compute_headline,
                                      facts_frame, fmt_count, fmt_range, fmt_share,
                                      forecast_frame, published_weekly, skill_frame)
from pipeline.names import COMPARTMENTS, DIRECTIONS

if TYPE_CHECKING:
    from pipeline.forecast.results import CountySkill, ForecastResults, ModelOutputs
    from pipeline.backtest.track_record import TrackRecord
    from pipeline.inference.smc import SMCResult

log = logging.getLogger(__name__)
STATES = COMPARTMENTS
LEVELS = figures.LEVELS
Q_COLUMNS = tuple(f"q{level:g}" for level in LEVELS)
_VERSIONED = ("torch", "numpy", "pandas", "scipy", "nflows", "zuko", "pyro-ppl", "prefect",
              "matplotlib", "weasyprint", "statsforecast")
HISTORY_WEEKS = 12          # weeks of observations before the forecast fan
FORECASTERS = {  # the published forecast first, the references last
    PUBLISHED: "published (log-scale ensemble)",
    "growth-qr": "growth regression pooled over counties (growth-qr)",
    "nf-growth": "conditional-flow member (nf-growth)",
    "nf-real": "flow fine-tuned on real counties (nf-real)",
    "nf-smc": "NF-seeded SMC (nf-smc; scored, not averaged)",
    "hub-baseline": "hub baseline",
    "autoets": "AutoETS (reference)",
}
TARGETS = {"cases": "weekly reported cases", "I": "I (share of the population)"}
_SHORT_TARGETS = {"cases": "weekly cases", "I": "I (share)"}


def _observed_at(sir: pd.DataFrame, dates: pd.DatetimeIndex) -> NDArray[np.float64]:
    frame = sir.assign(date=pd.to_datetime(sir["date"]).dt.normalize()).set_index("date")
    return frame.reindex(dates.normalize())[list(STATES)].to_numpy(dtype=np.float64)


def _fig(png: bytes, caption: str, alt: str) -> FigureItem:
    return FigureItem(png=png, caption=caption, alt=alt)


def _indices(names: Sequence[str], wanted: Sequence[str], what: str) -> list[int]:
    missing = [n for n in wanted if n not in names]
    if missing:
        raise ReportError(f"{what} lacks components {missing} (has {list(names)})")
    return [list(names).index(n) for n in wanted]


def _label(name: str) -> str:
    return FORECASTERS.get(name, name)


# ----------------------------------------------------------------------------- page 1

def headline_section(h: Headline, county: CountySkill | None = None) -> Section:
    """Page 1: the forecast table, the key facts, the backtest's verdict on the intervals, and
    the same method's skill across California's counties."""
    skill = {s.target: s for s in h.skill}
    cases = skill["cases"]
    return Section(key="headline", title=f"Forecast from {h.origin}: the next four weeks", items=(
        TableItem(forecast_frame(h), (
            f"Published forecast (log-scale ensemble) from Saturday {h.origin}: median and "
            "50%/90% intervals of the cases reported in each week (Sunday–Saturday) and of I "
            f"at its end (I·N = cases reported in the last 7 days; N = {h.population:,}); the "
            "hub submission's quantiles."), css="headline"),
        TableItem(facts_frame(h), "", css="facts"),
        TableItem(skill_frame(h, county), (
            f"Track record: the same method forecast in real time at {cases.n_origins} earlier "
            f"Saturdays ({cases.first_origin} … {cases.last_origin}). Relative WIS = Σ WIS / "
            "Σ WIS of the COVID-19 Forecast Hub baseline (below 1: better); coverage: share of "
            "observations inside the 50% and 90% intervals (nominal 0.50, 0.90)."
            + _county_caption(county)),
            decimals=2, css="skill")))


def _county_caption(county: CountySkill | None) -> str:
    if county is None:
        return (" No CDPH county data in the cache, so no skill across California's counties "
                "(`flowcast data import` the CDPH files).")
    share = county.share_beating_baseline["cases"]
    return (f" Last row: where the method was designed, every California county with at least "
            f"100,000 people (CDPH vintage {county.vintage}, {county.n_origins} Saturdays "
            f"{county.first_origin} … {county.last_origin}; geometric mean over counties of "
            f"each county's relative WIS; {share:.0%} of the counties beat the baseline).")


# ----------------------------------------------------------------------------- forecast

def _member_frame(weekly: TrackRecord) -> pd.DataFrame:
    """Every forecaster at the latest origin: median (90 % interval) per target and week."""
    forecasts = weekly.member_forecasts()
    rows, index = [], []
    for target in TARGETS:
        fmt = fmt_share if target == "I" else fmt_count
        for name in _shown(weekly):
            f = forecasts[name]
            q = {lv: f.values[target][:, int(np.argmin(np.abs(f.levels - lv)))]
                 for lv in (0.05, 0.5, 0.95)}
            # the first and last week only: four columns of intervals do not fit an A4 page
            rows.append([f"{fmt(q[0.5][k])} ({fmt_range(q[0.05][k], q[0.95][k], fmt)})"
                         for k in (0, len(f.horizons) - 1)])
            index.append((_SHORT_TARGETS[target], _label(name)))
    published = forecasts[PUBLISHED]
    horizons = (published.horizons[0], published.horizons[-1])
    origin = weekly.origin
    columns = [f"{(origin + pd.Timedelta(days=7 * h)).date()} (+{h} wk)" for h in horizons]
    return pd.DataFrame(rows, columns=columns,
                        index=pd.MultiIndex.from_tuples(index, names=["target", "forecaster"]))


def _weights_text(weekly: TrackRecord) -> str:
    w = weekly.result.weights_frame()
    now = w[pd.to_datetime(w["origin_date"]) == weekly.origin]
    if now.empty:
        return ""
    parts = []
    for h, group in now.groupby("horizon"):
        shares = ", ".join(f"{m} {x:.2f}" for m, x in zip(group["member"], group["weight"]))
        parts.append(f"{h} wk: {shares}")
    return "Weights at this origin: " + "; ".join(parts) + "."


def forecast_section(results: ForecastResults, h: Headline) -> Section:
    weekly = published_weekly(results)
    seen = daily_history(weekly).up_to(weekly.origin)
    cases, share = seen.weekly_cases()[-HISTORY_WEEKS:], seen.weekly_I()[-HISTORY_WEEKS:]
    ends = pd.DatetimeIndex([weekly.origin - pd.Timedelta(days=7 * k)
                             for k in range(len(cases))][::-1])
    q = {t: np.array([[getattr(f_t, a) for a in ("lo90", "lo50", "median", "hi50", "hi90")]
                      for f_t in (getattr(f, attr) for f in h.horizons)])
         for t, attr in (("cases", "cases"), ("I", "infectious"))}
    png = figures.published_forecast_figure(
        ends, cases, share, [f.target_end for f in h.horizons], q["cases"], q["I"],
        h.population)
    return Section.weekly(SectionKey.FORECAST, [
        _fig(png, f"The published forecast from {h.origin} (median, 50% and 90% intervals) "
                  f"after the last {len(cases)} weeks observed, on a log scale. Left: cases "
                  "reported per week (Sunday–Saturday); right: the infectious share I at the "
                  "week's end (right axis: people). Data after the origin (to "
                  f"{h.last_data_day}) wait for next week's forecast.",
             "Weekly reported cases and infectious share: observed weeks and the four-week "
             "forecast fan"),
        TableItem(_member_frame(weekly), (
            "Every forecaster at this origin: median (90% interval). The published forecast "
            "is the equal-weight average of the members' log(1 + quantile), the geometric mean "
            "of their quantiles, with no recalibration: the design that held across "
            "California's counties (docs/forecasting.md). " + _weights_text(weekly)),
            css="members")])


# ----------------------------------------------------------------------------- backtest

def _summary_tables(weekly: TrackRecord) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(relative WIS per target × horizon, coverage per target) — rows per forecaster."""
    by_target = weekly.summary()["by_target"]
    names = [n for n in _shown(weekly) if n in by_target["cases"]]
    horizons = weekly.result.horizons
    rel, cov = {}, {}
    for target, label in TARGETS.items():
        for h in (*horizons, "all"):
            key = f"h{h}" if h != "all" else "all"
            rel[(label, f"{h} wk" if h != "all" else "all")] = [
                by_target[target][n]["relative_wis_vs_baseline"][key] for n in names]
        for col, key in (("50%", "coverage50"), ("90%", "coverage90")):
            cov[(label, col)] = [by_target[target][n][key] for n in names]
        cov[(label, "scored")] = [by_target[target][n]["n_scored"] for n in names]
    index = pd.Index([_label(n) for n in names], name="forecaster")

    def frame(d: dict[tuple[str, str], list[float | int | None]]) -> pd.DataFrame:
        out = pd.DataFrame(d, index=index)
        out.columns = pd.MultiIndex.from_tuples(list(d))
        return out.astype({c: float for c in d if c[1] != "scored"})
    return frame(rel), frame(cov)


def _shown(weekly: TrackRecord) -> list[str]:
    """The forecasters the report lists, known ones first; the ensemble before recalibration
    only when there is a recalibration (otherwise it is the published forecast)."""
    names = list(weekly.member_forecasts())
    recalibrated = weekly.result.config.combine.calibration != "none"
    return [n for n in [*FORECASTERS, *(n for n in names if n not in FORECASTERS)]
            if n in names and (recalibrated or n != "ensemble-uncalibrated")]


def _past_forecasts(weekly: TrackRecord, target: str, horizons: Sequence[int]
                    ) -> pd.DataFrame:
    """Published quantiles at :data:`LEVELS` and the observed value per (origin, horizon)."""
    scores = weekly.scores
    mine = scores[(scores["forecaster"] == PUBLISHED) & (scores["target"] == target)]
    observed = {(pd.Timestamp(o), int(h)): y for o, h, y in
                zip(mine["origin_date"], mine["horizon"], mine["observed"])}
    rows = []
    for origin in weekly.origins:
        f = weekly.forecast_at(origin)
        idx = [int(np.argmin(np.abs(f.levels - lv))) for lv in LEVELS]
        for k, h in enumerate(f.horizons):
            if h not in horizons:
                continue
            row = {"target_end_date": origin + pd.Timedelta(days=7 * h), "horizon": h,
                   "observed": observed.get((origin, int(h)), np.nan)}
            row.update(zip(Q_COLUMNS, f.values[target][k, idx]))
            rows.append(row)
    return pd.DataFrame(rows)


def backtest_section(results: ForecastResults) -> Section:
    weekly = published_weekly(results)
    rel, cov = _summary_tables(weekly)
    scores = weekly.scores
    origins = pd.to_datetime(scores["origin_date"])
    span = f"{origins.nunique()} weekly origins ({origins.min().date()} … {origins.max().date()})"
    summary = weekly.summary()["by_target"]
    pit = {TARGETS[t]: {_label(n): summary[t][n]["pit_histogram"]["counts"]
                        for n in (PUBLISHED, "ensemble-uncalibrated")
                        if n in summary[t] and n in _shown(weekly)}
           for t in TARGETS}
    past = {TARGETS[t]: _past_forecasts(weekly, t, (1, 4)) for t in TARGETS}
    return Section.weekly(SectionKey.BACKTEST, [
        TableItem(rel, (
            f"Relative WIS against the COVID-19 Forecast Hub baseline per target and horizon, "
            f"over {span} forecast in real time: each forecast saw only the data up to its "
            "origin (the pooled members every county's data up to it, nothing later). "
            "Σ WIS(row) / Σ WIS(baseline) over the same forecasts; below 1 beats the baseline; "
            "bold: best in its column. Targets are never pooled."),
            decimals=2, highlight="col-min"),
        TableItem(cov, (
            "Coverage: share of observed values inside the 50% and 90% intervals (nominal 0.50 "
            "and 0.90; below nominal: intervals too narrow), and the number of scored forecasts "
            "(origins × horizons). Successive origins share target weeks, so these shares are "
            "noisier than their count suggests."), decimals=2),
        _fig(figures.past_forecasts_figure(past, (1, 4)),
             "Past published forecasts against what was reported, 1 and 4 weeks ahead: median "
             "and 50%/90% intervals at each target week (log scale), observed values in black.",
             "Past 1- and 4-week-ahead published forecasts with bands against observations"),
        _fig(figures.pit_figure(pit),
             "PIT histograms of the published forecast (all horizons; and of the ensemble "
             "before recalibration, when there is one): flat at 1 = calibrated; a U shape = "
             "intervals too narrow, a hump = too wide, a slope = biased.",
             "PIT histograms per target")], new_page=False, alerts=_skipped_places(weekly))


def _skipped_places(weekly: TrackRecord) -> list[str]:
    """The places the validation gate left out of the pooled members' data, named."""
    skipped = weekly.result.panel.skipped
    if not skipped:
        return []
    return [f"The validation gate left {len(skipped)} place(s) out of the data the pooled "
            f"members learn from, and this forecast was made without them: "
            f"{'; '.join(f'{p}: {why}' for p, why in sorted(skipped.items()))}."]


# ----------------------------------------------------------------------------- diagnostics

def series_section(results: ModelOutputs) -> Section:
    sir = results.sir_frame
    last = pd.to_datetime(sir["date"]).max().date()
    place = results.config.data.place
    png = figures.sir_series_figure(sir, vintage=str(results.vintage).split(";", 1)[0],
                                    place=place)
    counts = ("DataSF cases, tests and deaths" if results.config.data.county is None
              else "CDPH cases (by episode date) and deaths")
    return Section.weekly(SectionKey.SIR_SERIES, [_fig(
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
        png = figures.estimate_band_figure(dates, _observed_at(results.sir_frame, dates), q,
                                           direction=direction)
        side = "before" if direction == "forward" else "after"
        items.append(_fig(png, f"{direction.capitalize()} estimates of each day's state from "
                               f"the {results.config.resolved.window} observations {side} it: median, "
                               "50% and 90% intervals of the flow's samples; dots: observed.",
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
        idx = _indices(roll.names, STATES, f"{direction} {every}-day rollout")
        q = _path_quantiles(as_numpy(roll.samples)[..., idx])                      # (5, T, 3)
        png = figures.rollout_figure(dates, _observed_at(sir, dates), q,
                                     window_days=int(every), direction=direction)
        series_dates = pd.DatetimeIndex(pd.to_datetime(sir["date"]))
        alert = checks.rollout_overshoot(f"{direction} {every}-day rollout",
                                         q[LEVELS.index(0.5), :, STATES.index("I")],
                                         sir["I"].to_numpy(), dates=series_dates,
                                         anchors=roll.anchors, direction=direction)
        if alert:
            alerts.append(alert)
        items.append(_fig(png, f"{direction.capitalize()} rollout re-anchored on observations "
                               f"every {every} days: median, 50% and 90% intervals of the "
                               "sample paths; full series (left) and 60 days around the peak "
                               "of I (right).",
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
        _fig(png, "Joint estimates of the transmission rate β (per observed susceptible) and "
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
    idx = _indices(res.state_names, STATES, "the SMC result")
    q = _smc_quantiles(res, idx)
    dates = pd.DatetimeIndex(results.smc.dates)
    ess = as_numpy(res.ess)[0]
    n = results.config.smc.particles
    png = figures.smc_band_figure(dates, _observed_at(results.sir_frame, dates), q,
                                  ess=ess, n_particles=n,
                                  collapse_fraction=checks.ESS_COLLAPSE_FRACTION)
    alert = checks.ess_collapse(ess, n, dates)
    return Section.weekly(SectionKey.SMC, [_fig(
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
    return Section.weekly(SectionKey.TRAINING, [_fig(
        png, f"Training loss (mean since the previous evaluation) and validation NLL of the "
             f"forward and backward {results.models.encoder} joint flows ({reused}).",
        "Training and validation loss curves")], new_page=False)


# Diagnostics: a malformed input (ReportError) leaves the section out, named in the warnings.
_DIAGNOSTICS: Sequence[tuple[str, Callable[[ModelOutputs], Section]]] = (
    ("S/I/R series", series_section), ("β, γ, R_t", parameter_section),
    ("state estimates", estimates_section), ("rollouts", rollout_section),
    ("SMC", smc_section), ("NLL table", nll_section), ("loss curves", training_section))


# ----------------------------------------------------------------------------- provenance

def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in _VERSIONED:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def _provenance(results: ForecastResults) -> Provenance:
    csv = results.sir_frame.to_csv(index=False).encode("utf-8")
    checkpoint = ""
    models = results.models
    path = models.path / "forward" / "model.pt"
    if path.is_file():
        checkpoint = sha256_file(path)
    config = results.config
    cfg = config.as_dict()
    weekly = results.weekly
    extra = {"model cache key": str(models.key),
             "model": "reused from the model cache" if models.reused else "trained in this run",
             "forward checkpoint": str(path) if checkpoint else "—"}
    extra["published forecast: flow member"] = (
        f"{weekly.model_key or '—'} ("
        f"{'reused from the model cache' if weekly.model_reused else 'trained in this run'})")
    for direction, p in config.resolved.presets.items():  # the presets the models come from
        extra[f"{direction} training preset"] = (
            f"{p.run_name}: {p.train.iterations} iterations, batch {p.train.batch_size}, "
            f"lr {p.train.lr:g} ({p.train.schedule}), {p.dataset.name} "
            f"{p.dataset.n_trajectories or 'all'} trajectories")
    return Provenance(package_version=__version__, versions=_versions(), config=cfg,
                      data_sha256=sha256_bytes(csv), checkpoint_sha256=checkpoint,
                      seed=config.seed, extra=extra)


# ----------------------------------------------------------------------------- assembly

def data_banner(results: ForecastResults, today: dt.date | None = None) -> str | None:
    """The report's one data banner (stale or old data), else None."""
    last = pd.to_datetime(results.sir_frame["date"]).max().date()
    return checks.data_banner(stale=results.stale, vintage=results.vintage,
                              notes=results.stale_notes, last_day=last,
                              today=today or dt.date.today(), source=results.config.data.kind,
                              provider=results.config.data.provider)


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


def forecast_report_content(results: ForecastResults,
                            diagnostics: DiagnosticsUnderWay | None = None) -> ReportContent:
    """The ``ReportContent`` of one weekly run. ``diagnostics``: some of
    :func:`diagnostic_sections` already under way in a child process; the rest are drawn
    here."""
    headline = compute_headline(results)
    banner = data_banner(results)
    notes = [banner] if banner else []
    sections = [forecast_section(results, headline), backtest_section(results)]
    in_child = diagnostics.names if diagnostics is not None else ()
    here = diagnostic_sections(results.model_outputs(),
                               [n for n in DIAGNOSTICS if n not in in_child])
    forked = diagnostics.build.result() if diagnostics is not None else {}
    for name in DIAGNOSTICS:
        part = forked.get(name, here.get(name))
        if isinstance(part, Section):
            sections.append(part)
        elif part is not None:
            notes.append(part)
    # the header shows the vintage's first two parts (as of, days); the full one is in §3
    vintage = "; ".join(str(results.vintage).split("; ")[:2])
    return ReportContent(
        title=f"{headline.place} COVID-19 forecast from {headline.origin}",
        reference_date=headline.origin, data_vintage=vintage,
        sections=tuple(sections), provenance=_provenance(results), warnings=tuple(notes),
        summary=headline.sentence(),
        headline=headline_section(headline, results.county_skill))
