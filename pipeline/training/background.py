"""Models trained in a background Python process while this one trains others.

A run from scratch trains independent families of models (the weekly run: the joint pair and
the forecast's members; the hub round: each target's flows, their seeds and refits). Each
training runs on about one core: the layers are small, and a training on two torch threads ran
no faster than on one here (2-core VM; with ``OMP_WAIT_POLICY=PASSIVE`` two trainings side by
side each ran as fast as one alone). So :func:`start_background_training` starts a separate
Python process (:func:`main`, not a fork: a fork must not use an OpenMP pool the parent has
used) that runs a :class:`TrainingRequest` — the very builders the run calls, with the same
configs, data, seeds and number of torch threads, so it stores the same models bit for bit
(matrix products may sum in another order on another number of threads).

The two processes share the work through the model store, which lets one process build a model
at a time (:meth:`~pipeline.training.model_store.ModelStore.get_or_build`): each goes through
the models from its own end (the background one newest refits first), and a model the other
is building it waits for and reuses. :meth:`BackgroundTraining.wait` then waits for whatever
the background process has left (normally nothing). If it fails or dies, the run trains
whatever is missing itself: nothing is lost but the time. Its log lines (progress included) are
relayed to this process's log. It exits when this process dies, and is stopped when the run
fails first (a model it was building is not stored: store entries are committed whole).
"""
from __future__ import annotations

import contextvars
import logging
import os
import pickle
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

log = logging.getLogger(__name__)
# Started with -c, not -m: `-m` would make this module __main__, a second copy of its classes.
COMMAND = "import sys; from pipeline.training.background import main; sys.exit(main())"
# Lines of the background process's error output kept for the message of a failure.
TAIL_LINES = 20
STOP_GRACE_S = 5.0


@runtime_checkable
class TrainingRequest(Protocol):
    """What the background process runs: picklable, and importable by its module path."""

    @property
    def torch_threads(self) -> int: ...

    def train(self) -> None: ...


@dataclass(frozen=True)
class BackgroundOutcome:
    """How the background training ended: ``ok``, its seconds, and why not when it failed."""

    ok: bool
    seconds: float
    error: str = ""


@dataclass(eq=False)
class BackgroundTraining:
    """The background process (:meth:`wait` for it), or none (nothing to train)."""

    process: subprocess.Popen[bytes] | None = None
    logger: logging.Logger | logging.LoggerAdapter[logging.Logger] = log
    started: float = field(default_factory=time.monotonic)
    _tail: deque[str] = field(default_factory=lambda: deque(maxlen=TAIL_LINES))
    _relay: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self.process is not None

    def wait(self) -> BackgroundOutcome:
        """Wait for the background process; a failure is logged (the run then trains)."""
        if self.process is None:
            return BackgroundOutcome(ok=True, seconds=0.0)
        code = self.process.wait()
        if self._relay is not None:
            self._relay.join()
        seconds = time.monotonic() - self.started
        if code == 0:
            self.logger.info("models trained in the background in %.1f s", seconds)
            return BackgroundOutcome(ok=True, seconds=seconds)
        error = f"exit {code}: " + " | ".join(self._tail)
        self.logger.warning("the background training failed (%s); the run trains what is "
                            "missing itself", error)
        return BackgroundOutcome(ok=False, seconds=seconds, error=error)

    def stop(self) -> None:
        """End the background process if it still runs (the run failed before waiting)."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.terminate()
        try:
            self.process.wait(timeout=STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    def relay_log(self) -> None:
        """Relay the process's log lines from a thread, in this context (a Prefect run's logger
        needs its run's context and settings, which a new thread does not inherit: without
        them it would start an API of its own)."""
        context = contextvars.copy_context()
        self._relay = threading.Thread(target=context.run, args=(self._relay_log,),
                                       daemon=True, name="background-training-log")
        self._relay.start()

    def _relay_log(self) -> None:
        """Each line the background process logs, logged here (progress included)."""
        assert self.process is not None and self.process.stderr is not None
        for raw in self.process.stderr:
            line = raw.decode("utf-8", "replace").rstrip()
            if line:
                self._tail.append(line)
                self.logger.info("background training: %s", line)


def start_background_training(request: TrainingRequest, what: str,
                              logger: logging.Logger | logging.LoggerAdapter[logging.Logger]
                              = log) -> BackgroundTraining:
    """Start ``request`` in a background process (module docstring); where it cannot start,
    none is started (the run trains everything itself, as it would anyway). ``what``: the
    models, for the log."""
    try:
        payload = pickle.dumps(request, protocol=pickle.HIGHEST_PROTOCOL)
        # idle OpenMP threads sleep instead of spinning: two trainings share two cores
        env = {"OMP_WAIT_POLICY": "PASSIVE", **os.environ}
        process = subprocess.Popen([sys.executable, "-c", COMMAND], stdin=subprocess.PIPE,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    except (OSError, pickle.PicklingError, TypeError, AttributeError) as exc:
        logger.warning("%s not trained in the background (%s): the run trains them", what, exc)
        return BackgroundTraining()
    assert process.stdin is not None
    try:
        process.stdin.write(payload)
        process.stdin.close()
    except OSError as exc:          # it died at once; wait() reports its error
        logger.warning("could not hand the request to the background training: %s", exc)
    training = BackgroundTraining(process, logger)
    training.relay_log()
    logger.info("training %s in the background (pid %d)", what, process.pid)
    return training


def _exit_with_parent(parent: int) -> None:
    """Exit as soon as the process that started this one is gone (its run is over)."""
    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(3)

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()


def main() -> int:
    logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(message)s")
    _exit_with_parent(os.getppid())
    request = pickle.load(sys.stdin.buffer)
    if not isinstance(request, TrainingRequest):
        raise TypeError(f"expected a TrainingRequest, got {type(request).__name__}")
    import torch

    torch.set_num_threads(request.torch_threads)
    request.train()
    return 0
