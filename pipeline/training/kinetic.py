"""Optimal-transport-inspired kinetic-energy loss (paper, "Optimal Transport-inspired Kinetic Term").

    L(theta) = l1 * E[-log p_X(x)]
             + l2 * 1/(L-1) * sum_{l=1}^{L-1} E[ || f_{l+1}(x) - f_l(x) ||_2 ]
             + l3 * 1/(L-1) * sum_{l=1}^{L-1} E[ -log p_Z(f_l(x)) ]

Reading of the paper used here:
- ``f_l(x)`` is the output of layer ``l`` of the flow going from data to base: ``f_0 = x`` and
  ``f_L = z`` (``ConditionalFlow.layer_outputs``), each layer being [permutation, LU linear,
  masked affine autoregressive].
- Both sums run over l = 1 .. L-1, as written in the paper: the kinetic sum covers the L-1
  displacements between consecutive layer outputs f_1 -> f_2 -> ... -> f_L (the first step
  x -> f_1 is not penalised), and the prior-matching sum scores the L-1 *intermediate* outputs
  f_1 .. f_{L-1} under the base (f_L is already scored by the likelihood term). Both are
  averaged with 1/(L-1), so L >= 2 is required when l2 or l3 is non-zero.
- The norm is the Euclidean norm per sample (not squared), averaged over the batch.
- With a conditional base, p_Z(f_l(x)) is the base evaluated with the *same* context as x.
- The expectation is the batch mean; with l2 = l3 = 0 the loss is exactly the mean NLL.

In the estimator everything is computed on standardized targets, so the path lengths are in
standard-deviation units of the target.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from pipeline.errors import ConfigError
from pipeline.models.maf.base import ConditionalFlow, FlowTrajectory

if TYPE_CHECKING:
    from pipeline.models.estimator import ConditionalEstimator


@dataclass(frozen=True)
class KineticWeights:
    """(lambda1, lambda2, lambda3) of the loss; the default is plain maximum likelihood."""

    nll: float = 1.0               # lambda1
    path_length: float = 0.0       # lambda2, the kinetic term
    intermediate_nll: float = 0.0  # lambda3, the layer-wise prior matching term

    def __post_init__(self) -> None:
        for name in ("nll", "path_length", "intermediate_nll"):
            value = getattr(self, name)
            if not (value >= 0.0 and value < float("inf")):
                raise ConfigError(f"KineticWeights.{name}={value!r}: must be finite and >= 0")

    @property
    def is_plain_likelihood(self) -> bool:
        return self.path_length == 0.0 and self.intermediate_nll == 0.0


@dataclass(frozen=True)
class KineticLoss:
    """The weighted total and its three (unweighted) parts, each a scalar tensor.

    ``path_length`` and ``intermediate_nll`` are the layer-averaged terms (the 1/(L-1) sums);
    they are zero tensors when their weight is zero (then they are not computed).
    """

    total: Tensor
    nll: Tensor
    path_length: Tensor
    intermediate_nll: Tensor


def path_lengths(outputs: list[Tensor]) -> Tensor:
    """E||f_{l+1} - f_l|| for l = 0 .. L-1 (batch means), shape (L,)."""
    return torch.stack([(later - earlier).norm(dim=-1).mean()
                        for earlier, later in zip(outputs[:-1], outputs[1:])])


def kinetic_loss_from_trajectory(trajectory: FlowTrajectory,
                                 base_log_prob: Callable[[Tensor], Tensor],
                                 weights: KineticWeights) -> KineticLoss:
    """The loss from a flow trajectory. ``base_log_prob(z)`` scores (B, D) points under the
    (conditional) base with the batch's own contexts."""
    outputs = trajectory.outputs
    layers = len(outputs) - 1
    log_likelihood = base_log_prob(trajectory.latent) + trajectory.log_abs_det
    nll = -log_likelihood.mean()
    zero = nll.new_zeros(())
    if weights.is_plain_likelihood:
        # No extra work and bit-for-bit the plain maximum-likelihood objective.
        total = nll if weights.nll == 1.0 else weights.nll * nll
        return KineticLoss(total, nll, zero, zero)
    if layers < 2:
        raise ConfigError(f"the kinetic terms average over L-1 layers; the flow has L={layers} "
                          f"(KineticWeights.path_length={weights.path_length}, "
                          f"intermediate_nll={weights.intermediate_nll} need L >= 2)")
    kinetic = path_lengths(outputs)[1:].mean() if weights.path_length > 0 else zero
    prior = (torch.stack([-base_log_prob(f).mean() for f in outputs[1:-1]]).mean()
             if weights.intermediate_nll > 0 else zero)
    total = weights.nll * nll + weights.path_length * kinetic + weights.intermediate_nll * prior
    return KineticLoss(total, nll, kinetic, prior)


def kinetic_loss_terms(model: ConditionalFlow | ConditionalEstimator, target: Tensor,
                       context: Tensor, mask: Tensor | None = None,
                       weights: KineticWeights = KineticWeights()) -> KineticLoss:
    """The loss and its parts for one batch, in one pass through the flow.

    ``model`` is either a ``ConditionalFlow`` (``context`` (B, E) is the flow context, ``mask``
    must be None) or a ``ConditionalEstimator`` (``target`` (B, D), ``context`` (B, R, C) and
    ``mask`` (B, R) *standardized*, as in training; the context is embedded by its encoder).
    """
    if isinstance(model, ConditionalFlow):
        if mask is not None:
            raise ValueError("a ConditionalFlow takes a (B, E) context and no mask")
        flow, flow_context = model, context
    else:
        flow, flow_context = model.flow, model.embed(context, mask)
    trajectory = flow.trajectory(target, flow_context)
    return kinetic_loss_from_trajectory(
        trajectory, lambda z: flow.base_log_prob(z, flow_context), weights)


def kinetic_loss(model: ConditionalFlow | ConditionalEstimator, target: Tensor,
                 context: Tensor, mask: Tensor | None = None,
                 weights: KineticWeights = KineticWeights()) -> Tensor:
    """The scalar training loss (``kinetic_loss_terms(...).total``); see there for the inputs."""
    return kinetic_loss_terms(model, target, context, mask, weights).total
