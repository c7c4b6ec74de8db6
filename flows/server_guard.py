"""Stop Prefect's temporary API server when the run that started it dies, however it dies.

Without ``PREFECT_API_URL`` a flow run starts Prefect's *ephemeral* server: Prefect 3.8
(``prefect.server.api.server.SubprocessASGIServer``) launches ``python -m uvicorn …`` with
``subprocess.Popen`` and stops it from an ``atexit`` hook. ``atexit`` never runs on ``kill -9``
(nor on a plain SIGTERM, whose default action skips Python's shutdown), so a killed run left the
uvicorn process orphaned, holding its port and SQLite database (issue 15).

:func:`guard_ephemeral_server` owns that server instead of leaving it to ``atexit``: it starts
Prefect's own ephemeral server early (the same singleton the flow's client then reuses), turns
SIGTERM into a normal exit (so ``atexit`` runs), and starts a tiny watchdog process in its own
session that polls the parent and stops the server as soon as the parent is gone. The watchdog
exits by itself once the server is gone (normal ends stop it through ``atexit``).

Runs against a real server (``PREFECT_API_URL`` set) have nothing to guard.
"""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time

POLL_S = 0.5
STOP_GRACE_S = 5.0


def guard_ephemeral_server() -> int | None:
    """Start (or find) the ephemeral server and its watchdog; the server's pid, or None."""
    from prefect.settings import PREFECT_API_URL, PREFECT_SERVER_EPHEMERAL_ENABLED

    if PREFECT_API_URL.value() or not PREFECT_SERVER_EPHEMERAL_ENABLED.value():
        return None
    from prefect.server.api.server import SubprocessASGIServer

    server = SubprocessASGIServer()
    server.start()
    process = server.server_process
    if process is None:
        return None
    _exit_cleanly_on_sigterm()
    import psutil

    # Identities (pid + start time) are taken here, not by the watchdog: if this process is
    # killed before the watchdog starts, the watchdog still knows whom it guards.
    parent, server_pid = os.getpid(), process.pid
    subprocess.Popen([sys.executable, "-m", "flows.server_guard",
                      "--parent", str(parent),
                      "--parent-started", repr(psutil.Process(parent).create_time()),
                      "--server", str(server_pid),
                      "--server-started", repr(psutil.Process(server_pid).create_time())],
                     start_new_session=True, stdin=subprocess.DEVNULL,
                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=True)
    return process.pid


def _exit_cleanly_on_sigterm() -> None:
    """SIGTERM -> SystemExit, so Prefect's atexit hook stops the server (main thread only)."""
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))


def _alive(pid: int, started: float) -> bool:
    import psutil

    try:
        process = psutil.Process(pid)
        return process.create_time() == started and process.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def watch(parent: int, parent_started: float, server: int, server_started: float) -> int:
    """Poll until ``parent`` dies (then stop ``server``) or ``server`` ends by itself."""
    import psutil

    try:
        server_process = psutil.Process(server)
    except psutil.Error:
        return 0
    while _alive(server, server_started):
        if not _alive(parent, parent_started):
            try:
                server_process.terminate()
                server_process.wait(STOP_GRACE_S)
            except psutil.TimeoutExpired:
                server_process.kill()
            except psutil.Error:
                pass
            return 0
        time.sleep(POLL_S)
    return 0


def main(argv: list[str] | None = None) -> int:
    # __doc__ is None under python -OO
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--parent", type=int, required=True)
    parser.add_argument("--parent-started", type=float, required=True)
    parser.add_argument("--server", type=int, required=True)
    parser.add_argument("--server-started", type=float, required=True)
    args = parser.parse_args(argv)
    return watch(args.parent, args.parent_started, args.server, args.server_started)


if __name__ == "__main__":
    sys.exit(main())
