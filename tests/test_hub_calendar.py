"""The hub's calendar (issue 49, item 4): the round a release serves comes from the hub's
``tasks.json`` and its deadlines (holiday shifts included), not a fixed offset from the release
date; tested on the holiday weeks of the hubs' real releases in ``../shared/data``."""
from __future__ import annotations

import datetime as dt

import pandas as pd
import pytest

from pipeline.errors import ConfigError
from pipeline.hub_round.replay import calendar_check
from pipeline.hub_round.run import HubRunConfig
from pipeline.outputs.hub_calendar import HubCalendar
from pipeline.outputs.hub_conform import NoHubRoundError
from pipeline.outputs.hubverse_validation import load_tasks_config
from pipeline.panels.hub import reference_date_for
from tests.conftest import SHARED

D = dt.date.fromisoformat


def _calendar(hub: str, disease: str) -> HubCalendar:
    tasks = load_tasks_config(SHARED / "data" / hub / "hub-config" / "tasks.json")
    return HubCalendar.of_tasks(tasks, disease, hub)


@pytest.fixture(scope="module")
def covid() -> HubCalendar:
    return _calendar("nhsn", "covid")


@pytest.fixture(scope="module")
def flu() -> HubCalendar:
    return _calendar("flusight", "flu")


@pytest.fixture(scope="module")
def rsv() -> HubCalendar:
    return _calendar("rsv", "rsv")


def _release_days(hub: str) -> list[dt.date]:
    table = pd.read_parquet(SHARED / "data" / hub / "time-series.parquet", columns=["as_of"])
    return sorted({pd.Timestamp(d).date() for d in table["as_of"].unique()})


def test_the_calendars_are_the_hubs_rounds(covid, flu, rsv):
    assert (len(covid.references), covid.references[0], covid.references[-1]) == (
        133, D("2024-11-16"), D("2027-05-29"))
    assert (len(flu.references), flu.references[0]) == (89, D("2023-10-07"))
    assert (len(rsv.references), rsv.references[0]) == (37, D("2025-09-20"))
    assert covid.deadline(D("2025-10-04")) == D("2025-10-01")          # the Wednesday before
    assert covid.deadline(D("2025-12-27")) == D("2025-12-29")          # moved to a Monday
    assert flu.shifts == {} and set(rsv.shifts) == {D("2025-12-27")}


def test_the_covid_hubs_holiday_weeks_serve_their_own_rounds(covid):
    """NHSN's Thursday releases of Christmas and New Year 2024 (real), and the Monday release
    of 2025-12-29: each serves the round whose deadline the hub moved to that day; the weekly
    rule had mapped 2025-12-29 to 2026-01-03, made that round twice and 2025-12-27 never."""
    assert covid.round_for(D("2024-12-26")) == D("2024-12-28")
    assert covid.round_for(D("2025-01-02")) == D("2025-01-04")
    assert covid.round_for(D("2025-12-29")) == D("2025-12-27")
    assert covid.round_for(D("2025-12-31")) == D("2026-01-03")
    assert reference_date_for(pd.Timestamp("2025-12-29")) == pd.Timestamp("2026-01-03")
    assert covid.due_on(D("2025-12-29")) == D("2025-12-27")
    assert covid.due_on(D("2025-12-24")) is None        # not due that Wednesday
    assert covid.due_on(D("2025-12-31")) == D("2026-01-03")


def test_every_real_release_day_serves_the_round_of_its_week_or_none(covid, flu, rsv):
    """On every release day of the three hubs (NHSN 44, FluSight 59, RSV 44: 2 in its rounds)
    each day the calendar has a round for serves the first Saturday 2 to 9 days on (the
    holiday Thursdays two days on), never two days the same round, and a day with none is
    FluSight's off season or before the RSV hub's first round."""
    for hub, calendar in (("nhsn", covid), ("flusight", flu), ("rsv", rsv)):
        served = {d: calendar.round_for(d) for d in _release_days(hub)}
        made = [r for r in served.values() if r is not None]
        assert len(made) == len(set(made)), hub
        for day, ref in served.items():
            if ref is not None:
                assert 2 <= (ref - day).days <= 9 and ref.weekday() == 5, (hub, day, ref)
        none = [d for d, r in served.items() if r is None]
        if hub == "nhsn":
            assert none == []
        if hub == "rsv":
            assert all(d < D("2025-09-14") for d in none) and len(none) == 42  # of 44 days
        if hub == "flusight":
            assert D("2023-09-27") in none and D("2025-06-18") in none
            assert all(flu.round_for(d) is None for d in none)
            assert all(not D("2023-10-01") <= d <= D("2024-05-08") for d in none)


def test_off_season_and_outside_the_rounds_serve_no_round(flu):
    assert flu.round_for(D("2024-07-10")) is None                       # off season
    assert flu.round_for(D("2024-11-06")) is None       # more than a week before the season
    assert flu.round_for(D("2024-11-13")) == D("2024-11-16")            # the season's first
    assert flu.round_for(D("2026-06-03")) is None                       # after the last round
    # the track record still has a round for every release (the weekly rule outside the hub's)
    assert flu.serving(pd.Timestamp("2024-07-10")) == pd.Timestamp("2024-07-13")


def test_a_due_day_without_a_round_is_refused_before_any_work(monkeypatch):
    config = HubRunConfig(disease="flu", due=D("2024-07-10"))
    with pytest.raises(NoHubRoundError, match="the flu hub has no round open on 2024-07-10 "
                                              r"\(the flu hub's 89 rounds"):
        config.due_round(config.calendar())
    covid = HubRunConfig(disease="covid", due=D("2025-12-29"))
    assert covid.due_round(covid.calendar()) == D("2025-12-27")


def test_the_replays_calendar_check_counts_missed_and_duplicated_rounds(covid):
    """Three release days of the holiday weeks: the calendar's rounds make each round once;
    the weekly rule's mapping misses 2025-12-27 and makes 2026-01-03 from a release of the
    wrong window."""
    days = [D("2025-12-17"), D("2025-12-29"), D("2025-12-31")]

    def rounds(rule):  # noqa: ANN001, ANN202
        return [{"due": str(d), "reference_date": str(rule(d)), "model_output": "f.csv"}
                for d in days]

    good = calendar_check(rounds(covid.round_for), covid)
    assert good["rounds_missed"] == good["rounds_duplicated"] == []
    assert good["hub_rounds"] == 3 and good["rounds_without_release"] == []
    weekly = calendar_check(rounds(lambda d: reference_date_for(pd.Timestamp(d)).date()), covid)
    assert weekly["rounds_missed"] == ["2025-12-27"]
    assert weekly["rounds_duplicated"] == ["2026-01-03"]


def test_a_shift_for_no_round_and_rounds_out_of_order_are_config_errors():
    with pytest.raises(ConfigError, match="a deadline is moved for 2025-01-11"):
        HubCalendar((D("2025-01-04"),), {D("2025-01-11"): D("2025-01-09")})
    with pytest.raises(ConfigError, match="distinct and in order"):
        HubCalendar((D("2025-01-11"), D("2025-01-04")))


def test_the_deployments_make_a_round_only_on_its_deadline():
    """``deadline_only`` (the three hub deployments, run Monday to Thursday): the round is made
    on the day the hub's calendar has it due, in US Eastern time; other days and off season end
    before any work, saying when the next round is due."""
    from zoneinfo import ZoneInfo

    from flows.hub_forecast import due_today

    eastern = ZoneInfo("America/New_York")
    covid, flu = HubRunConfig(disease="covid"), HubRunConfig(disease="flu")
    assert due_today(covid, dt.datetime(2025, 12, 29, 15, tzinfo=eastern)) == D("2025-12-29")
    assert due_today(covid, dt.datetime(2025, 10, 1, 15, tzinfo=eastern)) == D("2025-10-01")
    # 02:00 UTC on Thursday is still Wednesday 22:00 in New York: the Wednesday's round
    assert due_today(covid, dt.datetime(2025, 10, 2, 2, tzinfo=ZoneInfo("UTC"))) == D("2025-10-01")
    with pytest.raises(NoHubRoundError, match=r"no covid hub round is due today \(2025-12-24\); "
                                              r"the round of 2025-12-27 is due 2025-12-29"):
        due_today(covid, dt.datetime(2025, 12, 24, 15, tzinfo=eastern))
    with pytest.raises(NoHubRoundError, match=r"no flu hub round is due today \(2025-07-09\)$"):
        due_today(flu, dt.datetime(2025, 7, 9, 15, tzinfo=eastern))
