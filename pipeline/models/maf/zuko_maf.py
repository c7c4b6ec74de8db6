"""zuko backend: the same architecture as ``nflows_maf`` built from zuko pieces.

Each layer is [reverse permutation, LU linear (+ bias), ``zuko.flows.MaskedAutoregressiveTransform``]
with zuko's ``MonotonicAffineTransform`` at slope e^-B, i.e. log-scale = a / (1 + |a| / B), the
same soft clip as the nflows backend. The base is our conditional diagonal Gaussian
(``base.ConditionalDiagonalGaussian``), not zuko's unconditional ``DiagNormal``.

Context in zuko's MADE: ``MaskedAutoregressiveTransform`` appends the context to the input and
gives every output an all-True adjacency row over the context columns, so ``zuko.nn.MaskedMLP``
routes the context through the hidden layers to *every* output, the first included (checked in
tests/test_flows.py). For D = 1 zuko substitutes an ``ElementWiseTransform`` whose parameters are
an MLP of the context. The MADE here has ``made_blocks`` hidden layers of ``hidden_features``
(nflows uses ``made_blocks`` residual blocks instead, so widths match and depth differs by one
linear layer per block).
"""
from __future__ import annotations

import math
from functools import partial
from typing import cast

import torch
from torch import Tensor, nn
from zuko.flows import MaskedAutoregressiveTransform
from zuko.transforms import LULinearTransform, MonotonicAffineTransform

from pipeline.models.maf.base import (ConditionalFlow, FlowConfig, LUParameters,
                                        reverse_permutation)


class ZukoLayer(nn.Module):
    """[permutation, LU linear, masked affine autoregressive transform] (data -> base)."""

    order: Tensor  # buffers, registered in __init__
    inverse_order: Tensor

    def __init__(self, config: FlowConfig) -> None:
        super().__init__()
        self.register_buffer("order", reverse_permutation(config.features))
        self.register_buffer("inverse_order", torch.argsort(reverse_permutation(config.features)))
        self.linear = LUParameters(config.features)
        univariate = partial(MonotonicAffineTransform, slope=math.exp(-config.max_log_scale))
        self.autoregressive = MaskedAutoregressiveTransform(
            features=config.features, context=config.context_features,
            univariate=univariate, hidden_features=(config.hidden_features,) * config.made_blocks)
        self.has_context = config.context_features > 0

    def _linear(self) -> LULinearTransform:
        return LULinearTransform(self.linear.lu_matrix())

    def forward(self, x: Tensor, context: Tensor) -> tuple[Tensor, Tensor]:
        x = x[:, self.order]
        linear = self._linear()
        # torch.distributions.Transform.__call__ and its inverse are unannotated; pyright infers
        # ``| None`` from their cache paths, which never return None.
        x = cast(Tensor, linear(x)) + self.linear.bias
        log_det_linear = torch.log(self.linear.diagonal()).sum().expand(x.shape[0])
        transform = self.autoregressive(context if self.has_context else None)
        x, log_det_affine = transform.call_and_ladj(x)
        return x, log_det_linear + log_det_affine

    def inverse(self, z: Tensor, context: Tensor) -> Tensor:
        transform = self.autoregressive(context if self.has_context else None)
        z = transform.inv(z)
        z = cast(Tensor, self._linear().inv(z - self.linear.bias))  # see forward
        return z[:, self.inverse_order]


class ZukoMAF(ConditionalFlow):
    """Conditional MAF from zuko pieces with our conditional base."""

    def __init__(self, config: FlowConfig) -> None:
        super().__init__(config)
        self.flow_layers = nn.ModuleList(ZukoLayer(config) for _ in range(config.layers))

    def _forward_layer(self, index: int, x: Tensor, context: Tensor) -> tuple[Tensor, Tensor]:
        return self.flow_layers[index](x, context)

    def _inverse_layer(self, index: int, z: Tensor, context: Tensor) -> Tensor:
        layer = self.flow_layers[index]
        assert isinstance(layer, ZukoLayer)  # ModuleList items are typed as plain Modules
        return layer.inverse(z, context)
