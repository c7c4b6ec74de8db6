"""Part of a step computed in a forked child process while this process does the rest.

The weekly run is single-threaded Python and small torch calls for most of its time, so on 2
cores one sits idle. Independent parts of a step — two of the four rollouts, the β track, the
NF-seeded SMC's batch beside the other members, half of the report's figures, the PDF's layout —
run in a child meanwhile. :func:`start_in_child` forks the process (the child shares everything
already in memory, nothing is pickled on the way in), runs the build there and sends
back its pickled value; :meth:`ChildBuild.result` waits for it. Builds whose numbers must not
depend on where they ran use torch on one thread in both places (matrix products may sum in
another order on two threads).

The child must stay away from what a fork does not carry safely: it runs torch on one thread (an
OpenMP pool used before a fork must not be used after it) and never runs the parent's ``atexit``
hooks (``multiprocessing`` ends a forked child with ``os._exit``). Whatever goes wrong there —
no ``fork`` on this platform, a child that dies, a value that does not pickle, a child that does
not answer within ``timeout_s`` — the build runs again in this process, so nothing is lost to the
speed-up; an error of the build itself (e.g. a ``ReportError``) is raised here as raised there.
The child logs nothing (``logging`` is disabled there): the parent's handlers may hand records to
threads a fork does not copy (Prefect's API log worker).
"""
from __future__ import annotations

import logging
import multiprocessing
import pickle
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Generic, TypeVar, cast

T = TypeVar("T")
log = logging.getLogger(__name__)
CHILD_TIMEOUT_S = 300.0


@dataclass(eq=False)
class ChildBuild(Generic[T]):
    """A build under way in a child process (or none: then :meth:`result` builds it here)."""

    build: Callable[[], T]
    process: BaseProcess | None
    connection: Connection | None
    timeout_s: float

    def result(self) -> T:
        outcome = self._from_child()
        if outcome is None:
            return self.build()
        ok, value = outcome
        if ok:
            return cast(T, value)
        raise cast(BaseException, value)

    def _from_child(self) -> tuple[bool, object] | None:
        if self.process is None or self.connection is None:
            return None
        try:
            if not self.connection.poll(self.timeout_s):
                log.warning("no answer from the child process in %.0f s; computed here "
                            "instead", self.timeout_s)
                return None
            return pickle.loads(self.connection.recv_bytes())
        except (EOFError, OSError, pickle.UnpicklingError) as error:   # the child died
            log.warning("the child process failed (%s); computed here instead", error)
            return None
        finally:
            self.connection.close()
            self.process.join(1.0)
            if self.process.is_alive():
                self.process.kill()
                self.process.join()


def start_in_child(build: Callable[[], T], timeout_s: float = CHILD_TIMEOUT_S) -> ChildBuild[T]:
    """Start ``build()`` in a forked child now (see the module docstring). In a child (a
    daemonic process, which ``multiprocessing`` lets start no children) it is built in place."""
    if ("fork" not in multiprocessing.get_all_start_methods()
            or multiprocessing.current_process().daemon):
        return ChildBuild(build, None, None, timeout_s)
    context = multiprocessing.get_context("fork")
    receiver, sender = context.Pipe(duplex=False)
    process = context.Process(target=_run_child, args=(build, sender), daemon=True)
    try:
        process.start()
    except OSError as error:      # e.g. no memory for a fork: build it here
        log.warning("cannot fork (%s); computed here instead", error)
        receiver.close()
        sender.close()
        return ChildBuild(build, None, None, timeout_s)
    sender.close()
    return ChildBuild(build, process, receiver, timeout_s)


def _run_child(build: Callable[[], object], sender: Connection) -> None:
    logging.disable(logging.CRITICAL)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)
    try:
        outcome: tuple[bool, object] = (True, build())
    except Exception as error:  # noqa: BLE001 - sent back and raised in the parent
        error.add_note("".join(traceback.format_exception(error)))
        outcome = (False, error)
    try:
        # plain pickle, not the connection's: multiprocessing's pickler would hand torch
        # tensors over as shared memory, which vanishes with this process
        sender.send_bytes(pickle.dumps(outcome, protocol=pickle.HIGHEST_PROTOCOL))
    except Exception:  # noqa: BLE001 - an unpicklable value: the parent builds it again
        pass
    finally:
        sender.close()
