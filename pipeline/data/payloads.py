"""Cached payload bytes -> frame of strings, for either form the cache holds (API JSON rows or a
CSV export). Shared by the series loader, the importer and the commit checks."""
from __future__ import annotations

import io
import json

import pandas as pd

from pipeline.data.cache import CachedPayload
from pipeline.errors import DataSourceError, ValidationError


def read_csv_bytes(data: bytes, *, source: str) -> pd.DataFrame:
    """All cells as strings (so validation sees exactly what the file says)."""
    if not data.strip():
        raise ValidationError(f"{source}: empty file")
    try:
        return pd.read_csv(io.BytesIO(data), dtype=str, keep_default_na=False,
                           na_values=[""], skipinitialspace=True)
    except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as exc:
        raise ValidationError(f"{source}: not a readable CSV: {exc}") from exc


def rows_frame(rows: list[dict[str, object]]) -> pd.DataFrame:
    """Socrata JSON rows -> frame of strings (absent keys, i.e. nulls, become NA)."""
    frame = pd.DataFrame.from_records(rows)
    return frame.astype("string") if len(frame.columns) else frame


def decode_cached(cached: CachedPayload) -> pd.DataFrame:
    source = str(cached.path)
    if cached.path.suffix == ".csv":
        return read_csv_bytes(cached.payload, source=source)
    try:
        rows = json.loads(cached.payload)
    except json.JSONDecodeError as exc:
        raise DataSourceError(f"{source}: cached JSON unreadable: {exc}") from exc
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise DataSourceError(f"{source}: cached JSON is not an array of objects")
    return rows_frame(rows)
