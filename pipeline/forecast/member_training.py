"""The forecast's members trained in a background process while the joint pair trains.

A weekly run from scratch trains two independent families of models: the joint forward/backward
flows (step ``train-or-reuse-models``) and the published forecast's own: the flow member on the
multi-wave prior, its nf-real fine-tunes at every refit date, and those of the county panel
(steps ``weekly-forecast`` and ``county-skill``). Each family trains on about one core: the
layers are small, and a training on two torch threads ran no faster than on one here (2-core
VM; with ``OMP_WAIT_POLICY=PASSIVE`` two trainings side by side each ran as fast as one
alone). So, when the joint pair must be trained, :func:`start_member_training` starts a
separate Python process (:func:`main`, not a fork: a fork
must not use an OpenMP pool the parent has used) that trains the members into the model store
while this process trains the pair.

The background process calls the very builders those steps call, with the same configs, data,
seeds and number of torch threads, so it stores the same models bit for bit (matrix products
may sum in another order on another number of threads). The two processes share the work
through the model store, which lets one process build a model at a time
(:meth:`~pipeline.training.model_store.ModelStore.get_or_build`): when the joint pair is done,
this process goes on to the weekly forecast and fine-tunes the nf-real refits oldest first
while the background process fine-tunes them newest first; a model one of them is building,
the other waits for and reuses. :meth:`MemberTraining.wait` then waits for whatever the
background process has left (normally nothing). If it fails or dies, the steps train whatever
is missing themselves: nothing is lost but the time. Its log lines (progress included) are
relayed to this process's log. It exits when this process dies, and is stopped when the run
fails first (a model it was building is not stored: store entries are committed whole).
"""
from __future__ import annotations

import contextlib
import contextvars
import logging
import os
import pickle
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.panels.history import EpiHistory
from pipeline.forecast.config import ForecastConfig

log = logging.getLogger(__name__)
# Started with -c, not -m: `-m` would make this module __main__, a second copy of its classes.
COMMAND = ("import sys; from pipeline.forecast.member_training import main; "
           "sys.exit(main())")
# Lines of the background process's error output kept for the message of a failure.
TAIL_LINES = 20
STOP_GRACE_S = 5.0


@dataclass(frozen=True)
class MemberTrainingRequest:
    """What the background process needs to train the members the steps will look up."""

    config: ForecastConfig
    history: EpiHistory
    store_root: Path
    torch_threads: int


@dataclass(frozen=True)
class MemberTrainingOutcome:
    """How the background training ended: ``ok``, its seconds, and why not when it failed."""

    ok: bool
    seconds: float
    error: str = ""


@dataclass(eq=False)
class MemberTraining:
    """The background process (:meth:`wait` for it), or none (nothing to train)."""

    process: subprocess.Popen[bytes] | None = None
    logger: logging.Logger | logging.LoggerAdapter[logging.Logger] = log
    started: float = field(default_factory=time.monotonic)
    _tail: deque[str] = field(default_factory=lambda: deque(maxlen=TAIL_LINES))
    _relay: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self.process is not None

    def wait(self) -> MemberTrainingOutcome:
        """Wait for the background process; a failure is logged (the steps then train)."""
        if self.process is None:
            return MemberTrainingOutcome(ok=True, seconds=0.0)
        code = self.process.wait()
        if self._relay is not None:
            self._relay.join()
        seconds = time.monotonic() - self.started
        if code == 0:
            self.logger.info("members trained in the background in %.1f s", seconds)
            return MemberTrainingOutcome(ok=True, seconds=seconds)
        error = f"exit {code}: " + " | ".join(self._tail)
        self.logger.warning("the background member training failed (%s); the steps train "
                            "what is missing themselves", error)
        return MemberTrainingOutcome(ok=False, seconds=seconds, error=error)

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
                                       daemon=True, name="member-training-log")
        self._relay.start()

    def _relay_log(self) -> None:
        """Each line the background process logs, logged here (progress included)."""
        assert self.process is not None and self.process.stderr is not None
        for raw in self.process.stderr:
            line = raw.decode("utf-8", "replace").rstrip()
            if line:
                self._tail.append(line)
                self.logger.info("member training: %s", line)


def start_member_training(config: ForecastConfig, history: EpiHistory, store_root: Path,
                          logger: logging.Logger | logging.LoggerAdapter[logging.Logger] = log
                          ) -> MemberTraining:
    """Start training the weekly forecast's members in a background process (module
    docstring); with nothing of them to train, or where it cannot start, none is started (the
    steps train in this process, as they would anyway)."""
    if not config.track_record_config().members.include_nf:
        return MemberTraining()
    import torch

    request = MemberTrainingRequest(config, history, store_root, torch.get_num_threads())
    try:
        payload = pickle.dumps(request)
        process = subprocess.Popen([sys.executable, "-c", COMMAND], stdin=subprocess.PIPE,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    except (OSError, pickle.PicklingError, TypeError, AttributeError) as exc:
        logger.warning("members not trained in the background (%s): the steps train them", exc)
        return MemberTraining()
    assert process.stdin is not None
    try:
        process.stdin.write(payload)
        process.stdin.close()
    except OSError as exc:          # it died at once; wait() reports its error
        logger.warning("could not hand the request to the background member training: %s", exc)
    training = MemberTraining(process, logger)
    training.relay_log()
    logger.info("training the forecast's members in the background (pid %d)", process.pid)
    return training


def wait_for_members(training: MemberTraining) -> MemberTrainingOutcome:
    """Step ``train-forecast-members``: the end of the background training."""
    return training.wait()


@contextlib.contextmanager
def member_training(config: ForecastConfig, history: EpiHistory, store_root: Path,
                    needed: bool, logger: logging.Logger | logging.LoggerAdapter[logging.Logger] = log
                    ) -> Iterator[MemberTraining]:
    """:func:`start_member_training` when ``needed``, stopped on leaving if still running."""
    training = (start_member_training(config, history, store_root, logger) if needed
                else MemberTraining())
    try:
        yield training
    finally:
        training.stop()


# ----------------------------------------------------------------------------- the process

def train_members(request: MemberTrainingRequest) -> None:
    """Train what the ``weekly-forecast`` and ``county-skill`` steps will look up: the same
    builder calls (refits newest first), so the same store keys and the same models."""
    from pipeline.forecast.county_skill import train_county_members
    from pipeline.forecast.sources import load_reference_histories
    from pipeline.members.published import build_members
    from pipeline.panels.california import place_panel
    from pipeline.progress import LogProgress

    progress = LogProgress(log, "training", 500)
    config = request.config
    record = config.track_record_config()
    panel = place_panel(config.data.place, request.history, load_reference_histories())
    build_members(record.members, request.store_root, panel, record.origins(request.history),
                  progress, newest_refits_first=True)
    train_county_members(config, request.store_root, progress)


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
    if not isinstance(request, MemberTrainingRequest):
        raise TypeError(f"expected a MemberTrainingRequest, got {type(request).__name__}")
    import torch

    torch.set_num_threads(request.torch_threads)
    train_members(request)
    return 0

