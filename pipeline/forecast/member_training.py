"""The forecast's members trained in a background process while the joint pair trains.

A weekly run from scratch trains two independent families of models: the joint forward/backward
flows (step ``train-or-reuse-models``) and the published forecast's own: the flow member on the
multi-wave prior, its nf-real fine-tunes at every refit date, and those of the county panel
(steps ``weekly-forecast`` and ``county-skill``). So, when the joint pair must be trained,
:func:`start_member_training` trains the members in a background process
(:mod:`pipeline.training.background`) while this process trains the pair. When the pair is
done, this process goes on to the weekly forecast and fine-tunes the nf-real refits oldest
first while the background process fine-tunes them newest first; a model one of them is
building, the other waits for and reuses (the model store). If the background process fails or
dies, the steps train whatever is missing themselves.
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from pipeline.forecast.config import ForecastConfig
from pipeline.panels.history import EpiHistory
from pipeline.training.background import (BackgroundOutcome, BackgroundTraining,
                                          start_background_training)

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class MemberTrainingRequest:
    """What the background process needs to train the members the steps will look up."""

    config: ForecastConfig
    history: EpiHistory
    store_root: Path
    torch_threads: int

    def train(self) -> None:
        train_members(self)


def start_member_training(config: ForecastConfig, history: EpiHistory, store_root: Path,
                          logger: logging.Logger | logging.LoggerAdapter[logging.Logger] = log
                          ) -> BackgroundTraining:
    """Start training the weekly forecast's members in a background process (module
    docstring); with nothing of them to train, or where it cannot start, none is started (the
    steps train in this process, as they would anyway)."""
    if not config.track_record_config().members.include_nf:
        return BackgroundTraining()
    import torch

    request = MemberTrainingRequest(config, history, store_root, torch.get_num_threads())
    return start_background_training(request, "the forecast's members", logger)


def wait_for_members(training: BackgroundTraining) -> BackgroundOutcome:
    """Step ``train-forecast-members``: the end of the background training."""
    return training.wait()


@contextlib.contextmanager
def member_training(config: ForecastConfig, history: EpiHistory, store_root: Path,
                    needed: bool, logger: logging.Logger | logging.LoggerAdapter[logging.Logger] = log
                    ) -> Iterator[BackgroundTraining]:
    """:func:`start_member_training` when ``needed``, stopped on leaving if still running."""
    training = (start_member_training(config, history, store_root, logger) if needed
                else BackgroundTraining())
    try:
        yield training
    finally:
        training.stop()


# ----------------------------------------------------------------------------- the process

def train_members(request: MemberTrainingRequest) -> None:
    """Train what the ``weekly-forecast`` and ``county-skill`` steps will look up: the same
    builder calls (refits newest first), so the same store keys and the same models."""
    from pipeline.forecast.county_skill import train_county_members
    from pipeline.forecast.sources import reference_panel
    from pipeline.members.published import build_members
    from pipeline.progress import LogProgress

    progress = LogProgress(log, "training", 500)
    config = request.config
    record = config.track_record_config()
    panel = reference_panel(config.data.place, request.history, config.data.folder)
    build_members(record.members, request.store_root, panel, record.origins(request.history),
                  progress, newest_refits_first=True)
    train_county_members(config, request.store_root, progress)
