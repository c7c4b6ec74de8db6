"""The run's files: CSV tables, the hub CSV, the hubverse submission, ``results.json`` and the
report, written into a staging folder and promoted to ``<output_dir>/<reference-date>/`` only when
all of them were written (:mod:`pipeline.outputs.run_folders`), so a failed run never replaces the
last good report. A California county's runs (``DataSourceConfig.county``) go to
``<output_dir>/<county-slug>/<reference-date>/``, with their own index, beside San Francisco's."""
from __future__ import annotations

import dataclasses

import datetime as dt
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.data.california.counties import county_fips, county_slug
from pipeline.backtest.track_record import TrackRecord
from pipeline.backtest.writers import hub_frame
from pipeline.combine.combiner import PUBLISHED
from pipeline.forecast.config import ForecastConfig
from pipeline.forecast.results import ForecastResults
from pipeline.forecast.published_forecast import published_skill
from pipeline.io import atomic_write_json, atomic_write_text
from pipeline.outputs.hubverse import (SF_COUNTY_FIPS, NowcastWeek, Submission, SubmissionConfig,
                                       write_model_output)
from pipeline.outputs.hubverse_validation import load_tasks_config
from pipeline.outputs.run_folders import RunOutputs, RunRecord, new_run_id
from pipeline.report.render import start_report
from pipeline.forecast.report.diagnostics import FORKED_DIAGNOSTICS, start_diagnostics
from pipeline.forecast.report.weekly import forecast_report_content
from pipeline.forecast.report.headline import compute_headline

HUB_TASKS = Path(__file__).resolve().parents[2] / "hub-config" / "tasks.json"


@dataclass(frozen=True)
class PublishedRun:
    reference_date: str
    folder: Path              # <output_dir>[/<county-slug>]/<reference-date>/
    files: tuple[str, ...]    # relative to ``folder``

    @property
    def report(self) -> str:
        return next((f for f in self.files if f.endswith(".html")), self.files[0])


def publish(results: ForecastResults) -> PublishedRun:
    """Write every file of the run into a staging folder, then promote it and update the index."""
    outputs = RunOutputs(output_root(results.config), place=results.config.data.place)
    run_id = new_run_id()
    with outputs.staged(results.reference_date, run_id) as staging:
        # about half the report's drawing is done meanwhile in a child process, and the PDF's
        # layout in another while the tables are written
        diagnostics = start_diagnostics(results.model_outputs(), FORKED_DIAGNOSTICS)
        report = start_report(forecast_report_content(results, diagnostics))
        files = write_tables(results, staging)
        written = report.write(staging)
        files += [written.html_path.name, written.pdf_path.name]
        record = RunRecord(
            reference_date=results.reference_date, run_id=run_id,
            finished_at=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            data_stale=results.stale, data_vintage=results.data_as_of or "unknown",
            model_key=results.models.key, seed=results.config.seed,
            preset=results.config.preset, files=tuple(files),
            summary={"model_reused": results.models.reused,
                     "nll": results.nll.to_dict(orient="records"),
                     "backtest": published_skill(results.weekly),
                     # reports/index.html shows it (pipeline.outputs.run_folders)
                     "headline": headline_record(results)})
        folder = outputs.promote(staging, record)
    return PublishedRun(results.reference_date, folder, tuple(files))


def output_root(config: ForecastConfig) -> Path:
    """Where the run's folders go: ``output_dir`` for San Francisco, its ``<county-slug>/``
    subfolder for a California county (so a county never replaces San Francisco's report)."""
    root = Path(config.outputs.output_dir)
    return root if config.data.county is None else root / county_slug(config.data.county)


def write_tables(results: ForecastResults, out_dir: Path) -> list[str]:
    """CSV tables + hub CSV + results.json into ``out_dir``; returns the file names written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    tables = {"sir_series.csv": results.sir_frame.assign(
                  date=pd.to_datetime(results.sir_frame["date"]).dt.strftime("%Y-%m-%d")),
              "latest_estimates.csv": results.latest.table,
              "parameter_estimates.csv": results.parameters,
              "nll_table.csv": results.nll,
              "smc_bands.csv": results.smc.band_frame(3.0)}
    for (direction, every), roll in results.rollouts.items():
        tables[f"rollout_{direction}_{every}d.csv"] = roll.summary_frame()
    tables.update(weekly_tables(results.weekly))
    for name, frame in tables.items():
        atomic_write_text(out_dir / name, frame.to_csv(index=False))
    atomic_write_json(out_dir / "backtest_summary.json", results.weekly.summary())
    submission = write_submission(results.weekly, out_dir, submission_run_date(results),
                                  max_samples=results.config.outputs.hub_samples,
                                  location=county_fips(results.config.data.place))
    atomic_write_json(out_dir / "results.json", results_summary(results))
    return sorted([*tables, "results.json", "backtest_summary.json",
                   submission.path.relative_to(out_dir).as_posix()])


def weekly_tables(weekly: TrackRecord) -> dict[str, pd.DataFrame]:
    """The published forecast in hub format (quantiles and sample paths of I and weekly cases),
    every forecaster's quantiles beside it, and the real-time backtest's scores."""
    population = weekly.history.population
    frames = [hub_frame(f, population).assign(forecaster=name)
              for name, f in weekly.member_forecasts().items() if name != PUBLISHED]
    scores = weekly.scores.assign(
        origin_date=lambda f: pd.to_datetime(f["origin_date"]).dt.strftime("%Y-%m-%d"),
        target_end_date=lambda f: pd.to_datetime(f["target_end_date"]).dt.strftime("%Y-%m-%d"))
    return {"hub_forecast.csv": hub_frame(weekly.latest, population),
            "member_forecasts.csv": pd.concat(frames, ignore_index=True),
            "backtest_scores.csv": scores}


def write_submission(weekly: TrackRecord, hub_dir: Path, run_date: dt.date, *,
                     max_samples: int = 200, location: str = SF_COUNTY_FIPS) -> Submission:
    """The hubverse model-output CSV of the published forecast under ``hub_dir/model-output/``
    (with the nowcast of the weeks in the data) for ``location`` (the place's FIPS code),
    validated against the repository's ``hub-config/tasks.json`` when it is there."""
    paths = weekly.latest.paths
    n_paths = 0 if paths is None else int(paths.shape[0])
    n = min(max_samples, n_paths)
    return write_model_output(weekly.latest, population=weekly.history.population,
                              run_date=run_date, hub_dir=hub_dir, tasks=_hub_tasks(),
                              config=SubmissionConfig(n_samples=n, location=location),
                              nowcasts=nowcast_weeks(weekly, n))


def nowcast_weeks(weekly: TrackRecord, n_samples: int) -> list[NowcastWeek]:
    """The nowcast weeks of the round: quantiles of their final cases and ``n_samples``
    samples ordered like the published paths' first week (a larger nowcast goes with a larger
    forecast: the comonotone pairing, as the ensemble's copula pairs weeks)."""
    nowcast, paths = weekly.nowcast, weekly.latest.paths
    if nowcast is None or paths is None or n_samples == 0:
        return []
    first_week = paths[:n_samples, 0, 1]
    ranks = np.argsort(np.argsort(first_week, kind="stable"), kind="stable")
    levels = (ranks + 0.5) / n_samples
    out = []
    for week in nowcast.weeks.weeks:
        if week.kind != "nowcast":
            continue
        samples = nowcast.week_samples(week.end)
        out.append(NowcastWeek(week.end.date(), np.quantile(samples, weekly.latest.levels),
                               np.quantile(samples, levels)))
    return out


def _hub_tasks() -> dict[str, object] | None:
    return load_tasks_config(HUB_TASKS) if HUB_TASKS.is_file() else None


def submission_run_date(results: ForecastResults) -> dt.date:
    """The run's date for the hub round: the data date, the last day the run read plus the days
    dropped (``trailing_days``, 0 by default; without a nowcast, its fallback's days too), so a
    re-run on the same data lands in the same round."""
    last = pd.Timestamp(results.sir_frame["date"].iloc[-1]).date()
    dropped = results.config.data.trailing_days
    if results.weekly.nowcast is None:
        dropped += results.config.nowcast.fallback_trailing_days
    return last + dt.timedelta(days=dropped)


def results_summary(results: ForecastResults) -> dict[str, object]:
    latest = results.latest.table
    fw = latest[latest["direction"] == "forward"]
    forward_next_day = {
        str(name): {"mean": float(mean), "q0.025": float(low), "q0.975": float(high)}
        for name, mean, low, high in zip(fw["component"], fw["mean"].to_numpy(np.float64),
                                         fw["q0.025"].to_numpy(np.float64),
                                         fw["q0.975"].to_numpy(np.float64), strict=True)}
    return {"reference_date": results.reference_date,
            "data_vintage": results.vintage, "data_stale": results.stale,
            "stale_notes": list(results.stale_notes),
            "degraded": bool(results.weekly.dropped()),
            "dropped": [dataclasses.asdict(d) for d in results.weekly.dropped()],
            "model_key": results.models.key,
            "model_reused": results.models.reused, "encoder": results.models.encoder,
            "forward_next_day": forward_next_day,
            "nll": results.nll.to_dict(orient="records"),
            "backtest": published_skill(results.weekly),
            "headline": headline_record(results),
            "seconds": dict(results.timings),
            "config": results.config.as_dict()}


def headline_record(results: ForecastResults) -> dict[str, object]:
    """The report's page-1 headline as JSON (``results.json``, the run index)."""
    return compute_headline(results).to_dict()

