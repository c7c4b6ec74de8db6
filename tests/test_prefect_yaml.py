"""prefect.yaml and flows/deploy.py describe the same deployment; the flow documents its
parameters for the UI form; the systemd units point at the right commands."""
from __future__ import annotations

import inspect
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def test_prefect_yaml_matches_the_served_deployment():
    from flows import deploy

    config = yaml.safe_load((REPO / "prefect.yaml").read_text())
    (deployment,) = config["deployments"]
    assert config["prefect-version"] == "3.8.8"
    assert deployment["name"] == deploy.DEPLOYMENT_NAME
    assert deployment["entrypoint"] == "flows/weekly_forecast.py:weekly_forecast"
    (schedule,) = deployment["schedules"]
    assert (schedule["cron"], schedule["timezone"]) == (deploy.CRON, deploy.TIMEZONE)
    assert deployment["tags"] == list(deploy.TAGS)
    assert deployment["concurrency_limit"] == 1
    assert deployment["work_pool"]["name"] == deploy.WORK_POOL
    args = deploy.build_parser().parse_args([])
    assert deployment["parameters"] == deploy.deployment_parameters(args)


def test_flow_parameters_are_documented():
    from flows.weekly_forecast import weekly_forecast

    doc = weekly_forecast.fn.__doc__ or ""
    for name in inspect.signature(weekly_forecast.fn).parameters:
        assert f"\n        {name}: " in doc, name


def test_systemd_units():
    worker = (REPO / "deploy" / "flowcast-worker.service").read_text()
    assert "ExecStart=/opt/flowcast/.venv/bin/prefect worker start --pool flowcast-process" \
        in worker
    assert "Restart=always" in worker and "PREFECT_API_URL=http://127.0.0.1:4200/api" in worker
    server = (REPO / "deploy" / "prefect-server.service").read_text()
    assert "server start --host 127.0.0.1 --port 4200" in server
