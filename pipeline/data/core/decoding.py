"""The decode boundary: payload bytes -> Python values, or one named rejection (issue 22).

A payload is whatever a remote source or a file handed us; decoding it may fail in ways no list
of exception types anticipates. The fault probe found two that escaped a ``JSONDecodeError``
handler as tracebacks: 200,000 nested ``[`` (``RecursionError``) and a 5,000-digit integer
(``ValueError: Exceeds the limit (4300 digits)``). So every decode runs inside
:func:`decode_boundary`, which turns *any* ``Exception`` raised while decoding into a
:class:`PayloadRejectedError` naming the source, the size and the problem. The caller keeps its
cache (a rejection is a :class:`~pipeline.errors.DataSourceError`); flowcast's own errors pass
through unchanged, and so do ``KeyboardInterrupt``/``SystemExit`` (not ``Exception``).

Memory is bounded *before* decoding: a body over ``max_bytes`` is refused unread
(:func:`check_size`), so a runaway payload cannot exhaust memory in the decoder.

Nothing here is DataSF-specific: any source (DataSF's JSON API and CSV exports, other public
health portals) decodes through :func:`decode_json_records` / :func:`decode_csv_frame`, or wraps
its own parser in :func:`decode_boundary`.
"""
from __future__ import annotations

import contextlib
import io
import json
from collections.abc import Iterator

import pandas as pd

from pipeline.errors import FlowcastError, ValidationError

# A daily series is well under 1 MB; 16 MB of JSON is ~150 MB of Python objects at most.
MAX_PAYLOAD_BYTES = 16 << 20


class PayloadRejectedError(ValidationError):
    """Payload bytes that cannot be decoded (malformed, too deep, too large): refused, the cache
    is kept."""


def _describe(exc: BaseException) -> str:
    """The decoder's own words, with why for the cases whose words do not say it."""
    if isinstance(exc, RecursionError):
        return f"nested too deeply to decode (RecursionError: {exc})"
    if isinstance(exc, MemoryError):
        return "too large to decode in memory (MemoryError)"
    return f"{type(exc).__name__}: {exc}"


@contextlib.contextmanager
def decode_boundary(what: str, source: str, size: int | None = None) -> Iterator[None]:
    """Run the block; any non-flowcast ``Exception`` becomes a :class:`PayloadRejectedError`
    "invalid <what> from <source> (<size> bytes): <problem>"."""
    where = f"{source} ({size} bytes)" if size is not None else source
    try:
        yield
    except FlowcastError:
        raise
    except Exception as exc:  # noqa: BLE001 - the point: no decode failure escapes unnamed
        raise PayloadRejectedError(
            f"invalid {what} from {where}: {_describe(exc)}") from exc


def check_size(data: bytes, *, what: str, source: str,
               max_bytes: int = MAX_PAYLOAD_BYTES) -> None:
    if len(data) > max_bytes:
        raise PayloadRejectedError(f"invalid {what} from {source}: {len(data):,} bytes, more than "
                                   f"the {max_bytes:,} a payload may have; refused unread")


def decode_json_records(data: bytes, *, source: str,
                        max_bytes: int = MAX_PAYLOAD_BYTES) -> list[dict[str, object]]:
    """A JSON array of objects (Socrata rows and the like), or a named rejection."""
    check_size(data, what="JSON", source=source, max_bytes=max_bytes)
    try:
        with decode_boundary("JSON", source, len(data)):
            value = json.loads(data)
    except PayloadRejectedError as exc:
        if isinstance(exc.__cause__, json.JSONDecodeError | UnicodeDecodeError):
            # The common case (a cut-off or HTML body): worded as users have seen it.
            raise PayloadRejectedError(
                f"invalid JSON from {source} ({len(data)} bytes, truncated or damaged): "
                f"{exc.__cause__}") from exc.__cause__
        raise
    if not isinstance(value, list) or not all(isinstance(r, dict) for r in value):
        raise PayloadRejectedError(f"{source}: expected a JSON array of objects, got "
                                   f"{type(value).__name__}")
    return value


def decode_csv_frame(data: bytes, *, source: str,
                     max_bytes: int = MAX_PAYLOAD_BYTES) -> pd.DataFrame:
    """Every cell as a string (validation sees exactly what the file says), or a named
    rejection."""
    check_size(data, what="CSV", source=source, max_bytes=max_bytes)
    if not data.strip():
        raise PayloadRejectedError(f"{source}: empty file")
    try:
        with decode_boundary("CSV", source, len(data)):
            return pd.read_csv(io.BytesIO(data), dtype=str, keep_default_na=False,
                               na_values=[""], skipinitialspace=True)
    except PayloadRejectedError as exc:
        # Kept as worded before the boundary existed: "<file>: not a readable CSV: <why>".
        raise PayloadRejectedError(f"{source}: not a readable CSV: {exc.__cause__}") from exc
