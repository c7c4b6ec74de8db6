"""Context transforms: the coordinates an estimator reads its observation windows in.

The one place that knows them. ``EstimatorConfig.context_transform`` names one; the estimator
applies it to every raw window it is given (:meth:`ConditionalEstimator.log_prob`, ``sample``,
``noise_to_data``), and the datasets that train such a model store their contexts already
transformed by the same function, so its standardization is fitted in these coordinates.

* ``identity``: the window as observed (the paper's set-ups).
* ``sir-log-infectious``: for S/I/R windows, the infectious share I (channel 1) becomes
  log(max(I, 0) + ε), ε = :data:`INFECTIOUS_FLOOR` (about one person in San Francisco). The SF
  series' I spans three decades (1e-5 … 2e-2): on a linear scale, standardized, the growth of a
  small wave is a few thousandths of a unit and an MLP encoder cannot read it; on a log scale
  growth is a slope at every level. S and R (near 1 and slowly rising) and the time channels
  are left as they are.
"""
from __future__ import annotations

from typing import Final

import torch
from torch import Tensor

from pipeline.errors import ConfigError

IDENTITY: Final = "identity"
SIR_LOG_INFECTIOUS: Final = "sir-log-infectious"
CONTEXT_TRANSFORMS: tuple[str, ...] = (IDENTITY, SIR_LOG_INFECTIOUS)
INFECTIOUS_FLOOR = 1e-6
_INFECTIOUS_CHANNEL = 1


def check_context_transform(name: str, context_channels: int) -> None:
    """Raise ConfigError for an unknown transform or a window it cannot read."""
    if name not in CONTEXT_TRANSFORMS:
        raise ConfigError(f"unknown context transform {name!r}; known: {list(CONTEXT_TRANSFORMS)}")
    if name == SIR_LOG_INFECTIOUS and context_channels < 4:
        raise ConfigError(f"context transform {name!r} needs S, I, R and a time channel; the "
                          f"context has {context_channels} channels")


def apply_context_transform(name: str, context: Tensor) -> Tensor:
    """``context (..., R, C)`` raw -> the transform's coordinates (a new tensor, same dtype)."""
    if name == IDENTITY:
        return context
    check_context_transform(name, context.shape[-1])
    infectious = context[..., _INFECTIOUS_CHANNEL].double().clamp(min=0.0) + INFECTIOUS_FLOOR
    out = context.clone()
    out[..., _INFECTIOUS_CHANNEL] = torch.log(infectious).to(context.dtype)
    return out
