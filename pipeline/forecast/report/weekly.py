"""The weekly report of one run's :class:`pipeline.forecast.results.ForecastResults`.

:func:`forecast_report_content` is what :func:`pipeline.forecast.publish.publish` renders (with
:func:`pipeline.report.render.start_report`). It is annotated against ``ForecastResults``
(imported for type checking only: the forecast package imports this module), turns arrays into
figures and frames into tables; ``report.html`` + ``report.pdf`` are written by
:mod:`pipeline.report.render`.

A decision document: page 1 is the headline (:mod:`pipeline.forecast.report.headline`, the published
forecast ``results.weekly.latest`` and its backtest), then the forecast and its track record, then
the model diagnostics (:mod:`pipeline.forecast.report.diagnostics`: S/I/R series, β/γ/R_t, state
estimates, rollouts, SMC, NLL, training), then the provenance appendix. Every band is a 50 % or
90 % central interval. Diagnostics that signal trouble (:mod:`pipeline.report.checks`) are said in
words in their section and listed on page 1.

A diagnostic section whose inputs are malformed (a :class:`ReportError` from its builder) is
left out and named in the report's warnings; anything else (a renamed field, a bug) fails the
report, so a test notices.
"""
from __future__ import annotations

import datetime as dt
import logging
import re
import platform
from collections.abc import Sequence
from importlib import metadata
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from torch import Tensor

from pipeline import __version__
from pipeline.io import sha256_bytes, sha256_file
from pipeline.report import checks, figures
from pipeline.report.content import (FigureItem, Notice, NoticeKind, PageOne, Provenance,
                                     ReportContent, Section, SectionKey, TableItem)
from pipeline.forecast.report.diagnostics import (DIAGNOSTICS, LEVELS, Q_COLUMNS, DiagnosticsUnderWay,
                                         diagnostic_sections, figure_item)
from pipeline.forecast.report.headline import (PUBLISHED, daily_history, Headline, Interval,
                                      compute_headline, facts_frame, fmt_count, fmt_prob,
                                      fmt_range, fmt_share, forecast_frame,
                                      published_weekly, skill_frame)
from pipeline.report.page1 import fan_chart_figure

if TYPE_CHECKING:
    from pipeline.forecast.results import CountySkill, ForecastResults
    from pipeline.backtest.track_record import TrackRecord

log = logging.getLogger(__name__)
_VERSIONED = ("torch", "numpy", "pandas", "scipy", "nflows", "zuko", "pyro-ppl", "prefect",
              "matplotlib", "weasyprint", "statsforecast")
HISTORY_WEEKS = 12          # weeks of observations before the forecast fan
FORECASTERS = {  # the published forecast first, the references last
    PUBLISHED: "published (log-scale ensemble)",
    "gbqr": "gradient-boosted quantile regression pooled over counties (gbqr)",
    "growth-qr": "growth regression pooled over counties (growth-qr)",
    "nf-growth": "conditional-flow member (nf-growth)",
    "nf-real": "flow fine-tuned on real counties (nf-real)",
    "nf-smc": "NF-seeded SMC (nf-smc; scored, not averaged)",
    "hub-baseline": "hub baseline",
    "autoets": "AutoETS (reference)",
}
TARGETS = {"cases": "weekly reported cases", "I": "I (share of the population)"}
_SHORT_TARGETS = {"cases": "weekly cases", "I": "I (share)"}


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


def _bands(x: Interval) -> list[float]:
    return [x.lo90, x.lo50, x.median, x.hi50, x.hi90]


def page_one_figure(results: ForecastResults, h: Headline) -> bytes:
    """Weekly cases: the last 12 weeks reported (the weeks still being reported hollow), their
    nowcast and the current week marked as nowcast, the four weeks' forecast fan."""
    weekly = published_weekly(results)
    seen = daily_history(weekly).up_to(weekly.origin)
    cases = seen.weekly_cases()[-HISTORY_WEEKS:]
    ends = [(weekly.origin - pd.Timedelta(days=7 * k)).date() for k in range(len(cases))][::-1]
    nowcast = sorted(h.nowcast_weeks, key=lambda w: w.target_end)
    targets = [w.target_end for w in nowcast] + [f.target_end for f in h.horizons]
    bands = np.array([_bands(w.cases) for w in nowcast] + [_bands(f.cases) for f in h.horizons])
    marked = np.array([True] * len(nowcast) + [f.kind == "current week" for f in h.horizons])
    in_nowcast = {w.target_end for w in nowcast}
    return fan_chart_figure(ends, np.asarray(cases, dtype=np.float64), targets, bands,
                            nowcast=marked, unit="cases reported per week", wide="90%",
                            incomplete=np.array([e in in_nowcast for e in ends]),
                            log=True, height_in=3.6)


def page_one_table(h: Headline) -> pd.DataFrame:
    """Weekly reported cases: the weeks still being reported (nowcast) and the four weeks
    ahead, median and 50 %/90 % intervals."""
    rows, labels = [], []
    for w in sorted(h.nowcast_weeks, key=lambda w: w.target_end):
        labels.append(f"{w.target_end} (nowcast, {fmt_prob(w.reported_share.median)} in)")
        rows.append(w.cases)
    for f in h.horizons:
        labels.append(f"{f.target_end} (+{f.horizon} wk"
                      + (", nowcast)" if f.kind == "current week" else ")"))
        rows.append(f.cases)
    return pd.DataFrame([[fmt_count(x.median), fmt_range(x.lo50, x.hi50),
                          fmt_range(x.lo90, x.hi90)] for x in rows],
                        index=pd.Index(labels, name="week ending"),
                        columns=["median", "50% interval", "90% interval"])


def page_one_headline(h: Headline) -> str:
    """Two sentences: the first and last week's forecast against the week to the origin; the
    chance of growth and R_t."""
    return h.forecast_clause(place=True)


def weekly_notices(results: ForecastResults, today: dt.date, n_left_out_sections: int
                   ) -> tuple[Notice, ...]:
    """What this run left out or held, briefly (the full banner and notes are on page 2):
    stale or old data, the places the gate left out of the pooled data, the members the
    published forecast went without (a hub round's rule), sections not drawn."""
    out = []
    last = pd.to_datetime(results.sir_frame["date"]).max().date()
    age = (today - last).days
    if results.stale:
        out.append(Notice(NoticeKind.HELD, f"Stale data: the live fetch failed and the cache was "
                          f"used; the newest day is {last} ({age:,} days old)."))
    elif age > checks.OLD_DATA_DAYS:
        out.append(Notice(NoticeKind.HELD, f"Old data: the newest day, {last}, is {age:,} days "
                          "before this run."))
    weekly = results.weekly
    skipped = weekly.result.panel.skipped if weekly is not None else {}
    if skipped:
        out.append(Notice(NoticeKind.LEFT_OUT, f"{len(skipped)} place(s) left out of the "
                          f"pooled members' data by the validation gate: "
                          f"{', '.join(sorted(skipped))}."))
    out += [Notice(NoticeKind.LEFT_OUT, f"Member {d.name} left out of the published forecast: "
                   f"{d.why}." if d.what == "member" else f"Refit {d.name} replaced: {d.why}.")
            for d in (weekly.dropped() if weekly is not None else ())]
    if n_left_out_sections:
        out.append(Notice(NoticeKind.NOTE, f"{n_left_out_sections} diagnostic section(s) could "
                          "not be drawn (named on page 2)."))
    return tuple(out)


def page_one(results: ForecastResults, h: Headline, notices: Sequence[Notice]) -> PageOne:
    figure = FigureItem(page_one_figure(results, h), (
        f"Weekly cases: last {HISTORY_WEEKS} weeks, nowcast, forecast (50%, 90%)."),
        "Weekly reported cases: observed weeks, the nowcast and the four-week forecast fan")
    return PageOne((figure,), page_one_headline(h), TableItem(page_one_table(h), "",
                                                             css="headline"), tuple(notices))


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
        figure_item(png, f"The published forecast from {h.origin} (median, 50% and 90% intervals) "
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
        figure_item(figures.past_forecasts_figure(past, (1, 4)),
             "Past published forecasts against what was reported, 1 and 4 weeks ahead: median "
             "and 50%/90% intervals at each target week (log scale), observed values in black.",
             "Past 1- and 4-week-ahead published forecasts with bands against observations"),
        figure_item(figures.pit_figure(pit),
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
    vintage = re.sub(r"\s*\([^()]*\)$", "", vintage)     # page 1 is short: the why is in §3
    left_out = len(notes) - (1 if banner else 0)
    return ReportContent(
        title=f"{headline.place} COVID-19 forecast from {headline.origin}",
        reference_date=headline.origin, data_vintage=vintage,
        sections=tuple(sections), provenance=_provenance(results), warnings=tuple(notes),
        summary=headline.sentence(),
        headline=headline_section(headline, results.county_skill),
        page1=page_one(results, headline, weekly_notices(results, dt.date.today(), left_out)))
