"""Reading observation CSVs for the CLI: a ``time`` (days) or ``date`` column plus named columns."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.errors import ConfigError


def read_timed_csv(path: Path, columns: tuple[str, ...]
                   ) -> tuple[np.ndarray, np.ndarray, pd.Series | None]:
    """(times (T,) in days, values (T, C) with NaN for empty cells, dates or None).

    Errors name the file, the row and the column; a cell that is neither empty nor a number
    (``abc``) is refused; times must be strictly increasing. Callers decide whether NaN values
    are allowed (the particle filter skips them, estimates refuse them).
    """
    if not path.is_file():
        raise ConfigError(f"{path}: file not found")
    try:
        frame = pd.read_csv(path)
    except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as error:
        raise ConfigError(f"{path}: not a readable CSV ({error})") from None
    missing = [c for c in columns if c not in frame.columns]
    if missing:
        raise ConfigError(f"{path}: missing column(s) {missing}; expected {list(columns)} and "
                          f"'time' or 'date' (found {list(frame.columns)})")
    dates = None
    if "time" in frame.columns:
        times = pd.to_numeric(frame["time"], errors="coerce").to_numpy(dtype=np.float64)
    elif "date" in frame.columns:
        dates = pd.to_datetime(frame["date"], errors="coerce")
        if dates.isna().any():
            raise ConfigError(f"{path}: column 'date' has unparseable values at rows "
                              f"{np.flatnonzero(dates.isna().to_numpy())[:5].tolist()}")
        times = ((dates - dates.iloc[0]) / pd.Timedelta(days=1)).to_numpy(dtype=np.float64)
    else:
        raise ConfigError(f"{path}: needs a 'time' or a 'date' column")
    if len(times) < 1 or np.isnan(times).any():
        raise ConfigError(f"{path}: column 'time' is empty or not numeric at rows "
                          f"{np.flatnonzero(np.isnan(times))[:5].tolist()}")
    if len(times) > 1 and not (np.diff(times) > 0).all():
        raise ConfigError(f"{path}: times must be strictly increasing")
    values = np.column_stack([_numeric_column(path, frame[c], c) for c in columns])
    return times, values.astype(np.float64), dates


def _numeric_column(path: Path, column: pd.Series, name: str) -> np.ndarray:
    """The column as floats; empty cells are NaN (missing), any other non-number is an error."""
    numbers = pd.to_numeric(column, errors="coerce")
    bad = (numbers.isna() & column.notna()) | np.isinf(numbers)
    if bad.any():
        row = int(np.flatnonzero(bad.to_numpy())[0])
        raise ConfigError(f"{path}: row {row + 1} (line {row + 2}), column {name!r}: "
                          f"{column.iloc[row]!r} is not a finite number (leave the cell empty "
                          "for a missing observation)")
    return numbers.to_numpy(dtype=np.float64)
