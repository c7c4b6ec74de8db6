"""Shared test configuration: offline, few threads, deterministic."""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads OpenMP; see pipeline/__init__

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
DATASF = SHARED / "data" / "datasf"

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
# Prefect's temporary server gets 20 s to start by default: too little on a loaded 2-core box
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
# Test models are tiny: one thread is as fast and never stalls on a shared 2-core machine.
torch.set_num_threads(1)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Longest files first. ``make test`` hands whole files to two xdist workers in collection
    order (``--dist loadfile --no-loadscope-reorder``); a long file handed out last keeps one
    worker busy while the other idles. xdist's own order (most tests first) put the two
    one-test integration files last, the suite's longest tests (real Prefect servers and
    workers, 1-2.5 min each on a loaded box). Files holding an ``integration`` test go first,
    then files holding a ``slow`` one, then the rest; within a file the order is kept."""
    rank: dict[Path, int] = {}
    for item in items:
        weight = (0 if item.get_closest_marker("integration") is not None
                  else 1 if item.get_closest_marker("slow") is not None else 2)
        rank[item.path] = min(rank.get(item.path, weight), weight)
    items.sort(key=lambda item: rank[item.path])    # stable: same-rank files keep their order


@pytest.fixture(autouse=True)
def _isolated_data_dir(tmp_path, monkeypatch):
    """Every test gets its own cache directory; nothing touches the user's data/."""
    monkeypatch.setenv("FLOWCAST_DATA_DIR", str(tmp_path / "flowcast-data"))


@pytest.fixture(scope="session")
def datasf_dir() -> Path:
    if not DATASF.is_dir():
        pytest.fail(f"real DataSF exports expected at {DATASF} (../shared beside the repo)")
    return DATASF


@pytest.fixture
def prefect_logging_rebound():
    """Run a flow inside typer's CliRunner, then give Prefect's console handler back a live
    stream: set up inside CliRunner it writes to CliRunner's stderr, which is closed when invoke
    returns, and every later flow of the session would log into a closed file."""
    yield
    from prefect.logging.configuration import setup_logging

    setup_logging(incremental=False)


@pytest.fixture(scope="session")
def prefect_harness():
    """Prefect's temporary test server, one per session (the flow tests of SF and a county)."""
    from prefect.testing.utilities import prefect_test_harness

    # generous start-up bound: the ephemeral server is slow to come up on a loaded 2-core box
    with prefect_test_harness(server_startup_timeout=120):
        yield
