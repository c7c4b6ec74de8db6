"""Cached payload bytes -> frame of strings, for either form the cache holds (API JSON rows or a
CSV export). Shared by the series loader, the importer and the commit checks. Every decode goes
through the boundary of :mod:`pipeline.data.core.decoding`, so no decoder exception escapes unnamed."""
from __future__ import annotations

import pandas as pd

from pipeline.data.core.cache import CachedPayload
from pipeline.data.core.decoding import decode_boundary, decode_csv_frame, decode_json_records


def read_csv_bytes(data: bytes, *, source: str) -> pd.DataFrame:
    """All cells as strings (so validation sees exactly what the file says)."""
    return decode_csv_frame(data, source=source)


def rows_frame(rows: list[dict[str, object]], *, source: str = "payload") -> pd.DataFrame:
    """Socrata JSON rows -> frame of strings (absent keys, i.e. nulls, become NA)."""
    with decode_boundary("rows", source):
        frame = pd.DataFrame.from_records(rows)
        return frame.astype("string") if len(frame.columns) else frame


def decode_cached(cached: CachedPayload) -> pd.DataFrame:
    source = str(cached.path)
    if cached.path.suffix == ".csv":
        return read_csv_bytes(cached.payload, source=source)
    return rows_frame(decode_json_records(cached.payload, source=source), source=source)
