"""The names every layer shares: SIR compartments, SIR parameters, estimation directions.

Defined once here so that a dataset's columns, a model's target, a filter's state and a report's
table all spell them the same way.
"""
from __future__ import annotations

from typing import Final, Literal, get_args

Compartment = Literal["S", "I", "R"]
Parameter = Literal["beta", "gamma"]
Direction = Literal["forward", "backward"]

COMPARTMENTS: Final[tuple[Compartment, ...]] = get_args(Compartment)
PARAMETERS: Final[tuple[Parameter, ...]] = get_args(Parameter)
# The joint state-and-parameter target of the paper's "joint estimation": (S, I, R, beta, gamma).
JOINT_NAMES: Final[tuple[str, ...]] = (*COMPARTMENTS, *PARAMETERS)
DIRECTIONS: Final[tuple[Direction, ...]] = get_args(Direction)
