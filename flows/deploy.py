"""Serve the deployments: ``weekly_forecast/sf-weekly`` (Mondays 06:00 America/Los_Angeles) and
the three CDC hubs' rounds, ``hub_forecast/hub-covid-weekly``, ``hub-flu-weekly`` (FluSight)
and ``hub-rsv-weekly``: each runs Monday to Thursday 15:00 America/New_York and makes its
round on the day its hub's calendar has one due (Wednesdays, a holiday's moved deadline); no
round off season.

Two ways to run the deployments, with the same schedules, parameters and tags:

* ``serve`` (this module): one long-running process registers the deployments and runs their
  flow runs itself; nothing else to set up.
* a work pool (``prefect.yaml`` at the repository root): ``prefect deploy --all`` registers them for the
  process work pool ``flowcast-process`` and a ``prefect worker`` (kept alive by
  ``deploy/flowcast-worker.service``) runs the flow runs; see docs/orchestration.md.

    PREFECT_API_URL=http://127.0.0.1:4200/api python -m flows.deploy [--preset default] ...
    prefect deployment run 'weekly_forecast/sf-weekly' [--param preset=tiny] --watch
    prefect deployment run 'hub_forecast/hub-covid-weekly' --watch

``serve`` registers (or updates) the deployments with the server at ``PREFECT_API_URL`` and then
runs their scheduled and manually triggered runs in subprocesses of this process until it gets
SIGINT/SIGTERM. We pass ``pause_on_shutdown=False``: Prefect's default pauses the deployment's
schedule when ``serve`` stops, so a restart of this process (a deploy, a reboot) would silently
stop the weekly runs until someone un-paused them.

The schedules are written with an explicit IANA timezone so 06:00 stays 06:00 local time across
daylight-saving changes (a plain cron string would be read in UTC).
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass

from prefect import serve as serve_deployments
from prefect.schedules import Cron, Schedule

from flows.hub_forecast import hub_forecast
from flows.weekly_forecast import FORECAST_PRESETS_CHOICES, weekly_forecast

WORK_POOL = "flowcast-process"  # prefect.yaml's process work pool


@dataclass(frozen=True)
class DeploymentSpec:
    """One scheduled deployment, as prefect.yaml and ``serve`` both register it."""

    name: str
    flow_name: str
    entrypoint: str
    cron: str
    timezone: str
    tags: tuple[str, ...]
    description: str

    @property
    def full_name(self) -> str:
        return f"{self.flow_name}/{self.name}"

    def schedule(self) -> Schedule:
        return Cron(self.cron, timezone=self.timezone)


SF_WEEKLY = DeploymentSpec(
    name="sf-weekly", flow_name="weekly_forecast",
    entrypoint="flows/weekly_forecast.py:weekly_forecast",
    cron="0 6 * * 1", timezone="America/Los_Angeles",      # Mondays 06:00
    tags=("flowcast", "san-francisco", "weekly"),
    description="Weekly San Francisco SIR forecast with conditional normalizing flows.")
# The hubs' rounds are due Wednesdays 23:59 US Eastern, except where a hub moved a deadline for a
# holiday (a Thursday in 2024, Monday 2025-12-29): each hub deployment runs at 15:00 US Eastern
# on every day a deadline has fallen on (Monday to Thursday), after NHSN's release, with hours
# left for a retry, and makes a round only on the day its hub's calendar has one due
# (``deadline_only``: tasks.json's rounds and pipeline.outputs.hub_calendar's moved deadlines);
# the other days, and FluSight's and the RSV hub's off season, end at once with "no round due
# today" (rc 0, nothing written).
HUB_CRON = "0 15 * * 1-4"


def hub_deployment(disease: str, description: str) -> DeploymentSpec:
    """The deployment of one hub's round (``hub-<disease>-weekly``)."""
    return DeploymentSpec(name=f"hub-{disease}-weekly", flow_name="hub_forecast",
                          entrypoint="flows/hub_forecast.py:hub_forecast", cron=HUB_CRON,
                          timezone="America/New_York",
                          tags=("flowcast", "forecast-hub", disease, "weekly"),
                          description=description)


HUB_COVID_WEEKLY = hub_deployment(
    "covid", "This week's CDC COVID-19 Forecast Hub round: NHSN admissions and the ED share "
             "for the US and every state.")
HUB_FLU_WEEKLY = hub_deployment(
    "flu", "This week's CDC FluSight round (in season): NHSN influenza admissions, their rate "
           "change and peak, for the US and every state.")
HUB_RSV_WEEKLY = hub_deployment(
    "rsv", "This week's CDC RSV Forecast Hub round (in season): NHSN RSV admissions and the "
           "NSSP ED share for the US and every state.")
HUB_DEPLOYMENTS = {"covid": HUB_COVID_WEEKLY, "flu": HUB_FLU_WEEKLY, "rsv": HUB_RSV_WEEKLY}
DEPLOYMENTS = (SF_WEEKLY, HUB_COVID_WEEKLY, HUB_FLU_WEEKLY, HUB_RSV_WEEKLY)


def deployment_parameters(args: argparse.Namespace) -> dict[str, object]:
    """The sf-weekly deployment's stored parameters (a triggered run may override any)."""
    params: dict[str, object] = {"preset": args.preset, "data_source": args.data_source,
                                 "output_dir": args.output_dir, "seed": args.seed}
    if args.encoder:
        params["encoder"] = args.encoder
    return params


def hub_parameters(args: argparse.Namespace, disease: str = "covid") -> dict[str, object]:
    """A hub deployment's stored parameters (hub-covid-weekly, hub-flu-weekly,
    hub-rsv-weekly): a round only on the day its hub has one due."""
    return {"disease": disease, "data_source": args.data_source,
            "output_dir": args.output_dir, "seed": args.seed, "deadline_only": True}


def serve(args: argparse.Namespace) -> None:
    """Register the chosen deployments and run them until stopped (``--limit`` concurrent runs:
    runs share one model cache and one output folder, so they should not overlap)."""
    flows = {SF_WEEKLY.name: (weekly_forecast, deployment_parameters(args)),
             **{spec.name: (hub_forecast, hub_parameters(args, disease))
                for disease, spec in HUB_DEPLOYMENTS.items()}}
    chosen = [spec for spec in DEPLOYMENTS if spec.name in args.deployments]
    serve_deployments(*[flows[spec.name][0].to_deployment(
        name=spec.name, schedules=[spec.schedule()], parameters=flows[spec.name][1],
        tags=list(spec.tags), description=spec.description) for spec in chosen],
        pause_on_shutdown=False, limit=args.limit)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m flows.deploy", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--deployments", nargs="+", default=[d.name for d in DEPLOYMENTS],
                        choices=[d.name for d in DEPLOYMENTS], help="which to serve (all)")
    parser.add_argument("--preset", default="default", choices=FORECAST_PRESETS_CHOICES)
    parser.add_argument("--encoder", default=None, help="override the preset's context encoder")
    parser.add_argument("--data-source", default="live", choices=["live", "cache"],
                        help="live: fetch DataSF / data.cdc.gov (cache fallback); cache: "
                             "offline")
    parser.add_argument("--output-dir", default="reports")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--limit", type=int, default=1, help="concurrent runs of this server")
    return parser


def main(argv: list[str] | None = None) -> int:
    serve(build_parser().parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
