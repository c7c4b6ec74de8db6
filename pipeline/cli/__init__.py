"""The ``flowcast`` command line: one sub-module per command group, each attaching to ``app``."""
from __future__ import annotations

import importlib
import typing
from importlib.metadata import PackageNotFoundError, version
from pathlib import PurePath
from typing import Annotated, Any

import typer
from typer.core import TyperGroup


class _FlowcastGroup(TyperGroup):
    """The root command group: plain help labels on every command below it (see
    :func:`_plain_metavars`), however the command is built (``main``, typer's CliRunner)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _plain_metavars(self)


app = typer.Typer(cls=_FlowcastGroup, no_args_is_help=True, add_completion=False,
                  help="flowcast: conditional normalizing flows for epidemic forecasting.")

# Modules that attach commands to ``app`` when imported.
# (``flowcast forecast`` runs the Prefect flow, so flows/cli.py attaches it: the entry point.)
COMMAND_MODULES = ("simulate", "data", "train", "demo", "estimate", "smc",
                   "reproduce", "backtest")
# Help labels for value types: what a user types, not Python type names (``<int>``, ``<str>``).
_METAVARS: dict[type, str] = {int: "INTEGER", float: "NUMBER", str: "TEXT"}


def package_version() -> str:
    try:
        return version("flowcast")
    except PackageNotFoundError:  # running from a checkout that was never installed
        return "unknown"


def _show_version(show: bool) -> None:
    if show:
        typer.echo(f"flowcast {package_version()}")
        raise typer.Exit()


@app.callback()
def _root(
    version_: Annotated[bool, typer.Option("--version", callback=_show_version, is_eager=True,
                                           help="Print the flowcast version and exit.")] = False,
) -> None:
    """flowcast: conditional normalizing flows for epidemic forecasting."""


def _register() -> None:
    for name in COMMAND_MODULES:
        importlib.import_module(f"pipeline.cli.{name}")


def _plain_metavars(command: Any) -> None:
    """Give every option without a metavar a plain label (INTEGER, NUMBER, TEXT, PATH; nothing
    for flags, ``--help`` included); choices keep their ``<a|b|c>`` list."""
    from typer.core import TyperArgument, TyperOption

    for param in command.params:
        if isinstance(param, TyperOption) and param.metavar is None:
            param.metavar = _metavar(param)
        elif isinstance(param, TyperArgument):
            label = _metavar(param)
            if label is not None:  # typer shows an argument's type from its annotation
                param.display_type_rich = lambda ctx, label=label: label
    original_help = command.get_help_option

    def help_option(ctx: Any) -> Any:
        option = original_help(ctx)
        if option is not None:
            option.metavar = ""
        return option

    command.get_help_option = help_option
    for sub in getattr(command, "commands", {}).values():
        _plain_metavars(sub)


def _metavar(option: Any) -> str | None:
    if getattr(option, "is_flag", False):
        return ""
    desc = option.type_descriptor
    if desc.is_choice:
        return None
    annotation = desc.annotation
    if desc.is_list:
        (annotation,) = typing.get_args(annotation) or (str,)
    is_path = desc.is_path or (isinstance(annotation, type) and issubclass(annotation, PurePath))
    label = "PATH" if is_path else _METAVARS.get(annotation)
    if label is None:
        return None
    return label + ("..." if desc.is_list else "")


def build_command() -> Any:
    """The click command of the whole CLI (all command modules registered)."""
    _register()
    return typer.main.get_command(app)


def main() -> None:
    _register()
    app(prog_name="flowcast")
