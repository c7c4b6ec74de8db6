"""The hub round's members trained in a background process while the round trains them too.

A round from an empty model store trains, for each target, the weekly flow, the context flow's
seeds (each pre-trained, then refitted at every refit date) and nf-real's refits: about 18
minutes on one core of the 2-core VM for the COVID hub's two targets, one after the other. A
background process (:mod:`pipeline.training.background`) fills the same model store from the
other end — the last target first, each context flow's last seed and latest refit first, then
the weekly flow and nf-real's refits newest first — while the round builds its members in its
own order; a model one of them is building, the other waits for and reuses. The round reads
back the same models bit for bit (the same builders, configs, data, seeds and torch threads).

It is started only for a round whose memo is not there yet (the first round of a folder, or
of a new target): a warm round trains one refit at most, which a second Python would cost more
than it saves.
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from pipeline.members.published import HubMembersConfig, build_hub_members, fit_hub_context
from pipeline.panels.hub import is_share
from pipeline.panels.panel import Panel
from pipeline.training.background import BackgroundTraining, start_background_training

log = logging.getLogger(__name__)

Vintages = Sequence[tuple[pd.Timestamp, Panel]]


@dataclass(frozen=True)
class TargetInputs:
    """What a target's members are built from (:func:`~pipeline.members.published.
    build_hub_members`): its vintages, the climatology's, the other signal's (or None)."""

    target: str
    vintages: Vintages
    climatology: Vintages
    other_signal: Vintages | None


def target_inputs(vintages: dict[str, list[tuple[pd.Timestamp, Panel]]]) -> list[TargetInputs]:
    """Each target with a release: its own vintages, the ED share's as the climatology (none
    released yet: empty), the other target's as its other signal."""
    climatology = next((v for t, v in vintages.items() if is_share(t)), [])
    return [TargetInputs(target, own, climatology,
                         next((v for t, v in vintages.items() if t != target and v), None))
            for target, own in vintages.items() if own]


@dataclass(frozen=True)
class HubMembersRequest:
    """The background process's work (module docstring)."""

    config: HubMembersConfig
    store_root: Path
    targets: tuple[TargetInputs, ...]
    seasonal_own_seasons: bool
    torch_threads: int

    def train(self) -> None:
        for inputs in reversed(self.targets):
            fit_hub_context(self.config, self.store_root, inputs.target, inputs.vintages,
                            inputs.climatology, inputs.other_signal, self.seasonal_own_seasons,
                            newest_first=True)
        for inputs in reversed(self.targets):
            build_hub_members(self.config, self.store_root, inputs.vintages,
                              inputs.climatology, target=inputs.target,
                              other_signal=inputs.other_signal,
                              seasonal_own_seasons=self.seasonal_own_seasons, newest_first=True)


@contextlib.contextmanager
def hub_member_training(config: HubMembersConfig, store_root: Path,
                        targets: Sequence[TargetInputs], seasonal_own_seasons: bool,
                        needed: bool) -> Iterator[BackgroundTraining]:
    """The background training (module docstring) when ``needed`` and the members include a
    flow, stopped on leaving: by then the round has built (or read back) every model itself."""
    if not (needed and config.background_training and targets):
        yield BackgroundTraining()
        return
    import torch

    request = HubMembersRequest(config, store_root, tuple(targets), seasonal_own_seasons,
                                torch.get_num_threads())
    training = start_background_training(request, "the round's members", log)
    try:
        yield training
    finally:
        training.stop()
