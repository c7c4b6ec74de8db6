"""The hub round's command-line options checked before any work (issue 39): a ``--hub-config``
folder must hold a readable ``tasks.json`` of a hubverse hub's shape, and ``--output-dir`` must
be a directory flowcast can write into. A folder without ``tasks.json`` used to be ignored
silently (the round validated against the default config and published with rc 0, the report
naming the folder given); a ``tasks.json`` holding ``[]`` ended, minutes later, in
``AttributeError: 'list' object has no attribute 'get'``.
"""
from __future__ import annotations

import json
from pathlib import Path

from pipeline.cli.output_paths import OutputPathError, output_dir
from pipeline.errors import ConfigError
from pipeline.io import JSONBoundError, read_bounded_json
from pipeline.outputs.hub_tasks import MAX_TASKS_BYTES, MAX_TASKS_DEPTH

TASKS = "tasks.json"


def read_tasks_json(tasks: Path) -> object:
    """``tasks`` parsed once its size and nesting are within bounds (:func:`read_bounded_json`);
    the file's problem as one :class:`ConfigError` otherwise."""
    try:
        return read_bounded_json(tasks, max_bytes=MAX_TASKS_BYTES, max_depth=MAX_TASKS_DEPTH)
    except JSONBoundError as exc:
        raise ConfigError(str(exc)) from None


def hub_config_folder(path: Path, *, option: str = "--hub-config") -> Path:
    """``path`` if it is a folder holding a readable ``tasks.json`` with a ``rounds`` list of
    objects that each have ``model_tasks``; otherwise one :class:`ConfigError` naming the file
    and the problem."""
    if not path.is_dir():
        raise ConfigError(f"{option} {path}: not a folder (give the hub's hub-config folder, "
                          f"which holds {TASKS})")
    tasks = path / TASKS
    try:
        config = read_tasks_json(tasks)
    except FileNotFoundError:
        raise ConfigError(f"{option} {path}: no {TASKS} in the folder") from None
    except ConfigError as exc:
        raise ConfigError(f"{option} {exc}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{option} {tasks}: not readable as JSON ({exc})") from None
    rounds = config.get("rounds") if isinstance(config, dict) else None
    if not isinstance(rounds, list) or not rounds or not all(
            isinstance(r, dict) and isinstance(r.get("model_tasks"), list) for r in rounds):
        shape = type(config).__name__ if not isinstance(config, dict) else \
            f"an object with keys {sorted(config)[:6]}"
        raise ConfigError(f"{option} {tasks}: not a hubverse tasks config (expected an object "
                          f"whose 'rounds' is a list of rounds with 'model_tasks'; got {shape})")
    return path


def writable_output_dir(path: Path, *, option: str = "--output-dir") -> Path:
    """``path`` checked as a directory the round's files can be written into."""
    try:
        return output_dir(path, option=option)
    except OutputPathError as exc:
        raise ConfigError(str(exc)) from None
