"""Issue 19: `flowcast forecast --county NAME`, the weekly run for a California county from CDPH.

The FIPS rule against the Census Bureau's codes; a tiny-preset run (``run_forecast``, no Prefect)
for Santa Cruz from two real shared CDPH vintages imported into a temporary data dir (their rows
of three counties only, read from ``../shared/data/cdph`` and written to tmp, so the delay model
and the pooled members take seconds; the cross-county skill step, tested in
``test_county_backtest``, is left out): the county's population in the S/I/R conversion, its own
delay-model effect in the nowcast, a hubverse file with its FIPS code that validates against
``hub-config/tasks.json``, the report's content named after it, its own output folder; an
unknown county fails with one line before any work. (Rendering and promoting a run's files are
``test_forecast_flow``'s and ``test_run_outputs``'s.)
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from pipeline.data.california.counties import (COUNTIES, COUNTY_FIPS, california_county,
                                               county_fips, county_slug)
from pipeline.data.california.cdph import read_cdph_csv
from pipeline.errors import ConfigError
from pipeline.forecast.config import DataSourceConfig, resolve_config
from pipeline.forecast.run import StepRunner

REPO = Path(__file__).resolve().parents[1]
CDPH = REPO.parent / "shared" / "data" / "cdph"
VINTAGES = (CDPH / "hhaeri__CA_State_COVID-19_Cases_Deaths_Tests" / "covid19cases_test.csv",
            CDPH / "ofaye98__CSC508_Mentor_Class" / "covid19cases_test.csv")  # 09-23, 11-04
COUNTY = "Santa Cruz"
OTHERS = ("Marin", "Monterey")     # the pooled members' reference places beside it (>= 100k)
AS_OF = "2021-11-04"               # the latest vintage's last day: the run's data date


# ---------------------------------------------------------------------------- FIPS codes


def test_fips_codes_follow_the_alphabetical_odd_number_rule():
    # the Census Bureau's codes (known answers, not the rule restated)
    known = {"Alameda": "06001", "Alpine": "06003", "Los Angeles": "06037",
             "San Diego": "06073", "San Francisco": "06075", "Santa Cruz": "06087",
             "Yuba": "06115"}
    assert {name: county_fips(name) for name in known} == known
    codes = [COUNTY_FIPS[c] for c in sorted(COUNTIES)]
    assert len(COUNTIES) == 58 and len(set(codes)) == 58
    assert codes == [f"06{n:03d}" for n in range(1, 116, 2)]
    from pipeline.outputs.hubverse import SF_COUNTY_FIPS
    from pipeline.outputs.hubverse_validation import load_tasks_config

    assert SF_COUNTY_FIPS == "06075"
    task = load_tasks_config(REPO / "hub-config" / "tasks.json")["rounds"][0]["model_tasks"][0]
    assert task["task_ids"]["location"]["optional"] == codes


def test_county_names_resolve_or_fail_naming_the_closest_spelling():
    assert california_county("  santa   CRUZ ") == "Santa Cruz"
    assert county_slug("San Luis Obispo") == "san-luis-obispo"
    with pytest.raises(ConfigError, match=r"unknown California county 'Santa Cruzz'; did you "
                                          r"mean 'Santa Cruz'"):
        california_county("Santa Cruzz")
    with pytest.raises(ConfigError, match="is spelled 'Santa Cruz' in the CDPH data"):
        DataSourceConfig(county="santa cruz")
    sf = DataSourceConfig()
    assert (sf.county, sf.place, sf.provider) == (None, "San Francisco", "DataSF")


def test_cli_unknown_county_is_one_line_before_any_work(tmp_path):
    from flows.cli import app

    result = CliRunner().invoke(app, ["forecast", "--county", "Los Angles", "--preset", "tiny",
                                      "--output-dir", str(tmp_path / "reports")])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert lines == ["error: unknown California county 'Los Angles'; did you mean "
                     "'Los Angeles'?"]
    assert not (tmp_path / "reports").exists()


# ---------------------------------------------------------------------------- the tiny run


def _three_counties(source: Path, out: Path) -> Path:
    """The real file's rows of the three counties (every column as written)."""
    frame = pd.read_csv(source, dtype=str, keep_default_na=False)
    out.parent.mkdir(parents=True)
    frame[frame["area"].isin([COUNTY, *OTHERS])].to_csv(out, index=False)
    return out


class _WithoutCountySkill(StepRunner):
    def invoke(self, step, fn, *args, **kwargs):  # type: ignore[no-untyped-def]
        return None if step == "county-skill" else fn(*args, **kwargs)


@pytest.fixture(scope="module")
def county_run(tmp_path_factory):
    """One tiny run for Santa Cruz from the cache (imported: two vintages of three counties),
    its tables and hubverse file written to its run folder."""
    missing = [str(p) for p in VINTAGES if not p.is_file()]
    if missing:
        pytest.fail(f"real CDPH vintages expected at {missing}")
    from pipeline.data.california.cdph_source import cached_vintages
    from pipeline.forecast.publish import output_root, write_tables
    from pipeline.forecast.run import run_forecast
    from pipeline.forecast.sources import load_series, series_to_sir

    root = tmp_path_factory.mktemp("county-run")
    for p in VINTAGES:
        _three_counties(p, root / "cdph" / p.parent.name / p.name)
    base = resolve_config("tiny")
    # --data-source import with the folder of downloads: both vintages go into the cache
    config = resolve_config("tiny", output_dir=str(root / "reports"),
                            data=dataclasses.replace(base.data, kind="import", county=COUNTY,
                                                     import_paths=(str(root / "cdph"),)))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FLOWCAST_DATA_DIR", str(root / "data"))
        mp.delenv("FLOWCAST_CDPH_ARCHIVE", raising=False)
        results = run_forecast(config, runner=_WithoutCountySkill())
        series = load_series(dataclasses.replace(config.data, kind="cache"))
        sir = series_to_sir(series)
        assert [v.as_of for v in cached_vintages()] == [pd.Timestamp("2021-09-23"),
                                                        pd.Timestamp(AS_OF)]
    folder = output_root(config) / results.reference_date
    write_tables(results, folder)
    return root, series, sir, results, folder


@pytest.mark.slow
def test_county_series_on_its_own_population(county_run):
    _, series, sir, results, _ = county_run
    truth = read_cdph_csv(VINTAGES[1]).county(COUNTY)
    assert series.place == COUNTY and series.population == truth.population == 273_999
    assert sir.provenance.conversion.population == truth.population
    assert series.vintage.data_as_of == AS_OF and series.vintage.publisher == "CDPH"
    frame = series.frame
    assert frame["date"].iloc[-1] == pd.Timestamp(AS_OF)
    np.testing.assert_array_equal(frame["new_cases"], truth.cases)
    np.testing.assert_array_equal(frame["cumulative_deaths"], np.cumsum(truth.deaths))
    # I·N = the cases of the last 7 days, on every day (N: the county's CDPH population)
    weekly = np.convolve(truth.cases, np.ones(7, dtype=np.int64))[: len(truth.cases)]
    np.testing.assert_array_equal(np.rint(sir.frame["I"] * truth.population), weekly)
    assert round(float(sir.frame["I"].iloc[-1]) * truth.population) == truth.cases[-7:].sum()
    np.testing.assert_allclose(sir.frame[["S", "I", "R"]].sum(axis=1), 1.0, atol=1e-12)
    # in people: S + I + R is Santa Cruz's CDPH population on every day, not San Francisco's
    people = sir.counts[["S", "I", "R"]].sum(axis=1)
    assert (people == 273_999).all()
    assert results.weekly.history.population == truth.population


@pytest.mark.slow
def test_county_nowcast_uses_its_own_delay_effect(county_run):
    _, _, _, results, _ = county_run
    nowcast = results.weekly.nowcast
    assert nowcast is not None
    assert "Santa Cruz with its own county effect" in nowcast.delay_model
    assert f"lags from {AS_OF}" in nowcast.delay_model
    assert nowcast.weeks.data_date == pd.Timestamp(AS_OF)
    # the recent days are the nowcast's median: never below what CDPH had reported
    reported = read_cdph_csv(VINTAGES[1]).county(COUNTY).cases
    assert (results.weekly.history.cases >= reported).all()
    assert (results.weekly.history.cases[-7:] > reported[-7:]).any()


@pytest.mark.slow
def test_county_run_writes_its_own_hub_file_and_report(county_run):
    from pipeline.outputs.hubverse_validation import load_tasks_config, validate_model_output
    from pipeline.outputs.run_folders import render_index_html
    from pipeline.forecast.report.weekly import forecast_report_content

    root, _, _, results, folder = county_run
    # its own folder beside San Francisco's reports/<reference-date>/
    assert folder == root / "reports" / "santa-cruz" / AS_OF == \
        root / "reports" / "santa-cruz" / results.reference_date
    [submission] = (folder / "model-output" / "flowcast-nfens").glob("*.csv")
    tasks = load_tasks_config(REPO / "hub-config" / "tasks.json")
    frame = validate_model_output(submission, tasks)
    assert set(frame["location"]) == {"06087"}
    assert sorted(frame["horizon"].unique()) == [-1, 0, 1, 2, 3]
    # weekly cases are I·N with the county's N (not San Francisco's)
    hub = pd.read_csv(folder / "hub_forecast.csv", dtype={"output_type_id": str})
    q = hub[hub["output_type"] == "quantile"]
    wide = q.pivot_table(index=["horizon", "output_type_id"], columns="target", values="value")
    np.testing.assert_allclose(wide["cases"], wide["I"] * 273_999, rtol=1e-9)

    summary = json.loads((folder / "results.json").read_text())
    assert summary["config"]["data"]["county"] == COUNTY
    assert summary["headline"]["place"] == COUNTY
    assert set(results.timings) >= {"fetch-cdph", "nowcast-recent-days", "weekly-forecast"}

    content = forecast_report_content(results)
    assert content.title == "Santa Cruz COVID-19 forecast from 2021-10-30"
    assert content.summary.startswith("Nowcast") and "people in Santa Cruz are" in content.summary
    # page 1 (issue 41): the county's own fan chart, headline and table, its nowcast week marked
    page = content.page1
    assert page is not None and len(page.figures) == 1
    assert page.headline.startswith("Weekly reported cases in Santa Cruz are forecast at")
    assert any("(nowcast," in label for label in page.table.frame.index)
    from pipeline.report.render import write_report
    from tests.browser import missing_tool_reason, overflowing_text_boxes, pdf_page_words

    if missing_tool_reason("pdftotext") is None:     # the county's tables fit their pages
        pdf = write_report(content, root / "report").pdf_path
        assert overflowing_text_boxes(pdf) == [] and pdf_page_words(pdf, 1) <= 150
    series = next(s for s in content.sections if s.key == "sir-series")
    assert series.title == "Santa Cruz S/I/R series"
    assert "Santa Cruz population, derived from CDPH" in series.items[0].caption
    assert "<h1>Santa Cruz weekly forecasts</h1>" in render_index_html([], COUNTY)


# ------------------------------------------------ live: the CHHS portal down, the cache used


@pytest.mark.slow
def test_county_live_fetch_falls_back_to_the_cache_and_says_so(county_run, monkeypatch):
    import re

    import requests
    import responses

    from pipeline.forecast.sources import data_is_stale, load_series, staleness_notes
    from pipeline.report import checks

    root, cached, *_ = county_run
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(root / "data"))
    monkeypatch.delenv("FLOWCAST_CHHS_BASE_URL", raising=False)
    source = DataSourceConfig(kind="live", county=COUNTY, http_retries=1, http_backoff_s=0.0)
    with responses.RequestsMock(assert_all_requests_are_fired=False) as rsps:
        rsps.add(responses.GET, re.compile(r"https://data\.chhs\.ca\.gov/.*"),
                 body=requests.ConnectionError("network unreachable (test)"))
        series = load_series(source)
        assert len(rsps.calls) == 2          # 1 + 1 HTTP retry; DataSF is never asked
    assert series.place == COUNTY and series.population == 273_999
    pd.testing.assert_frame_equal(series.frame, cached.frame)
    assert data_is_stale(series, "live")
    notes = staleness_notes(series)
    assert any(n.startswith("cdph-counties: CHHS portal unreachable") for n in notes), notes
    banner = checks.data_banner(stale=True, vintage=series.vintage.describe(), notes=notes,
                                last_day=series.frame["date"].iloc[-1].date(),
                                today=series.frame["date"].iloc[-1].date(), source="live",
                                provider=source.provider)
    assert banner is not None and banner.startswith("Stale data: CDPH could not be reached")
    assert "CHHS portal unreachable" not in banner   # the transport's text stays in the log
    assert re.search(r"Per dataset: cdph-counties \(https://data\.chhs\.ca\.gov/\S+\): cache "
                     r"fetched 0 days ago, last day 2021-11-04\.$", banner), banner


# ------------------------------------------- the Prefect flow from the CLI, CDPH file imported


@pytest.mark.slow
def test_cli_flow_run_for_a_county_from_the_imported_cdph_files(county_run, prefect_harness,
                                                                prefect_logging_rebound,
                                                                monkeypatch):
    """`flowcast forecast --county "santa cruz" --preset tiny --data-source import` end to end
    (every step as a Prefect task, the county-skill step included), in the library run's data
    dir: the same models (reused), the same S/I/R series, its own report folder, index and
    artifacts, and a hubverse file whose location is Santa Cruz's FIPS code."""
    from prefect.artifacts import Artifact

    from flows.cli import app
    from pipeline.outputs.hubverse_validation import load_tasks_config, validate_model_output

    root, _, _, results, folder = county_run
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(root / "data"))
    monkeypatch.delenv("FLOWCAST_CDPH_ARCHIVE", raising=False)
    reports = root / "flow-reports"
    cli = CliRunner().invoke(app, ["forecast", "--county", "santa cruz", "--preset", "tiny",
                                   "--data-source", "import", "--import-from",
                                   str(root / "cdph"), "--output-dir", str(reports)])
    assert cli.exit_code == 0, cli.output
    out = reports / "santa-cruz" / AS_OF
    assert f"report: {out}" in cli.output and "warning" not in cli.output
    assert not (reports / "index.json").exists()     # San Francisco's own index untouched

    summary = json.loads((out / "results.json").read_text())
    assert summary["config"]["data"]["county"] == COUNTY and not summary["data_stale"]
    assert summary["model_reused"] and summary["model_key"] == results.models.key
    assert summary["data_vintage"].startswith(f"CDPH data as of {AS_OF}")
    assert {"fetch-cdph", "county-skill"} <= set(summary["seconds"])
    assert "fetch-datasf" not in summary["seconds"]
    pd.testing.assert_frame_equal(pd.read_csv(out / "sir_series.csv"),
                                  pd.read_csv(folder / "sir_series.csv"))

    [submission] = (out / "model-output" / "flowcast-nfens").glob("*.csv")
    frame = validate_model_output(submission, load_tasks_config(REPO / "hub-config" /
                                                                "tasks.json"))
    assert set(frame["location"]) == {"06087"}
    members = set(pd.read_csv(out / "member_forecasts.csv")["forecaster"])
    assert "nf-real" in members          # Marin and Monterey are its reference places

    report = (out / "report.html").read_text()
    assert "Santa Cruz COVID-19 forecast from 2021-10-30" in report
    assert "Santa Cruz S/I/R series" in report and "Stale data" not in report
    index = json.loads((reports / "santa-cruz" / "index.json").read_text())
    assert [r["reference_date"] for r in index["runs"]] == [AS_OF]
    assert "<h1>Santa Cruz weekly forecasts</h1>" in \
        (reports / "santa-cruz" / "index.html").read_text()

    # its artifacts under the county's keys, beside (never over) San Francisco's
    for key in ("santa-cruz-weekly-nll", "santa-cruz-weekly-beta-gamma",
                "santa-cruz-weekly-report", "santa-cruz-weekly-summary"):
        assert Artifact.get(key) is not None, key
    headline = Artifact.get("santa-cruz-weekly-summary")
    assert headline is not None and isinstance(headline.data, str)
    assert headline.data.startswith("# Santa Cruz weekly COVID-19 forecast from 2021-10-30")
    link = Artifact.get("santa-cruz-weekly-report")
    assert link is not None and isinstance(link.data, str)
    assert f"santa-cruz/{AS_OF}" in link.data and "report.html" in link.data
