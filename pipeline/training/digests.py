"""Training-data hashes remembered by what the data are cut from.

A model-store key names the SHA-256 of a model's training windows
(:mod:`pipeline.training.model_store`). Cutting the windows only to hash them is most of what a
run that reuses every model does: the flow member's synthetic windows take 1.7 s, and the two
dozen nf-real refits of a weekly run 2 s more, to find models that are all stored. So the hashes
are kept beside the models, in ``<store>/.digests/<fingerprint>.json``: one small file per
fingerprint (:mod:`pipeline.fingerprint`) of the inputs the windows are computed from *and of
the pipeline's code*, so a change to the windowing code, to a config or to a single count of the
data is a new fingerprint and the windows are cut again. A digest file is a cache: written
atomically, and one that cannot be read is reported and recomputed.
"""
from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pipeline.fingerprint import code_fingerprint, fingerprint
from pipeline.io import atomic_write_json

log = logging.getLogger(__name__)
DIGESTS_DIR = ".digests"
Digests = dict[str, str]


@dataclass(frozen=True)
class DataDigests:
    """The digest files under ``<store_root>/.digests`` (module docstring)."""

    store_root: Path

    def path(self, inputs: tuple[object, ...]) -> Path:
        return self.store_root / DIGESTS_DIR / f"{fingerprint(code_fingerprint(), *inputs)}.json"

    def get_or_compute(self, inputs: tuple[object, ...],
                       compute: Callable[[], Digests]) -> Digests:
        """The digests recorded for ``inputs`` (and this code), else ``compute()``, recorded."""
        path = self.path(inputs)
        try:
            recorded = json.loads(path.read_text(encoding="utf-8"))["digests"]
            if isinstance(recorded, dict) and all(isinstance(v, str) for v in recorded.values()):
                return recorded
            log.warning("ignoring malformed training-data digests %s", path)
        except FileNotFoundError:
            pass
        except (OSError, ValueError, KeyError, TypeError) as error:
            log.warning("ignoring unreadable training-data digests %s (%s)", path, error)
        digests = compute()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_json(path, {"digests": digests})
        except OSError as error:        # a cache: the next run computes them again
            log.warning("could not record training-data digests %s: %s", path, error)
        return digests
