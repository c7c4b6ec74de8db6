"""Model checkpoints: atomic, weights-only, self-describing, verified on load.

File layout (one ``torch.save`` dictionary, read back with ``torch.load(weights_only=True)``, so
loading a file can never execute code):

* ``format`` = ``"flowcast-checkpoint"`` and ``format_version`` (:data:`FORMAT_VERSION`),
* ``config``: the :class:`~pipeline.models.estimator.EstimatorConfig` as a plain dict,
* ``state_dict``: the estimator's tensors, and ``state_sha256``: a SHA-256 over their names,
  dtypes, shapes and bytes (detects silent corruption that still unpickles),
* ``stats``: the training-split standardization as tensors (``context_mean`` ...) and the name
  of its ``target_transform`` (absent in older files: identity),
* ``versions``: flowcast, torch, nflows, zuko, python; ``data_sha256``: the training data hash,
* ``history``: the training history (list of plain dicts), ``extra``: free plain data (train
  config, kinetic weights, best validation NLL ...), ``created_at`` (UTC ISO time).

Loading rejects, with :class:`~pipeline.errors.CheckpointError` naming the file and problem: a
missing, truncated or corrupt file; a foreign file or another format version; tensors whose hash
does not match; a config different from the one the caller expects ("checkpoint ... was trained
for encoder 'mamba', asked for 'transformer'"); weights that do not fit the config.
"""
from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import platform
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import torch
from torch import Tensor, nn

from pipeline.errors import CheckpointError, ConfigError
from pipeline.io import atomic_open

if TYPE_CHECKING:  # annotations only: the functions below import these where they use them
    from _typeshed import DataclassInstance

    from pipeline.models.estimator import ConditionalEstimator, EstimatorConfig
    from pipeline.models.standardization import Standardization

_D = TypeVar("_D", bound="DataclassInstance")

FORMAT = "flowcast-checkpoint"
FORMAT_VERSION = 1
_STATS_FIELDS = ("context_mean", "context_std", "target_mean", "target_std")


@dataclass(frozen=True)
class CheckpointMeta:
    """What a checkpoint records besides the model. ``history`` and ``extra`` are the plain data
    the writer stored (``torch.load`` output: dicts of str, numbers, lists, None)."""

    format_version: int
    versions: dict[str, str]
    data_sha256: str
    history: list[dict[str, Any]]
    extra: dict[str, Any]
    created_at: str
    path: Path


@dataclass
class LoadedCheckpoint:
    estimator: ConditionalEstimator
    config: EstimatorConfig
    meta: CheckpointMeta


def package_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in ("flowcast", "torch", "nflows", "zuko"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    return out


def state_sha256(state: dict[str, Tensor]) -> str:
    """SHA-256 over (name, dtype, shape, bytes) of every tensor, in name order."""
    digest = hashlib.sha256()
    for name in sorted(state):
        tensor = state[name].detach().cpu().contiguous()
        digest.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes()
                      if tensor.numel() else b"")
    return digest.hexdigest()


def save_checkpoint(path: str | Path, estimator: nn.Module, *, config: EstimatorConfig,
                    stats: Standardization,
                    history: Sequence[Mapping[str, object]] | None = None,
                    data_sha256: str = "", extra: Mapping[str, object] | None = None) -> Path:
    """Write ``estimator``'s weights with everything needed to rebuild it (atomic)."""
    if not dataclasses.is_dataclass(config):
        raise ConfigError(f"checkpoint config must be a dataclass (EstimatorConfig), "
                          f"got {type(config).__name__}")
    state = {k: v.detach().cpu().clone() for k, v in estimator.state_dict().items()}
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": _plain(dataclasses.asdict(config)),
        "config_type": f"{type(config).__module__}.{type(config).__qualname__}",
        "state_dict": state,
        "state_sha256": state_sha256(state),
        "stats": {**{name: t.detach().cpu().clone() for name, t in stats.as_dict().items()},
                  "target_transform": stats.target_transform},
        "versions": package_versions(),
        "data_sha256": data_sha256,
        "history": _plain(list(history or [])),
        "extra": _plain(dict(extra or {})),
        "created_at": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    }
    target = Path(path)
    with atomic_open(target, "wb") as handle:
        torch.save(payload, handle)
    return target


def load_checkpoint(path: str | Path,
                    expected_config: EstimatorConfig | None = None) -> LoadedCheckpoint:
    """Read, verify and rebuild an estimator; see the module docstring for what is rejected."""
    target = Path(path)
    payload = _read_payload(target)
    config = _config_from_payload(target, payload)
    if expected_config is not None:
        _check_config(target, config, expected_config)
    stats = _stats_from_payload(target, payload)
    estimator = _rebuild(target, config, stats, payload["state_dict"])
    meta = CheckpointMeta(format_version=payload["format_version"],
                          versions=dict(payload.get("versions", {})),
                          data_sha256=str(payload.get("data_sha256", "")),
                          history=list(payload.get("history", [])),
                          extra=dict(payload.get("extra", {})),
                          created_at=str(payload.get("created_at", "")), path=target)
    return LoadedCheckpoint(estimator=estimator, config=config, meta=meta)


# ----------------------------------------------------------------------------- reading


def _read_payload(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises RuntimeError/UnpicklingError/EOFError/... here
        raise CheckpointError(f"checkpoint {path} is truncated or corrupt (torch.load with "
                              f"weights_only=True failed: {type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else ''})") from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a flowcast checkpoint (no format={FORMAT!r} tag)")
    found = payload.get("format_version")
    if found != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path} has format version {found!r}; this flowcast "
                              f"reads version {FORMAT_VERSION} (retrain or use a matching "
                              "flowcast release)")
    for key in ("config", "state_dict", "state_sha256", "stats"):
        if key not in payload:
            raise CheckpointError(f"checkpoint {path} lacks the {key!r} entry")
    if state_sha256(payload["state_dict"]) != payload["state_sha256"]:
        raise CheckpointError(f"checkpoint {path} is corrupt: its weights do not match the "
                              "SHA-256 recorded when it was saved")
    return payload


def _config_from_payload(path: Path, payload: dict[str, Any]) -> EstimatorConfig:
    from pipeline.models.estimator import EstimatorConfig

    try:
        return dataclass_from_dict(EstimatorConfig, payload["config"])
    except (TypeError, ValueError, ConfigError) as exc:
        raise CheckpointError(f"checkpoint {path}: its config does not fit this flowcast's "
                              f"EstimatorConfig ({exc})") from exc


def _stats_from_payload(path: Path, payload: dict[str, Any]) -> Standardization:
    from pipeline.models.standardization import Standardization

    stats = payload["stats"]
    missing = [name for name in _STATS_FIELDS if name not in stats]
    if missing:
        raise CheckpointError(f"checkpoint {path}: standardization lacks {missing}")
    # Checkpoints from before target transforms hold identity statistics.
    return Standardization(**{name: stats[name] for name in _STATS_FIELDS},
                           target_transform=str(stats.get("target_transform", "identity")))


def _rebuild(path: Path, config: EstimatorConfig, stats: Standardization,
             state: dict[str, Tensor]) -> ConditionalEstimator:
    from pipeline.models.estimator import build_estimator

    estimator = build_estimator(config, stats)
    try:
        estimator.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise CheckpointError(f"checkpoint {path}: weights do not fit its config "
                              f"({str(exc).splitlines()[0]})") from exc
    estimator.eval()
    return estimator


def _check_config(path: Path, saved: EstimatorConfig, expected: EstimatorConfig) -> None:
    """Name the first field where the saved config differs from the expected one."""
    saved_flat = _flatten(dataclasses.asdict(saved))
    expected_flat = _flatten(dataclasses.asdict(expected))
    for key in sorted(set(saved_flat) | set(expected_flat)):
        a, b = saved_flat.get(key, "<absent>"), expected_flat.get(key, "<absent>")
        if a != b:
            label = key.replace(".", " ").replace("_", " ")
            raise CheckpointError(f"checkpoint {path} was trained for {label} {a!r}, "
                                  f"asked for {b!r}")


def _flatten(data: Mapping[str, object], prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, f"{name}."))
        else:
            out[name] = list(value) if isinstance(value, tuple) else value
    return out


# ----------------------------------------------------------------------------- plain data


def _plain(value: object) -> object:
    """Only what ``weights_only`` unpickling accepts: dicts, lists, str, numbers, None, tensors."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _plain(dataclasses.asdict(value))
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if value is None or isinstance(value, (bool, int, float, str, Tensor)):
        return value
    raise ConfigError(f"cannot store a value of type {type(value).__name__} in a checkpoint: "
                      f"{value!r}")


def dataclass_from_dict(cls: type[_D], data: Mapping[str, Any]) -> _D:
    """Rebuild a (nested) frozen dataclass from ``dataclasses.asdict`` output (lists → tuples)."""
    if not isinstance(data, dict):
        raise TypeError(f"{cls.__name__}: expected a dict, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = set(data) - names
    if unknown:
        raise TypeError(f"{cls.__name__} has no fields {sorted(unknown)}")
    kwargs = {name: _coerce(hints.get(name, Any), value) for name, value in data.items()}
    return cls(**kwargs)


def _coerce(hint: object, value: object) -> object:
    """``value`` (plain data) as the annotation ``hint`` wants it: dicts become dataclasses,
    lists tuples."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(hint) if a is not type(None)]
        if value is None:
            return None
        for option in options:
            if _is_dataclass_type(option) and isinstance(value, dict):
                return dataclass_from_dict(option, value)
        return _coerce(options[0], value) if len(options) == 1 else _tuplify(value)
    if _is_dataclass_type(hint) and isinstance(value, dict):
        return dataclass_from_dict(hint, value)
    if origin is tuple or hint is tuple:
        return _tuplify(value)
    return value


def _is_dataclass_type(hint: object) -> typing.TypeGuard[type[DataclassInstance]]:
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def _tuplify(value: object) -> object:
    return tuple(_tuplify(v) for v in value) if isinstance(value, list) else value
