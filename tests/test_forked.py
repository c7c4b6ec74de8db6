"""pipeline.forked: a build runs in a forked child and comes back whole; whatever goes wrong
there, it is built here instead (or its own error is raised here)."""
from __future__ import annotations

import os

import pytest
import torch

from pipeline.forked import ChildBuild, start_in_child


def test_the_value_is_built_in_another_process_and_comes_back_whole() -> None:
    tensor = torch.arange(12, dtype=torch.float64).reshape(3, 4)
    pending = start_in_child(lambda: (os.getpid(), tensor * 2, torch.get_num_threads()))
    pid, doubled, threads = pending.result()
    assert pid != os.getpid()
    assert torch.equal(doubled, tensor * 2)       # a copy, not memory shared with a dead child
    assert threads == 1                            # torch on one thread after a fork


def test_an_error_of_the_build_is_raised_here() -> None:
    def build() -> int:
        raise ValueError("bad input 42")

    with pytest.raises(ValueError, match="bad input 42"):
        start_in_child(build).result()


def test_a_child_that_dies_is_built_here_instead() -> None:
    parent = os.getpid()

    def build() -> int:
        if os.getpid() != parent:
            os._exit(3)           # the child dies without an answer
        return 7

    assert start_in_child(build).result() == 7


def test_a_value_that_does_not_pickle_is_built_here_instead() -> None:
    parent = os.getpid()

    def build() -> object:
        return (lambda: None) if os.getpid() != parent else "built here"

    assert start_in_child(build).result() == "built here"


def test_a_child_that_does_not_answer_in_time_is_built_here_instead() -> None:
    parent = os.getpid()

    def build() -> str:
        if os.getpid() != parent:
            import time
            time.sleep(30)
        return "built here"

    pending = start_in_child(build, timeout_s=0.5)
    assert isinstance(pending, ChildBuild) and pending.result() == "built here"
