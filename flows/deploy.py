"""Serve the ``weekly_forecast/sf-weekly`` deployment: Mondays 06:00 America/Los_Angeles.

Two ways to run the deployment, with the same schedule, parameters and tags:

* ``serve`` (this module): one long-running process registers the deployment and runs its flow
  runs itself; nothing else to set up.
* a work pool (``prefect.yaml`` at the repository root): ``prefect deploy`` registers it for the
  process work pool ``flowcast-process`` and a ``prefect worker`` (kept alive by
  ``deploy/flowcast-worker.service``) runs the flow runs; see docs/orchestration.md.

    PREFECT_API_URL=http://127.0.0.1:4200/api python -m flows.deploy [--preset default] ...
    prefect deployment run 'weekly_forecast/sf-weekly' [--param preset=tiny] --watch

``serve`` registers (or updates) the deployment with the server at ``PREFECT_API_URL`` and then
runs its scheduled and manually triggered runs in subprocesses of this process until it gets
SIGINT/SIGTERM. We pass ``pause_on_shutdown=False``: Prefect's default pauses the deployment's
schedule when ``serve`` stops, so a restart of this process (a deploy, a reboot) would silently
stop the weekly runs until someone un-paused them.

The schedule is written with an explicit IANA timezone so 06:00 stays 06:00 local time across
daylight-saving changes (a plain cron string would be read in UTC).
"""
from __future__ import annotations

import argparse
import sys

from prefect.schedules import Cron, Schedule

from flows.weekly_forecast import FORECAST_PRESETS_CHOICES, weekly_forecast

DEPLOYMENT_NAME = "sf-weekly"
FLOW_NAME = "weekly_forecast"
FULL_NAME = f"{FLOW_NAME}/{DEPLOYMENT_NAME}"
CRON = "0 6 * * 1"  # Mondays 06:00
TIMEZONE = "America/Los_Angeles"
TAGS = ("flowcast", "san-francisco", "weekly")
WORK_POOL = "flowcast-process"  # prefect.yaml's process work pool


def weekly_schedule() -> Schedule:
    return Cron(CRON, timezone=TIMEZONE)


def deployment_parameters(args: argparse.Namespace) -> dict[str, object]:
    """The default parameters stored on the deployment (a triggered run may override any)."""
    params: dict[str, object] = {"preset": args.preset, "data_source": args.data_source,
                              "output_dir": args.output_dir, "seed": args.seed}
    if args.encoder:
        params["encoder"] = args.encoder
    return params


def serve(parameters: dict[str, object], *, limit: int = 1) -> None:
    """Register the deployment and run it until stopped (``limit`` concurrent runs: weekly
    runs share one model cache and one output folder, so they should not overlap)."""
    weekly_forecast.serve(
        name=DEPLOYMENT_NAME,
        schedules=[weekly_schedule()],
        parameters=parameters,
        pause_on_shutdown=False,
        limit=limit,
        tags=list(TAGS),
        description="Weekly San Francisco SIR forecast with conditional normalizing flows.",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m flows.deploy", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="default", choices=FORECAST_PRESETS_CHOICES)
    parser.add_argument("--encoder", default=None, help="override the preset's context encoder")
    parser.add_argument("--data-source", default="live", choices=["live", "cache"],
                        help="live: fetch DataSF (cache fallback); cache: offline")
    parser.add_argument("--output-dir", default="reports")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--limit", type=int, default=1, help="concurrent runs of this server")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    serve(deployment_parameters(args), limit=args.limit)
    return 0


if __name__ == "__main__":
    sys.exit(main())
