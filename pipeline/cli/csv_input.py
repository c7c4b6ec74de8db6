"""Reading observation CSVs for the CLI: a ``time`` (days) or ``date`` column plus named columns."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.errors import ConfigError


def read_timed_csv(path: Path, columns: tuple[str, ...]
                   ) -> tuple[np.ndarray, np.ndarray, pd.Series | None]:
    """(times (T,) in days, values (T, C) with NaN for empty/non-numeric cells, dates or None).

    Errors name the file and the column; times must be strictly increasing. Callers decide
    whether NaN values are allowed (the particle filter skips them, estimates refuse them).
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
    values = frame[list(columns)].apply(pd.to_numeric, errors="coerce").to_numpy(np.float64)
    return times, np.array(values), dates
