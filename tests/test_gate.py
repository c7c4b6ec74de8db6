"""The one validation gate every source passes (issue 32): the known tables it reads populations
from, its rules on rows built here (a failing place skipped and named, the others kept; a
broken payload one named error), and every real payload of every source passing it."""
from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from pipeline.data.california.counties import (CALIFORNIA_POPULATION_2020, COUNTIES,
                                               COUNTY_POPULATION_2020)
from pipeline.data.california.cdph import CDPH_GATE, read_cdph_csv
from pipeline.data.core.gate import CountBound, GateError, GateRules, Places, ShareBound, gate
from pipeline.data.core.plausibility import DAILY, JumpRule, history_bounds
from tests.conftest import SHARED

CDPH = SHARED / "data" / "cdph"
PLACES = Places("town", {p: 100_000 for p in "ABCD"}, "a table")
DAYS = pd.date_range("2021-03-01", periods=30)


def rows(values: dict[str, list[object]], days: pd.DatetimeIndex = DAYS) -> pd.DataFrame:
    return pd.concat([pd.DataFrame({"place": p, "date": days[:len(v)], "n": [str(x) for x in v]})
                      for p, v in values.items()], ignore_index=True)


RULES = GateRules(source="test", places=PLACES, counts=(CountBound("n", per_day=0.05,
                                                                   per_week=0.10, floor=10),),
                  jump=DAILY)
STEADY = [20] * 30


# ------------------------------------------------------------------ the known tables


def test_californias_census_table_sums_to_the_state_and_agrees_with_cdph():
    """The 2020 Census counts of the 58 counties sum to California's 39,538,223; CDPH's own
    population column (Department of Finance estimates) lies within 0.83–1.09× of them."""
    assert list(COUNTY_POPULATION_2020) == list(COUNTIES)
    assert sum(COUNTY_POPULATION_2020.values()) == CALIFORNIA_POPULATION_2020 == 39_538_223
    assert (COUNTY_POPULATION_2020["San Francisco"], COUNTY_POPULATION_2020["Alpine"],
            COUNTY_POPULATION_2020["Los Angeles"]) == (873_965, 1_204, 10_014_009)
    cdph = read_cdph_csv(CDPH / "ofaye98__CSC508_Mentor_Class" / "covid19cases_test.csv")
    ratio = {c: p / COUNTY_POPULATION_2020[c] for c, p in cdph.populations().items()}
    assert min(ratio.values()) == pytest.approx(0.829, abs=1e-3)  # Trinity
    assert max(ratio.values()) == pytest.approx(1.089, abs=1e-3)  # Modoc
    assert CDPH_GATE.population_tolerance == 0.25


# ------------------------------------------------------------------ one place fails, others kept


def test_a_poisoned_cell_skips_its_place_only_and_names_it():
    frame = rows({"A": STEADY, "B": [*STEADY[:10], "Infinity", *STEADY[11:]], "C": STEADY,
                  "D": STEADY})
    gated = gate(frame, RULES, source="t")
    assert dict(gated.skipped) == {"B": "B: 'n' is not finite ('Infinity') on 2021-03-11"}
    assert sorted(gated.frame["place"].unique()) == ["A", "C", "D"]
    assert gated.frame["n"].dtype == np.int64 and len(gated.frame) == 90


@pytest.mark.parametrize(("cell", "why"), [
    ("", "'n' is empty ('') on 2021-03-11"),
    ("12a", "'n' is not a number ('12a') on 2021-03-11"),
    ("1.5", "'n' is not a whole number of people ('1.5') on 2021-03-11"),
    ("-3", "'n' is negative ('-3') on 2021-03-11"),
    ("1e19", "implausible count 1e+19 in 'n' on 2021-03-11: more than 5% of the population "
             "100,000 (a table) in one day"),
    ("1e300", "implausible count 1e+300 in 'n' on 2021-03-11"),
    ("2000", "implausible count 2,000 in 'n' on 2021-03-11: more than 20× the plausible bracket "
             "of the previous 10 day(s) (median 20, largest of the last 7 20, bound 1,400)"),
])
def test_every_cell_rule_names_the_cell(cell, why):
    frame = rows({"A": STEADY, "B": [*STEADY[:10], cell, *STEADY[11:]], "C": STEADY,
                  "D": STEADY})
    assert gate(frame, RULES, source="t").skipped["B"].startswith(f"B: {why}")


def test_a_week_under_the_daily_bound_can_break_the_weekly_one():
    ramp = [*STEADY[:20], *[3_000] * 10]  # each day under 5 % of 100,000
    gated = gate(rows({"A": STEADY, "B": ramp, "C": STEADY, "D": STEADY}), RULES, source="t")
    assert gated.skipped["B"] == ("B: implausible count 12,060 in 'n' in the 7 days ending "
                                  "2021-03-24: more than 10% of the population 100,000 (a table) "
                                  "in one week")


def test_places_dates_and_the_broken_payload():
    gated = gate(rows({"A": STEADY, "Atlantis": STEADY, "C": STEADY[:-1], "D": STEADY}),
                 dataclasses.replace(RULES, max_skipped_share=0.5), source="t")
    assert gated.skipped == {
        "Atlantis": "'Atlantis' is not one of the 4 known town names (test)",
        "C": "C: ends on 2021-03-29, the payload on 2021-03-30"}
    gap = rows({"A": STEADY, "B": STEADY, "C": STEADY, "D": STEADY})
    gap = gap.drop(index=gap.index[(gap["place"] == "D") & (gap["date"] == DAYS[5])])
    assert gate(gap, RULES, source="t").skipped["D"] == "D: a gap of 1 day(s) before 2021-03-07"
    broken = rows({"A": ["-1"] * 30, "B": ["-1"] * 30, "C": STEADY, "D": STEADY})
    with pytest.raises(GateError, match=r"^t: 2 of the 4 towns fail the validation gate \(more "
                                        r"than 25%: a broken payload, not a broken place\)"):
        gate(broken, RULES, source="t")


def test_weekly_rows_fall_on_saturday_and_shares_stay_in_bounds():
    saturdays = pd.date_range("2025-01-04", periods=6, freq="7D")
    rules = GateRules(source="w", places=PLACES, shares=(ShareBound("n", 0.5),), step_days=7,
                      weekday=5, max_skipped_share=0.5)
    frame = rows({"A": [0.01] * 6, "B": [0.01] * 5 + [0.9], "C": [0.01] * 6, "D": [0.01] * 6},
                 saturdays)
    frame.loc[(frame["place"] == "C") & (frame["date"] == saturdays[2]), "date"] = \
        saturdays[2] - pd.Timedelta(days=1)
    skipped = gate(frame, rules, source="w").skipped
    assert skipped == {"B": "B: 'n' is 0.9 on 2025-02-08, outside 0 … 0.5",
                       "C": "C: week ending 2025-01-17 is a Friday, not a Saturday"}


def test_the_history_rule_on_a_grid_equals_it_series_by_series():
    rng = np.random.default_rng(0)
    grid = rng.poisson(50, size=(5, 60)).astype(float)
    grid[2, :10] = np.nan   # a place that begins later
    rule = JumpRule(window=8, jump_factor=10, floor=20, growth_factor=6, growth_window=2)
    together = history_bounds(grid, rule)
    alone = np.vstack([history_bounds(row, rule) for row in grid])
    np.testing.assert_array_equal(together, alone)
    assert np.isinf(together[:, 0]).all() and np.isinf(together[2, 10])


# ------------------------------------------------------------------ real payloads pass


def test_every_real_cdph_vintage_passes_every_county():
    for path in sorted(CDPH.glob("*/covid19cases_test.csv")):
        vintage = read_cdph_csv(path)
        assert len(vintage.counties) == 58 and dict(vintage.skipped) == {}, path


# ------------------------------------------------------------------ a poisoned county, end to end


@pytest.mark.slow
def test_a_poisoned_county_cell_stops_neither_san_franciscos_nor_a_countys_forecast(
        tmp_path, monkeypatch, datasf_dir):
    """Issue 32: one cell of one county ('Infinity' in Marin's cases) used to be stored as
    INT64_MIN and fail every forecast. Now Marin is skipped by name, left out of the pooled
    members, and the tiny San Francisco forecast (DataSF, pooling CDPH's counties) and a county
    forecast (Santa Cruz, from the same CDPH vintage) both run to completion; a forecast of
    Marin itself is one named error."""
    import dataclasses

    from pipeline.data.california.cdph_source import import_cdph_exports, load_cdph
    from pipeline.forecast.config import resolve_config
    from pipeline.forecast.run import run_forecast
    from pipeline.forecast.sources import load_reference_histories, load_series
    from pipeline.forecast.report.weekly import backtest_section

    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.delenv("FLOWCAST_CDPH_ARCHIVE", raising=False)
    real = pd.read_csv(CDPH / "ofaye98__CSC508_Mentor_Class" / "covid19cases_test.csv",
                       dtype=str, keep_default_na=False)
    # four counties' rows, every column as written; Marin poisoned on one day
    frame = real[real["area"].isin(["Marin", "Monterey", "San Francisco", "Santa Cruz"])].copy()
    frame.loc[(frame["area"] == "Marin") & (frame["date"] == "2021-06-01"), "cases"] = "Infinity"
    poisoned = tmp_path / "cdph" / "covid19cases_test.csv"
    poisoned.parent.mkdir()
    frame.to_csv(poisoned, index=False)
    why = "Marin: 'cases' is not finite ('Infinity') on 2021-06-01"
    [summary] = import_cdph_exports([poisoned])
    assert summary.action == "imported" and summary.counties == 3 and why in summary.note
    loaded = load_cdph(offline=True)
    assert dict(loaded.provenance.skipped) == {"Marin": why}
    assert sorted(load_reference_histories()) == ["Monterey", "San Francisco", "Santa Cruz"]

    base = resolve_config("tiny")
    sf = resolve_config("tiny", output_dir=str(tmp_path / "reports"), data=dataclasses.replace(
        base.data, kind="import", import_paths=(str(datasf_dir),)))
    sf_results = run_forecast(sf)
    assert sf_results.reference_date == "2022-03-02"
    assert all(np.isfinite(v).all() for v in sf_results.weekly.latest.values.values())
    # the report names the county left out of the pooled members' data, and why
    assert dict(sf_results.weekly.result.panel.skipped) == {"Marin": why}
    [alert] = backtest_section(sf_results).alerts
    assert "left 1 place(s) out" in alert and why in alert

    county = resolve_config("tiny", output_dir=str(tmp_path / "reports"),
                            data=dataclasses.replace(base.data, kind="cache",
                                                     county="Santa Cruz"))
    county_results = run_forecast(county)
    assert county_results.weekly.history.population == 273_999
    assert all(np.isfinite(v).all() for v in county_results.weekly.latest.values.values())
    [provenance] = load_series(county.data).provenance.datasets  # what the run read
    assert dict(provenance.skipped) == {"Marin": why}
    assert any(why in note for note in provenance.notes)

    with pytest.raises(Exception, match=r"Marin is skipped in the CDPH vintage of 2021-11-04 "
                                        r"\(.*\): Marin: 'cases' is not finite"):
        load_series(dataclasses.replace(county.data, county="Marin"))
