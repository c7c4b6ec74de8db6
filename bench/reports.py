"""Page 1 of every kind of report, measured on the rendered files (issue 41).

``python -m bench.reports`` makes four real reports on the ``tiny`` presets, each in its own
temporary ``FLOWCAST_DATA_DIR``, and measures their PDF and HTML:

* ``sf``: the weekly San Francisco run on the recorded DataSF exports;
* ``county``: the weekly run for Santa Cruz from two real CDPH vintages (their rows of Santa
  Cruz, Marin and Monterey, as ``tests/test_county_forecast.py`` does; no cross-county skill);
* ``hub_covid``: a COVID-19 hub round from the NHSN/NSSP releases since 2025-08-01 (8 rounds);
* ``hub_flu``: a FluSight round from the flu releases since 2025-01-01. The shared FluSight data
  hold no ED-visit share, which ``run_hub_round`` (``--hub flu``) requires; the round is made
  from the same library calls with the admissions' own vintages as the seasonal member's
  climatology.

Per kind: ``page1.figures`` (images on the PDF's page 1, ``pdfimages``), ``page1.words``
(``pdftotext``), ``overflowing_text_boxes`` (words past the right margin on any page,
``pdftotext -bbox``), ``browser.console_errors`` and ``browser.page1_images_rendered``
(headless Chromium); ``hub_covid.track_record`` the published forecast's relative WIS per
horizon against the hub's baseline as scored (horizon −1 against the last reported value).
Writes ``bench/results/reports.json`` and the PNG of each page 1 under
``bench/results/reports/``.
"""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.data.core.cache import data_folder
from pipeline.io import atomic_write_json
from tests.browser import (browser_check, overflowing_text_boxes, pdf_page_images,
                           pdf_page_words)

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "bench" / "results"
PNG_DIR = RESULTS / "reports"
CDPH_VINTAGES = (SHARED / "cdph" / "hhaeri__CA_State_COVID-19_Cases_Deaths_Tests"
                 / "covid19cases_test.csv",
                 SHARED / "cdph" / "ofaye98__CSC508_Mentor_Class" / "covid19cases_test.csv")
COUNTY, OTHERS = "Santa Cruz", ("Marin", "Monterey")
COVID_SINCE, FLU_SINCE = "2025-08-01", "2025-01-01"


def sf_report(root: Path) -> Any:
    from pipeline import forecast as fc
    from pipeline.forecast.report.weekly import forecast_report_content

    results = fc.run_forecast(fc.resolve_config("tiny", data=fc.DataSourceConfig(
        kind="import", import_paths=(str(SHARED / "datasf"),))))
    return forecast_report_content(results), {}


def county_report(root: Path) -> Any:
    from pipeline.forecast.config import resolve_config
    from pipeline.forecast.run import StepRunner, run_forecast
    from pipeline.forecast.report.weekly import forecast_report_content

    class WithoutCountySkill(StepRunner):
        def invoke(self, step, fn, *args, **kwargs):  # type: ignore[no-untyped-def]
            return None if step == "county-skill" else fn(*args, **kwargs)

    for path in CDPH_VINTAGES:
        frame = pd.read_csv(path, dtype=str, keep_default_na=False)
        out = root / "cdph" / path.parent.name / path.name
        out.parent.mkdir(parents=True)
        frame[frame["area"].isin([COUNTY, *OTHERS])].to_csv(out, index=False)
    base = resolve_config("tiny")
    config = resolve_config("tiny", output_dir=str(root / "reports"), data=dataclasses.replace(
        base.data, kind="import", county=COUNTY, import_paths=(str(root / "cdph"),)))
    os.environ.pop("FLOWCAST_CDPH_ARCHIVE", None)
    return forecast_report_content(run_forecast(config, runner=WithoutCountySkill())), {}


def _import_hub(source: Path, since: str, root: Path) -> None:
    from pipeline.data.hub.target_import import import_hub_time_series

    series = pd.read_parquet(source)
    series[pd.to_datetime(series["as_of"]) >= pd.Timestamp(since)].to_parquet(
        root / "time-series.parquet")
    import_hub_time_series(root / "time-series.parquet", accept_revisions=True)


def _hub_content(results: dict[str, Any], skipped: dict[str, dict[str, str]], vintage: str
                 ) -> Any:
    from pipeline.report.hub import hub_report_content

    reference = max(r.rounds[-1].reference for r in results.values()).date()
    return hub_report_content(results, reference_date=reference, model_id="flowcast-nfhub",
                              data_vintage=vintage, warnings=[], skipped=skipped, config={})


def _track_record(result: Any) -> dict[str, Any]:
    from pipeline.report.hub import like_with_like, scored_rounds

    scored = like_with_like(result)
    by_horizon = scored.relative((0, 1))
    return {f"h{h}": {"published_vs_hub_baseline": round(float(by_horizon[k]), 4),
                      "cells_scored": int(np.isfinite(scored.wis[:, :, k]).sum())}
            for k, h in enumerate(result.horizons)} | {
        "rounds_scored": int(scored_rounds(result).sum()), "rounds": len(result.rounds)}


def hub_covid_report(root: Path) -> Any:
    from pipeline.hub_round.run import HubRunConfig, run_hub_round

    _import_hub(SHARED / "nhsn" / "time-series.parquet", COVID_SINCE, root)
    run = run_hub_round(HubRunConfig.of_preset("tiny", disease="covid", data_source="cache"))
    vintage = "; ".join(f"{p.target}: as of {p.as_of}" for p in run.provenance.values())
    main = run.results["wk inc covid hosp"]
    return _hub_content(run.results, run.skipped(), vintage), {
        "track_record": _track_record(main)}


def hub_flu_report(root: Path) -> Any:
    from pipeline.backtest.hub_rounds import HubBacktestConfig, run_hub_rounds
    from pipeline.hub_round.run import hub_members_preset, load_vintages
    from pipeline.members.published import build_hub_members
    from pipeline.panels.hub import hub_rounds
    from pipeline.training.model_store import default_store_root

    _import_hub(SHARED / "flusight" / "time-series.parquet", FLU_SINCE, root)
    target = "wk inc flu hosp"
    vintages = load_vintages(target)
    members = build_hub_members(hub_members_preset("tiny"), default_store_root(), vintages,
                                vintages, target=target)
    result = run_hub_rounds(hub_rounds(vintages), vintages[-1][1], members.published,
                            HubBacktestConfig(), references=members.references)
    skipped = {target: dict(result.rounds[-1].panel.skipped)}
    return _hub_content({target: result}, skipped, f"{target}: as of "
                        f"{result.rounds[-1].as_of.date()}"), {
        "track_record": _track_record(result)}


KINDS: dict[str, Callable[[Path], Any]] = {"sf": sf_report, "county": county_report,
                                           "hub_covid": hub_covid_report,
                                           "hub_flu": hub_flu_report}


def measure(kind: str, make: Callable[[Path], Any]) -> dict[str, Any]:
    from pipeline.report.render import write_report

    with tempfile.TemporaryDirectory(prefix=f"bench-reports-{kind}-") as tmp:
        root = Path(tmp)
        started = time.perf_counter()
        with data_folder(root / "data"):
            content, extra = make(root)
        files = write_report(content, root / "report")
        seconds = time.perf_counter() - started
        pdf, html = files.pdf_path, files.html_path
        boxes = overflowing_text_boxes(pdf)
        browser = browser_check(html)
        PNG_DIR.mkdir(parents=True, exist_ok=True)
        subprocess.run(["pdftoppm", "-png", "-r", "80", "-f", "1", "-l", "1", "-singlefile",
                        str(pdf), str(PNG_DIR / f"{kind}-page1")], check=True, timeout=120)
        row = {"page1": {"figures": pdf_page_images(pdf, 1), "words": pdf_page_words(pdf, 1)},
               "pages": files.n_pages, "overflowing_text_boxes": len(boxes),
               "overflowing_examples": [f"p{p} {w!r} x={x:.0f}" for p, w, x in boxes[:5]],
               "browser": {"console_errors": len(browser.console_errors),
                           "page1_images_rendered": sum(browser.page1_images),
                           "console_messages": browser.console_errors},
               "seconds": round(seconds, 1)} | extra
    return row


def main() -> None:
    out: dict[str, Any] = {"command": "python -m bench.reports", "preset": "tiny"}
    for kind, make in KINDS.items():
        out[kind] = measure(kind, make)
        r = out[kind]
        print(f"{kind}: page 1 {r['page1']['figures']} figure(s), {r['page1']['words']} words; "
              f"{r['pages']} pages, {r['overflowing_text_boxes']} text boxes past the margin; "
              f"browser: {r['browser']['page1_images_rendered']} page-1 images rendered, "
              f"{r['browser']['console_errors']} console errors ({r['seconds']} s)")
        if "track_record" in r:
            t = r["track_record"]
            print("  track record (published / hub baseline as scored): "
                  + ", ".join(f"{k} {v['published_vs_hub_baseline']}" for k, v in t.items()
                              if k.startswith("h")))
    RESULTS.mkdir(parents=True, exist_ok=True)
    atomic_write_json(RESULTS / "reports.json", out)
    print(f"wrote {RESULTS / 'reports.json'} and {PNG_DIR}/<kind>-page1.png")


if __name__ == "__main__":
    main()
