"""The one place a command's ``--out`` is checked, before any work (issue 22).

Every ``--out`` names either a file or a directory, and the rule is the same for every command:

* ``--out FILE`` (``smc filter``, ``data sir``, ``simulate``): an existing *directory* is refused
  with an error that names it and suggests a file inside it (flowcast never invents a file name
  there); an existing *file* is replaced atomically (the old one stays whole until the new one
  is complete, ``pipeline.io.atomic_open``);
* ``--out DIR`` (``data plot``, ``backtest``, ``demo kinetic``): an existing *file* is refused;
  a missing directory is created when written; the files written inside it are replaced atomically;
* for both, missing parent directories are created, and a parent that is a file, or a nearest
  existing directory that is not writable, is refused.

The checks run before data are loaded or anything simulated, so a wrong path costs nothing.
Before, a directory given as a file ended in ``IsADirectoryError`` and a file given as a
directory in ``FileExistsError``, both tracebacks.
"""
from __future__ import annotations

import os
from pathlib import Path

from pipeline.errors import ConfigError


class OutputPathError(ConfigError):
    """An output path of the wrong kind (a directory for a file, or the reverse), or one that
    cannot be created."""


def _check_parents(path: Path, option: str) -> None:
    """The nearest existing ancestor must be a writable directory (it receives the output)."""
    for parent in path.absolute().parents:
        if not parent.exists():
            continue
        if not parent.is_dir():
            raise OutputPathError(f"{option} {path}: {parent} is a file, so {path} cannot be "
                                  f"created under it")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise OutputPathError(f"{option} {path}: cannot write into {parent} (permission "
                                  f"denied)")
        return


def output_file(path: Path, *, option: str = "--out", example: str = "out.csv") -> Path:
    """``path`` checked as a file to write (see module doc); returned unchanged."""
    if path.is_dir():
        raise OutputPathError(f"{option} {path} is a directory; {option} names the file to "
                              f"write, e.g. {path / example}")
    if path.exists() and not path.is_file():
        raise OutputPathError(f"{option} {path} exists and is not a regular file")
    _check_parents(path, option)
    return path


def output_dir(path: Path, *, option: str = "--out") -> Path:
    """``path`` checked as a directory to write into (see module doc); the writers create it
    (and its missing parents) when they write, so a failed command leaves no empty folder."""
    if path.exists() and not path.is_dir():
        raise OutputPathError(f"{option} {path} is a file; {option} names a directory (the "
                              f"outputs are written inside it)")
    _check_parents(path, option)
    return path
