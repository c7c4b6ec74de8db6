"""Live with cache fallback: the one policy every source's loader follows (DataSF, CDPH, NHSN).

A live fetch ends in one of three ways, and each source's loader treats them alike:

* the source could not be reached after every retry (:class:`~pipeline.data.core.transport.
  NetworkError`): the cache is used, and the run's later fetches from the same host go straight
  to the cache (``unreachable``); without a cache the source's cache reader raises its
  :class:`~pipeline.errors.OfflineError` naming the import command;
* the payload was fetched but may not be stored: refused by the validation gate, the revision
  policy, a decoder, a 4xx, a refused redirect (:class:`~pipeline.errors.DataSourceError`), or the
  dataset's cache lock is held longer than ``lock_timeout_s`` by another run
  (:class:`~pipeline.io.LockTimeoutError`: a commit holds the lock for milliseconds, so a lock
  held this long belongs to a stuck run; readers take no lock, so the committed copy is still
  readable). The cache is used with a note saying why; without a cache the error itself is
  raised. The CDPH loader used to end a held lock in "still locked", rc 1, after 120 s (a live
  ``forecast --county`` stalled 190 s on it; issue 32);
* anything else (a configuration error, a bug) is raised: the cache never hides it.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

from pipeline.data.core.transport import NetworkError
from pipeline.errors import DataSourceError, OfflineError
from pipeline.io import LockTimeoutError

T = TypeVar("T")

# How long a commit waits for a dataset's cache lock before the fetched payload is dropped.
DEFAULT_LOCK_TIMEOUT_S = 20.0


@dataclass(frozen=True)
class Live(Generic[T]):
    """A live result, or (``value`` None) why the cache is used instead."""

    value: T | None
    why: str | None = None
    unreachable: bool = False


def live_or_cache(fetch: Callable[[], T], *, source: str, has_cache: Callable[[], bool]
                  ) -> Live[T]:
    """``fetch()`` under the policy of the module doc (``source`` names the publisher)."""
    try:
        return Live(fetch())
    except NetworkError as exc:
        return Live(None, f"{source} unreachable: {exc}", unreachable=True)
    except LockTimeoutError as exc:
        if not has_cache():
            raise
        return Live(None, f"{source} payload fetched but not stored, cache kept: {exc}")
    except DataSourceError as exc:  # includes ValidationError: gate, policy, decoder, 4xx
        if not has_cache():
            raise
        return Live(None, f"{source} payload rejected, cache kept: {exc}")


def no_cache_error(what: str, directory: object, why: str | None, *, fetch: str,
                   otherwise: str) -> OfflineError:
    """The error of a cache reader with nothing cached: what is missing, where, why the cache
    was asked (when a fetch failed), and the two ways to fill it."""
    reason = f" ({why})" if why else ""
    return OfflineError(f"no cached {what} in {directory}{reason}. Fetch it with `{fetch}` when "
                        f"online, or {otherwise}.")
