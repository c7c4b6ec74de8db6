"""Schema and value rules of pipeline.data.sf.validation, on small frames and on the real exports."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.data.sf.csv_import import validate_csv_export
from pipeline.data.sf.datasf import CASES, DEATHS, TESTS
from pipeline.data.sf.validation import GapPolicy, find_column, parse_dates, validate_frame
from pipeline.errors import ValidationError
from tests.test_datasf_client import EXPORTS


def frame(dates, new, cumulative=None, *, date_col="Specimen Collection Date") -> pd.DataFrame:
    cum = cumulative if cumulative is not None else list(np.cumsum([int(x) for x in new]))
    return pd.DataFrame({date_col: dates, "New Cases": [str(x) for x in new],
                         "Cumulative Cases": [str(x) for x in cum]}, dtype="string")


def test_unsorted_us_dates_are_sorted_and_typed():
    raw = frame(["03/05/2020 12:00:00 AM", "03/03/2020 12:00:00 AM", "03/04/2020 12:00:00 AM"],
                ["4", "1", "2"], ["7", "1", "3"])
    v = validate_frame(raw, CASES, source="t")
    assert v.frame["date"].dt.strftime("%Y-%m-%d").tolist() == ["2020-03-03", "2020-03-04",
                                                                "2020-03-05"]
    assert v.frame["new_cases"].tolist() == [1, 2, 4] and v.frame["new_cases"].dtype == np.int64
    assert v.report.cumulative_mismatch_days == 0 and v.report.final_cumulative == 7


def test_all_date_forms_datasf_uses_parse_to_the_same_day():
    values = pd.Series(["2020-03-04T00:00:00.000", "03/04/2020 12:00:00 AM", "2020/03/04",
                        "2020-03-04"])
    assert parse_dates(values, CASES.date_formats).nunique() == 1


def test_integers_written_as_floats_are_accepted_but_fractions_are_not():
    v = validate_frame(frame(["2020-03-03", "2020-03-04"], ["1.0", "2"], ["1", "3"]), CASES,
                       source="t")
    assert v.frame["new_cases"].tolist() == [1, 2]
    with pytest.raises(ValidationError, match=r"t: non-integer count '1.5' in 'New Cases' at "
                                              r"row 2 \(date 2020-03-04\)"):
        validate_frame(frame(["2020-03-03", "2020-03-04"], ["1", "1.5"], ["1", "3"]), CASES,
                       source="t")


def test_empty_cell_is_named():
    raw = frame(["2020-03-03", "2020-03-04"], ["1", "2"], ["1", "3"])
    raw.loc[1, "New Cases"] = pd.NA
    with pytest.raises(ValidationError, match=r"empty value in 'New Cases' at row 2 "
                                              r"\(date 2020-03-04\); 1 such row"):
        validate_frame(raw, CASES, source="t")


def test_negative_cumulative_is_named_too():
    with pytest.raises(ValidationError, match=r"negative count '-1' in 'Cumulative Cases'"):
        validate_frame(frame(["2020-03-03"], ["1"], ["-1"]), CASES, source="t")


def test_missing_columns_are_all_named_with_what_is_present():
    raw = pd.DataFrame({"Date of Death": ["2020-03-03"], "Deaths": ["1"]}, dtype="string")
    with pytest.raises(ValidationError) as info:
        validate_frame(raw, DEATHS, source="f.csv")
    message = str(info.value)
    assert "missing column 'New Deaths' (API field 'new_deaths')" in message
    assert "missing column 'Cumulative Deaths' (API field 'cumulative_deaths')" in message
    assert "columns present: 'Date of Death', 'Deaths'" in message


def test_column_names_match_in_any_of_the_three_forms_case_insensitively():
    for name in ("New Cases", "new_cases", " NEW CASES "):
        assert find_column(["x", name], CASES.counts[0]) == name
    assert find_column(["New_Kases"], CASES.counts[0]) is None


def test_gap_zero_fill_carries_cumulative_and_reports():
    # 2020-03-05 and 03-06 missing; the next day's cumulative (10) exceeds 6 + its own 2 by 2,
    # i.e. the missing days had 2 cases: the zero fill is visible in the cumulative check.
    raw = frame(["2020-03-03", "2020-03-04", "2020-03-07"], ["1", "5", "2"], ["1", "6", "10"])
    v = validate_frame(raw, CASES, source="t")
    assert v.frame["new_cases"].tolist() == [1, 5, 0, 0, 2]
    assert v.frame["cumulative_cases"].tolist() == [1, 6, 6, 6, 10]
    r = v.report
    assert (r.filled_days, len(r.gaps), str(r.gaps[0])) == (2, 1, "2020-03-05…2020-03-06 (2 d)")
    assert (r.cumulative_mismatch_days, r.cumulative_max_abs_diff) == (1, 2)
    assert str(r.first_cumulative_mismatch.date()) == "2020-03-07"
    assert r.warnings[0] == "1 gap(s) zero-filled: 2020-03-05…2020-03-06 (2 d)"
    assert "disagrees with the running sum of 'New Cases' on 1 day(s), max |diff| 2" in \
        r.warnings[1]


def test_gap_policy_error_refuses_gaps():
    raw = frame(["2020-03-03", "2020-03-06"], ["1", "0"], ["1", "1"])
    with pytest.raises(ValidationError, match=r"1 gap\(s\) in the daily series: "
                                              r"2020-03-04…2020-03-05 \(2 d\)"):
        validate_frame(raw, CASES, source="t", gap_policy=GapPolicy.ERROR)


def test_cumulative_disagreement_is_reported_not_fixed():
    v = validate_frame(frame(["2020-03-03", "2020-03-04", "2020-03-05"], ["1", "2", "3"],
                             ["1", "3", "5"]), CASES, source="t")
    assert v.frame["cumulative_cases"].tolist() == [1, 3, 5]   # DataSF's column kept as is
    assert (v.report.cumulative_mismatch_days, v.report.cumulative_max_abs_diff) == (1, 1)


def test_duplicate_dates_are_an_error_even_when_equal_rows():
    raw = frame(["2020-03-03", "03/03/2020 12:00:00 AM"], ["1", "1"], ["1", "1"])
    with pytest.raises(ValidationError, match=r"duplicate date\(s\) in 'Specimen Collection "
                                              r"Date': 2020-03-03"):
        validate_frame(raw, CASES, source="t")


@pytest.mark.parametrize("key", ["cases", "deaths", "tests"])
def test_real_exports_validate_cleanly(key, datasf_dir):
    v, raw_bytes = validate_csv_export(datasf_dir / EXPORTS[key])
    r = v.report
    assert r.gaps == () and r.cumulative_mismatch_days == 0 and r.warnings == ()
    assert len(raw_bytes) == {"cases": 58_200, "deaths": 57_783, "tests": 62_066}[key]
    if key == "tests":
        f = v.frame
        assert (f["tests"] == f["positives"] + f["negatives"] + f["indeterminate"]).all()
        assert int(f["tests"].sum()) == 3_955_179
        assert v.spec is TESTS and str(r.data_as_of) == "2022-05-02 04:33:30"
