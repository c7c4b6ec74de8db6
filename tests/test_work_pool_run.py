"""Integration: prefect.yaml deployed to a process work pool, run by a real worker.

Starts `prefect server start` on 127.0.0.1 (temporary PREFECT_HOME, free port), creates the
`flowcast-process` work pool, runs `prefect deploy --all` from prefect.yaml (both deployments),
starts `prefect worker`, triggers `prefect deployment run` of sf-weekly (tiny preset, offline
cache, `--watch`, bounded) and checks the run's markdown summary artifact. DataSF points at a
closed local port, so the run falls back to the cache: it must finish as "Completed (stale
data)", carry the `stale-data` tag and say so in the artifact. Every process started here is stopped (its whole process group) in a `finally`.
"""
from __future__ import annotations

import os
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from tests.test_deployment_run import api_post, free_port, start, start_prefect_server, stop

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(240)]

REPO = Path(__file__).resolve().parents[1]
PREFECT = str(Path(sys.executable).with_name("prefect"))
POOL = "flowcast-process"


def _cli(args: list[str], env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run([PREFECT, *args], env=env, cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def _api_get(api: str, path: str) -> object:
    import json

    with urllib.request.urlopen(f"{api}{path}", timeout=10) as r:
        return json.loads(r.read())


def test_prefect_yaml_deploy_worker_run_and_stale_artifact(tmp_path, datasf_dir):
    from flows.weekly_forecast import ARTIFACT_SUMMARY, STALE_STATE_NAME, STALE_TAG
    from pipeline.forecast.sources import import_exports

    port, closed = free_port(), free_port()
    api = f"http://127.0.0.1:{port}/api"
    data_dir = tmp_path / "data"
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect-home"), "PREFECT_API_URL": api,
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1",
           "PREFECT_WORKER_QUERY_SECONDS": "1", "PREFECT_WORKER_PREFETCH_SECONDS": "5",
           "PREFECT_LOGGING_LEVEL": "INFO", "FLOWCAST_DATA_DIR": str(data_dir),
           # DataSF unreachable (nothing listens there): the run must use the cache, stale
           "FLOWCAST_DATASF_BASE_URL": f"https://127.0.0.1:{closed}",
           "PYTHONUNBUFFERED": "1"}
    os.environ["FLOWCAST_DATA_DIR"] = str(data_dir)  # the autouse fixture restores it
    import_exports([str(datasf_dir)])
    reports = tmp_path / "reports"
    yaml_before = (REPO / "prefect.yaml").read_bytes()
    procs: list[subprocess.Popen] = []
    try:
        procs.append(start_prefect_server(tmp_path, env, port, api))

        pool = _cli(["work-pool", "create", POOL, "--type", "process"], env, 60)
        assert pool.returncode == 0, pool.stdout + pool.stderr
        deploy = _cli(["--no-prompt", "deploy", "--all"], env, 120)
        assert deploy.returncode == 0, deploy.stdout[-3000:] + deploy.stderr[-3000:]
        assert (REPO / "prefect.yaml").read_bytes() == yaml_before  # deploy did not rewrite it
        deployments = api_post(api, "/deployments/filter",
                               {"deployments": {"name": {"any_": ["sf-weekly"]}}})
        assert len(deployments) == 1
        deployment = deployments[0]
        (hub,) = api_post(api, "/deployments/filter",
                          {"deployments": {"name": {"any_": ["hub-covid-weekly"]}}})
        assert hub["entrypoint"] == "flows/hub_forecast.py:hub_forecast"
        assert hub["work_pool_name"] == POOL
        assert (hub["schedules"][0]["schedule"]["cron"],
                hub["schedules"][0]["schedule"]["timezone"]) == ("0 15 * * 1-4",
                                                                 "America/New_York")
        assert hub["parameters"]["deadline_only"] is True
        assert deployment["work_pool_name"] == POOL
        assert deployment["entrypoint"] == "flows/weekly_forecast.py:weekly_forecast"
        schedule = deployment["schedules"][0]["schedule"]
        assert (schedule["cron"], schedule["timezone"]) == ("0 6 * * 1", "America/Los_Angeles")
        # the UI form explains every parameter (docstring Args)
        form = deployment["parameter_openapi_schema"]["properties"]
        assert all(form[name].get("description") for name in
                   ("preset", "encoder", "data_source", "import_from", "output_dir", "seed",
                    "retrain")), form

        worker_log = tmp_path / "worker.log"
        procs.append(start([PREFECT, "worker", "start", "--pool", POOL, "--limit", "1"], env,
                           worker_log))
        run = _cli(["deployment", "run", "weekly_forecast/sf-weekly",
                    "--param", "preset=tiny", "--param", f"output_dir={reports}",
                    "--watch", "--watch-timeout", "170"], env, 190)
        output = run.stdout + run.stderr
        assert run.returncode == 0, output[-3000:] + worker_log.read_text()[-4000:]
        assert "COMPLETED" in output.upper()

        runs = api_post(api, "/flow_runs/filter",
                        {"deployments": {"id": {"any_": [deployment["id"]]}}})
        assert len(runs) >= 1
        flow_run = next(r for r in runs if r["parameters"].get("preset") == "tiny")
        assert flow_run["state"]["type"] == "COMPLETED"
        assert flow_run["state"]["name"] == STALE_STATE_NAME
        assert STALE_TAG in flow_run["tags"]

        artifacts = api_post(api, "/artifacts/filter",
                             {"artifacts": {"key": {"any_": [ARTIFACT_SUMMARY]}}})
        assert artifacts, "no summary artifact"
        summary = artifacts[0]
        assert summary["type"] == "markdown" and summary["flow_run_id"] == flow_run["id"]
        assert "stale data" in summary["data"].lower() and "2022-03-02" in summary["data"]
        assert (reports / "2022-03-02" / "report.html").stat().st_size > 0
        assert _api_get(api, f"/work_pools/{POOL}")["type"] == "process"
    finally:
        for proc in reversed(procs):
            stop(proc)
    assert all(p.poll() is not None for p in procs)
