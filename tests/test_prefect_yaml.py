"""prefect.yaml and flows/deploy.py describe the same deployments; the flow documents its
parameters for the UI form; the systemd units point at the right commands."""
from __future__ import annotations

import inspect
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def test_prefect_yaml_matches_the_served_deployments():
    from flows import deploy

    config = yaml.safe_load((REPO / "prefect.yaml").read_text())
    assert config["prefect-version"] == "3.8.8"
    by_name = {d["name"]: d for d in config["deployments"]}
    assert sorted(by_name) == sorted(spec.name for spec in deploy.DEPLOYMENTS)
    args = deploy.build_parser().parse_args([])
    parameters = {deploy.SF_WEEKLY.name: deploy.deployment_parameters(args),
                  **{spec.name: deploy.hub_parameters(args, disease)
                     for disease, spec in deploy.HUB_DEPLOYMENTS.items()}}
    for spec in deploy.DEPLOYMENTS:
        deployment = by_name[spec.name]
        assert deployment["entrypoint"] == spec.entrypoint
        (schedule,) = deployment["schedules"]
        assert (schedule["cron"], schedule["timezone"]) == (spec.cron, spec.timezone)
        assert deployment["tags"] == list(spec.tags)
        assert deployment["description"] == spec.description
        assert deployment["concurrency_limit"] == 1
        assert deployment["work_pool"]["name"] == deploy.WORK_POOL
        assert deployment["parameters"] == parameters[spec.name]
    assert (deploy.SF_WEEKLY.cron, deploy.SF_WEEKLY.timezone) == ("0 6 * * 1",
                                                                  "America/Los_Angeles")
    # the three hubs, each its own deployment, each making a round only on its deadline
    assert {spec.name for spec in deploy.HUB_DEPLOYMENTS.values()} == {
        "hub-covid-weekly", "hub-flu-weekly", "hub-rsv-weekly"}
    assert all(parameters[spec.name]["deadline_only"] is True
               and parameters[spec.name]["disease"] == disease
               for disease, spec in deploy.HUB_DEPLOYMENTS.items())
    # every deadline of every hub's calendar (moved ones included) falls on a day the
    # schedule runs: Monday (1) to Thursday (4), 15:00 US Eastern
    from pipeline.hub_round.run import HubRunConfig
    days = {int(d) for d in range(1, 5)}
    for disease, spec in deploy.HUB_DEPLOYMENTS.items():
        assert (spec.cron, spec.timezone) == ("0 15 * * 1-4", "America/New_York")
        calendar = HubRunConfig(disease=disease).calendar()   # type: ignore[arg-type]
        assert calendar is not None
        deadlines = [calendar.deadline(r) for r in calendar.references]
        assert all(d.isoweekday() in days for d in deadlines), disease


def test_flow_parameters_are_documented():
    from flows.hub_forecast import hub_forecast
    from flows.weekly_forecast import weekly_forecast

    for flow in (weekly_forecast, hub_forecast):
        doc = flow.fn.__doc__ or ""
        for name in inspect.signature(flow.fn).parameters:
            assert f"\n        {name}: " in doc, (flow.name, name)


def test_systemd_units():
    worker = (REPO / "deploy" / "flowcast-worker.service").read_text()
    assert "ExecStart=/opt/flowcast/.venv/bin/prefect worker start --pool flowcast-process" \
        in worker
    assert "Restart=always" in worker and "PREFECT_API_URL=http://127.0.0.1:4200/api" in worker
    server = (REPO / "deploy" / "prefect-server.service").read_text()
    assert "server start --host 127.0.0.1 --port 4200" in server
