"""DataSF Socrata client and live loading, against the real exports replayed as API responses.

The shared folder holds DataSF *CSV exports* (display names, US dates, unsorted rows). A live
``/resource/<id>.json`` answer carries the same rows with snake_case field names, every value a
string and ISO floating timestamps (``2020-03-04T00:00:00.000``), sorted by the requested
``$order`` and cut into ``$limit``/``$offset`` pages. ``api_rows`` does that conversion here, in
the test, and ``replay`` serves the pages with ``responses`` — nothing is copied into the project.
"""
from __future__ import annotations

import json
import re
from datetime import date, timedelta
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import pandas as pd
import pytest
import requests
import responses

from pipeline.data.core.cache import DatasetCache
from pipeline.data.sf.datasf import (CASES, DATASETS, DEATHS, TESTS, ClientConfig, DataSFClient,
                                     DatasetSpec, NetworkError)
from pipeline.data.sf.series import SFDataConfig, load_dataset, load_sf_series
from pipeline.data.sf.validation import find_column
from pipeline.errors import DataSourceError, OfflineError, ValidationError

EXPORTS = {
    "cases": "AndrewCorry__data_wrangling_1/COVID-19_Cases_Over_Time.csv",
    "deaths": "Yi-Angela__sf-covid-animation/COVID-19_Deaths_Over_Time.csv",
    "tests": "Yi-Angela__sf-covid-animation/Covid-19_Tests.csv",
}
# SOURCE.md: rows, first day, last day, final cumulative (None: the tests export has none).
KNOWN = {
    "cases": (744, "2020-03-03", "2022-03-16", 122_918),
    "deaths": (772, "2020-03-17", "2022-04-27", 862),
    "tests": (788, "2020-03-01", "2022-04-27", None),
}
PAGE = 300
FAST = ClientConfig(page_size=PAGE, backoff_base_s=0.0, max_retries=2, timeout_s=5.0)


def _iso(values: pd.Series) -> pd.Series:
    """Any DataSF CSV date/timestamp -> the API's floating timestamp 'YYYY-MM-DDTHH:MM:SS.000'."""
    parsed = pd.Series(pd.NaT, index=values.index, dtype="datetime64[us]")
    for fmt in ("%m/%d/%Y %I:%M:%S %p", "%Y/%m/%d"):
        todo = parsed.isna()
        parsed[todo] = pd.to_datetime(values[todo], format=fmt, errors="coerce")
    assert parsed.notna().all()
    return parsed.dt.strftime("%Y-%m-%dT%H:%M:%S.000")


def api_rows(datasf_dir: Path, spec: DatasetSpec) -> list[dict[str, str]]:
    """The export's rows as Socrata JSON rows: API names, string values, ISO dates, date order."""
    raw = pd.read_csv(datasf_dir / EXPORTS[spec.key], dtype=str, keep_default_na=False)
    out = pd.DataFrame(index=raw.index)
    for field in (*spec.required, *spec.as_of):
        column = find_column(list(raw.columns), field)
        assert column is not None, (spec.key, field)
        is_time = field in (spec.date, *spec.as_of)
        out[field.api] = _iso(raw[column]) if is_time else raw[column]
    out = out.sort_values(spec.date.api, kind="stable")
    return out.to_dict(orient="records")


def replay(rows: list[dict[str, str]], spec: DatasetSpec) -> None:
    """Serve ``rows`` as DataSF would: honour $limit/$offset, require the date $order."""
    def callback(request: requests.PreparedRequest):  # type: ignore[no-untyped-def]
        query = {k: v[0] for k, v in parse_qs(urlsplit(request.url).query).items()}
        assert query["$order"] == f"{spec.date.api} ASC"
        offset, limit = int(query["$offset"]), int(query["$limit"])
        return 200, {"Content-Type": "application/json"}, json.dumps(rows[offset:offset + limit])

    responses.add_callback(responses.GET, spec.resource_url(), callback=callback)


def page_queries() -> list[dict[str, str]]:
    return [{k: v[0] for k, v in parse_qs(urlsplit(c.request.url).query).items()}
            for c in responses.calls]


def cache_snapshot(root: Path) -> dict[str, bytes]:
    """Every file under the cache (names and bytes), to prove a failure changed nothing.
    Lock files (``datasf/.locks/``) are coordination, not content, and are left out."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and ".locks" not in p.parts} if root.exists() else {}


@pytest.fixture
def cache_root(tmp_path: Path) -> Path:
    return tmp_path / "flowcast-data"  # = $FLOWCAST_DATA_DIR set by conftest


@pytest.fixture(scope="module")
def real_rows(datasf_dir: Path) -> dict[str, list[dict[str, str]]]:
    return {key: api_rows(datasf_dir, DATASETS[key]) for key in EXPORTS}


# ------------------------------------------------------------------------------ pagination


@responses.activate
@pytest.mark.parametrize("key", ["cases", "deaths", "tests"])
def test_paginated_fetch_of_real_data_matches_source_md(key, real_rows, cache_root, monkeypatch):
    monkeypatch.setenv("FLOWCAST_DATASF_APP_TOKEN", "tok-123")
    spec = DATASETS[key]
    replay(real_rows[key], spec)
    validated, prov = load_dataset(spec, SFDataConfig(client=FAST))

    rows, first, last, final = KNOWN[key]
    expected_pages = rows // PAGE + 1          # the last (short) page ends the loop
    assert [q["$offset"] for q in page_queries()] == [str(PAGE * i) for i in range(expected_pages)]
    assert all(q["$limit"] == str(PAGE) for q in page_queries())
    assert all(c.request.headers["X-App-Token"] == "tok-123" for c in responses.calls)
    assert all(c.request.url.startswith(f"https://data.sfgov.org/resource/{spec.dataset_id}.json?")
               for c in responses.calls)
    report = validated.report
    assert (report.row_count, str(report.first_date.date()), str(report.last_date.date()),
            report.final_cumulative) == (rows, first, last, final)
    assert len(validated.frame) == rows and report.gaps == ()
    assert not prov.from_cache and prov.stale_days == 0.0
    manifest = DatasetCache(cache_root).read_manifest(spec)
    assert manifest is not None and manifest.source_kind == "api"
    assert manifest.source == spec.resource_url() and manifest.row_count == rows
    assert (manifest.first_date, manifest.last_date) == (first, last)
    assert json.loads(DatasetCache(cache_root).load(spec).payload) == real_rows[key]


@responses.activate
def test_page_size_equal_to_row_count_needs_one_empty_page(real_rows):
    rows = real_rows["cases"][:600]
    replay(rows, CASES)
    result = DataSFClient(FAST).fetch(CASES)
    assert result.pages == 3 and len(result.rows) == 600
    assert [q["$offset"] for q in page_queries()] == ["0", "300", "600"]


@responses.activate
def test_no_token_header_without_env(real_rows, monkeypatch):
    monkeypatch.delenv("FLOWCAST_DATASF_APP_TOKEN", raising=False)
    replay(real_rows["deaths"][:10], DEATHS)
    DataSFClient(FAST).fetch(DEATHS)
    assert "X-App-Token" not in responses.calls[0].request.headers


def test_backoff_schedule_is_exponential_and_capped():
    client = DataSFClient(ClientConfig(backoff_base_s=0.5, backoff_max_s=3.0))
    assert [client.backoff_delay(a) for a in range(1, 6)] == [0.5, 1.0, 2.0, 3.0, 3.0]


# ------------------------------------------------------------------------- network faults

URL = CASES.resource_url()


@responses.activate
def test_429_then_success_retries_with_backoff(real_rows):
    slept: list[float] = []
    responses.add(responses.GET, URL, status=429, body="slow down")
    replay(real_rows["cases"], CASES)
    client = DataSFClient(ClientConfig(page_size=1000, backoff_base_s=0.25, max_retries=3),
                          sleep=slept.append)
    result = client.fetch(CASES)
    assert len(result.rows) == 744 and slept == [0.25]
    assert [c.response.status_code for c in responses.calls] == [429, 200]


@responses.activate
def test_timeout_then_success_and_timeout_passed_to_requests(real_rows):
    responses.add(responses.GET, URL, body=requests.ConnectTimeout("timed out"))
    replay(real_rows["cases"], CASES)
    result = DataSFClient(ClientConfig(page_size=1000, backoff_base_s=0.0, timeout_s=7.5)).fetch(
        CASES)
    assert len(result.rows) == 744
    # (connect, read): each capped by what is left of the request deadline
    assert responses.calls[-1].request.req_kwargs["timeout"] == (7.5, 7.5)


@responses.activate
def test_500_exhausts_retries_with_network_error():
    responses.add(responses.GET, URL, status=500, body="internal error")
    slept: list[float] = []
    with pytest.raises(NetworkError, match=r"failed after 3 attempts; last: HTTP 500"):
        DataSFClient(ClientConfig(max_retries=2, backoff_base_s=0.1), sleep=slept.append).fetch(
            CASES)
    assert len(responses.calls) == 3 and slept == [0.1, 0.2]


@responses.activate
def test_404_is_not_retried_and_names_status_and_url():
    responses.add(responses.GET, URL, status=404, body='{"message":"dataset not found"}')
    with pytest.raises(DataSourceError, match=r"HTTP 404 from https://data.sfgov.org/resource/"
                                              r"gyr2-k29z.json.*dataset not found"):
        DataSFClient(FAST).fetch(CASES)
    assert len(responses.calls) == 1


@responses.activate
def test_truncated_json_is_an_error_naming_the_url(real_rows):
    body = json.dumps(real_rows["cases"][:50])[:-40]  # connection dropped mid-payload
    responses.add(responses.GET, URL, body=body, status=200)
    with pytest.raises(DataSourceError, match=r"invalid JSON from .*gyr2-k29z.*truncated"):
        DataSFClient(FAST).fetch(CASES)


# ---------------------- bad payloads never replace a good cache; fallback and its staleness


def _prime_cache(real_rows) -> None:
    """A good cached copy of cases from an earlier (replayed) fetch; the registry is cleared."""
    replay(real_rows["cases"], CASES)
    load_dataset(CASES, SFDataConfig(client=FAST))
    responses.reset()


def _mutated(rows, index: int, **changes) -> list[dict[str, str]]:
    out = [dict(r) for r in rows]
    out[index].update(changes)
    return out


def _renamed(rows) -> list[dict[str, str]]:
    return [{("new_kases" if k == "new_cases" else k): v for k, v in r.items()} for r in rows]


# kind -> (rows transform or None, error without a cache, message (with or without a cache))
BAD_PAYLOADS = {
    "renamed field": (_renamed, ValidationError,
                      r"missing column 'New Cases' \(API field 'new_cases'\)"),
    "non-numeric": (lambda rows: _mutated(rows, 100, new_cases="12a"), ValidationError,
                    r"non-numeric value '12a' in 'New Cases' at row 101 \(date 2020-06-11\)"),
    "negative": (lambda rows: _mutated(rows, 5, new_cases="-3"), ValidationError,
                 r"negative count '-3' in 'New Cases' at row 6 \(date 2020-03-08\)"),
    "duplicate date": (lambda rows: rows[:10] + [dict(rows[9])] + rows[10:], ValidationError,
                       r"duplicate date\(s\) in 'Specimen Collection Date': 2020-03-12"),
    "empty": (lambda rows: [], ValidationError, r"empty payload \(no rows\) for cases"),
    "truncated JSON": (None, DataSourceError, r"invalid JSON from .*truncated or damaged"),
    "500 exhausting retries": (None, OfflineError, r"failed after 3 attempts; last: HTTP 500"),
    "timeout": (None, OfflineError, r"failed after 3 attempts; last: ReadTimeout"),
}


def _serve_bad(kind: str, rows) -> None:
    transform = BAD_PAYLOADS[kind][0]
    if kind == "truncated JSON":
        responses.add(responses.GET, URL, body=json.dumps(rows[:PAGE])[:5000])
    elif kind.startswith("500"):
        responses.add(responses.GET, URL, status=500, body="internal error")
    elif kind == "timeout":
        responses.add(responses.GET, URL, body=requests.ReadTimeout("read timed out"))
    else:
        replay(transform(rows), CASES)


@responses.activate
@pytest.mark.parametrize("kind", list(BAD_PAYLOADS))
def test_bad_payload_without_cache_is_a_clear_error_and_writes_nothing(kind, real_rows,
                                                                       cache_root):
    _, error, message = BAD_PAYLOADS[kind]
    _serve_bad(kind, real_rows["cases"])
    with pytest.raises(error, match=message) as info:
        load_dataset(CASES, SFDataConfig(client=FAST))
    if error is OfflineError:  # unreachable and nothing cached: say how to get data offline
        assert "flowcast data import" in str(info.value)
    assert cache_snapshot(cache_root) == {}


@responses.activate
@pytest.mark.parametrize("kind", list(BAD_PAYLOADS))
def test_bad_payload_keeps_cache_bytes_and_falls_back(kind, real_rows, cache_root):
    _prime_cache(real_rows)
    before = cache_snapshot(cache_root)
    assert sorted(Path(k).name.split("-")[0] for k in before) == ["manifest.json", "payload"]
    _serve_bad(kind, real_rows["cases"])
    validated, prov = load_dataset(CASES, SFDataConfig(client=FAST))
    assert len(responses.calls) >= 1                      # DataSF was asked, and failed
    assert cache_snapshot(cache_root) == before          # bytes and manifest untouched
    assert prov.from_cache and validated.report.row_count == 744
    assert validated.report.final_cumulative == 122_918
    assert any(re.search(BAD_PAYLOADS[kind][2], note) for note in prov.notes), prov.notes
    assert any(n.startswith("using cache, fetched 0 days ago (its last day, 2022-03-16")
               for n in prov.notes), prov.notes


@responses.activate
def test_gap_in_api_payload_is_zero_filled_and_reported(real_rows):
    rows = [r for r in real_rows["cases"]
            if r["specimen_collection_date"] != "2020-07-01T00:00:00.000"]
    missing_day = next(r for r in real_rows["cases"]
                       if r["specimen_collection_date"] == "2020-07-01T00:00:00.000")
    replay(rows, CASES)
    validated, prov = load_dataset(CASES, SFDataConfig(client=FAST))
    frame = validated.frame.set_index("date")
    assert validated.report.filled_days == 1 and len(frame) == 744
    assert frame.loc["2020-07-01", "new_cases"] == 0
    # The repair is exposed: the next day's cumulative jump exceeds its own new count by the
    # filled day's true count.
    assert validated.report.cumulative_mismatch_days == 1
    assert validated.report.cumulative_max_abs_diff == int(missing_day["new_cases"])
    assert any("1 gap(s) zero-filled: 2020-07-01…2020-07-01 (1 d)" in n for n in prov.notes)


# ------------------------------------------------------------------------- offline / stale


def test_offline_without_cache_names_flowcast_data_import():
    with pytest.raises(OfflineError, match=r"no cached DataSF cases data \(gyr2-k29z\).*"
                                           r"`flowcast data import FILE`"):
        load_sf_series(SFDataConfig(datasets=("cases",)), offline=True)


@responses.activate
def test_unreachable_without_cache_is_offline_error_naming_import():
    responses.add(responses.GET, URL, body=requests.ConnectionError("no route to host"))
    with pytest.raises(OfflineError, match=r"DataSF unreachable.*no route to host.*"
                                           r"flowcast data import"):
        load_dataset(CASES, SFDataConfig(client=FAST))


@responses.activate
def test_unreachable_host_is_tried_once_then_every_dataset_comes_from_the_cache(real_rows):
    """One host serves all three datasets: after its retries fail, the others are not retried."""
    for key, spec in (("cases", CASES), ("deaths", DEATHS), ("tests", TESTS)):
        replay(real_rows[key], spec)
        load_dataset(spec, SFDataConfig(client=FAST))
    responses.reset()
    responses.add(responses.GET, re.compile(r"https://data\.sfgov\.org/.*"),
                  body=requests.ConnectionError("no route to host"))
    series = load_sf_series(SFDataConfig(client=FAST))
    assert len(responses.calls) == 1 + FAST.max_retries  # the first dataset only
    first, *others = series.provenance.datasets
    assert all(p.from_cache for p in series.provenance.datasets)
    assert "DataSF unreachable" in first.notes[0] and "not retried" not in first.notes[0]
    assert all(f"not retried for {p.dataset_key}" in p.notes[0] for p in others)
    assert len(series.frame) > 700


@responses.activate
def test_offline_with_cache_uses_it_and_reports_age(real_rows, cache_root):
    _prime_cache(real_rows)
    manifest = DatasetCache(cache_root).read_manifest(CASES)
    later = manifest.fetched_at_dt + timedelta(days=3, hours=12)
    series = load_sf_series(SFDataConfig(datasets=("cases",)), offline=True, now=later)
    assert len(responses.calls) == 0  # offline means offline
    prov = series.provenance.datasets[0]
    assert prov.from_cache and prov.stale_days == pytest.approx(3.5)
    # The note gives the cache's age and the age of the data themselves (last day 2022-03-16).
    data_age = (later.date() - date(2022, 3, 16)).days
    assert (f"using cache, fetched 4 days ago (its last day, 2022-03-16, is {data_age} days "
            "before today)") in prov.notes
    assert series.provenance.max_stale_days == pytest.approx(3.5)


@responses.activate
def test_damaged_cached_payload_is_detected_by_sha256(real_rows, cache_root):
    _prime_cache(real_rows)
    cached = DatasetCache(cache_root).load(CASES)
    cached.path.write_bytes(cached.payload.replace(b'"0"', b'"9"', 1))
    with pytest.raises(DataSourceError, match=r"does not match its manifest sha256"):
        load_sf_series(SFDataConfig(datasets=("cases",)), offline=True)


def test_tests_spec_reads_the_export_field_names():
    assert TESTS.dataset_id == "nfpa-mg4g" and TESTS.date.api == "specimen_collection_date"
