"""Target transforms: the coordinates a conditional flow models its target in.

The one place that knows them. The estimator (``pipeline.models.estimator``) and the dataset
standardization (``pipeline.training.datasets.Standardization``) both go through
:func:`get_target_transform`; a model's choice is recorded in ``EstimatorConfig.target_transform``
(so a checkpoint rebuilds it; configs without the field are ``"identity"``).

* ``identity``: the flow models the target as it is (the paper's set-ups). D_flow = D.
* ``sir-log-ratio``: for SIR targets (S, I, R[, beta, gamma, ...]). The flow models

      u = (log(I/S), log(R/S), log beta, log gamma, ...)

  the additive log-ratio (alr) of the simplex point (S, I, R) plus the logs of the (positive)
  rates, so D_flow = D - 1. Every u maps back to a valid target: the inverse is
  (S, I, R) = softmax(0, u1, u2) and rate = exp(u_k), so samples lie on the open simplex with
  positive rates *by construction*, not by clipping. Since S is determined by I and R, the
  density in original units is a density w.r.t. (I, R, beta, gamma) with S = 1 - I - R:

      log p(I, R, beta, gamma) = log p_u(u) + log|det du/d(I, R, beta, gamma)|
                               = log p_u(u) - log(I R S) - log(beta gamma)

  (du/d(I, R) has determinant 1/(I R S): (1/I + 1/S)(1/R + 1/S) - 1/S^2 = (S + I + R)/(I R S)).
  Targets outside the support (a non-positive entry, or S + I + R off 1 by more than
  :data:`SIMPLEX_TOLERANCE`) have density 0: ``in_support`` is False there and the estimator's
  ``log_prob`` returns -inf. The forward map reads (S, I, R) as a composition (the alr is
  invariant to its scale), and the log-det is taken at the closed composition, so rounding in
  S + I + R (float32 targets) does not bias either.

The transforms compute in float64 and return the input's dtype: in float32, exp of a log-ratio
near -90 would otherwise underflow I to 0 a few ulps earlier than necessary.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Final, Literal

import torch
from torch import Tensor

from pipeline.errors import ConfigError

TargetTransformName = Literal["identity", "sir-log-ratio"]
IDENTITY: Final = "identity"
SIR_LOG_RATIO: Final = "sir-log-ratio"
TARGET_TRANSFORMS: tuple[str, ...] = (IDENTITY, SIR_LOG_RATIO)
# |S + I + R - 1| above this is off the simplex (float32 targets sum to 1 within ~1e-7).
SIMPLEX_TOLERANCE = 1e-4
_SIMPLEX = 3  # S, I, R: the first three target components of an SIR model


class TargetTransform(ABC):
    """A bijection between the target's support (original units, D components) and R^D_flow."""

    name: str

    @abstractmethod
    def flow_features(self, features: int) -> int:
        """D_flow, the flow's dimension, for a target of ``features`` components."""

    @abstractmethod
    def target_features(self, flow_features: int) -> int:
        """D, the target's size in original units, for a flow of ``flow_features`` dimensions."""

    @abstractmethod
    def forward(self, target: Tensor) -> Tensor:
        """Original units ``(..., D)`` -> flow coordinates ``(..., D_flow)``."""

    @abstractmethod
    def inverse(self, u: Tensor) -> Tensor:
        """Flow coordinates ``(..., D_flow)`` -> original units ``(..., D)``."""

    @abstractmethod
    def log_abs_det(self, target: Tensor) -> Tensor:
        """``(...)``: log|det du/dy| at ``target``, y the target's free coordinates (module doc);
        log p_y(target) = log p_u(forward(target)) + this."""

    @abstractmethod
    def in_support(self, target: Tensor) -> Tensor:
        """``(...)`` bool: where ``target`` lies in the transform's domain."""

    def check_features(self, features: int) -> None:
        """Raise ConfigError when the transform cannot model a target of this size."""
        if features < 1:
            raise ConfigError(f"target transform {self.name!r}: features={features} must be >= 1")


class IdentityTransform(TargetTransform):
    """The flow models the target as it is (every real vector is in the support)."""

    name = IDENTITY

    def flow_features(self, features: int) -> int:
        return features

    def target_features(self, flow_features: int) -> int:
        return flow_features

    def forward(self, target: Tensor) -> Tensor:
        return target

    def inverse(self, u: Tensor) -> Tensor:
        return u

    def log_abs_det(self, target: Tensor) -> Tensor:
        return torch.zeros(target.shape[:-1], dtype=target.dtype, device=target.device)

    def in_support(self, target: Tensor) -> Tensor:
        return torch.ones(target.shape[:-1], dtype=torch.bool, device=target.device)


class SIRLogRatioTransform(TargetTransform):
    """(S, I, R, rates...) <-> (log(I/S), log(R/S), log rates...) (module doc)."""

    name = SIR_LOG_RATIO

    def check_features(self, features: int) -> None:
        if features < _SIMPLEX:
            raise ConfigError(f"target transform {self.name!r} needs the SIR state (S, I, R) as "
                              f"the first 3 target components; the target has {features}")

    def flow_features(self, features: int) -> int:
        self.check_features(features)
        return features - 1

    def target_features(self, flow_features: int) -> int:
        return flow_features + 1

    def forward(self, target: Tensor) -> Tensor:
        self.check_features(target.shape[-1])
        y = target.double()
        log_s = torch.log(y[..., :1])
        ratios = torch.log(y[..., 1:_SIMPLEX]) - log_s
        return torch.cat([ratios, torch.log(y[..., _SIMPLEX:])], dim=-1).to(target.dtype)

    def inverse(self, u: Tensor) -> Tensor:
        v = u.double()
        logits = torch.cat([torch.zeros_like(v[..., :1]), v[..., :_SIMPLEX - 1]], dim=-1)
        simplex = torch.softmax(logits, dim=-1)  # S = 1 / (1 + e^u1 + e^u2), stable for any u
        return torch.cat([simplex, torch.exp(v[..., _SIMPLEX - 1:])], dim=-1).to(u.dtype)

    def log_abs_det(self, target: Tensor) -> Tensor:
        self.check_features(target.shape[-1])
        y = target.double()
        composition = y[..., :_SIMPLEX]
        log_closed = torch.log(composition) - torch.log(composition.sum(-1, keepdim=True))
        log_rates = torch.log(y[..., _SIMPLEX:])
        return (-log_closed.sum(-1) - log_rates.sum(-1)).to(target.dtype)

    def in_support(self, target: Tensor) -> Tensor:
        self.check_features(target.shape[-1])
        y = target.double()
        positive = (torch.isfinite(y) & (y > 0)).all(-1)
        on_simplex = (y[..., :_SIMPLEX].sum(-1) - 1.0).abs() <= SIMPLEX_TOLERANCE
        return positive & on_simplex


_TRANSFORMS: dict[str, TargetTransform] = {t.name: t for t in (IdentityTransform(),
                                                               SIRLogRatioTransform())}


def get_target_transform(name: str) -> TargetTransform:
    """The transform called ``name`` (one of :data:`TARGET_TRANSFORMS`)."""
    try:
        return _TRANSFORMS[name]
    except KeyError:
        raise ConfigError(f"unknown target transform {name!r}; known: "
                          f"{list(TARGET_TRANSFORMS)}") from None
