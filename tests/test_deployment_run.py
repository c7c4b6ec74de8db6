"""Integration: a real Prefect server on 127.0.0.1, the served deployment, `prefect deployment run`.

Starts `prefect server start` (temporary PREFECT_HOME, free port), serves
`weekly_forecast/sf-weekly` and `hub_forecast/hub-covid-weekly` from flows/deploy.py, triggers
the first with the CLI (`--watch`, bounded), then checks the run COMPLETED, its report exists, and the deployment carries the Monday 06:00
America/Los_Angeles cron schedule and is not paused. Every process started here is stopped (its
whole process group) in a `finally`.
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
from pathlib import Path

import pytest

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(240)]

REPO = Path(__file__).resolve().parents[1]
PREFECT = str(Path(sys.executable).with_name("prefect"))


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


def test_serve_and_run_deployment(tmp_path, datasf_dir):
    port = free_port()
    api = f"http://127.0.0.1:{port}/api"
    data_dir = tmp_path / "data"
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect-home"), "PREFECT_API_URL": api,
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1",
           "PREFECT_RUNNER_POLL_FREQUENCY": "1", "PREFECT_LOGGING_LEVEL": "INFO",
           "FLOWCAST_DATA_DIR": str(data_dir), "PYTHONUNBUFFERED": "1"}
    from pipeline.forecast.sources import import_exports

    os.environ["FLOWCAST_DATA_DIR"] = str(data_dir)  # the autouse fixture restores it
    import_exports([str(datasf_dir)])
    reports = tmp_path / "reports"
    procs: list[subprocess.Popen] = []
    try:
        procs.append(start_prefect_server(tmp_path, env, port, api))

        serve_log = tmp_path / "serve.log"
        procs.append(start([sys.executable, "-m", "flows.deploy", "--preset", "tiny",
                            "--data-source", "cache", "--output-dir", str(reports)],
                           env, serve_log))
        # serve registers the two deployments one after the other: wait for both (on a loaded
        # box the hub's came a moment after the SF one, and a lookup in between found none)
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

        run = subprocess.run([PREFECT, "deployment", "run", "weekly_forecast/sf-weekly",
                              "--param", "seed=3", "--watch", "--watch-timeout", "150"],
                             env=env, cwd=REPO, capture_output=True, text=True, timeout=170)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:] + \
            serve_log.read_text()[-3000:]
        assert "COMPLETED" in (run.stdout + run.stderr).upper()

        runs = api_post(api, "/flow_runs/filter",
                        {"deployments": {"id": {"any_": [deployment["id"]]}}})
        manual = [r for r in runs if r["parameters"].get("seed") == 3]
        assert manual and manual[0]["state"]["type"] == "COMPLETED"

        index = json.loads((reports / "index.json").read_text())
        latest = index["runs"][0]
        assert latest["reference_date"] == "2022-03-02" and latest["seed"] == 3
        assert (reports / "2022-03-02" / "report.html").stat().st_size > 0
    finally:
        for proc in reversed(procs):
            stop(proc)
    assert all(p.poll() is not None for p in procs)
