"""The ``flowcast`` command line: one sub-module per command group, each attaching to ``app``."""
from __future__ import annotations

import importlib

import typer

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="flowcast: conditional normalizing flows for epidemic forecasting.")

# Modules that attach commands to ``app`` when imported.
COMMAND_MODULES = ("simulate", "data", "train", "demo", "estimate", "smc", "reproduce")


def _register() -> None:
    for name in COMMAND_MODULES:
        importlib.import_module(f"pipeline.cli.{name}")


def main() -> None:
    _register()
    app()
