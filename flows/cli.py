"""The ``flowcast`` entry point: the library's commands (:mod:`pipeline.cli`) plus
``flowcast forecast``, which runs the weekly SF (``--county NAME``: a California county's)
forecast flow once (Prefect's local ephemeral API,
or the server at ``PREFECT_API_URL``; ``make forecast`` calls it). It lives with the flows
because it runs one: the library never imports Prefect."""
from __future__ import annotations

import os
import sys
from pathlib import Path
from enum import Enum
from typing import TYPE_CHECKING, Annotated, NoReturn, TypeAlias, TypeVar

import typer

from pipeline.cli import app, build_command
from pipeline.cli import main as library_main
from pipeline.cli.choices import DataSource, Encoder, choices_enum, value
from pipeline.names import FORECAST_PRESET_NAMES

if TYPE_CHECKING:
    from prefect.client.schemas.objects import State

    ForecastPreset: TypeAlias = Enum  # built from the preset names at run time (see choices)
else:
    ForecastPreset = choices_enum("ForecastPreset", FORECAST_PRESET_NAMES)


@app.command("forecast")
def forecast_command(
    preset: Annotated[ForecastPreset, typer.Option(
        help="default: the product (about 10 min from scratch, well under a minute with cached models); "
             "tiny: a seconds-long smoke run")] = ForecastPreset("default"),
    encoder: Annotated[Encoder | None, typer.Option(
        help="context encoder (default: the preset's)")] = None,
    county: Annotated[str | None, typer.Option(
        metavar="NAME", help="a California county (e.g. 'Los Angeles'), forecast from CDPH's "
                             "county data on its own population; default: San Francisco from "
                             "DataSF")] = None,
    data_source: Annotated[DataSource, typer.Option(
        help="live: DataSF (CDPH for --county) with cache fallback; cache: offline; import: "
             "the --import-from exports first")] = DataSource("live"),
    import_from: Annotated[list[Path] | None, typer.Option(
        metavar="PATH", help="DataSF CSV export or folder (CDPH covid19cases_test.csv for "
                             "--county) for --data-source import (repeat the option for "
                             "several)")] = None,
    output_dir: Annotated[Path, typer.Option(help="reports folder")] = Path("reports"),
    seed: Annotated[int, typer.Option(help="seed of every random step")] = 0,
    retrain: Annotated[bool, typer.Option("--retrain", help="ignore the cached model")] = False,
    hub: Annotated[str | None, typer.Option(
        metavar="DISEASE", help="make this week's round of the CDC COVID-19 Forecast Hub "
                                "(covid; NHSN admissions and the NSSP ED share of the US, the "
                                "states, DC and PR) instead of the San Francisco forecast")] = None,
    hub_config: Annotated[Path | None, typer.Option(
        help="the hub's hub-config folder (its tasks.json validates the round file); default: "
             "$FLOWCAST_HUB_CONFIG or ../shared/data/nhsn/hub-config")] = None,
) -> None:
    """Run the weekly San Francisco (or --county) forecast once, or with --hub this week's hub
    round, and print where the report went."""
    from pipeline.data.california.counties import california_county
    from pipeline.errors import ConfigError

    if hub is not None:
        _hub_round(hub, value(data_source), value(preset), output_dir, seed, hub_config)
        return

    from pipeline.cli.hub_options import writable_output_dir
    from pipeline.errors import OfflineError
    from pipeline.forecast.config import DataSourceConfig
    from pipeline.forecast.sources import require_offline_data
    # a misspelt county, an unwritable --output-dir or an empty cache offline fails here,
    # before Prefect starts
    try:
        county = california_county(county) if county is not None else None
        writable_output_dir(output_dir)
        if value(data_source) == "cache":
            require_offline_data(DataSourceConfig(kind="cache", county=county))
    except (ConfigError, OfflineError) as error:
        typer.secho(f"error: {error}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from None

    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    from flows.server_guard import start_temporary_server

    start_temporary_server()  # comes up while the flow's module imports
    from flows.weekly_forecast import local_api, weekly_forecast  # imports Prefect: when run

    with local_api():
        state = weekly_forecast(preset=value(preset), encoder=value(encoder),
                                data_source=value(data_source),
                                import_from=[str(p) for p in import_from] if import_from else None,
                                output_dir=str(output_dir), seed=seed, retrain=retrain,
                                county=county, return_state=True)
    result = _outcome(state, "the forecast run")
    typer.echo(f"report: {result['output_dir']}")
    if result["data_stale"]:
        typer.secho(f"warning: {'DataSF' if county is None else 'the CHHS portal (CDPH)'} "
                    "could not be reached; the forecast used cached data "
                    f"(run state '{state.name}')", fg=typer.colors.YELLOW, err=True)


# what a flow returns: its outcome (a dict), or the State it ends in (the weekly run's stale data)
Returned = TypeVar("Returned")


def _outcome(state: State[Returned], what: str) -> dict[str, object]:
    """The flow run's result; a failed run: one line naming the problem (the log has the
    rest), exit 1."""
    from pipeline.errors import FlowcastError

    if not state.is_completed():
        try:
            state.result()
        except FlowcastError as error:
            typer.secho(f"error: {error}", fg=typer.colors.RED, err=True)
        except Exception as error:  # noqa: BLE001 - a failed run: one line, the log has the rest
            typer.secho(f"error: {what} failed ({type(error).__name__}: {error})",
                        fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1)
    result = state.result()
    assert isinstance(result, dict)  # the flow's outcome (a stale run's Completed state holds it)
    return result


def _hub_round(disease: str, data_source: str, preset: str, output_dir: Path, seed: int,
               hub_config: Path | None) -> None:
    """``flowcast forecast --hub DISEASE``: the hub_forecast flow once."""
    if (disease not in ("covid", "flu", "rsv") or data_source not in ("live", "cache")
            or preset not in ("default", "tiny")):
        typer.secho(f"error: --hub takes covid, flu or rsv (got {disease!r}) with "
                    f"--data-source live or cache (got {data_source!r}) and --preset default "
                    f"or tiny (got {preset!r}); hub data are imported with `flowcast data "
                    "import <hub folder>`", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2)
    from pipeline.cli.hub_options import hub_config_folder, writable_output_dir
    from pipeline.errors import ConfigError
    from pipeline.hub_round.run import HubRunConfig
    try:  # every option checked before Prefect starts (issue 39)
        writable_output_dir(output_dir)
        # the option, $FLOWCAST_HUB_CONFIG or the default: each tasks.json judged (issue 49)
        folder = hub_config or HubRunConfig(disease=disease).hub_config_dir()
        if folder is not None:
            hub_config_folder(folder, option="--hub-config" if hub_config else "hub-config")
    except ConfigError as error:
        typer.secho(f"error: {error}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from None
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    from flows.server_guard import start_temporary_server

    start_temporary_server()
    from flows.hub_forecast import hub_forecast
    from flows.weekly_forecast import local_api

    with local_api():
        state = hub_forecast(disease=disease, data_source=data_source,
                             output_dir=str(output_dir),
                             hub_config=str(hub_config) if hub_config else None, seed=seed,
                             preset=preset, return_state=True)
    result = _outcome(state, "the hub round")
    if result.get("no_round"):        # e.g. FluSight off season: said clearly, rc 0
        typer.echo(f"no hub round: {result['no_round']}")
        return
    typer.echo(f"hub round {result['reference_date']}: {result['model_output']}")
    typer.echo(f"report: {result['output_dir']}")
    if result["data_stale"]:
        typer.secho("warning: the round used cached data for a target (data.cdc.gov "
                    "unreachable, its release refused or held, or the cache lock held); the "
                    "report's data notes say which and why",
                    fg=typer.colors.YELLOW, err=True)
    if result.get("degraded"):
        typer.secho(f"warning: the round is degraded ({state.message})",
                    fg=typer.colors.YELLOW, err=True)


@app.command("replay")
def replay_command(
    out: Annotated[Path, typer.Option(
        help="the replay's folder: model-output/<model>/ (every round's file), rounds/ (each "
             "round's run folder: report, summary), data/ (its cache, model store, memo), "
             "replay.json (the summary); a rerun replays only the Wednesdays not done yet")],
    hub: Annotated[str, typer.Option(
        metavar="DISEASE", help="the hub's disease (covid)")] = "covid",
    start: Annotated[str | None, typer.Option(
        "--from", metavar="YYYY-MM-DD", help="first Wednesday (default: the first release)")
    ] = None,
    end: Annotated[str | None, typer.Option(
        "--to", metavar="YYYY-MM-DD", help="last Wednesday (default: the last release)")
    ] = None,
    source: Annotated[Path | None, typer.Option(
        metavar="PARQUET", help="a hub's time-series.parquet to take the releases from "
                                "(default: every release in the cache)")] = None,
    preset: Annotated[str, typer.Option(help="default or tiny")] = "default",
    seed: Annotated[int, typer.Option(help="seed of every random step")] = 0,
    hub_config: Annotated[Path | None, typer.Option(
        help="the hub's hub-config folder; default: $FLOWCAST_HUB_CONFIG or "
             "../shared/data/nhsn/hub-config")] = None,
) -> None:
    """Replay the hub's Wednesdays: every release in order, from an empty model store, each
    week the deployment's run (the hub_forecast flow) offline into OUT."""
    from pipeline.errors import FlowcastError
    from pipeline.hub_round import replay as rp
    from pipeline.cli.replay_input import judge_replay_input

    if hub not in ("covid", "flu", "rsv") or preset not in ("default", "tiny"):
        typer.secho(f"error: --hub takes covid, flu or rsv (got {hub!r}) and --preset default "
                    f"or tiny (got {preset!r})", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2)
    try:  # every option and the source judged before Prefect starts (issue 49)
        judged = judge_replay_input(out, hub, preset, seed, start, end, source, hub_config)
    except (FlowcastError, OSError) as error:
        typer.secho(f"error: {error}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=1) from None
    config, releases, run = judged.config, judged.releases, judged.config.run
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    from flows.server_guard import start_temporary_server

    start_temporary_server()
    from flows.hub_forecast import flow_step
    from flows.weekly_forecast import local_api

    rp.copy_hub_config(run.hub_config_dir(), out)
    with local_api():
        summary = rp.replay(config, releases, flow_step())
    degraded, no_round, replaced = summary["degraded"], summary["no_round"], summary["replaced"]
    assert isinstance(degraded, list) and isinstance(no_round, list)
    assert isinstance(replaced, list)
    typer.echo(f"replay: {summary['rounds_due']} rounds due, {summary['rounds_published']} "
               f"published ({len(degraded)} degraded, {len(replaced)} replacing an earlier "
               f"file of their round), {summary['rounds_failed']} failed; {len(no_round)} "
               f"day(s) with no hub round open (off season) → {out / rp.SUMMARY_NAME}")
    if summary["rounds_failed"]:
        raise typer.Exit(code=1)


def main() -> NoReturn:
    """The console script: the command, then :func:`flows.server_guard.exit_now` (its exit
    hooks, without the interpreter's 2–3 s teardown after a forecast run)."""
    from flows.server_guard import exit_now

    try:
        library_main()
        code = 0
    except SystemExit as stop:
        if isinstance(stop.code, str):
            print(stop.code, file=sys.stderr)
        code = stop.code if isinstance(stop.code, int) else int(stop.code is not None)
    exit_now(code)


__all__ = ["app", "build_command", "main"]


if __name__ == "__main__":
    main()
