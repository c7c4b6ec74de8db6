"""DataSF CSV exports -> cache -> combined, vintage-trimmed SF series (real files, offline)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.data.core.cache import MANIFEST_NAME, DatasetCache
from pipeline.data.sf.csv_import import detect_dataset, import_csv_exports, read_csv_bytes
from pipeline.data.sf.datasf import CASES, DATASETS, DEATHS, TESTS
from pipeline.data.sf.series import SFDataConfig, load_sf_series, trim_trailing_days
from pipeline.errors import ConfigError, ValidationError
from pipeline.io import sha256_file
from tests.test_datasf_client import EXPORTS, KNOWN, cache_snapshot

VACCINATIONS = "Yi-Angela__sf-covid-animation/COVID_Vaccinations_Given_to_SF_Residents_Over_Time.csv"
TRANSMISSION = ("kaleb-ball__stat4410-covid-project/COVID-19_Cases_Summarized_by_Date__"
                "Transmission_and_Case_Disposition.csv")


@pytest.fixture
def cache_root(tmp_path: Path) -> Path:
    return tmp_path / "flowcast-data"


@pytest.fixture
def exports(datasf_dir: Path) -> dict[str, Path]:
    return {key: datasf_dir / rel for key, rel in EXPORTS.items()}


@pytest.fixture
def imported(exports, cache_root) -> list:
    return import_csv_exports([exports["cases"], exports["deaths"], exports["tests"]])


def _independent_daily(path: Path, date_col: str, fmt: str) -> pd.DataFrame:
    """The export read with plain pandas (no flowcast code), sorted by date."""
    raw = pd.read_csv(path)
    raw["date"] = pd.to_datetime(raw[date_col], format=fmt)
    return raw.sort_values("date").set_index("date")


def test_import_real_exports_matches_source_md(imported, exports, cache_root):
    by_key = {s.dataset_key: s for s in imported}
    for key, (rows, first, last, final) in KNOWN.items():
        s = by_key[key]
        assert (s.row_count, s.first_date, s.last_date, s.final_cumulative) == (
            rows, first, last, final), key
        assert s.imported and s.warnings == ()
        manifest = DatasetCache(cache_root).read_manifest(DATASETS[key])
        assert manifest.source_kind == "csv-import"
        assert manifest.source == str(exports[key].resolve())
        assert (manifest.row_count, manifest.first_date, manifest.last_date) == (rows, first, last)
        # The raw export is cached byte for byte, under its sha256.
        assert manifest.sha256 == sha256_file(exports[key])
        assert manifest.payload_file == f"payload-{manifest.sha256[:16]}.csv"
    assert by_key["cases"].data_as_of == "2022-03-21T04:30:01"
    assert by_key["deaths"].data_as_of == "2022-05-02T04:30:00"
    assert by_key["tests"].data_as_of == "2022-05-02T04:33:30"


def test_cache_layout_is_one_directory_per_dataset_id(imported, cache_root):
    files = sorted(str(p.relative_to(cache_root)) for p in cache_root.rglob("*")
                   if p.is_file() and ".locks" not in p.parts)  # the commit locks: datasf/.locks/
    assert len(files) == 6 and all(f.startswith("datasf/") for f in files)
    for spec in (CASES, DEATHS, TESTS):
        names = sorted(p.name for p in (cache_root / "datasf" / spec.dataset_id).iterdir())
        assert names[0] == MANIFEST_NAME and names[1].startswith("payload-")
        manifest = json.loads((cache_root / "datasf" / spec.dataset_id / MANIFEST_NAME).read_text())
        assert set(manifest) >= {"source", "fetched_at", "row_count", "first_date", "last_date",
                                 "sha256", "payload_file", "data_as_of", "final_cumulative"}


def test_combined_series_trims_14_days_and_records_the_vintage(imported, exports):
    series = load_sf_series(SFDataConfig(), offline=True)
    frame = series.frame
    # Cases end 2022-03-16 -> last kept 2022-03-02; deaths/tests end later, so cases decide.
    assert str(frame["date"].iloc[0].date()) == "2020-03-03"
    assert str(frame["date"].iloc[-1].date()) == "2022-03-02" and len(frame) == 730
    assert (frame["date"].diff().dropna() == pd.Timedelta(days=1)).all()
    v = series.vintage
    assert (v.data_as_of, v.first_date, v.last_date_kept, v.trimmed_days) == (
        "2022-03-21T04:30:01", "2020-03-03", "2022-03-02", 14)
    assert "data as of 2022-03-21T04:30:01" in v.describe()
    assert "last 14 days of each dataset dropped" in v.describe()

    # Every column against the exports read independently with pandas.
    cases = _independent_daily(exports["cases"], "Specimen Collection Date", "%m/%d/%Y %I:%M:%S %p")
    deaths = _independent_daily(exports["deaths"], "Date of Death", "%m/%d/%Y %I:%M:%S %p")
    tests = _independent_daily(exports["tests"], "specimen_collection_date", "%Y/%m/%d")
    last = pd.Timestamp("2022-03-02")
    f = frame.set_index("date")
    assert f["cumulative_cases"].iloc[-1] == cases.loc[last, "Cumulative Cases"] == \
        cases.loc[:last, "New Cases"].sum()
    assert f["cumulative_deaths"].iloc[-1] == deaths.loc[last, "Cumulative Deaths"]
    assert (f.loc[:"2020-03-16", "new_deaths"] == 0).all()          # before the first death row
    assert f["new_deaths"].sum() == deaths.loc[:last, "New Deaths"].sum()
    # Tests start 2020-03-01, before cases: the combined frame starts with cases.
    assert f["tests"].sum() == tests.loc["2020-03-03":last, "tests"].sum()
    # Conservation in the real tests export: tests = positives + negatives + indeterminate.
    assert (f["tests"] == f["positives"] + f["negatives"] + f["indeterminate"]).all()


@pytest.mark.parametrize(("days", "last", "n"), [(0, "2022-03-16", 744), (1, "2022-03-15", 743),
                                                 (30, "2022-02-14", 714)])
def test_trailing_days_is_configurable(imported, days, last, n):
    series = load_sf_series(SFDataConfig(datasets=("cases",), trailing_days=days), offline=True)
    assert str(series.frame["date"].iloc[-1].date()) == last and len(series.frame) == n
    assert series.vintage.trimmed_days == days
    if days == 0:
        assert series.frame["cumulative_cases"].iloc[-1] == 122_918


def test_trim_trailing_days_on_a_small_frame():
    frame = pd.DataFrame({"date": pd.date_range("2021-01-01", periods=5), "x": np.arange(5)})
    assert trim_trailing_days(frame, 2)["x"].tolist() == [0, 1, 2]
    assert trim_trailing_days(frame, 0) is frame
    with pytest.raises(ConfigError, match="trailing_days must be >= 0"):
        SFDataConfig(trailing_days=-1)


def test_too_much_trimming_is_an_error_naming_the_dataset(imported):
    with pytest.raises(ValidationError, match=r"no days left in \['cases'\] after dropping the "
                                              r"last 800 days"):
        load_sf_series(SFDataConfig(datasets=("cases",), trailing_days=800), offline=True)


def _renamed_copy(src: Path, tmp_path: Path, old: str, new: str) -> Path:
    data = src.read_bytes()
    header, rest = data.split(b"\n", 1)
    out = tmp_path / "renamed.csv"
    out.write_bytes(header.replace(old.encode(), new.encode()) + b"\n" + rest)
    return out


def test_renamed_column_fails_naming_it_and_leaves_cache_untouched(imported, exports, tmp_path,
                                                                   cache_root):
    before = cache_snapshot(cache_root)
    bad = _renamed_copy(exports["cases"], tmp_path, "New Cases", "New Kases")
    with pytest.raises(ValidationError, match=r"renamed.csv: missing column 'New Cases' \(API "
                                              r"field 'new_cases'\) for cases \(gyr2-k29z\)"):
        import_csv_exports([bad])
    assert cache_snapshot(cache_root) == before


def test_one_bad_file_means_nothing_is_imported(exports, tmp_path, cache_root):
    bad = _renamed_copy(exports["deaths"], tmp_path, "New Deaths", "Deaths New")
    with pytest.raises(ValidationError, match="missing column 'New Deaths'"):
        import_csv_exports([exports["cases"], bad])
    assert cache_snapshot(cache_root) == {}


def test_two_exports_of_one_dataset_are_refused(exports, tmp_path, cache_root):
    copy = tmp_path / "cases_copy.csv"
    copy.write_bytes(exports["cases"].read_bytes())
    with pytest.raises(ValidationError, match=r"several files hold the same dataset \(cases\)"):
        import_csv_exports([exports["cases"], copy])
    assert cache_snapshot(cache_root) == {}


def test_if_empty_skips_cached_dataset_but_fills_missing_ones(exports, tmp_path, cache_root):
    import_csv_exports([exports["cases"]])
    before = cache_snapshot(cache_root)
    older = tmp_path / "older_cases.csv"  # a different vintage: drop the last 10 rows by date
    raw = read_csv_bytes(exports["cases"].read_bytes(), source="x")
    raw["d"] = pd.to_datetime(raw["Specimen Collection Date"], format="%m/%d/%Y %I:%M:%S %p")
    raw.sort_values("d").iloc[:-10].drop(columns="d").to_csv(older, index=False)
    summaries = import_csv_exports([older, exports["deaths"]], if_empty=True)
    assert [(s.dataset_key, s.imported) for s in summaries] == [("cases", False), ("deaths", True)]
    assert "--if-empty" in summaries[0].note
    after = cache_snapshot(cache_root)
    assert {k: v for k, v in after.items() if "gyr2-k29z" in k} == before
    # Without --if-empty an export ending earlier is refused by name (issue 15: a shorter
    # series used to replace the cache); accepted deliberately, it replaces the cached copy and
    # the previous payload is kept for readers of the previous manifest (only that one).
    with pytest.raises(ValidationError, match="cases: last date moves backwards: new payload "
                                              "ends 2022-03-06, the cached copy 2022-03-16"):
        import_csv_exports([older])
    assert {k: v for k, v in cache_snapshot(cache_root).items() if "gyr2-k29z" in k} == before
    import_csv_exports([older], accept_revisions=True)
    manifest = DatasetCache(cache_root).read_manifest(CASES)
    assert (manifest.row_count, manifest.last_date) == (734, "2022-03-06")
    payloads = sorted(p.name for p in (cache_root / "datasf" / "gyr2-k29z").glob("payload-*"))
    assert payloads == sorted([manifest.payload_file, manifest.previous_payload_file])
    import_csv_exports([exports["cases"]])  # later again: the oldest payload is collected
    assert len(list((cache_root / "datasf" / "gyr2-k29z").glob("payload-*"))) == 2


@pytest.mark.parametrize("rel", [VACCINATIONS, TRANSMISSION])
def test_other_datasf_exports_are_not_mistaken_for_known_ones(rel, datasf_dir, cache_root):
    path = datasf_dir / rel
    with pytest.raises(ValidationError) as info:
        import_csv_exports([path])
    message = str(info.value)
    assert message.startswith(f"{path}: cannot tell which DataSF dataset this is")
    for expected in ("'Specimen Collection Date', 'New Cases', 'Cumulative Cases'",
                     "'Date of Death', 'New Deaths', 'Cumulative Deaths'",
                     "'Tests', 'Pos', 'Neg'"):
        assert expected in message
    assert cache_snapshot(cache_root) == {}


def test_detect_dataset_by_columns_not_file_name():
    assert detect_dataset(["Date of Death", "New Deaths", "Cumulative Deaths"], source="x") is DEATHS
    assert detect_dataset(["specimen_collection_date", "tests", "pos", "neg", "indeterminate"],
                          source="x") is TESTS
    # One renamed count column still identifies cases, so the error can name the missing field.
    assert detect_dataset(["Specimen Collection Date", "New Kases", "Cumulative Cases",
                           "Data As Of"], source="x") is CASES


@pytest.mark.parametrize(("content", "message"), [
    (b"", r"empty file"),
    (b"Specimen Collection Date,New Cases,Cumulative Cases\n", r"empty payload \(no rows\)"),
    (b"Specimen Collection Date,New Cases,Cumulative Cases\n13/45/2020 12:00:00 AM,1,1\n",
     r"unparseable date '13/45/2020 12:00:00 AM' in 'Specimen Collection Date' at row 1"),
])
def test_broken_csv_files_give_named_errors(content, message, tmp_path, cache_root):
    path = tmp_path / "broken.csv"
    path.write_bytes(content)
    with pytest.raises(ValidationError, match=message):
        import_csv_exports([path])
    assert cache_snapshot(cache_root) == {}


# ----------------------------------------------- every DataSF vintage (issue 13, item 5)

LATER_TESTING = Path(__file__).parent / "fixtures" / "datasf" / "testing_over_time_later_schema.csv"


def test_later_testing_export_schema_is_imported(cache_root):
    """DataSF's later "COVID-19 Testing Over Time" export: DATE, tests, pos, neg, indet."""
    [summary] = import_csv_exports([LATER_TESTING])
    assert (summary.dataset_key, summary.row_count, summary.first_date, summary.last_date) == (
        "tests", 5, "2022-04-23", "2022-04-27")
    assert summary.data_as_of is None and summary.warnings == ()
    from pipeline.data.sf.payloads import decode_cached
    from pipeline.data.sf.validation import validate_frame

    cached = DatasetCache(cache_root).load(TESTS)
    assert cached.manifest.source == str(LATER_TESTING.resolve())
    frame = validate_frame(decode_cached(cached), TESTS, source="cache").frame
    assert frame["date"].dt.strftime("%Y-%m-%d").tolist() == [
        "2022-04-23", "2022-04-24", "2022-04-25", "2022-04-26", "2022-04-27"]
    assert frame["indeterminate"].tolist() == [3, 6, 8, 8, 5]
    assert (frame["tests"] == frame["positives"] + frame["negatives"]
            + frame["indeterminate"]).all()


def test_later_testing_schema_from_the_api(cache_root):
    """The client reads the same schema from the API (fields date, tests, pos, neg, indet);
    when DataSF refuses ``$order=specimen_collection_date`` (HTTP 400) it orders by ``date``."""
    from bench.faults import FakeDataSF, client_config
    from pipeline.data.sf.series import load_dataset

    later = pd.read_csv(LATER_TESTING, dtype=str)
    rows = [{"date": d.replace("/", "-") + "T00:00:00.000", "tests": t, "pos": p, "neg": n,
             "indet": i} for d, t, p, n, i in later.itertuples(index=False)]

    def respond(h):
        if "specimen_collection_date" in h.path:
            h.send_body(400, b'{"message": "No such column: specimen_collection_date"}')
        else:
            h.send_rows(sorted(rows, key=lambda r: r["date"]))

    with FakeDataSF() as server:
        server.respond(respond)
        validated, provenance = load_dataset(TESTS, SFDataConfig(
            datasets=("cases", "tests"), client=client_config(server)))
    assert (provenance.row_count, provenance.first_date, provenance.last_date) == (
        5, "2022-04-23", "2022-04-27")
    assert validated.frame["indeterminate"].tolist() == [3, 6, 8, 8, 5]


def test_unknown_schema_is_refused_by_name(tmp_path, cache_root):
    unknown = tmp_path / "testing_2023.csv"
    unknown.write_text("DAY,total_tests,positive_tests\n2023/01/01,10,1\n")
    with pytest.raises(ValidationError) as info:
        import_csv_exports([unknown])
    message = str(info.value)
    assert message.startswith(f"{unknown}: cannot tell which DataSF dataset this is from its "
                              f"columns ['DAY', 'total_tests', 'positive_tests']; expected one of")
    assert ("tests (nfpa-mg4g): 'Specimen Collection Date', 'Tests', 'Pos', 'Neg', "
            "'Indeterminate' (also read as specimen_collection_date|DATE, tests, pos, neg, "
            "indeterminate|indet)") in message
    # A known dataset with one field renamed again: the missing field is named with every name
    # it is accepted under, beside the columns the file has.
    renamed = tmp_path / "testing_renamed.csv"
    renamed.write_text(LATER_TESTING.read_text().replace("indet", "indeterm", 1))
    with pytest.raises(ValidationError, match=re.escape(
            f"{renamed}: missing column 'Indeterminate' (API field 'indeterminate' or 'indet') "
            f"for tests (nfpa-mg4g); columns present: 'DATE', 'tests', 'pos', 'neg', 'indeterm'")):
        import_csv_exports([renamed])
    assert cache_snapshot(cache_root) == {}
