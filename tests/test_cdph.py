"""Issue 19: California county data from CDPH (data.chhs.ca.gov) beside DataSF.

The parser against the six real vintages in ``../shared/data/cdph`` (read in place, never
copied); the CKAN client against recorded responses (CKAN JSON built here, the real CSV bytes);
the fault catalogue of ``bench.faults_cdph`` through the real ``requests`` stack on 127.0.0.1, each
case asserting the message and that the cache bytes are unchanged; import, vintages and the CLI.
Offline and fast (a few seconds per group)."""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import responses
import typer
from typer.testing import CliRunner

from bench.faults import bytes_lost, cache_bytes
from bench.faults_cdph import (CDPH, DOWNLOAD_PATH, GOOD_VINTAGE, FakeCKAN, client_config,
                               closed_port, run_concurrent_imports,
                               edited, faults, held_files, package_show, revised_settled,
                               run_fault, vintage_bytes)
from pipeline.cli.data import data_app
from pipeline.data.core.cache import CacheDamagedError, DatasetCache, RevisionRefusedError
from pipeline.data.california.cdph import CDPHFormatError, parse_cdph_csv, read_cdph_csv
from pipeline.data.california.cdph_source import (SPEC, CDPHConfig, accept_county_revisions,
                                                  cached_vintages, check_cdph_successor,
                                                  counties_waiting, import_cdph_exports,
                                                  is_cdph_export, load_cdph, load_cdph_vintage,
                                                  peek_columns, vintages_dir)
from pipeline.data.california.chhs import (BASE_URL_ENV, CDPH_COUNTIES, CHHSClient,
                                           CHHSClientConfig, CKANResponseError)
from pipeline.data.core.gate import CountBound, GateError, GateRules, Places, gate
from pipeline.data.core.plausibility import DAILY
from pipeline.errors import ConfigError, OfflineError, ValidationError

REPO = Path(__file__).resolve().parents[1]
VINTAGES = {  # folder -> the vintage's last day
    "Chithra1996__GTProject1": "2021-04-28",
    "Cricelio23__The-Role-of-SARS-CoV-2-Testing-on-Hospitalizations-in-California": "2021-09-06",
    "OlinaZhu__BIS633_Fall2021_qz258": "2021-09-12",
    "rolnasz95__csv_parsing": "2021-09-19",
    "hhaeri__CA_State_COVID-19_Cases_Deaths_Tests": "2021-09-23",
    "ofaye98__CSC508_Mentor_Class": "2021-11-04",
}
FAULTS = {f.name: f for f in faults()}


def path_of(folder: str) -> Path:
    return CDPH / folder / "covid19cases_test.csv"


@pytest.fixture(scope="module")
def vintages():  # type: ignore[no-untyped-def]
    if not CDPH.is_dir():
        pytest.fail(f"real CDPH vintages expected at {CDPH} (../shared beside the repo)")
    return {folder: read_cdph_csv(path_of(folder)) for folder in VINTAGES}


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    return tmp_path / "flowcast-data"  # = $FLOWCAST_DATA_DIR (conftest)


# ------------------------------------------------------------------ the parser, real vintages


def test_every_real_vintage_parses(vintages):
    for folder, as_of in VINTAGES.items():
        v = vintages[folder]
        assert str(v.as_of.date()) == as_of
        assert len(v.counties) == 58 and "Unknown" not in v.counties
        assert "Out of state" not in v.counties and "California" not in v.counties
        assert v.populations()["San Francisco"] == 892_280
        days = (v.as_of - pd.Timestamp("2020-02-01")).days + 1
        assert len(v.frame) == 58 * days  # one row per county and day, no gaps


def test_large_counties_of_the_2021_11_04_vintage(vintages):
    v = vintages[GOOD_VINTAGE]
    large = v.counties_with_population(100_000)
    assert len(large) == 36 and "San Francisco" in large and "Alpine" not in large
    assert v.populations()["Los Angeles"] > 10_000_000


def test_totals_hold_in_the_file(vintages):
    """Each county's daily cases sum to the file's own cumulative_cases on the last day."""
    raw = pd.read_csv(path_of(GOOD_VINTAGE), dtype=str, keep_default_na=False)
    last = raw[(raw["date"] == "2021-11-04") & (raw["area_type"] == "County")
               & ~raw["area"].isin(["Unknown", "Out of state"])]
    cumulative = last.set_index("area")["cumulative_cases"].astype(float).astype(np.int64)
    sums = vintages[GOOD_VINTAGE].frame.groupby("area")["cases"].sum()
    assert (sums == cumulative.reindex(sums.index)).all()
    assert int(sums["San Francisco"]) == int(cumulative["San Francisco"]) > 50_000


def test_m_d_yyyy_dates_of_the_2021_04_28_file(vintages):
    text = path_of("Chithra1996__GTProject1").read_text().splitlines()
    assert text[1].startswith("2/1/2020,Alameda,County,1685886,")
    assert "cumulative_cases" not in text[0]  # the early file has fewer columns
    sf = vintages["Chithra1996__GTProject1"].county("San Francisco")
    assert sf.dates[0] == pd.Timestamp("2020-02-01") and sf.last_date == pd.Timestamp("2021-04-28")


def test_negative_reported_cases_are_corrections(vintages):
    frame = vintages[GOOD_VINTAGE].frame
    worst = frame.loc[frame["reported_cases"].idxmin()]
    assert int(worst["reported_cases"]) == -5_064 and worst["area"] == "San Diego"
    assert (frame["cases"] >= 0).all() and (frame["deaths"] >= 0).all()


def test_empty_date_total_rows_are_dropped(vintages):
    raw = pd.read_csv(path_of(GOOD_VINTAGE), dtype=str, keep_default_na=False)
    assert (raw["date"] == "").sum() == 61  # 58 counties, Unknown, Out of state, California
    assert vintages[GOOD_VINTAGE].frame["date"].notna().all()


def test_negative_episode_date_cases_skip_the_county_only():
    bad = edited(lambda f: f.assign(cases=f["cases"].where(
        ~((f["area"] == "Napa") & (f["date"] == "2021-03-03")), "-4.0")))
    vintage = parse_cdph_csv(bad, "edited.csv")
    assert dict(vintage.skipped) == {"Napa": "Napa: 'cases' is negative ('-4.0') on 2021-03-03"}
    assert len(vintage.counties) == 57 and "Napa" not in vintage.counties
    with pytest.raises(CDPHFormatError, match=r"Napa is skipped in the CDPH vintage of "
                                              r"2021-11-04 \(edited.csv\): Napa: 'cases' is "
                                              r"negative"):
        vintage.county("Napa")
    good = read_cdph_csv(path_of(GOOD_VINTAGE))
    same = good.frame[good.frame["area"] != "Napa"].reset_index(drop=True)
    assert vintage.frame.reset_index(drop=True).equals(same)


# ------------------------------------------------------------------ plausibility, revisions


def test_no_real_county_is_skipped_by_the_gate(vintages):
    """Every county of every real vintage passes every rule of the gate (the bounds leave
    margins measured on these files: docs/data.md)."""
    for v in vintages.values():
        assert dict(v.skipped) == {} and len(v.counties) == 58


def test_shared_gate_refuses_an_absurd_day_and_keeps_corrections():
    frame = pd.DataFrame({"place": "X", "date": pd.date_range("2021-01-01", periods=6),
                          "cases": [10, 12, 9, 11, 15, 600_000]})
    rules = GateRules(source="t", places=Places("place", {"X": 1_000_000}, "a table"),
                      counts=(CountBound("cases", per_day=0.10, per_week=0.5),), jump=DAILY)
    with pytest.raises(GateError, match=r"implausible count 600,000 in 'cases' on "
                                        r"2021-01-06: more than 10% of the popul"):
        gate(frame, rules, source="t")
    corrections = frame.assign(cases=[5, -5_064, 7, 6, 5, 9])
    negative_ok = GateRules(source="t", places=Places("place", {"X": 1_000}, "a table"),
                            counts=(CountBound("cases", per_day=0.10, per_week=0.5,
                                               negative_ok=True),), jump=DAILY)
    assert gate(corrections, negative_ok, source="t").skipped == {}


def test_weekly_real_successors_pass_the_revision_policy(vintages):
    ordered = [vintages[f] for f in VINTAGES]
    for older, newer in zip(ordered[1:], ordered[2:], strict=False):
        assert check_cdph_successor(newer, older) == {}   # no county held


def test_four_month_step_holds_los_angeles_alone(vintages):
    """The four-month step revises one settled day of one county beyond the policy: that county
    is held alone (the whole vintage used to be); more than a quarter of the counties revised
    at once still holds the whole vintage."""
    older = vintages["Chithra1996__GTProject1"]
    newer = vintages["Cricelio23__The-Role-of-SARS-CoV-2-Testing-on-Hospitalizations-in-"
                     "California"]
    held = check_cdph_successor(newer, older)
    assert list(held) == ["Los Angeles"]
    assert ("'cases' changed on 1 settled county-day(s) (on or before 2021-03-31) by more than "
            "max(100, 50%), e.g. Los Angeles 2020-06-21 1,043 -> 1,573") in held["Los Angeles"]
    # judged against its own reference (the vintage before), Los Angeles breaks there too
    assert list(check_cdph_successor(newer, newer, references={"Los Angeles": older})) == \
        ["Los Angeles"]
    frame = newer.frame.copy()
    sixteen = frame["area"].isin(older.counties[:16]) & (frame["date"] == "2020-12-01")
    frame.loc[sixteen, "cases"] = frame.loc[sixteen, "cases"] * 3 + 200
    with pytest.raises(RevisionRefusedError, match=r"1[67] of the 58 counties revise settled days "
                                                   r"beyond the policy \(more than 25%") as caught:
        check_cdph_successor(dataclasses.replace(newer, frame=frame), older)
    assert caught.value.hold


def test_a_county_revised_on_import_is_held_alone_until_accepted(data_dir):
    """The real vintages imported in order without --accept-revisions: all six go live,
    Los Angeles is held from 2021-09-06 (its series of 2021-04-28 kept, judged against it by
    every later vintage) and named; accepting it alone brings it back."""
    files = [path_of(f) for f in VINTAGES]
    summaries = import_cdph_exports(files, data_dir)
    assert [s.action for s in summaries] == ["imported"] * 6
    [(county, hold)] = counties_waiting(data_dir).items()
    assert (county, hold.since, hold.reference) == ("Los Angeles", "2021-09-06", "2021-04-28")
    kept = cached_vintages(data_dir)
    assert [len(v.counties) for v in kept] == [58, 57, 57, 57, 57, 57]
    assert kept[-1].skipped["Los Angeles"].startswith(
        "Los Angeles: revision held for review since the release of 2021-09-06 (its series of "
        "2021-04-28 kept)")
    with pytest.raises(CDPHFormatError, match="Los Angeles is skipped in the CDPH vintage"):
        kept[-1].county("Los Angeles")
    assert load_cdph_vintage(CDPHConfig(data_dir=data_dir), offline=True).counties == \
        kept[-1].counties
    status = run("status")       # the CLI names it and how to accept it ($FLOWCAST_DATA_DIR)
    assert ("Los Angeles: revision waiting since the vintage of 2021-09-06 (`flowcast data "
            "accept-revisions --cdph 'Los Angeles'`)") in " ".join(status.output.split())
    assert run("accept-revisions", "Los Angeles").exit_code == 1     # --cdph or --target
    accepted = run("accept-revisions", "--cdph", "Los Angeles")
    assert accepted.exit_code == 0, accepted.output
    assert "accepted CDPH Los Angeles: its revision held since the release of 2021-09-06" in \
        " ".join(accepted.output.split())
    assert counties_waiting(data_dir) == {}
    assert "Los Angeles" in cached_vintages(data_dir)[-1].counties
    with pytest.raises(ConfigError, match="no revision waits for Alameda"):
        accept_county_revisions(["Alameda"], data_dir)


# ------------------------------------------------------------------ the CKAN client


@responses.activate
def test_client_resolves_the_resource_through_package_show():
    base = "https://data.chhs.ca.gov"
    url = base + DOWNLOAD_PATH
    responses.get(f"{base}/api/3/action/package_show", body=package_show(url),
                  content_type="application/json")
    responses.get(url, body=vintage_bytes(), content_type="text/csv")
    fetched = CHHSClient(CHHSClientConfig(base_url=base)).fetch(CDPH_COUNTIES)
    assert fetched.payload == vintage_bytes()
    assert fetched.resource.id == "046cdd2b-31e5-4d34-9ed3-b48cdbc4be7a"
    assert fetched.final_url == url
    calls = [c.request for c in responses.calls]
    assert calls[0].url == (f"{base}/api/3/action/package_show?"
                            f"id=covid-19-time-series-metrics-by-county-and-state")
    assert str(calls[1].headers["Accept"]).startswith("text/csv")


@responses.activate
def test_client_finds_the_resource_by_file_name_when_the_id_changed():
    base = "https://data.chhs.ca.gov"
    url = f"{base}/dataset/new/resource/new-id/download/covid19cases_test.csv"
    resources = [{"id": "new-id", "name": "Statewide COVID-19 Cases Deaths Tests", "url": url}]
    responses.get(f"{base}/api/3/action/package_show",
                  body=package_show(url, resources=resources))
    responses.get(url, body=vintage_bytes())
    assert CHHSClient(CHHSClientConfig(base_url=base)).fetch().resource.id == "new-id"


@responses.activate
def test_ckan_failure_is_named():
    base = "https://data.chhs.ca.gov"
    responses.get(f"{base}/api/3/action/package_show", status=404,
                  json={"success": False, "error": {"__type": "Not Found Error"}})
    with pytest.raises(Exception, match=r"HTTP 404 from .*package_show.*Not Found Error"):
        CHHSClient(CHHSClientConfig(base_url=base)).fetch()
    with pytest.raises(CKANResponseError, match="did not succeed"):
        from pipeline.data.california.chhs import parse_package_show
        parse_package_show(b'{"success": false, "error": {"message": "Not found"}}', "u")


def test_live_load_caches_the_vintage_and_keeps_it(data_dir):
    with FakeCKAN() as portal:
        loaded = load_cdph(CDPHConfig(client=client_config(portal.url), data_dir=data_dir))
        assert portal.seen[0].startswith("/api/3/action/package_show?id=covid-19-time-series")
        assert portal.seen[1] == DOWNLOAD_PATH
    p = loaded.provenance
    assert not p.from_cache and p.source_kind == "api" and p.last_date == "2021-11-04"
    assert p.final_url == portal.url + DOWNLOAD_PATH and "last modified 2021-11-04" in p.notes[0]
    cache = DatasetCache(data_dir)
    assert cache.directory(SPEC) == data_dir / "chhs" / SPEC.dataset_id
    live = cache.load(SPEC)
    assert live is not None and live.payload == vintage_bytes()
    assert [p.name for p in vintages_dir(cache).iterdir()] == [
        f"2021-11-04-{live.manifest.sha256[:16]}.csv"]
    again = load_cdph_vintage(CDPHConfig(data_dir=data_dir), offline=True)
    assert again.populations() == loaded.vintage.populations()


# ------------------------------------------------------------------ the fault catalogue


@pytest.mark.parametrize("name", list(FAULTS))
def test_fault_falls_back_to_the_untouched_cache(name, data_dir):
    fault = FAULTS[name]
    result = run_fault(fault, data_dir)
    assert fault.expect in result.note, result
    if fault.skipped is None:
        assert "using cache, fetched 0 days ago (its last day, 2021-11-04" in result.note
    else:  # the new payload, the made-up county skipped by name, nothing of the cache lost
        assert "1 county(ies) left out of the vintage" in result.note
    assert result.bytes_lost == 0
    assert result.passed, result
    # Bounded by the client's deadlines, not by the server (the drip would take 4 s more);
    # the margin is for a loaded machine (the cache fallback parses a 4 MB file).
    deadline = fault.config.get("fetch_deadline_s", client_config("http://x").fetch_deadline_s)
    assert result.seconds < deadline + 2.0, result


def test_concurrent_imports_of_an_older_and_a_newer_vintage_both_land(tmp_path):
    """Issue 32, item 7: the older of two vintages imported at the same moment is archived by
    its own date (decided under the cache lock), never refused as "moving backwards"."""
    result = run_concurrent_imports(tmp_path, trials=2)
    assert result.passed, result.note


def test_a_revised_county_is_held_alone_and_taken_after_review(data_dir):
    revised = edited(revised_settled)
    with FakeCKAN() as portal:
        good = load_cdph(CDPHConfig(client=client_config(portal.url), data_dir=data_dir))
        portal.download = lambda h: h.send_body(200, revised, "text/csv")
        held = load_cdph(CDPHConfig(client=client_config(portal.url), data_dir=data_dir))
        assert not held.provenance.from_cache and not held_files(data_dir)
        assert "Los Angeles" not in held.vintage.counties and len(held.vintage.counties) == 57
        assert held.vintage.skipped["Los Angeles"].startswith(
            "Los Angeles: revision held for review since the release of 2021-11-04")
        assert list(counties_waiting(data_dir)) == ["Los Angeles"]
        taken = load_cdph(CDPHConfig(client=client_config(portal.url), data_dir=data_dir,
                                     accept_revisions=True))
    assert not taken.provenance.from_cache and counties_waiting(data_dir) == {}
    day = (pd.Timestamp("2021-01-04") - pd.Timestamp("2020-02-01")).days
    assert int(taken.vintage.county("Los Angeles").cases[day]) == 3 * int(
        good.vintage.county("Los Angeles").cases[day])


def test_rejected_payload_without_a_cache_writes_nothing(data_dir):
    with FakeCKAN() as portal:
        portal.download = lambda h: h.send_body(
            200, edited(lambda f: f.drop(columns=["cases"])), "text/csv")
        with pytest.raises(CDPHFormatError, match=r"missing column\(s\) \['cases'\]"):
            load_cdph(CDPHConfig(client=client_config(portal.url), data_dir=data_dir))
    assert cache_bytes(data_dir) == {}


def test_unreachable_without_a_cache_names_import(data_dir):
    config = CDPHConfig(client=client_config(closed_port()), data_dir=data_dir)
    with pytest.raises(OfflineError, match=r"CHHS portal unreachable.*`flowcast data import "
                                           r"FILE`"):
        load_cdph(config)
    with pytest.raises(OfflineError, match=r"no cached CDPH county data in .*chhs.*"
                                           r"`flowcast data import FILE`"):
        load_cdph_vintage(CDPHConfig(data_dir=data_dir), offline=True)


def test_base_url_is_read_at_use_not_at_import(data_dir, monkeypatch):
    env = {**os.environ, BASE_URL_ENV: "data.chhs.ca.gov", "PYTHONPATH": str(REPO)}
    imported = subprocess.run(
        [sys.executable, "-c", "import pipeline.data.california.cdph_source, pipeline.data.california.chhs, "
                               "pipeline.cli.data"], env=env, capture_output=True, text=True,
        timeout=120)
    assert imported.returncode == 0, imported.stderr
    import_cdph_exports([path_of(GOOD_VINTAGE)], data_dir)
    monkeypatch.setenv(BASE_URL_ENV, "data.chhs.ca.gov")
    with pytest.raises(ConfigError, match=r"must be http\(s\)://host\[/path\], got "
                                          r"'data.chhs.ca.gov' \(\$FLOWCAST_CHHS_BASE_URL\)"):
        load_cdph(CDPHConfig(data_dir=data_dir))  # a config error is never hidden by the cache


# ------------------------------------------------------------------ import and vintages


def test_import_keeps_every_vintage_in_any_order(data_dir):
    files = [path_of(f) for f in ("ofaye98__CSC508_Mentor_Class",
                                  "OlinaZhu__BIS633_Fall2021_qz258")]
    summaries = import_cdph_exports(files, data_dir)
    assert [(s.as_of, s.action) for s in summaries] == [("2021-09-12", "imported"),
                                                          ("2021-11-04", "imported")]
    older = import_cdph_exports([path_of("rolnasz95__csv_parsing")], data_dir)
    assert older[0].action == "archived" and "live copy unchanged" in older[0].note
    manifest = DatasetCache(data_dir).read_manifest(SPEC)
    assert manifest is not None and manifest.last_date == "2021-11-04"
    assert [str(v.as_of.date()) for v in cached_vintages(data_dir)] == [
        "2021-09-12", "2021-09-19", "2021-11-04"]
    skipped = import_cdph_exports([path_of(GOOD_VINTAGE)], data_dir, if_empty=True)
    assert skipped[0].action == "skipped"


def test_import_validates_every_file_before_storing_any(data_dir, tmp_path):
    bad = tmp_path / "covid19cases_test.csv"
    bad.write_bytes(edited(lambda f: f.drop(columns=["deaths"])))
    with pytest.raises(CDPHFormatError, match=r"missing column\(s\) \['deaths'\]"):
        import_cdph_exports([path_of(GOOD_VINTAGE), bad], data_dir)
    assert cache_bytes(data_dir) == {}


def test_a_county_reporting_an_absurd_population_is_skipped_by_name(data_dir, tmp_path):
    bad = tmp_path / "covid19cases_test.csv"
    bad.write_bytes(edited(lambda f: with_population(f, "Alpine", "0")))
    [summary] = import_cdph_exports([bad], data_dir)
    assert summary.action == "imported" and summary.counties == 57
    assert ("1 county(ies) left out of the vintage of 2021-11-04: Alpine: its "
            "population '0' is not within 25% of the 2020 Census figure 1,204") in summary.note


def with_population(frame: pd.DataFrame, area: str, value: str) -> pd.DataFrame:
    frame.loc[frame["area"] == area, "population"] = value
    return frame


def test_a_damaged_vintage_file_is_named(data_dir):
    import_cdph_exports([path_of(GOOD_VINTAGE)], data_dir)
    [kept] = vintages_dir(DatasetCache(data_dir)).iterdir()
    kept.write_bytes(kept.read_bytes()[:-100])
    with pytest.raises(CacheDamagedError, match="does not match the hash in its name"):
        cached_vintages(data_dir)


def test_cdph_files_are_told_apart_by_columns(datasf_dir):
    assert is_cdph_export(peek_columns(path_of("Chithra1996__GTProject1")))
    assert not is_cdph_export(peek_columns(
        datasf_dir / "AndrewCorry__data_wrangling_1/COVID-19_Cases_Over_Time.csv"))


# ------------------------------------------------------------------ the CLI


cli = typer.Typer()
cli.add_typer(data_app, name="data")


def run(*args: str | Path):  # type: ignore[no-untyped-def]
    return CliRunner().invoke(cli, ["data", *map(str, args)])


def test_cli_import_status_counties_and_fetch(datasf_dir, data_dir):
    cases = datasf_dir / "AndrewCorry__data_wrangling_1/COVID-19_Cases_Over_Time.csv"
    result = run("import", path_of(GOOD_VINTAGE), cases)
    assert result.exit_code == 0, result.output
    assert "imported covid19cases_test.csv: CDPH counties vintage of 2021-11-04" in result.output
    assert "imported COVID-19_Cases_Over_Time.csv: cases (gyr2-k29z)" in result.output
    status = run("status")
    assert status.exit_code == 0, status.output
    assert "cdph-counties (covid-19-time-series-metrics-by-county-and-state): csv-import" \
        in status.output and "1 vintage(s) kept (2021-11-04 … 2021-11-04)" in status.output
    counties = run("counties", "--min-population", "100000")
    assert counties.exit_code == 0, counties.output
    assert "36 of 58 counties with at least 100,000 people" in counties.output
    assert any(line.split()[:2] == ["San", "Francisco"] and line.endswith("892,280")
               for line in counties.output.splitlines())
    assert len(run("counties").output.splitlines()) == 59
    with FakeCKAN() as portal:
        portal.download = lambda h: h.send_body(
            200, vintage_bytes("hhaeri__CA_State_COVID-19_Cases_Deaths_Tests"), "text/csv")
        fetched = run("fetch", "--source", "chhs", "--chhs-base-url", portal.url)
    assert fetched.exit_code == 0, fetched.output
    assert "from cache" in fetched.output and "last date moves backwards" in fetched.output


def test_cli_import_names_the_missing_column_of_a_cdph_file(tmp_path, data_dir):
    broken = tmp_path / "covid19cases_test.csv"
    broken.write_bytes(edited(lambda f: f.drop(columns=["cases"])))
    result = run("import", broken)
    assert result.exit_code == 1
    assert "missing column(s) ['cases']" in result.output and "CDPH" in result.output
    assert cache_bytes(data_dir) == {}


def test_cli_fetch_refuses_a_base_url_without_scheme(data_dir):
    result = run("fetch", "--source", "chhs", "--chhs-base-url", "data.chhs.ca.gov")
    assert result.exit_code == 1
    assert "CHHS portal base URL must be http(s)://host[/path]" in result.output
    assert run("counties").exit_code == 1  # no cache: OfflineError, named
    assert "flowcast data import" in run("counties").output


def test_cache_bytes_helper_sees_changes(data_dir):
    import_cdph_exports([path_of(GOOD_VINTAGE)], data_dir)
    before = cache_bytes(data_dir)
    assert bytes_lost(before, cache_bytes(data_dir)) == 0
    manifest = DatasetCache(data_dir).manifest_path(SPEC)
    manifest.write_text(json.dumps({"x": 1}))
    assert bytes_lost(before, cache_bytes(data_dir)) > 0
    with pytest.raises(CacheDamagedError):
        load_cdph(CDPHConfig(data_dir=data_dir), offline=True)


def test_validation_error_is_a_data_source_error():
    assert issubclass(CDPHFormatError, ValidationError)
    with pytest.raises(CDPHFormatError, match=r"x.csv: missing column\(s\)"):
        parse_cdph_csv(b"a,b\n1,2\n", "x.csv")


def test_a_stored_parse_reads_back_the_same_vintage(vintages, tmp_path, monkeypatch):
    """The parse kept beside the cached vintages (``parsed/<sha256>.npz``) is the same frame,
    is used instead of parsing again, and a damaged one is parsed again and replaced."""
    import pipeline.data.california.cdph as cdph_module

    path = path_of("ofaye98__CSC508_Mentor_Class")
    data = path.read_bytes()
    folder = tmp_path / "parsed"
    monkeypatch.setattr(cdph_module, "_PARSED", {})
    parsed = cdph_module.parse_cdph_csv(data, "first", parsed_dir=folder)
    stored = next(folder.glob("*.npz"))
    monkeypatch.setattr(cdph_module, "_PARSED", {})
    monkeypatch.setattr(cdph_module, "_parse", lambda *a: pytest.fail("parsed again"))
    again = cdph_module.parse_cdph_csv(data, "second", parsed_dir=folder)
    pd.testing.assert_frame_equal(again.frame, parsed.frame, check_exact=True)
    assert again.as_of == parsed.as_of and again.source == "second"
    monkeypatch.undo()
    monkeypatch.setattr(cdph_module, "_PARSED", {})
    stored.write_bytes(b"damaged")
    third = cdph_module.parse_cdph_csv(data, "third", parsed_dir=folder)
    pd.testing.assert_frame_equal(third.frame, parsed.frame, check_exact=True)
    assert cdph_module._read_parsed(stored) is not None
