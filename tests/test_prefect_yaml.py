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
                  deploy.HUB_COVID_WEEKLY.name: deploy.hub_parameters(args),
                  deploy.HUB_FLU_WEEKLY.name: deploy.hub_parameters(args, "flu")}
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
    # the hub's rounds are due Wednesdays: the run comes the same afternoon, US Eastern
    assert (deploy.HUB_COVID_WEEKLY.cron, deploy.HUB_COVID_WEEKLY.timezone) == (
        "0 15 * * 3", "America/New_York")
    # FluSight's: the same Wednesday afternoon, October to May only: every round its own
    # tasks.json lists is due (reference date − 3) on a Wednesday of those months
    import datetime as dt

    from pipeline.outputs.hub_tasks import hub_round_ids
    from pipeline.outputs.hubverse_validation import load_tasks_config
    tasks = load_tasks_config(REPO.parent / "shared" / "data" / "flusight" / "hub-config"
                              / "tasks.json")
    dues = [dt.date.fromisoformat(r) - dt.timedelta(days=3) for r in hub_round_ids(tasks)]
    months = {int(m) for m in deploy.HUB_FLU_WEEKLY.cron.split()[3].split(",")}
    assert len(dues) == 89 and all(d.weekday() == 2 and d.month in months for d in dues)
    assert months == {d.month for d in dues}
    assert (deploy.HUB_FLU_WEEKLY.cron, deploy.HUB_FLU_WEEKLY.timezone) == (
        "0 15 * 10,11,12,1,2,3,4,5 3", "America/New_York")
    assert deploy.hub_parameters(args, "flu")["disease"] == "flu"


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
