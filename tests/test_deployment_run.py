"""Integration: one real Prefect server on 127.0.0.1 (`prefect server start`, temporary
PREFECT_HOME, free port) and the two ways the deployments run on it.

* served (flows/deploy.py): `weekly_forecast/sf-weekly` and the hubs' rounds registered with
  their schedules, not paused; a manual `prefect deployment run` of `hub-covid-weekly`
  (`--watch`, bounded) on a day its hub has no round ends COMPLETED at once, as the deployment
  does on every day but a deadline.
* deployed from prefect.yaml to a process work pool and run by a real `prefect worker`:
  `prefect deployment run` of sf-weekly (tiny preset, offline cache, `--watch`, bounded) with
  DataSF pointed at a closed local port, so the run falls back to the cache: it must finish as
  "Completed (stale data)", carry the `stale-data` tag and say so in its summary artifact; its
  report is written.

The two share the server (its start is most of a test's seconds). Every process started here
is stopped (its whole process group) in a `finally`.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(240)]

REPO = Path(__file__).resolve().parents[1]
PREFECT = str(Path(sys.executable).with_name("prefect"))
POOL = "flowcast-process"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(cmd: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    return subprocess.Popen(cmd, env=env, cwd=REPO, stdout=log.open("wb"),
                            stderr=subprocess.STDOUT, start_new_session=True)


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM the process group, wait, then SIGKILL what is left."""
    if proc.poll() is not None:
        return
    for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 5)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait)
            return
        except subprocess.TimeoutExpired:
            continue


def wait_healthy(api: str, proc: subprocess.Popen, log: Path, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"prefect server exited early:\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(f"{api}/health", timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.5)
    pytest.fail(f"prefect server not healthy after {timeout} s:\n{log.read_text()[-3000:]}")


def start_prefect_server(tmp_path: Path, env: dict[str, str], port: int,
                         api: str) -> subprocess.Popen:
    """A Prefect server on 127.0.0.1:``port``, healthy (its log in ``tmp_path/server.log``)."""
    server_log = tmp_path / "server.log"
    proc = start([PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(port),
                  "--analytics-off"], env, server_log)
    # 120 s, as the test harness's own bound (conftest): the first server of a fresh venv
    # compiles prefect's server modules as it imports them, on a 2-core box shared with the
    # other test worker and pyright (60 s ran out once beside a `make forecast`)
    wait_healthy(api, proc, server_log, 120)
    return proc


def api_post(api: str, path: str, body: dict) -> object:
    req = urllib.request.Request(f"{api}{path}", data=json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json"}, method="POST")
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())


@dataclass(frozen=True)
class Server:
    """The module's Prefect server: its API, the environment every process here runs with, and a
    scratch folder."""

    api: str
    env: dict[str, str]
    root: Path


@pytest.fixture(scope="module")
def server(tmp_path_factory, datasf_dir):
    """A Prefect server, and a data folder holding the recorded DataSF exports (imported)."""
    from pipeline.data.core.cache import data_folder
    from pipeline.forecast.sources import import_exports

    root = tmp_path_factory.mktemp("prefect-server")
    port, closed = free_port(), free_port()
    api = f"http://127.0.0.1:{port}/api"
    data_dir = root / "data"
    env = {**os.environ, "PREFECT_HOME": str(root / "prefect-home"), "PREFECT_API_URL": api,
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1",
           "PREFECT_RUNNER_POLL_FREQUENCY": "1", "PREFECT_WORKER_QUERY_SECONDS": "1",
           "PREFECT_WORKER_PREFETCH_SECONDS": "5", "PREFECT_LOGGING_LEVEL": "INFO",
           "FLOWCAST_DATA_DIR": str(data_dir),
           # DataSF unreachable (nothing listens there): a run must use the cache, stale
           "FLOWCAST_DATASF_BASE_URL": f"https://127.0.0.1:{closed}",
           "PYTHONUNBUFFERED": "1"}
    with data_folder(data_dir):
        import_exports([str(datasf_dir)])
    proc = start_prefect_server(root, env, port, api)
    try:
        yield Server(api, env, root)
    finally:
        stop(proc)
    assert proc.poll() is not None


def _cli(args: list[str], env: dict[str, str], timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run([PREFECT, *args], env=env, cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def _api_get(api: str, path: str) -> object:
    with urllib.request.urlopen(f"{api}{path}", timeout=10) as r:
        return json.loads(r.read())


def test_served_deployments_are_scheduled_and_run(server, tmp_path):
    api, env = server.api, server.env
    serve_log = tmp_path / "serve.log"
    serving = start([sys.executable, "-m", "flows.deploy", "--preset", "tiny",
                     "--data-source", "cache", "--output-dir", str(tmp_path / "reports")],
                    env, serve_log)
    try:
        # serve registers the deployments one after the other: wait for both (on a loaded box
        # the hub's came a moment after the SF one, and a lookup in between found none)
        deadline = time.monotonic() + 40
        registered: dict[str, dict] = {}
        while time.monotonic() < deadline and len(registered) < 2:
            found = api_post(api, "/deployments/filter", {"deployments": {"name": {
                "any_": ["sf-weekly", "hub-covid-weekly"]}}})
            registered = {d["name"]: d for d in found}
            time.sleep(0.5)
        assert set(registered) == {"sf-weekly", "hub-covid-weekly"}, \
            f"deployments registered: {sorted(registered)}\n{serve_log.read_text()[-3000:]}"
        assert len(found) == 2          # one of each
        deployment = registered["sf-weekly"]
        schedule = deployment["schedules"][0]["schedule"]
        assert schedule["cron"] == "0 6 * * 1"
        assert schedule["timezone"] == "America/Los_Angeles"
        assert deployment["paused"] is False
        # the hub round's deployment is served beside it, Monday to Thursday afternoons
        # (a round only on its hub's deadline: deadline_only)
        hub = registered["hub-covid-weekly"]
        hub_schedule = hub["schedules"][0]["schedule"]
        assert (hub_schedule["cron"], hub_schedule["timezone"]) == ("0 15 * * 1-4",
                                                                    "America/New_York")
        assert hub["paused"] is False and hub["parameters"]["disease"] == "covid"
        assert hub["parameters"]["deadline_only"] is True

        # a served run on a day the hub has no round open: COMPLETED, nothing written (the SF
        # forecast's own run is the worker test's below)
        run = _cli(["deployment", "run", "hub_forecast/hub-covid-weekly",
                    "--param", "deadline_only=false", "--param", "due=2031-01-08",
                    "--watch", "--watch-timeout", "150"], env, 170)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:] + \
            serve_log.read_text()[-3000:]
        assert "COMPLETED" in (run.stdout + run.stderr).upper()
        runs = api_post(api, "/flow_runs/filter",
                        {"deployments": {"id": {"any_": [hub["id"]]}}})
        manual = [r for r in runs if r["parameters"].get("due") == "2031-01-08"]
        assert manual and manual[0]["state"]["type"] == "COMPLETED"
        assert "has no round open on 2031-01-08" in serve_log.read_text()
        assert not (tmp_path / "reports").exists()
    finally:
        stop(serving)
    assert serving.poll() is not None


def test_prefect_yaml_deploy_worker_run_and_stale_artifact(server, tmp_path):
    from flows.weekly_forecast import ARTIFACT_SUMMARY, STALE_STATE_NAME, STALE_TAG

    api, env = server.api, server.env
    reports = tmp_path / "reports"
    yaml_before = (REPO / "prefect.yaml").read_bytes()
    pool = _cli(["work-pool", "create", POOL, "--type", "process"], env, 60)
    assert pool.returncode == 0, pool.stdout + pool.stderr
    deploy = _cli(["--no-prompt", "deploy", "--all"], env, 120)
    assert deploy.returncode == 0, deploy.stdout[-3000:] + deploy.stderr[-3000:]
    assert (REPO / "prefect.yaml").read_bytes() == yaml_before  # deploy did not rewrite it
    deployments = api_post(api, "/deployments/filter",
                           {"deployments": {"name": {"any_": ["sf-weekly"]}}})
    assert len(deployments) == 1
    deployment = deployments[0]
    hubs = {d["name"]: d for d in api_post(api, "/deployments/filter", {"deployments": {
        "name": {"any_": ["hub-covid-weekly", "hub-flu-weekly", "hub-rsv-weekly"]}}})}
    assert sorted(hubs) == ["hub-covid-weekly", "hub-flu-weekly", "hub-rsv-weekly"]
    for name, hub in hubs.items():
        assert hub["entrypoint"] == "flows/hub_forecast.py:hub_forecast", name
        assert hub["work_pool_name"] == POOL, name
        assert (hub["schedules"][0]["schedule"]["cron"],
                hub["schedules"][0]["schedule"]["timezone"]) == ("0 15 * * 1-4",
                                                                 "America/New_York"), name
        assert hub["parameters"]["deadline_only"] is True, name
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
    worker = start([PREFECT, "worker", "start", "--pool", POOL, "--limit", "1"], env, worker_log)
    try:
        run = _cli(["deployment", "run", "weekly_forecast/sf-weekly",
                    "--param", "preset=tiny", "--param", f"output_dir={reports}",
                    "--watch", "--watch-timeout", "170"], env, 190)
        output = run.stdout + run.stderr
        assert run.returncode == 0, output[-3000:] + worker_log.read_text()[-4000:]
        assert "COMPLETED" in output.upper()
    finally:
        stop(worker)
    assert worker.poll() is not None

    runs = api_post(api, "/flow_runs/filter",
                    {"deployments": {"id": {"any_": [deployment["id"]]}}})
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
