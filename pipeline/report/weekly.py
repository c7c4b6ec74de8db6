"""The weekly report from the forecast pipeline's results (``pipeline.forecast.ForecastResults``).

``build_forecast_report(results, out_dir)`` is the hook ``pipeline.forecast.write_report``
calls. It reads the results by attribute (no import of ``pipeline.forecast``, which imports
torch-heavy modules), turns arrays into figures and frames into tables, and writes
``report.html`` + ``report.pdf`` with :func:`pipeline.report.render.write_report`.

Attributes read (as ``pipeline.forecast`` defines them):
``sir_frame`` (date, S, I, R), ``vintage``, ``stale``, ``stale_notes``, ``config`` (dataclass,
``seed``), ``future`` (dates, samples (P, H, ≥3), reference_date), ``parameters`` (long:
direction, date, component ∈ S, I, R, beta, gamma, mean, std, q0.025, q0.5, q0.975),
``rollouts`` {(direction, every): RolloutResult with times (days since the first date),
mean (H, D), band(2.0), names}, ``smc`` (result with mean (1, T, D), sigma_band(3), ess (1, T),
num_particles, state_names; dates), ``nll`` (direction, variant, mean_nll), ``models``
(key, reused, encoder, path, histories {direction: [ {iteration, train_loss, val_nll}, ...]}),
optional ``backtest`` (a :class:`pipeline.backtest.BacktestResult`).

A section whose inputs are missing or malformed is left out and named in the report's warnings
(the run's other results are still worth publishing); the error is also logged.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import platform
from collections.abc import Callable, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline import __version__
from pipeline.io import sha256_bytes, sha256_file
from pipeline.report import figures
from pipeline.report.content import (FigureItem, Provenance, ReportContent, Section, SectionKey,
                                     TableItem, nll_table, stale_data_warning)
from pipeline.report.render import ReportFiles, write_report

log = logging.getLogger(__name__)
STATES = ("S", "I", "R")
_VERSIONED = ("torch", "numpy", "pandas", "scipy", "nflows", "zuko", "pyro-ppl", "prefect",
              "matplotlib", "weasyprint")


def _numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def _observed_at(sir: pd.DataFrame, dates: pd.DatetimeIndex) -> np.ndarray:
    frame = sir.assign(date=pd.to_datetime(sir["date"]).dt.normalize()).set_index("date")
    return frame.reindex(dates.normalize())[list(STATES)].to_numpy(dtype=np.float64)


def _fig(png: bytes, caption: str, alt: str) -> FigureItem:
    return FigureItem(png=png, caption=caption, alt=alt)


# ----------------------------------------------------------------------------- sections

def _series_section(r: Any) -> Section:
    sir = r.sir_frame
    last = pd.to_datetime(sir["date"]).max().date()
    # the figure's subtitle gets the short vintage; the caption carries the full one
    png = figures.sir_series_figure(sir, vintage=str(r.vintage).split(";", 1)[0])
    return Section.weekly(SectionKey.SIR_SERIES, [_fig(
        png, f"S, I and R as fractions of the San Francisco population, derived from DataSF "
             f"cases, tests and deaths; last day {last}. Data: {r.vintage}.",
        "Three stacked time series: susceptible, infectious and removed fractions")])


def _forecast_section(r: Any) -> Section:
    f = r.future
    samples = _numpy(f.samples)[..., :3]
    sir = r.sir_frame
    png = figures.forecast_fan_figure(pd.to_datetime(sir["date"]),
                                      sir[list(STATES)].to_numpy(dtype=float),
                                      pd.DatetimeIndex(f.dates), samples)
    return Section.weekly(SectionKey.FORECAST, [_fig(
        png, f"Forecast from {f.reference_date} for {len(f.dates)} days: median and 50%/90% "
             f"intervals of {samples.shape[0]} sample paths of the forward flow rollout; dots: "
             "the last 8 weeks observed. The same paths give hub_forecast.csv.",
        "Fan charts of the four-week forecast of S, I and R")])


def _long_to_arrays(frame: pd.DataFrame, direction: str) -> tuple[pd.DatetimeIndex, dict]:
    part = frame[frame["direction"] == direction]
    wide = {c: part[part["component"] == c].assign(date=lambda d: pd.to_datetime(d["date"]))
            .set_index("date").sort_index() for c in part["component"].unique()}
    dates = wide["S"].index
    return pd.DatetimeIndex(dates), {c: w.reindex(dates) for c, w in wide.items()}


def _estimates_section(r: Any) -> Section:
    items = []
    for direction in ("forward", "backward"):
        dates, wide = _long_to_arrays(r.parameters, direction)
        mean = np.column_stack([wide[c]["mean"] for c in STATES])
        std = np.column_stack([wide[c]["std"] for c in STATES])
        png = figures.estimate_band_figure(dates, _observed_at(r.sir_frame, dates), mean,
                                           mean - 2 * std, mean + 2 * std, direction=direction)
        side = "before" if direction == "forward" else "after"
        items.append(_fig(png, f"{direction.capitalize()} estimates of each day's state from the "
                               f"{r.config.window} observations {side} it: mean ± 2σ of the "
                               "flow's samples; dots: observed.",
                          f"{direction} state estimates of S, I, R with 2 sigma bands"))
    return Section.weekly(SectionKey.STATE_ESTIMATES, items)


def _rollout_section(r: Any) -> Section:
    sir = r.sir_frame
    start = pd.to_datetime(sir["date"]).min()
    items = []
    for (direction, every), roll in sorted(r.rollouts.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        dates = start + pd.to_timedelta(np.asarray(roll.times, dtype=float), unit="D")
        names = list(roll.names)
        idx = [names.index(c) for c in STATES]
        mean = _numpy(roll.mean)[:, idx]
        lower, upper = (_numpy(b)[:, idx] for b in roll.band(2.0))
        png = figures.rollout_figure(pd.DatetimeIndex(dates), _observed_at(sir, pd.DatetimeIndex(dates)),
                                     mean, lower, upper, window_days=int(every),
                                     direction=direction)
        items.append(_fig(png, f"{direction.capitalize()} rollout re-anchored on observations "
                               f"every {every} days: mean ± 2σ of the sample paths; full series "
                               "(left) and 60 days around the peak of I (right).",
                          f"{direction} {every}-day rollout of S, I, R, full and zoomed"))
    return Section.weekly(SectionKey.ROLLOUTS, items)


def _parameter_section(r: Any) -> Section:
    dates, wide = _long_to_arrays(r.parameters, "forward")
    q = ["q0.025", "q0.5", "q0.975"]
    prior_beta = prior_gamma = None
    prior = getattr(r.config, "prior", None)  # the training prior's ranges, when known
    if prior is not None:
        prior_beta, prior_gamma = tuple(prior.beta), tuple(prior.gamma)
    png = figures.parameter_figure(dates, wide["beta"][q].to_numpy(), wide["gamma"][q].to_numpy(),
                                   beta_prior=prior_beta, gamma_prior=prior_gamma)
    latest = {c: wide[c].iloc[-1] for c in ("beta", "gamma")}
    table = pd.DataFrame({"median": [latest[c]["q0.5"] for c in latest],
                          "2.5%": [latest[c]["q0.025"] for c in latest],
                          "97.5%": [latest[c]["q0.975"] for c in latest]},
                         index=pd.Index(["β (per day)", "γ (per day)"], name="parameter"))
    return Section.weekly(SectionKey.PARAMETERS, [
        _fig(png, "Joint estimates of the transmission rate β and recovery rate γ from the "
                  f"{r.config.window} observations before each day: median and 95% credible "
                  "interval; dotted lines: range of the synthetic training prior (for β its "
                  "starting range: in the SF prior β drifts over time, and the estimate is the "
                  "β in effect on the day).",
             "Time series of beta and gamma with credible intervals"),
        TableItem(table, f"β and γ on {dates[-1].date()} (latest day).", decimals=4)])


def _smc_section(r: Any) -> Section:
    res = r.smc.result
    names = list(res.state_names)
    idx = [names.index(c) for c in STATES]
    mean = _numpy(res.mean)[0][:, idx]
    lower, upper = (_numpy(b)[0][:, idx] for b in res.sigma_band(3.0))
    dates = pd.DatetimeIndex(r.smc.dates)
    ess = _numpy(res.ess)[0]
    n = int(getattr(res, "num_particles", 0) or r.config.smc_particles)
    png = figures.smc_band_figure(dates, _observed_at(r.sir_frame, dates), mean, lower, upper,
                                  ess=ess, n_particles=n)
    return Section.weekly(SectionKey.SMC, [_fig(
        png, f"Bootstrap particle filter ({n} particles) seeded with flow samples at "
             f"{dates[0].date()}: filtered mean ± 3σ; bottom: effective sample size.",
        "Particle filter estimates of S, I, R with 3 sigma bands and effective sample size")])


# The paper's Table 5 columns, then any other variant this store holds (e.g. MLP).
_PAPER_VARIANTS = ("Transformer", "Transformer + KE", "Mamba-SSM")


def _nll_section(r: Any) -> Section:
    frame = r.nll
    short = {"forward": "fw", "backward": "bw"}
    ours = list(dict.fromkeys(frame["variant"].astype(str)))
    variants = [*_PAPER_VARIANTS, *(v for v in ours if v not in _PAPER_VARIANTS)]
    values = {(short.get(d, d), str(v)): float(x)
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


def _training_section(r: Any) -> Section:
    frames = []
    for direction, history in r.models.histories.items():
        h = pd.DataFrame(list(history))
        if h.empty:
            continue
        frames.append(pd.DataFrame({"step": h["iteration"], "train": h["train_loss"],
                                    "validation": h["val_nll"], "variant": f"{direction} flow"}))
    png = figures.loss_curve_figure(pd.concat(frames, ignore_index=True),
                                    ylabel="loss (standardized NLL)")
    reused = "reused from the model cache" if r.models.reused else "trained in this run"
    return Section.weekly(SectionKey.TRAINING, [_fig(
        png, f"Training loss (mean since the previous evaluation) and validation NLL of the "
             f"forward and backward {r.models.encoder} flows ({reused}).",
        "Training and validation loss curves")])


_BACKTEST_LABELS = {"nf-rollout": "NF rollout (this model)", "smc": "plain SMC",
                    "persistence": "persistence"}


def backtest_table(result: Any) -> pd.DataFrame:
    """One row per forecaster: relative WIS against persistence and against the plain SMC,
    mean WIS and its parts, 50%/90% interval coverage, number of scored cells."""
    from pipeline.backtest import relative_wis, summarize

    summary = summarize(result)
    names = list(summary.index)
    vs_smc = ([relative_wis(result.scores, name, "smc") for name in names]
              if "smc" in names else [float("nan")] * len(names))
    return pd.DataFrame({
        "rel. WIS vs persistence": summary["relative_wis"].to_numpy(),
        "rel. WIS vs plain SMC": vs_smc,
        "mean WIS": summary["mean_wis"].to_numpy(),
        "50% coverage": summary["coverage_50"].to_numpy(),
        "90% coverage": summary["coverage_90"].to_numpy(),
        "scored cells": summary["n_forecasts"].to_numpy()},
        index=pd.Index([_BACKTEST_LABELS.get(n, n) for n in names], name="forecaster"))


def _backtest_section(r: Any) -> Section:
    from pipeline.backtest import summary_by_horizon

    result = r.backtest
    scores = result.scores
    origins = pd.to_datetime(scores["origin"])
    by_h = summary_by_horizon(result)
    return Section.weekly(SectionKey.BACKTEST, [
        _fig(figures.backtest_figure(by_h), "Relative WIS against the persistence baseline by "
             "horizon (left; below 1 beats persistence) and 50%/90% interval coverage (right).",
             "Bar chart of relative WIS by horizon and coverage lines"),
        TableItem(backtest_table(result),
                  f"Rolling-origin backtest: forecasts from {origins.nunique()} weekly origins "
                  f"({origins.min().date()} … {origins.max().date()}), "
                  f"{result.config.n_samples} sample paths each, scored at 1–4 weeks on S, I and "
                  "R with the weighted interval score of the 23 hub quantiles. Relative WIS = "
                  "Σ WIS(row) / Σ WIS(baseline) over the same forecasts (below 1: better than "
                  "the baseline).", decimals=3)])


_BUILDERS: Sequence[tuple[str, Callable[[Any], Section]]] = (
    ("S/I/R series", _series_section), ("forecast", _forecast_section),
    ("state estimates", _estimates_section), ("rollouts", _rollout_section),
    ("β, γ", _parameter_section), ("SMC", _smc_section), ("NLL table", _nll_section),
    ("loss curves", _training_section), ("backtest", _backtest_section))


# ----------------------------------------------------------------------------- provenance

def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in _VERSIONED:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def _provenance(r: Any) -> Provenance:
    csv = r.sir_frame.to_csv(index=False).encode("utf-8")
    checkpoint = ""
    models = getattr(r, "models", None)
    path = Path(getattr(models, "path", "") or ".") / "forward" / "model.pt"
    if models is not None and path.is_file():
        checkpoint = sha256_file(path)
    config = r.config
    cfg = dataclasses.asdict(config) if dataclasses.is_dataclass(config) else dict(config)
    extra = {"model cache key": str(getattr(models, "key", "—")),
             "model": ("reused from the model cache" if getattr(models, "reused", False)
                       else "trained in this run"),
             "forward checkpoint": str(path) if checkpoint else "—"}
    preset_for = getattr(config, "training_preset_for", None)
    if preset_for is not None:  # the resolved pipeline.presets entries the models come from
        for direction in ("forward", "backward"):
            p = preset_for(direction)
            extra[f"{direction} training preset"] = (
                f"{p.run_name}: {p.train.iterations} iterations, batch {p.train.batch_size}, "
                f"lr {p.train.lr:g} ({p.train.schedule}), {p.dataset.name} "
                f"{p.dataset.n_trajectories or 'all'} trajectories")
    return Provenance(package_version=__version__, versions=_versions(), config=cfg,
                      data_sha256=sha256_bytes(csv), checkpoint_sha256=checkpoint,
                      seed=getattr(config, "seed", None), extra=extra)


STALE_HEADLINE = ("Stale data: DataSF could not be reached (every retry failed), so this "
                  "forecast was made from the cached data")


def stale_warnings(results: Any, last_day: dt.date) -> list[str]:
    """The report's stale-data warnings: why (DataSF unreachable, cache used), how old, and the
    per-dataset cache notes."""
    headline = f"{STALE_HEADLINE} ({results.vintage})."
    age = stale_data_warning(last_day, dt.date.today(), as_of_label="today (the run date)")
    notes = [_short_note(str(n)) for n in getattr(results, "stale_notes", ())]
    details = ["Per dataset: " + "; ".join(notes) + "."] if notes else []
    return [headline, *([age] if age else []), *details]


def _short_note(note: str, limit: int = 160) -> str:
    """A cache note without the transport's nested exception text (the run log keeps it)."""
    note = note.split(" (Caused by", 1)[0].split("; last: ", 1)[0].rstrip(" .;")
    return note if len(note) <= limit else note[: limit - 1] + "…"


def forecast_report_content(results: Any) -> ReportContent:
    """The ``ReportContent`` of one weekly run (sections that cannot be drawn become warnings)."""
    reference = results.future.reference_date
    last = pd.to_datetime(results.sir_frame["date"]).max().date()
    warnings = stale_warnings(results, last) if results.stale else []
    sections = []
    for name, build in _BUILDERS:
        if name == "backtest" and getattr(results, "backtest", None) is None:
            continue
        try:
            sections.append(build(results))
        except Exception as exc:  # noqa: BLE001 - publish the rest, say what is missing
            log.exception("report section %s failed", name)
            warnings.append(f"The {name} section could not be drawn: "
                            f"{type(exc).__name__}: {exc}")
    return ReportContent(
        title=f"San Francisco COVID-19 SIR forecast — {reference}",
        reference_date=reference, data_vintage=str(results.vintage), sections=tuple(sections),
        provenance=_provenance(results), warnings=tuple(warnings),
        summary=(f"Forecasts and estimates of the susceptible (S), infectious (I) and removed (R) "
                 f"fractions of San Francisco's population from normalizing flows trained on "
                 f"simulated SIR epidemics ({results.models.encoder} encoder), conditioned on "
                 f"the latest DataSF observations up to {last}."))


def build_forecast_report(results: Any, out_dir: str | Path) -> list[str]:
    """Write report.html and report.pdf for one weekly run; returns the file names written."""
    files: ReportFiles = write_report(forecast_report_content(results), out_dir)
    return [files.html_path.name, files.pdf_path.name]
