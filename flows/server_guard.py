"""Prefect's temporary API server for one local run: started early, stopped however the run ends.

Without ``PREFECT_API_URL`` a flow run needs Prefect's *ephemeral* server. Prefect 3.8 starts it
itself (``prefect.server.api.server.SubprocessASGIServer``: ``python -m uvicorn …`` under
``subprocess.Popen``, stopped from an ``atexit`` hook) when the flow's first client opens, that
is after every import of the run, and importing that class alone costs the run about 5 s. The
server then needs 6–8 s on 2 cores to answer: the cached weekly run spent 20 s before its first
step.

So a local run (``python -m flows.weekly_forecast``, ``flowcast forecast``) launches the same
server command itself, first thing (:func:`start_temporary_server`), lets it come up while the
run imports torch, pandas and the pipeline, then points the run's settings at it
(:func:`ephemeral_api`, with Prefect's own ``temporary_settings``). A server that cannot come up
is named in the error. A run whose Prefect profile names an API stops the early server unused.

It also owns that server's end (issue 15): ``atexit`` never runs on ``kill -9`` (nor on a plain
SIGTERM, whose default action skips Python's shutdown), which left the uvicorn process orphaned,
holding its port and SQLite database. :func:`ephemeral_api` turns SIGTERM into a normal exit (so
``atexit`` stops the server) and starts a tiny watchdog process in its own session that polls the
parent and stops the server as soon as the parent is gone. The watchdog exits by itself once the
server is gone.

Runs against a real server (``PREFECT_API_URL`` set) have nothing to start or guard.
"""
from __future__ import annotations

import argparse
import atexit
import contextlib
import importlib.util
import logging
import os
import random
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

POLL_S = 0.5
STOP_GRACE_S = 5.0
HEALTH_POLL_S = 0.1
STARTUP_TIMEOUT_S = 120.0
PORTS = range(8000, 9000)            # Prefect's own range for its temporary server
PORT_IN_USE_EXIT = 3                 # uvicorn's exit status when the port was taken meanwhile
# What Prefect sets for its ephemeral server (no UI; the server knows it is temporary).
SERVER_ENV = {"PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
              "PREFECT__SERVER_FINAL": "1"}
log = logging.getLogger(__name__)


class ServerStartError(RuntimeError):
    """Prefect's temporary API server did not come up."""


@dataclass
class TemporaryServer:
    process: subprocess.Popen[bytes]
    port: int

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"


_server: TemporaryServer | None = None


def needs_temporary_server() -> bool:
    """No API configured (``PREFECT_API_URL``, env or profile) and ephemeral mode allowed."""
    from prefect.settings import PREFECT_API_URL, PREFECT_SERVER_EPHEMERAL_ENABLED

    return not PREFECT_API_URL.value() and bool(PREFECT_SERVER_EPHEMERAL_ENABLED.value())


def start_temporary_server() -> TemporaryServer | None:
    """Launch the temporary server without waiting for it (once per process), unless
    ``PREFECT_API_URL`` is in the environment; None then. Nothing of Prefect is imported here
    (``prefect.settings`` alone takes 1.5 s): an API configured in a Prefect profile is found
    by :func:`ephemeral_api`, which stops the server again."""
    global _server
    if _server is None and not os.environ.get("PREFECT_API_URL"):
        _server = _launch(_free_port())
        atexit.register(stop_temporary_server)
    return _server


def _free_port() -> int:
    for _ in range(50):
        port = random.choice(PORTS)
        with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise ServerStartError(f"no free port in {PORTS.start}–{PORTS.stop - 1} for Prefect's "
                           "temporary API server")


def _launch(port: int) -> TemporaryServer:
    spec = importlib.util.find_spec("prefect")    # where it is installed, without importing it
    if spec is None or spec.origin is None:
        raise ServerStartError("Prefect is not installed in this environment")
    app_dir = Path(spec.origin).resolve().parents[1]
    command = [sys.executable, "-m", "uvicorn", "--app-dir", str(app_dir), "--factory",
               "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port",
               str(port), "--log-level", "error", "--lifespan", "on"]
    log.info("starting Prefect's temporary API server on http://127.0.0.1:%d", port)
    return TemporaryServer(subprocess.Popen(command, env={**os.environ, **SERVER_ENV}), port)


def wait_until_up(server: TemporaryServer, timeout_s: float) -> TemporaryServer:
    """Poll ``/health`` until it answers 200; relaunch on another port if uvicorn lost its port
    meanwhile. The server that answered (module state follows)."""
    global _server
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        code = server.process.poll()
        if code == PORT_IN_USE_EXIT:
            server = _server = _launch(_free_port())
            continue
        if code is not None:
            raise ServerStartError(f"Prefect's temporary API server exited with status {code} "
                                   "before answering (its error is printed above)")
        try:
            with urllib.request.urlopen(f"{server.api_url}/health", timeout=2) as response:
                if response.status == 200:
                    return server
        except (urllib.error.URLError, ConnectionError, TimeoutError, OSError):
            pass
        time.sleep(HEALTH_POLL_S)
    server.process.kill()       # hung: nothing to shut down gracefully
    _server = None
    raise ServerStartError(f"Prefect's temporary API server did not answer within "
                           f"{timeout_s:.0f} s (PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS)")


def stop_temporary_server() -> None:
    """Ask the server to stop (SIGTERM) without waiting for it: uvicorn's graceful shutdown
    waits for this process's open connections (Prefect's event stream), which close only when
    the process ends, so waiting here cost every run 5 s. The watchdog kills a server that is
    still up :data:`STOP_GRACE_S` after this process is gone."""
    global _server
    server, _server = _server, None
    if server is None or server.process.poll() is not None:
        return
    log.info("stopping Prefect's temporary API server on http://127.0.0.1:%d", server.port)
    server.process.terminate()


@contextlib.contextmanager
def ephemeral_api() -> Iterator[int | None]:
    """The run's API for the block: the temporary server (started now unless
    :func:`start_temporary_server` already did), up and guarded, with Prefect's settings
    pointing at it. Yields the server's pid, or None with a configured API."""
    from prefect.settings import (PREFECT_API_URL,
                                  PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS,
                                  temporary_settings)

    if not needs_temporary_server():
        stop_temporary_server()     # launched before the profile's API could be read
        yield None
        return
    server = start_temporary_server()
    assert server is not None
    # Prefect waits 20 s by default; on a busy 2-core machine start-up was seen to take longer
    timeout_s = max(STARTUP_TIMEOUT_S, float(PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS.value()))
    server = wait_until_up(server, timeout_s)
    _exit_cleanly_on_sigterm()
    _start_watchdog(server.process.pid)
    with temporary_settings({PREFECT_API_URL: server.api_url}):
        yield server.process.pid


def exit_now(code: int) -> NoReturn:
    """End a command-line process: the ``atexit`` hooks (Prefect's log and event flush, the
    temporary server's stop), then the exit, without the interpreter's teardown (after a
    forecast run, freeing its 2 GB of objects and torch's globals took 2–3 s)."""
    _send_last_api_logs()
    atexit._run_exitfuncs()
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _send_last_api_logs() -> None:
    """Flush Prefect's API log handlers while the server and Prefect's event loop still run,
    then detach them. Left to ``logging``'s own ``atexit`` hook, which runs after both were
    stopped, the flush waited out its 5 s timeout in about one run in five."""
    handlers = sys.modules.get("prefect.logging.handlers")
    if handlers is None:        # Prefect never started: nothing was sent to an API
        return
    loggers = [logging.getLogger(), *(logger for logger in logging.Logger.manager.loggerDict.values()
                                      if isinstance(logger, logging.Logger))]
    for logger in loggers:
        for handler in list(logger.handlers):
            if isinstance(handler, handlers.APILogHandler):
                handler.flush()
                logger.removeHandler(handler)


def _start_watchdog(server_pid: int) -> None:
    import psutil

    # Identities (pid + start time) are taken here, not by the watchdog: if this process is
    # killed before the watchdog starts, the watchdog still knows whom it guards.
    parent = os.getpid()
    subprocess.Popen([sys.executable, "-m", "flows.server_guard",
                      "--parent", str(parent),
                      "--parent-started", repr(psutil.Process(parent).create_time()),
                      "--server", str(server_pid),
                      "--server-started", repr(psutil.Process(server_pid).create_time())],
                     start_new_session=True, stdin=subprocess.DEVNULL,
                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=True)


def _exit_cleanly_on_sigterm() -> None:
    """SIGTERM -> SystemExit, so the atexit hook stops the server (main thread only)."""
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
