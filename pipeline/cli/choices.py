"""Fixed choices of the command line as Enums, so `--help` lists them (``<mlp|transformer|…>``)
and typos fail with the list; numeric option checks that click's ranges miss (NaN, inf)."""
from __future__ import annotations

import math
from enum import Enum
from typing import TYPE_CHECKING, TypeAlias, cast, overload

import typer

from pipeline.names import BACKENDS, ENCODER_CHOICES, RECIPES, SIR_PRIOR_NAMES, TRAINING_SETUPS


def choices_enum(name: str, values: tuple[str, ...] | list[str]) -> type[Enum]:
    """A ``str`` Enum whose values (what the user types) are ``values``."""
    members = {v.replace("-", "_").replace("+", "_"): v for v in values}
    # Enum's functional API returns a class, but with a non-literal name pyright reads the call
    # as a member lookup and types it as an Enum instance.
    return cast("type[Enum]", Enum(name, members, type=str))


if TYPE_CHECKING:
    # Built at run time from tuples of names, so a checker cannot know their members; to it each
    # is a plain Enum (value() turns a choice into its string). typer reads the real classes.
    Direction: TypeAlias = Enum
    Encoder: TypeAlias = Enum
    Backend: TypeAlias = Enum
    Recipe: TypeAlias = Enum
    TrainPreset: TypeAlias = Enum
    SIRPriorName: TypeAlias = Enum
    SMCSystem: TypeAlias = Enum
    DataSource: TypeAlias = Enum
else:
    Direction = choices_enum("Direction", ("forward", "backward"))
    Encoder = choices_enum("Encoder", ENCODER_CHOICES)
    Backend = choices_enum("Backend", BACKENDS)
    Recipe = choices_enum("Recipe", RECIPES)
    TrainPreset = choices_enum("TrainPreset", TRAINING_SETUPS)
    SIRPriorName = choices_enum("SIRPriorName", SIR_PRIOR_NAMES)
    SMCSystem = choices_enum("SMCSystem", ("sir", "sir-params", "vehicle"))
    DataSource = choices_enum("DataSource", ("live", "cache", "import"))


@overload
def value(choice: Enum | str) -> str: ...
@overload
def value(choice: None) -> None: ...
@overload
def value(choice: Enum | str | None) -> str | None: ...
def value(choice: Enum | str | None) -> str | None:
    """The plain string of an Enum choice (None stays None)."""
    return str(choice.value) if isinstance(choice, Enum) else choice


def finite(minimum: float | None = None, *, strictly: bool = False):  # noqa: ANN201
    """A typer callback refusing NaN/inf and values below ``minimum`` (or at it, ``strictly``)."""

    def check(ctx: typer.Context, param: typer.CallbackParam,
              number: float | None) -> float | None:
        if number is None or ctx.resilient_parsing:
            return number
        name = f"--{param.name.replace('_', '-')}" if param.name else "value"
        if not math.isfinite(number):
            raise typer.BadParameter(f"{name} must be a finite number, got {number}")
        if minimum is not None and (number < minimum or (strictly and number == minimum)):
            relation = ">" if strictly else ">="
            raise typer.BadParameter(f"{name} must be {relation} {minimum:g}, got {number:g}")
        return number

    return check
