"""NHSN hospital admissions and NSSP ED-visit shares as a source (issue 29, item 1).

The import of the hub's real target data (``../shared/data/nhsn/time-series.parquet``, read in
place, every vintage kept: real recorded values asserted); the Socrata client through the real
``requests`` stack against the fake data.cdc.gov of ``bench.faults_nhsn`` on 127.0.0.1 (paging,
the jurisdiction mapping, a revised week held by the revision policy); every fault of the NHSN
catalogue, asserting the message and that the cache bytes are unchanged; the concurrent import
of an older and a newer vintage; the command line."""
from __future__ import annotations

from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import pandas as pd
import pytest
from typer.testing import CliRunner

from bench.faults import bytes_lost, cache_bytes
from bench.faults_nhsn import (HRD_ORDER, NHSN, RELEASE_NOW, FakeCDC, edited, faults, held_files, hrd_rows,
                               hub_vintage, nhsn_config, revised_settled, run_concurrent_imports,
                               run_fault, send_pages, write_target_csv)
from pipeline.cli.data import data_app
from pipeline.data.hub.locations import BY_LOCATION, HUB_LOCATIONS, hub_location
from pipeline.data.hub.nhsn_vintages import accept_location_revisions
from pipeline.data.hub.nhsn import (ED_COVID, HOSP_COVID, NHSNConfig, cached_weekly_vintages,
                                    import_hub_time_series, import_target_csv, load_nhsn,
                                    vintage_as_of)
from pipeline.errors import ConfigError, OfflineError

FAULTS = {f.name: f for f in faults()}


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    return tmp_path / "flowcast-data"  # = $FLOWCAST_DATA_DIR (conftest)


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    if not (NHSN / "time-series.parquet").is_file():
        pytest.fail(f"the hub's real time series expected in {NHSN} (../shared beside the repo)")
    root = tmp_path_factory.mktemp("nhsn") / "data"
    summary = import_hub_time_series(NHSN, root)
    return root, summary


# ------------------------------------------------------------------ the 53 locations


def test_the_table_of_locations_is_the_hubs():
    real = pd.read_csv(NHSN / "locations.csv", dtype={"location": str})
    assert [(h.abbreviation, h.location, h.name, h.population) for h in HUB_LOCATIONS] == [
        (r.abbreviation, r.location, r.location_name, int(r.population))
        for r in real.itertuples()]
    assert len(HUB_LOCATIONS) == 53
    assert (hub_location("USA").location, hub_location("CA").location,
            hub_location("06").name, BY_LOCATION["72"].jurisdiction) == (
        "US", "06", "California", "PR")
    with pytest.raises(ConfigError, match=r"unknown hub location 'CX'; did you mean"):
        hub_location("CX")


# ------------------------------------------------------------------ the hub's time series


def test_every_vintage_of_the_real_time_series_is_kept(imported):
    root, summary = imported
    by_target = summary.targets()
    assert sorted(by_target) == [HOSP_COVID, ED_COVID] and summary.unknown_targets == ()
    assert all(v.action == "live" and v.note == "" for v in summary.vintages)
    hosp = cached_weekly_vintages(HOSP_COVID, root)
    ed = cached_weekly_vintages(ED_COVID, root)
    assert len(hosp) == 44 and len(ed) == 15
    assert (str(hosp[0].as_of.date()), str(hosp[-1].as_of.date())) == ("2024-11-20",
                                                                       "2025-09-24")
    assert (str(ed[0].as_of.date()), str(ed[-1].as_of.date())) == ("2025-06-18", "2025-09-24")
    assert all(dict(v.skipped) == {} for v in (*hosp, *ed))


def test_the_first_vintage_holds_two_weeks_of_53_locations(imported):
    first = cached_weekly_vintages(HOSP_COVID, imported[0])[0]
    frame = first.frame
    assert len(frame) == 106 and len(first.locations) == 53
    assert [str(d.date()) for d in frame["target_end_date"].unique()] == ["2024-11-09",
                                                                          "2024-11-16"]
    assert str(frame["target_end_date"].dtype) == "datetime64[ns]"
    assert (frame["target_end_date"].dt.weekday == 5).all()
    week = frame.set_index(["target_end_date", "location"])["value"]
    assert week[(pd.Timestamp("2024-11-09"), "01")] == 111.0
    assert week[(pd.Timestamp("2024-11-09"), "06")] == 611.0
    assert week[(pd.Timestamp("2024-11-09"), "US")] == 7_739.0
    assert week[(pd.Timestamp("2024-11-16"), "US")] == 17_593.0


def test_a_revised_week_keeps_both_of_its_values(imported):
    """Pennsylvania's week ending 2024-11-16: 6,124 admissions in the release of 2024-11-20,
    1,005 a week later (a real revision, kept as two vintages)."""
    vintages = cached_weekly_vintages(HOSP_COVID, imported[0])

    def pa(v):  # type: ignore[no-untyped-def]
        f = v.frame
        return float(f.loc[(f["location"] == "42")
                           & (f["target_end_date"] == pd.Timestamp("2024-11-16")), "value"].iloc[0])

    assert (pa(vintages[0]), pa(vintages[1])) == (6_124.0, 1_005.0)


def test_the_vintage_as_of_a_date_is_the_newest_released_by_then(imported):
    vintages = cached_weekly_vintages(HOSP_COVID, imported[0])
    # no release on 2025-01-22: the one known on 2025-01-28 is that of 2025-01-15
    assert str(vintage_as_of(vintages, "2025-01-28").as_of.date()) == "2025-01-15"
    assert str(vintage_as_of(vintages, "2025-01-29").as_of.date()) == "2025-01-29"
    assert vintage_as_of(vintages, "2024-11-19") is None
    latest = vintage_as_of(vintages, pd.Timestamp("2030-01-01"))
    assert latest is not None and latest.last_week == pd.Timestamp("2025-09-20")
    ed = cached_weekly_vintages(ED_COVID, imported[0])[-1].frame
    assert ed.loc[(ed["location"] == "US")
                  & (ed["target_end_date"] == pd.Timestamp("2025-09-20")), "value"].iloc[0] \
        == pytest.approx(0.0098)


def test_a_target_csv_imports_one_vintage_by_abbreviation_or_code(data_dir, tmp_path):
    path = write_target_csv(tmp_path, "2025-09-17")
    frame = pd.read_csv(path, dtype={"location": str})
    frame["location"] = frame["location"].map(lambda c: BY_LOCATION[c].jurisdiction)  # CA, USA
    frame.to_csv(path, index=False)
    [done] = import_target_csv(path, target=HOSP_COVID, as_of="2025-09-17",
                               data_dir=data_dir).vintages
    assert (done.action, done.rows, done.last_week) == ("live", 2385, "2025-09-13")
    [vintage] = cached_weekly_vintages(HOSP_COVID, data_dir)
    real = hub_vintage(HOSP_COVID, "2025-09-17")
    assert vintage.frame["value"].tolist() == real["observation"].tolist()
    assert vintage.frame["location"].tolist() == real["location"].tolist()


# ------------------------------------------------------------------ live, through requests


def test_the_socrata_client_pages_in_a_total_order_and_maps_jurisdictions(data_dir):
    with FakeCDC() as cdc:
        loaded = load_nhsn(nhsn_config(cdc.url, data_dir, HOSP_COVID, page_size=500),
                           now=RELEASE_NOW)
        queries = [{k: v[0] for k, v in parse_qs(urlsplit(s.path).query).items()}
                   for s in cdc.http.seen]
    rows = hrd_rows()
    assert len(rows) == 2438 + 3 * 46   # the hub's 53 locations + GU, VI, Region 1 a week
    assert [q["$offset"] for q in queries] == ["0", "500", "1000", "1500", "2000", "2500"]
    assert all(q["$order"] == HRD_ORDER and q["$limit"] == "500"
               and q["$select"] == "weekendingdate,jurisdiction,totalconfc19newadm"
               and q["$where"] == "weekendingdate >= '2024-11-09'" for q in queries)
    vintage, provenance = loaded[HOSP_COVID], loaded.provenance[HOSP_COVID]
    assert not provenance.from_cache and provenance.notes[0].startswith(
        "ua7e-t2fy: 2,576 rows in 6 page(s)")
    real = hub_vintage(HOSP_COVID)
    assert len(vintage.locations) == 53 and "US" in vintage.locations   # USA -> US
    assert vintage.frame["location"].tolist() == real["location"].tolist()  # CA -> 06, ...
    assert vintage.frame["value"].tolist() == real["observation"].tolist()


def test_the_ed_share_is_the_states_own_rows_over_100(data_dir):
    with FakeCDC() as cdc:
        loaded = load_nhsn(nhsn_config(cdc.url, data_dir, ED_COVID), now=RELEASE_NOW)
    real = hub_vintage(ED_COVID)
    frame = loaded[ED_COVID].frame
    assert len(frame) == len(real)   # the sub-state (county != All) rows left out
    assert frame["value"].to_numpy() == pytest.approx(real["observation"].to_numpy(), abs=5e-5)


def test_a_revised_settled_week_holds_that_location_alone_until_accepted(data_dir):
    """Issue 37, item 4: California's settled week times ten holds California alone (its cached
    series kept, named); the other 52 locations go live; while held, California is read from
    its accepted series (issue 49: the revised week at its accepted value, 594); the operator
    accepts California."""
    with FakeCDC() as cdc:
        load_nhsn(nhsn_config(cdc.url, data_dir), now=RELEASE_NOW)
        vintages = {p.name: p.read_bytes() for p in (data_dir / "nhsn" / "wk-inc-covid-hosp" /
                                                       "vintages").iterdir()}
        cdc.hrd = send_pages(edited(hrd_rows(), revised_settled), HRD_ORDER)
        held = load_nhsn(nhsn_config(cdc.url, data_dir),
                         now=RELEASE_NOW + pd.Timedelta(days=1))
    provenance, vintage = held.provenance[HOSP_COVID], held[HOSP_COVID]
    assert not provenance.from_cache and len(vintage.locations) == 53
    california = vintage.frame[vintage.frame["location"] == "06"]
    assert california[california["target_end_date"] == pd.Timestamp("2025-06-07")][
        "value"].item() == 594
    assert list(provenance.held) == ["06"]
    assert provenance.held["06"].endswith("; forecast from its accepted series")
    assert ("revision beyond policy: 'value' changed on 1 settled week(s) (on or before "
            "2025-08-23) by more than max(100, 200%), e.g. 06 week ending 2025-06-07 594 -> "
            "5,940 (against its series in the release of 2025-09-24)") in provenance.held["06"]
    assert "06" not in vintage.skipped
    assert vintage.held["06"].startswith("06: revision held for review since the release "
                                         "of 2025-09-25 (its series of 2025-09-24 kept)")
    assert held_files(data_dir, HOSP_COVID) == []
    folder = data_dir / "nhsn" / "wk-inc-covid-hosp" / "vintages"
    assert all((folder / name).read_bytes() == data for name, data in vintages.items())
    accept_location_revisions(HOSP_COVID, ["06"], data_dir)
    frame = load_nhsn(NHSNConfig(targets=(HOSP_COVID,), data_dir=data_dir), offline=True
                      )[HOSP_COVID].frame
    week = frame[(frame["location"] == "06")
                 & (frame["target_end_date"] == pd.Timestamp("2025-06-07"))]["value"].iloc[0]
    assert week == 5940


def test_offline_uses_the_cache_and_without_one_names_the_import(data_dir):
    with pytest.raises(OfflineError, match=r"no cached NHSN data for 'wk inc covid hosp'.*"
                                           r"`flowcast data import <hub folder"):
        load_nhsn(NHSNConfig(data_dir=data_dir), offline=True)
    import_hub_time_series(NHSN / "time-series.parquet", data_dir)
    loaded = load_nhsn(NHSNConfig(data_dir=data_dir), offline=True)
    assert sorted(loaded.vintages) == [HOSP_COVID, ED_COVID] and loaded.stale
    p = loaded.provenance[HOSP_COVID]
    assert p.from_cache and p.as_of == "2025-09-24" and p.last_week == "2025-09-20"


@pytest.mark.parametrize("name", list(FAULTS))
def test_fault_falls_back_to_the_untouched_cache(name, data_dir):
    fault = FAULTS[name]
    result = run_fault(fault, data_dir)
    assert fault.expect in result.note, result
    if fault.skipped is None and fault.held_place is None:   # else: the new payload, live
        assert "using cache: the vintage of" in result.note
    assert result.bytes_lost == 0
    assert result.passed, result


def test_concurrent_imports_of_an_older_and_a_newer_vintage_both_land(tmp_path):
    result = run_concurrent_imports(tmp_path, trials=2)
    assert result.passed, result.note


# ------------------------------------------------------------------ the command line


def test_cli_imports_a_hub_folder_and_lists_its_vintages(data_dir, tmp_path):
    runner = CliRunner()
    done = runner.invoke(data_app, ["import", str(NHSN)])
    assert done.exit_code == 0, done.output
    assert ("wk inc covid hosp: 44 vintage(s) 2024-11-20 … 2025-09-24 from "
            "time-series.parquet (44 live)") in done.output
    status = runner.invoke(data_app, ["status"])
    assert "wk inc covid hosp: csv-import" in status.output
    assert "44 vintage(s) kept (2024-11-20 … 2025-09-24)" in status.output
    csv = write_target_csv(tmp_path, "2025-09-17")
    missing = runner.invoke(data_app, ["import", str(csv)])
    assert missing.exit_code == 1 and "give its target and vintage date" in missing.output
    older = runner.invoke(data_app, ["import", str(csv), "--target", HOSP_COVID,
                                     "--as-of", "2025-09-17"])
    assert older.exit_code == 0, older.output
    assert "2025-09-17 archived: older than the live vintage of 2025-09-24" in older.output


def test_cli_fetch_from_a_mirror(data_dir):
    with FakeCDC() as cdc:
        done = CliRunner().invoke(data_app, ["fetch", "--source", "nhsn", "--nhsn-base-url",
                                             cdc.url])
    # fetched today, the mirror's release of 2025-09-24 is stale (its newest week over a year
    # old): held by name, never stored as today's vintage (issue 39)
    assert done.exit_code == 1, done.output
    assert "wk inc covid hosp: stale release: its newest week ends 2025-09-20" in done.output
    assert "(at most 21 accepted)" in done.output
    bad = CliRunner().invoke(data_app, ["fetch", "--source", "nhsn", "--disease", "measles"])
    assert bad.exit_code == 1 and "disease must be one of covid, flu, rsv" in bad.output
