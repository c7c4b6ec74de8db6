"""The names every layer shares: SIR compartments, SIR parameters, estimation directions, and
the fixed choices of the configs and the command line (flow backends, encoders, recipes,
training set-ups, SIR priors, forecast presets).

Defined once here so that a dataset's columns, a model's target, a filter's state and a report's
table all spell them the same way; and light (no torch, no pandas), so that the command line
lists its choices, e.g. in ``flowcast --help``, without loading the engine.
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

Backend = Literal["nflows", "zuko"]
EncoderChoice = Literal["mlp", "transformer", "transformer-ke", "mamba"]
Recipe = Literal["paper", "fast"]
BACKENDS: Final[tuple[Backend, ...]] = get_args(Backend)
ENCODER_CHOICES: Final[tuple[EncoderChoice, ...]] = get_args(EncoderChoice)
RECIPES: Final[tuple[Recipe, ...]] = get_args(Recipe)
# The keys of the registries that hold what each name means (tests/test_cli.py checks them):
# pipeline.training.presets.SETUPS, pipeline.systems.sir.SIR_PRIORS and
# pipeline.forecast.config.FORECAST_PRESETS.
TRAINING_SETUPS: Final[tuple[str, ...]] = ("vehicle", "vehicle-sparse", "sir-single", "sir-multi",
                                           "sir-joint", "sir-sf-joint", "sf-waves-joint")
SIR_PRIOR_NAMES: Final[tuple[str, ...]] = ("sir-single", "sir-multi", "sir-sf")
FORECAST_PRESET_NAMES: Final[tuple[str, ...]] = ("default", "tiny")
# A windowed dataset's context length R and validation share, unless set.
DEFAULT_WINDOW: Final = 5
DEFAULT_VAL_FRACTION: Final = 0.1
