"""A week's data judged place by place (issue 39) and revisions held per location (issue 37,
item 4), on the hub's real releases: unknown names never crash and count as failures, one
location's later row refuses that location alone, NA weeks cost the week, a future-dated,
stale or implausible release never goes live, and FluSight's 2024-11-20 revision holds
Louisiana and Ohio only."""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.data.core.gate import GateError, gate
from pipeline.data.hub.held_locations import HOLDS_FILE
from pipeline.data.hub.nhsn_vintages import (HOSP_COVID, TARGETS, accept_location_revisions,
                                             cached_weekly_vintages, gate_rules,
                                             revisions_waiting)
from pipeline.data.hub.release import ReleaseDateError, implausible_event, stale_reason
from pipeline.data.hub.target_import import import_hub_time_series, import_target_csv
from tests.conftest import SHARED

NHSN = SHARED / "data" / "nhsn" / "time-series.parquet"
FLUSIGHT = SHARED / "data" / "flusight" / "time-series.parquet"
RULES = gate_rules(TARGETS[HOSP_COVID], "value")


@functools.cache
def _release(as_of: str) -> pd.DataFrame:
    table = pd.read_parquet(NHSN)
    rows = table[(table["target"] == HOSP_COVID) & (table["as_of"].astype(str) == as_of)]
    return rows[["target_end_date", "location", "observation"]].rename(
        columns={"observation": "value"}).reset_index(drop=True)


def release(as_of: str) -> pd.DataFrame:
    return _release(as_of).copy()


def rows(frame: pd.DataFrame) -> pd.DataFrame:
    return pd.DataFrame({"place": frame["location"], "date":
                         pd.to_datetime(frame["target_end_date"]),
                         "value": frame["value"].map(lambda v: f"{v:.0f}")})


def write(frame: pd.DataFrame, folder: Path, name: str) -> Path:
    path = folder / f"{name}.csv"
    frame.rename(columns={"target_end_date": "date"}).to_csv(path, index=False)
    return path


def test_unknown_names_never_crash_and_count_toward_the_broken_payload_share():
    real = rows(release("2025-09-24"))
    names = {"06": "California", "US": "United States"}
    all_named = real.assign(place=real["place"].map(lambda p: f"State {p}"))
    with pytest.raises(GateError, match=r"no row names one of the 53 known hub location names "
                                        r"\(53 unknown name\(s\)"):
        gate(all_named, RULES, source="t")
    # NSSP's place column holding postal codes: the US alone is known, 52 names are not
    mixed = real.assign(place=real["place"].where(real["place"] == "US", "X" + real["place"]))
    with pytest.raises(GateError, match=r"52 of the 53 hub locations fail the validation gate, "
                                        r"52 of them unknown names"):
        gate(mixed, RULES, source="t")
    one = real.assign(place=real["place"].replace(names).where(real["place"] == "06",
                                                               real["place"]))
    assert list(gate(one, RULES, source="t").skipped) == ["California"]


def test_one_locations_later_row_refuses_that_location_alone():
    real = rows(release("2025-09-24"))
    later = pd.DataFrame({"place": ["06"], "date": [pd.Timestamp("2025-09-27")],
                          "value": ["900"]})
    gated = gate(pd.concat([real, later], ignore_index=True), RULES, source="t")
    assert gated.skipped == {"06": "06: a row for 2025-09-27, after the payload's last date "
                                   "2025-09-20 (the date most places end on)"}
    assert gated.frame["place"].nunique() == 52
    assert gated.frame["date"].max() == pd.Timestamp("2025-09-20")


def test_na_weeks_cost_the_week_not_the_place():
    real = rows(release("2025-09-24"))
    real.loc[(real["place"] == "25") & (real["date"] == "2025-05-17"), "value"] = "NA"
    real.loc[(real["place"] == "27") & (real["date"] == "2025-05-24"), "value"] = ""
    gated = gate(real, RULES, source="t")
    assert gated.skipped == {}
    assert gated.missing == {"25": ("2025-05-17",), "27": ("2025-05-24",)}
    assert len(gated.frame) == len(real) - 2


def test_release_dates_staleness_and_whole_release_events():
    assert stale_reason(pd.Timestamp("2025-09-24"), pd.Timestamp("2025-09-13")) is None
    assert "62 weeks" in str(stale_reason(pd.Timestamp("2025-09-24"),
                                          pd.Timestamp("2024-07-13")))
    frame = release("2025-09-24")
    frame["target_end_date"] = pd.to_datetime(frame["target_end_date"])
    assert implausible_event(frame, counts=True) is None
    last = frame["target_end_date"] == frame["target_end_date"].max()
    zero = frame.assign(value=frame["value"].where(~last, 0.0))
    assert "every one of the 53 locations reads 0 for the week ending 2025-09-20" in str(
        implausible_event(zero, counts=True))
    fall = frame.copy()
    us_now = last & (fall["location"] == "US")
    fall["value"] = fall["value"].where(~us_now, fall["value"] * 0.2)
    assert "the national value falls 82% in the week ending 2025-09-20 (9,990 -> 1,768.8)" in \
        str(implausible_event(fall, counts=True))


def test_future_stale_and_unreadable_releases_are_refused_by_name(tmp_path):
    data = tmp_path / "data"
    good = write(release("2025-09-17"), tmp_path, "good")
    assert import_target_csv(good, target=HOSP_COVID, as_of="2025-09-17",
                             data_dir=data).vintages[0].action == "live"
    future = import_target_csv(good, target=HOSP_COVID, as_of="2031-01-01", data_dir=data)
    assert future.vintages[0].action == "refused"
    assert "dated 2031-01-01, after today" in future.vintages[0].note
    old = release("2024-11-20")      # its newest week ends 2024-11-16: stale on 2025-09-24
    stale = import_target_csv(write(old, tmp_path, "old"), target=HOSP_COVID,
                              as_of="2025-09-24", data_dir=data)
    assert stale.vintages[0].action == "held"
    assert "stale release: its newest week ends 2024-11-16, 312 days (44 weeks)" in \
        stale.vintages[0].note
    assert [str(v.as_of.date()) for v in cached_weekly_vintages(HOSP_COVID, data)] == \
        ["2025-09-17"]
    with pytest.raises(ReleaseDateError, match="--as-of: release date 'notadate' is not a date"):
        import_target_csv(good, target=HOSP_COVID, as_of="notadate", data_dir=data)
    table = pd.read_parquet(NHSN).head(100).astype({"as_of": str})
    table.loc[3, "as_of"] = "notadate"
    table.to_parquet(tmp_path / "bad.parquet")
    with pytest.raises(ReleaseDateError, match=r"1 row\(s\) with an unreadable release date in "
                                               r"as_of, e.g. 'notadate'"):
        import_hub_time_series(tmp_path / "bad.parquet", data)
    table.head(0).to_parquet(tmp_path / "empty.parquet")
    with pytest.raises(Exception, match=r"an empty time series \(no rows\); nothing imported"):
        import_hub_time_series(tmp_path / "empty.parquet", data)


def test_a_nationwide_zero_is_held_and_the_cache_stays(tmp_path):
    data = tmp_path / "data"
    import_target_csv(write(release("2025-09-17"), tmp_path, "good"), target=HOSP_COVID,
                      as_of="2025-09-17", data_dir=data)
    frame = release("2025-09-24")
    frame.loc[frame["target_end_date"] == frame["target_end_date"].max(), "value"] = 0.0
    done = import_target_csv(write(frame, tmp_path, "zero"), target=HOSP_COVID,
                             as_of="2025-09-24", data_dir=data).vintages[0]
    assert done.action == "held" and "every one of the 53 locations reads 0" in done.note
    assert [str(v.as_of.date()) for v in cached_weekly_vintages(HOSP_COVID, data)] == \
        ["2025-09-17"]


def test_a_settled_revision_holds_that_location_alone_until_accepted(tmp_path):
    data = tmp_path / "data"
    import_target_csv(write(release("2025-09-17"), tmp_path, "a"), target=HOSP_COVID,
                      as_of="2025-09-17", data_dir=data)
    revised = release("2025-09-24")
    ca = (revised["location"] == "06") & (revised["target_end_date"].astype(str) == "2025-06-07")
    revised.loc[ca, "value"] *= 10
    done = import_target_csv(write(revised, tmp_path, "b"), target=HOSP_COVID,
                             as_of="2025-09-24", data_dir=data).vintages[0]
    assert done.action == "live" and "held for review, their cached series kept: 06" in done.note
    assert list(revisions_waiting(HOSP_COVID, data)) == ["06"]
    newest = cached_weekly_vintages(HOSP_COVID, data)[-1]
    # held, California is forecast from its accepted series: in the vintage, its revised week
    # back at the accepted value, every other week the release's own
    assert "06" in newest.locations and len(newest.locations) == 53 and "06" not in newest.skipped
    assert newest.held["06"].startswith("06: revision held for review since the release of "
                                        "2025-09-24 (its series of 2025-09-17 kept)")
    ca_rows = newest.frame[newest.frame["location"] == "06"].set_index("target_end_date")["value"]
    accepted = release("2025-09-17")
    accepted = accepted[accepted["location"] == "06"].set_index(
        pd.to_datetime(accepted[accepted["location"] == "06"]["target_end_date"]))["value"]
    this = release("2025-09-24")
    this = this[this["location"] == "06"].set_index(
        pd.to_datetime(this[this["location"] == "06"]["target_end_date"]))["value"]
    week = pd.Timestamp("2025-06-07")
    assert ca_rows[week] == accepted[week] != this[week]      # 593, where this release had 594
    assert revised.loc[ca, "value"].iloc[0] == this[week] * 10
    assert ca_rows.drop(week).equals(this.drop(week).astype(float))
    accept_location_revisions(HOSP_COVID, ["CA"], data)
    assert revisions_waiting(HOSP_COVID, data) == {}
    assert "06" in cached_weekly_vintages(HOSP_COVID, data)[-1].locations
    assert (data / "nhsn" / "wk-inc-covid-hosp" / HOLDS_FILE).is_file()


@pytest.mark.parametrize("next_release", ["repeats", "takes back"])
def test_a_held_revision_the_next_release_repeats_is_accepted_and_one_taken_back_ends(
        tmp_path, next_release):
    """California's week of 2025-06-07 revised tenfold on 2025-09-24: held one release. The
    next release (a copy of 2025-09-24's data dated 2025-10-01) either repeats the revision
    (the source stands by it: accepted by itself, recorded, California reads the revised
    series) or takes it back (the hold ends, the accepted value stands)."""
    from pipeline.data.hub.held_locations import read_holds

    data = tmp_path / "data"
    import_target_csv(write(release("2025-09-17"), tmp_path, "a"), target=HOSP_COVID,
                      as_of="2025-09-17", data_dir=data)
    revised = release("2025-09-24")
    ca = (revised["location"] == "06") & (revised["target_end_date"].astype(str) == "2025-06-07")
    original = float(revised.loc[ca, "value"].iloc[0])
    revised.loc[ca, "value"] *= 10
    import_target_csv(write(revised, tmp_path, "b"), target=HOSP_COVID, as_of="2025-09-24",
                      data_dir=data)
    later = revised if next_release == "repeats" else release("2025-09-24")
    done = import_target_csv(write(later, tmp_path, "c"), target=HOSP_COVID, as_of="2025-10-01",
                             data_dir=data).vintages[0]
    assert done.action == "live"
    assert revisions_waiting(HOSP_COVID, data) == {}
    [hold] = read_holds(data / "nhsn" / "wk-inc-covid-hosp").entries
    assert (hold.location, hold.since, hold.until) == ("06", "2025-09-24", "2025-10-01")
    newest = cached_weekly_vintages(HOSP_COVID, data)[-1]
    assert newest.held == {} and "06" in newest.locations
    value = newest.frame[(newest.frame["location"] == "06") & (
        newest.frame["target_end_date"] == pd.Timestamp("2025-06-07"))]["value"].item()
    if next_release == "repeats":
        assert hold.settled == ("accepted on 2025-10-01: the release of 2025-10-01 repeats the "
                                "revision (the source stands by it)")
        assert value == original * 10
    else:
        assert hold.settled == ("ended on 2025-10-01: the release of 2025-10-01 takes the "
                                "revision back")
        assert value == original


def test_flusight_holds_the_revised_locations_alone_and_keeps_its_na_states(tmp_path):
    """The real FluSight releases: all 59 go live (27 used to be held for one Louisiana
    revision); Louisiana and Ohio are held from 2024-11-20, Arizona from 2025-02-05, Puerto
    Rico from 2025-03-19, each for one release: the next release repeats each revision, which
    is then accepted (they used to stay out of every later round). While held, each is forecast
    from its accepted series, never left out. Massachusetts, Minnesota and West Virginia (NA
    weeks in the 2024 off-season) are in every release."""
    from pipeline.data.hub.held_locations import read_holds

    data = tmp_path / "data"
    summary = import_hub_time_series(FLUSIGHT, data)
    assert [v.action for v in summary.vintages] == ["live"] * 59
    assert revisions_waiting("wk inc flu hosp", data) == {}
    holds = read_holds(data / "nhsn" / "wk-inc-flu-hosp").entries
    assert {h.location: (h.since, h.until) for h in holds} == {
        "22": ("2024-11-20", "2024-12-04"), "39": ("2024-11-20", "2024-12-04"),
        "04": ("2025-02-05", "2025-02-12"), "72": ("2025-03-19", "2025-03-26")}
    assert all(h.settled is not None and "repeats the revision" in h.settled for h in holds)
    assert "22 week ending 2022-02-19 39 -> 170" in holds[0].reason
    vintages = cached_weekly_vintages("wk inc flu hosp", data)
    by_date = {str(v.as_of.date()): v for v in vintages}
    assert "22" in by_date["2024-05-01"].locations and "22" in by_date["2024-11-20"].locations
    assert set(by_date["2024-11-20"].held) == {"22", "39"} and by_date["2024-12-04"].held == {}
    louisiana = by_date["2024-11-20"].frame
    assert louisiana[(louisiana["location"] == "22") & (louisiana["target_end_date"] == pd.Timestamp(
        "2022-02-19"))]["value"].item() == 39          # the accepted value, not 170
    assert all({"25", "27", "54"} <= set(v.locations) for v in vintages)
    assert [len(v.locations) for v in vintages[-1:]] == [53]


def test_a_release_without_a_national_row_takes_the_states_sum(tmp_path):
    data = tmp_path / "data"
    frame = release("2025-09-24")
    us = frame[frame["location"] == "US"].set_index("target_end_date")["value"]
    done = import_target_csv(write(frame[frame["location"] != "US"], tmp_path, "no-us"),
                             target=HOSP_COVID, as_of="2025-09-24", data_dir=data).vintages[0]
    assert done.action == "live"
    [vintage] = cached_weekly_vintages(HOSP_COVID, data)
    assert vintage.derived == {"US": "no national row in the release: the national value is "
                                     "the sum of the 52 states (46 weeks)"}
    derived = vintage.frame[vintage.frame["location"] == "US"].set_index("target_end_date")
    ratio = derived["value"] / us.set_axis(pd.to_datetime(us.index))
    assert 0.998 <= ratio.min() and ratio.max() <= 1.0   # measured: 0.9983 … 1.0


def test_a_slow_ramp_is_refused_against_the_fastest_real_growth():
    from pipeline.data.core.plausibility import GrowthRule, growth_sums
    steady = np.array([[100.0] * 14 + [2000.0] + [12000.0] * 6])
    now, before = growth_sums(steady, GrowthRule(columns=("x",)))
    assert now[0, 14] == 2600 and before[0, 14] == 700          # 6 × 100 + 2,000 after 7 × 100
    assert now[0, 15] > 11 * (before[0, 15] + 100)              # 14,500 > 11 × 800
    # real series pass: the CDPH vintages (tests/test_gate.py), San Francisco's cases (3.5×)


def test_hub_options_are_checked_before_any_work(tmp_path):
    from pipeline.cli.hub_options import hub_config_folder, writable_output_dir
    from pipeline.errors import ConfigError
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match=r"--hub-config .*empty: no tasks.json in the folder"):
        hub_config_folder(tmp_path / "empty")
    (tmp_path / "list").mkdir()
    (tmp_path / "list" / "tasks.json").write_text("[]")
    with pytest.raises(ConfigError, match=r"not a hubverse tasks config .*got list"):
        hub_config_folder(tmp_path / "list")
    assert hub_config_folder(NHSN.parent / "hub-config") == NHSN.parent / "hub-config"
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match=r"--output-dir .*file is a file"):
        writable_output_dir(tmp_path / "file")


def test_the_national_total_is_never_spread_over_a_subset_of_the_states():
    from pipeline.combine.reconcile import reconcilable
    from pipeline.data.hub.locations import POPULATION
    every = list(POPULATION)
    assert reconcilable(every, "US", POPULATION)
    assert not reconcilable([p for p in every if p not in ("25", "27", "54")], "US", POPULATION)
    assert not reconcilable([p for p in every if p != "US"], "US", POPULATION)


def test_missing_weeks_are_said_on_the_vintage(tmp_path):
    from pipeline.data.hub.nhsn_vintages import skipped_note
    frame = release("2025-09-24")
    ma = (frame["location"] == "25") & (frame["target_end_date"].astype(str) == "2025-05-17")
    frame.loc[ma, "value"] = float("nan")
    import_target_csv(write(frame, tmp_path, "na"), target=HOSP_COVID, as_of="2025-09-24",
                      data_dir=tmp_path / "data")
    [vintage] = cached_weekly_vintages(HOSP_COVID, tmp_path / "data")
    assert vintage.missing == {"25": ("2025-05-17",)} and "25" in vintage.locations
    assert "25 1 week(s) from 2025-05-17" in skipped_note(vintage)[0]


def test_holds_open_end_and_are_accepted_one_location_at_a_time():
    from pipeline.data.hub.held_locations import Holds
    from pipeline.errors import ConfigError
    holds = Holds().opened({"22": "r22", "39": "r39"}, since="2024-11-20", reference="2024-05-01")
    holds = holds.opened({"22": "again", "39": "again"}, since="2024-12-04",
                         reference="2024-11-20")
    assert {h.location: (h.since, h.reference, h.reason) for h in holds.entries} == {
        "22": ("2024-11-20", "2024-05-01", "r22"), "39": ("2024-11-20", "2024-05-01", "r39")}
    holds = holds.accepted(("22",), live="2024-12-04")
    assert holds.entries[0].settled == "accepted by the operator from the release of 2024-12-04"
    holds = holds.opened({}, since="2024-12-11", reference="2024-12-04")   # 39 taken back
    assert holds.waiting() == {}
    assert [(h.location, h.until) for h in holds.entries] == [("22", "2024-12-04"),
                                                              ("39", "2024-12-11")]
    assert list(holds.at("2024-11-27")) == ["22", "39"] and holds.at("2024-12-11") == {}
    with pytest.raises(ConfigError, match="no revision waits for 22; waiting: none"):
        holds.accepted(("22",), live="2024-12-11")


def test_a_future_dated_live_vintage_left_by_an_older_flowcast_blocks_nothing(tmp_path):
    """Issue 39, problem 8: a live vintage dated 2031-01-01 (imported before releases from the
    future were refused) used to refuse or archive every later release."""
    from pipeline.data.core.cache import DatasetCache
    from pipeline.data.hub.nhsn_vintages import canonical_csv, commit_weekly, parse_vintage
    from datetime import date
    data, spec = tmp_path / "data", TARGETS[HOSP_COVID]
    frame = release("2025-09-17").assign(target_end_date=lambda f: pd.to_datetime(
        f["target_end_date"]))
    payload = canonical_csv(frame)
    future = parse_vintage(spec, payload, suffix="csv", as_of=date(2031, 1, 1), source="old")
    commit_weekly(DatasetCache.default(data), future, payload, suffix="csv",
                  source_kind="csv-import", source="old", older="archive",
                  today=date(2031, 1, 2), accept_revisions=True)   # as an older flowcast did
    done = import_target_csv(write(release("2025-09-24"), tmp_path, "new"), target=HOSP_COVID,
                             as_of="2025-09-24", data_dir=data).vintages[0]
    assert done.action == "live", done.note


def test_a_state_missing_from_a_newer_release_is_held_alone_until_it_is_back(tmp_path):
    """Issue 39: California missing from the release of 2025-09-17 used to refuse the whole
    release ("location dropped"). Now the other 52 go live, California is held with its series
    of 2025-09-10 as reference and named; when the release of 2025-09-24 has it again (and
    agrees with that reference), the hold ends by itself."""
    data = tmp_path / "data"

    def imported(as_of: str, frame: pd.DataFrame) -> str:
        done = import_target_csv(write(frame, tmp_path, as_of), target=HOSP_COVID, as_of=as_of,
                                 data_dir=data).vintages[0]
        return done.action
    assert imported("2025-09-10", release("2025-09-10")) == "live"
    without_ca = release("2025-09-17")
    assert imported("2025-09-17", without_ca[without_ca["location"] != "06"]) == "live"
    [hold] = revisions_waiting(HOSP_COVID, data).values()
    assert (hold.location, hold.kind, hold.since, hold.reference) == \
        ("06", "missing", "2025-09-17", "2025-09-10")
    newest = cached_weekly_vintages(HOSP_COVID, data)[-1]
    assert len(newest.locations) == 52 and "06" not in newest.locations
    assert newest.skipped == {"06": "06: missing from the release of 2025-09-17 (its series of "
                                    "2025-09-10 kept until it is back): wk inc covid hosp: no "
                                    "row of 06 in the release of 2025-09-17"}
    # back in the next release, judged against its series of 2025-09-10: the hold ends
    assert imported("2025-09-24", release("2025-09-24")) == "live"
    assert revisions_waiting(HOSP_COVID, data) == {}
    vintages = cached_weekly_vintages(HOSP_COVID, data)
    assert [len(v.locations) for v in vintages] == [53, 52, 53]


def test_a_state_missing_again_stays_held_and_many_missing_refuse_the_release(tmp_path):
    data = tmp_path / "data"
    import_target_csv(write(release("2025-09-10"), tmp_path, "a"), target=HOSP_COVID,
                      as_of="2025-09-10", data_dir=data)
    for as_of in ("2025-09-17", "2025-09-24"):
        frame = release(as_of)
        done = import_target_csv(write(frame[frame["location"] != "06"], tmp_path, as_of),
                                 target=HOSP_COVID, as_of=as_of, data_dir=data).vintages[0]
        assert done.action == "live"
    [hold] = revisions_waiting(HOSP_COVID, data).values()
    assert (hold.location, hold.since, hold.reference) == ("06", "2025-09-17", "2025-09-10")
    assert "06" not in cached_weekly_vintages(HOSP_COVID, data)[-1].locations
    # fourteen states missing (more than a quarter of 53): a broken payload, refused whole
    data2 = tmp_path / "data2"
    import_target_csv(write(release("2025-09-17"), tmp_path, "b"), target=HOSP_COVID,
                      as_of="2025-09-17", data_dir=data2)
    frame = release("2025-09-24")
    gone = sorted(set(frame["location"]) - {"US"})[:14]
    done = import_target_csv(write(frame[~frame["location"].isin(gone)], tmp_path, "c"),
                             target=HOSP_COVID, as_of="2025-09-24", data_dir=data2).vintages[0]
    assert done.action == "refused"
    assert ("14 of the 53 locations are missing from the release of 2025-09-24 (more than 25%: "
            "a broken payload, refused)") in done.note
    assert revisions_waiting(HOSP_COVID, data2) == {}
    # a payload of the same date without a location is refused, as before
    same = import_target_csv(write(release("2025-09-17").query("location != '06'"), tmp_path,
                                   "d"), target=HOSP_COVID, as_of="2025-09-17",
                             data_dir=data2).vintages[0]
    assert same.action == "refused" and "location dropped: 06" in same.note


def test_an_ed_share_release_without_the_us_row_goes_live_without_the_us(tmp_path):
    """A share cannot be summed from the states: the release without its national row went
    unused ("location dropped: US"); now the states go live and the US is left out, named."""
    ed = "wk inc covid prop ed visits"
    table = pd.read_parquet(NHSN)
    data = tmp_path / "data"
    for as_of in ("2025-09-17", "2025-09-24"):
        frame = table[(table["target"] == ed) & (table["as_of"].astype(str) == as_of)]
        frame = frame[["target_end_date", "location", "observation"]].rename(
            columns={"observation": "value"})
        if as_of == "2025-09-24":
            frame = frame[frame["location"] != "US"]
        done = import_target_csv(write(frame, tmp_path, f"ed-{as_of}"), target=ed,
                                 as_of=as_of, data_dir=data).vintages[0]
        assert done.action == "live", done.note
    newest = cached_weekly_vintages(ed, data)[-1]
    assert "US" not in newest.locations and len(newest.locations) == 50
    assert newest.skipped == {"US": "US: no national row in the release; a share cannot be "
                                    "summed from the states: the national forecast is left out"}
    assert revisions_waiting(ed, data) == {}


def test_no_national_row_and_a_state_missing_leaves_the_us_out_by_name():
    """Admissions without the US row are summed from the states only when every state reports:
    with California missing too, the US is left out and named (not a sum of 51 states)."""
    from datetime import date
    from pipeline.data.hub.nhsn_vintages import canonical_csv, parse_vintage
    frame = release("2025-09-24").assign(target_end_date=lambda f: pd.to_datetime(
        f["target_end_date"]))
    payload = canonical_csv(frame[~frame["location"].isin(["US", "06"])])
    vintage = parse_vintage(TARGETS[HOSP_COVID], payload, suffix="csv",
                            as_of=date(2025, 9, 24), source="t")
    assert vintage.derived == {} and len(vintage.locations) == 51
    assert vintage.skipped == {"US": "US: no national row in the release; the states do not all "
                                     "report (1 missing, e.g. 06): the national forecast is left "
                                     "out"}
