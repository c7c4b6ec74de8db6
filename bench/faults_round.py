"""Faults of a newer release met by the hub round (issue 39): the round is published, and what it
left out is named (``round_published``, ``dropped`` per case).

Each case imports the hub's real releases of 2025-09-10 and 2025-09-17 (both targets) and the
other target's of 2025-09-24 into a fresh ``FLOWCAST_DATA_DIR``, then the faulted target's
release of 2025-09-24 with one fault (``import_target_csv``; admissions unless the case says
the ED share), and runs the round from the cache on the ``tiny`` preset through the library
(``run_hub_round``, ``publish_hub_round``: what the ``hub_forecast`` flow runs, without
Prefect), validated against the hub's ``tasks.json``. The models are trained once into a store
every case shares. A location left out must be named both in the panel's ``skipped`` and in
``HubRun.dropped``, and the other target's file rows keep their US.

Cases: a settled revision held alone, no national row (admissions: the US from the states), an
NA week, one location's later row, one state missing from the newer release (admissions and
the ED share: held alone), the ED share without its national row (the states published, the US
left out and said), and a stale admissions release (the target left out and said, problem 7).
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from bench.faults import CaseResult
from bench.faults_nhsn import NHSN
from pipeline.data.core.cache import data_folder
from pipeline.data.hub.nhsn import ED_COVID, HOSP_COVID

Change = Callable[[pd.DataFrame], pd.DataFrame]


@dataclass(frozen=True)
class RoundFault:
    """A fault in ``target``'s release of 2025-09-24 (``change`` on its rows: ``date``,
    ``location``, ``value``); ``dropped``: the locations the round must leave out of that
    target and name, in ``HubRun.dropped`` too (``expect`` in the reason of the first);
    ``kept``: locations that must be in the round; ``target_left_out``: the target has no
    current release, so the round publishes the other alone and names the target as left out
    (issue 39 problem 7); ``held``: locations held for review and still forecast, from their
    accepted series (issue 49; ``expect`` in the hold's words in ``HubRun.held``)."""

    name: str
    change: Change
    dropped: tuple[str, ...] = ()
    held: tuple[str, ...] = ()
    expect: str = ""
    kept: tuple[str, ...] = ()
    target_left_out: bool = False
    target: str = HOSP_COVID


def _tenfold(frame: pd.DataFrame) -> pd.DataFrame:
    ca = (frame["location"] == "06") & (frame["date"].astype(str) == "2025-06-07")
    return frame.assign(value=frame["value"].where(~ca, frame["value"] * 10))


def _na_week(frame: pd.DataFrame) -> pd.DataFrame:
    ma = (frame["location"] == "25") & (frame["date"].astype(str) == "2025-08-02")
    return frame.assign(value=frame["value"].where(~ma))


def _later_row(frame: pd.DataFrame) -> pd.DataFrame:
    newest = frame["date"].max()
    return frame[(frame["date"] != newest) | (frame["location"] == "06")]


def _without(location: str) -> Change:
    return lambda frame: frame[frame["location"] != location]


def round_faults() -> list[RoundFault]:
    return [
        RoundFault("round-location-revised-held-alone", _tenfold, held=("06",), kept=("06",),
                   expect="revision beyond policy"),
        RoundFault("round-no-national-row", lambda f: f[f["location"] != "US"],
                   kept=("US", "06")),
        RoundFault("round-na-week-keeps-its-state", _na_week, kept=("25",)),
        RoundFault("round-one-location-later-week", _later_row, dropped=("06",),
                   expect="after the payload's last date 2025-09-13"),
        # a location missing from a newer release: held alone, the round publishes the others
        RoundFault("round-one-state-missing", _without("06"), dropped=("06",),
                   expect="06: missing from the release of 2025-09-24", kept=("US", "36")),
        RoundFault("round-ed-one-state-missing", _without("06"), dropped=("06",),
                   expect="06: missing from the release of 2025-09-24", kept=("US", "36"),
                   target=ED_COVID),
        # the ED share without its national row: the states published, the US left out, said
        RoundFault("round-ed-no-national-row", _without("US"), dropped=("US",),
                   expect="a share cannot be summed from the states", kept=("06", "36"),
                   target=ED_COVID),
        RoundFault("round-stale-release-held",
                   lambda f: f[f["date"].astype(str) <= "2025-08-23"], target_left_out=True),
    ]


def _seed_cache(folder: Path, fault: RoundFault, places: Sequence[str] | None) -> None:
    from pipeline.data.hub.target_import import import_hub_time_series, import_target_csv
    series = pd.read_parquet(NHSN / "time-series.parquet")
    if places is not None:
        series = series[series["location"].isin(places)]
    as_of = series["as_of"].astype(str)
    recent = series[(as_of >= "2025-09-10")
                    & ~((as_of == "2025-09-24") & (series["target"] == fault.target))]
    recent.to_parquet(folder / "time-series.parquet")
    import_hub_time_series(folder / "time-series.parquet")
    newest = series[(as_of == "2025-09-24") & (series["target"] == fault.target)]
    rows = newest[["target_end_date", "location", "observation"]].rename(
        columns={"target_end_date": "date", "observation": "value"}).reset_index(drop=True)
    fault.change(rows).to_csv(folder / "newest.csv", index=False)
    import_target_csv(folder / "newest.csv", target=fault.target, as_of="2025-09-24")


def run_round_fault(fault: RoundFault, folder: Path, models: Path,
                    places: Sequence[str] | None = None) -> CaseResult:
    """``fault``'s round, at every hub location or at ``places`` alone (the hub's releases cut
    to them: a test's dozen places, the same work at each)."""
    from pipeline.hub_round.publish import publish_hub_round
    from pipeline.hub_round.run import HubRunConfig, run_hub_round
    started = time.monotonic()
    data = folder / "data"
    data.mkdir(parents=True)
    models.mkdir(parents=True, exist_ok=True)
    (data / "models").symlink_to(models, target_is_directory=True)
    with data_folder(data):
        try:
            _seed_cache(folder, fault, places)
            config = HubRunConfig.of_preset("tiny", data_source="cache",
                                            output_dir=str(folder / "reports"),
                                            hub_config=str(NHSN / "hub-config"))
            run = run_hub_round(config)
            published = publish_hub_round(run)
        except Exception as exc:  # noqa: BLE001 - a crash is a failed case, reported
            return CaseResult(fault.name, False, time.monotonic() - started, 0,
                              f"round_published: false; raised {type(exc).__name__}: {exc}",
                              source="hub_round", issue=39,
                              detail={"round_published": False, "dropped": {}})
    target = fault.target
    left_out = run.skipped().get(target, {})
    said = {d.target: d.why for d in run.dropped if d.what == "target"}
    named = sorted(d.name for d in run.dropped if d.what == "location" and d.target == target)
    frame = pd.read_csv(published.model_output, dtype={"location": str})
    hosp = set(frame.loc[frame["target"] == target, "location"])
    other = set(frame.loc[frame["target"] != target, "location"])   # the unfaulted target
    dropped = sorted(left_out)
    if fault.target_left_out:       # not in the file, and said
        passed = (published.model_output.is_file() and not hosp and target in said
                  and bool(set(frame["target"]) - {target}))
    else:
        passed = (published.model_output.is_file() and bool(hosp)
                  and dropped == sorted(fault.dropped) == named
                  and all(loc not in hosp for loc in fault.dropped)
                  and all(loc in hosp for loc in fault.kept)
                  and "US" in other
                  and (not fault.dropped or fault.expect in left_out[fault.dropped[0]])
                  and all(fault.expect in run.held().get(target, {}).get(loc, "")
                          for loc in fault.held))
    note = (f"round_published: true ({published.reference_date}, {len(hosp)} locations of "
            f"{target}); dropped: "
            + ("; ".join([*left_out.values(), *(f"target {t}: {why}" for t, why in said.items())])
               or "none"))
    return CaseResult(fault.name, passed, time.monotonic() - started, 0, note,
                      source="hub_round", issue=39,
                      detail={"round_published": True, "reference_date": published.reference_date,
                              "locations": {t: int(n) for t, n in frame.groupby("target")[
                                  "location"].nunique().items()},
                              "dropped": {**{t: dict(d) for t, d in run.skipped().items()},
                                          **{t: {"target": why} for t, why in said.items()}}})


def run_all(scratch: Path) -> list[CaseResult]:
    from bench.faults import show
    models = scratch / "models"
    return [show(run_round_fault(f, scratch / f"round-{k}", models))
            for k, f in enumerate(round_faults())]
