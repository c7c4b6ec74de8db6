"""The replay's input judged before any work (issue 49), as ``flowcast data import`` judges its
files: each fault is one named error, raised before the Prefect server starts and before
anything is written under ``--out``.

A fault probe of ``flowcast replay`` found: a ``--source`` without a column ended in a
``KeyError`` traceback; ``--out`` naming a file in ``NotADirectoryError`` after the server
started; a 174 KB parquet of 10 million rows was read whole (4.3 GB, 169 s) and a 180 MB
release written before a later bound refused it; a source without the disease's targets said
"no release to replay" naming neither the targets found nor those expected; ``--from
2025-13-45`` said "month must be in 1..12" without naming the option; a deeply nested or a
300 MB ``tasks.json`` crashed the parser or held the round for minutes.
"""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path

from pipeline.cli.hub_options import hub_config_folder, writable_output_dir
from pipeline.data.hub.nhsn_vintages import disease_targets
from pipeline.data.hub.target_import import hub_time_series_file, read_hub_time_series
from pipeline.errors import ConfigError, ValidationError
from pipeline.hub_round.replay import (Release, ReplayConfig, cached_releases,
                                       releases_of_time_series, wednesdays)
from pipeline.hub_round.run import Disease, HubRunConfig


@dataclass(frozen=True, eq=False)
class ReplayInput:
    """What a replay runs on, judged: its config and the releases it replays."""

    config: ReplayConfig
    releases: list[Release]


def option_date(text: str | None, option: str) -> dt.date | None:
    """``--from``/``--to`` as a date; anything but ``YYYY-MM-DD`` names the option."""
    if text is None:
        return None
    try:
        return dt.date.fromisoformat(text)
    except ValueError as exc:
        raise ConfigError(f"{option} {text!r}: not a date (YYYY-MM-DD; {exc})") from None


def source_releases(source: Path, disease: Disease) -> list[Release]:
    """The releases of a hub ``time-series.parquet``: its size and rows bounded from the
    parquet's metadata before it is read (:func:`read_hub_time_series`), its columns named
    when one is missing (``as_of`` too: each release is dated by it)."""
    file = hub_time_series_file(source)
    if not file.is_file():
        raise ValidationError(f"--source {file}: no such file (give a hub's "
                              "time-series.parquet or its folder)")
    frame = read_hub_time_series(file)
    if "as_of" not in frame.columns:
        raise ValidationError(f"--source {file}: missing column ['as_of'] (each release is "
                              f"dated by it); columns present: {list(frame.columns)}")
    return releases_of_time_series(frame, disease)


def require_releases(releases: list[Release], disease: Disease, start: dt.date | None,
                     end: dt.date | None, found: set[str] | None, where: str) -> None:
    """At least one Wednesday to replay; else the targets expected and those found, or the
    span, named."""
    if wednesdays(releases, start, end):
        return
    expected = ", ".join(disease_targets(disease))
    if not releases:
        held = ", ".join(sorted(found)) if found else "none"
        raise ValidationError(f"no release of the {disease} hub's targets ({expected}) in "
                              f"{where}; targets found: {held}. Import the hub's target data "
                              f"first (`flowcast data import <hub folder>`) or give its "
                              f"time-series.parquet")
    span = f"{releases[0].as_of} … {releases[-1].as_of}"
    raise ConfigError(f"no release to replay from {start or 'the first'} to "
                      f"{end or 'the last'}: the releases of {expected} in {where} are dated "
                      f"{span}")


def _targets_in(source: Path) -> set[str]:
    """The targets a (bounded, already judged) time series holds."""
    frame = read_hub_time_series(hub_time_series_file(source))
    return {str(t) for t in frame["target"].unique()}


def judge_replay_input(out: Path, disease: Disease, preset: str, seed: int, start: str | None,
                       end: str | None, source: Path | None, hub_config: Path | None
                       ) -> ReplayInput:
    """Every option of ``flowcast replay`` checked, in the order a user reads them; one
    :class:`~pipeline.errors.FlowcastError` naming the first problem, nothing written."""
    first, last = option_date(start, "--from"), option_date(end, "--to")
    writable_output_dir(out, option="--out")
    run = HubRunConfig.of_preset(preset, disease=disease, seed=seed,
                                 hub_config=str(hub_config) if hub_config else None)
    folder = run.hub_config_dir()
    if folder is not None:    # the option, $FLOWCAST_HUB_CONFIG or the default: judged alike
        hub_config_folder(folder, option="--hub-config" if hub_config else "hub-config")
    config = ReplayConfig(out, run, first, last)
    releases = source_releases(source, disease) if source else cached_releases(disease)
    if not wednesdays(releases, first, last):
        found = _targets_in(source) if source and not releases else None
        require_releases(releases, disease, first, last, found,
                         f"--source {source}" if source else "the cache")
    return ReplayInput(config, releases)


__all__ = ["ReplayInput", "judge_replay_input", "option_date", "require_releases",
           "source_releases"]
