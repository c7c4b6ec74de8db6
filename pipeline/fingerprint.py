"""SHA-256 fingerprints of what a result is computed from: objects (recursively) and the code.

What counts, by type: a dataclass by its public fields (private ones, ``_name``, are derived
caches and are skipped), a torch module by its layers' classes, weights, buffers and public
settings, arrays and tensors by dtype, shape and bytes, mappings and sequences item by item,
scalars and strings by their ``repr``. An object of any other type is refused
(:class:`FingerprintError`) rather than keyed unsafely. :func:`code_fingerprint` hashes every
source file of the ``pipeline`` package, so a result keyed with it is recomputed after any change
to the code. The forecast memo (:mod:`pipeline.backtest.memo`) and the training-data digests
(:mod:`pipeline.training.digests`) key their entries with these.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from numpy.typing import NDArray

from pipeline.errors import FlowcastError

PACKAGE_ROOT = Path(__file__).resolve().parent     # the pipeline package


class FingerprintError(FlowcastError):
    """An object that cannot be fingerprinted (a result would be keyed unsafely)."""


def _update(h: Any, obj: object) -> None:
    """Feed ``obj`` into the hash ``h``: its type, then its content (recursively)."""
    h.update(type(obj).__qualname__.encode())
    if obj is None or isinstance(obj, (bool, int, float, str, bytes)):
        h.update(repr(obj).encode())
    elif isinstance(obj, pd.Timestamp):
        h.update(str(obj.value).encode())
    elif isinstance(obj, pd.DatetimeIndex):
        _update_array(h, obj.as_unit("ns").to_numpy(dtype=np.int64))
    elif isinstance(obj, np.ndarray):
        _update_array(h, obj)
    elif isinstance(obj, (np.generic,)):
        _update_array(h, np.asarray(obj))
    elif isinstance(obj, torch.Tensor):
        _update_array(h, obj.detach().cpu().numpy())
    elif isinstance(obj, torch.nn.Module):
        _update_module(h, obj)
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            if not f.name.startswith("_"):
                h.update(f.name.encode())
                _update(h, getattr(obj, f.name))
    elif isinstance(obj, Mapping):
        for key, value in obj.items():
            _update(h, key)
            _update(h, value)
    elif isinstance(obj, (list, tuple)):
        h.update(str(len(obj)).encode())
        for item in obj:
            _update(h, item)
    elif hasattr(obj, "__dict__") and not callable(obj):
        _update(h, {k: v for k, v in vars(obj).items() if not k.startswith("_")})
    else:
        raise FingerprintError(f"cannot fingerprint a {type(obj).__qualname__}")


def _update_array(h: Any, array: NDArray[Any]) -> None:
    h.update(f"{array.dtype.str}{array.shape}".encode())
    h.update(np.ascontiguousarray(array).tobytes())


def _update_module(h: Any, module: torch.nn.Module) -> None:
    """A torch module: its layers' classes, its weights and buffers, its public settings."""
    for name, child in module.named_modules():
        h.update(f"{name}:{type(child).__qualname__}".encode())
    for name, tensor in module.state_dict().items():
        h.update(name.encode())
        _update_array(h, tensor.detach().cpu().numpy())
    _update(h, {k: v for k, v in vars(module).items()
                if not k.startswith("_") and k != "training"
                and not isinstance(v, (torch.nn.Module, torch.Tensor))})


def fingerprint(*objects: object) -> str:
    """Hex SHA-256 of ``objects`` (see the module docstring for what counts)."""
    h = hashlib.sha256()
    for obj in objects:
        _update(h, obj)
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """SHA-256 of every source file of the ``pipeline`` package (path and bytes)."""
    h = hashlib.sha256()
    for path in sorted(PACKAGE_ROOT.rglob("*.py")):
        h.update(path.relative_to(PACKAGE_ROOT).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()
