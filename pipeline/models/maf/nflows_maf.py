"""nflows backend, with the MADE context defect fixed.

The defect (nflows 0.14, upstream PR #85 unmerged): MADE gives hidden units degrees 1..D-1 and
an output of degree d may only read hidden units of degree < d. The first output (degree 1)
therefore reads no hidden unit at all: its scale and shift are the final layer's bias, so the
first variable of every autoregressive layer ignores the context (for D >= 2; with D = 1 nflows
happens to give the hidden units degree 0, which is why the bug hides in 1-D tests).

Fix (``ContextMADE``): the context features ``h_c = relu(W_c c + b_c)`` that nflows already adds
to every hidden unit are, in addition, mapped by an unmasked linear layer into *every* output.
``h_c`` depends on the context only, so this is exactly a set of degree-0 hidden units: the
autoregressive property is kept and every output, the first included, depends (non-linearly)
on the context.

Affine parametrisation: log-scale = soft_clip(a, max_log_scale) instead of nflows'
softplus(a) + 1e-3, whose unbounded-above scale and 1e-3 floor let an untrained flow expand a
sample by up to 1000x per layer when sampling (stack.md measured 1e10-1e24 samples early in
training). ``NaiveLinear.inverse`` is broken on torch 2.13, so the linear layer is ``LULinear``.
"""
from __future__ import annotations

import torch
from nflows.transforms.autoregressive import AutoregressiveTransform
from nflows.transforms.lu import LULinear
from nflows.transforms.made import MADE
from nflows.transforms.permutations import Permutation
from torch import Tensor, nn
from torch.nn import functional as F

from pipeline.models.maf.base import ConditionalFlow, FlowConfig, reverse_permutation, soft_clip


class ContextMADE(MADE):
    """nflows MADE (residual blocks) whose context also feeds every output directly."""

    def __init__(self, features: int, hidden_features: int, context_features: int,
                 num_blocks: int, output_multiplier: int) -> None:
        super().__init__(features=features, hidden_features=hidden_features,
                         context_features=context_features or None, num_blocks=num_blocks,
                         output_multiplier=output_multiplier, use_residual_blocks=True,
                         activation=F.relu)
        self.context_output_layer = (nn.Linear(hidden_features, features * output_multiplier)
                                     if context_features else None)

    def forward(self, inputs: Tensor, context: Tensor | None = None) -> Tensor:
        hidden = self.initial_layer(inputs)
        context_term = None
        if self.context_output_layer is not None:
            context_hidden = self.activation(self.context_layer(context))
            hidden = hidden + context_hidden
            context_term = self.context_output_layer(context_hidden)
        for block in self.blocks:
            hidden = block(hidden, context)
        outputs = self.final_layer(hidden)
        if context_term is not None:
            outputs = outputs + context_term
        return outputs


class ContextAffineAutoregressive(AutoregressiveTransform):
    """Masked affine autoregressive transform z = exp(s) * x + t on top of ``ContextMADE``.

    ``(s_d, t_d)`` are functions of ``x_{<d}`` and the context; s is soft-clipped.
    """

    def __init__(self, features: int, hidden_features: int, context_features: int,
                 num_blocks: int, max_log_scale: float) -> None:
        made = ContextMADE(features, hidden_features, context_features, num_blocks,
                           output_multiplier=2)
        super().__init__(made)
        self.features = features
        self.max_log_scale = max_log_scale

    def _output_dim_multiplier(self) -> int:
        return 2

    def _log_scale_and_shift(self, params: Tensor) -> tuple[Tensor, Tensor]:
        # nflows' MADE interleaves the outputs per feature: (..., D, [scale, shift]).
        params = params.view(-1, self.features, 2)
        return soft_clip(params[..., 0], self.max_log_scale), params[..., 1]

    def _elementwise_forward(self, inputs: Tensor, autoregressive_params: Tensor):
        log_scale, shift = self._log_scale_and_shift(autoregressive_params)
        return inputs * torch.exp(log_scale) + shift, log_scale.sum(-1)

    def _elementwise_inverse(self, inputs: Tensor, autoregressive_params: Tensor):
        log_scale, shift = self._log_scale_and_shift(autoregressive_params)
        return (inputs - shift) * torch.exp(-log_scale), -log_scale.sum(-1)


class NflowsLayer(nn.Module):
    """[permutation, LU linear, fixed masked affine autoregressive transform] (data -> base)."""

    def __init__(self, config: FlowConfig) -> None:
        super().__init__()
        self.permutation = Permutation(reverse_permutation(config.features))
        self.linear = LULinear(config.features, identity_init=True)
        self.autoregressive = ContextAffineAutoregressive(
            config.features, config.hidden_features, config.context_features,
            config.made_blocks, config.max_log_scale)
        self.has_context = config.context_features > 0

    def forward(self, x: Tensor, context: Tensor) -> tuple[Tensor, Tensor]:
        ctx = context if self.has_context else None
        x, _ = self.permutation(x)
        x, log_det_linear = self.linear(x)
        x, log_det_affine = self.autoregressive(x, ctx)
        return x, log_det_linear + log_det_affine

    def inverse(self, z: Tensor, context: Tensor) -> Tensor:
        ctx = context if self.has_context else None
        z, _ = self.autoregressive.inverse(z, ctx)
        z, _ = self.linear.inverse(z)
        z, _ = self.permutation.inverse(z)
        return z


class NflowsMAF(ConditionalFlow):
    """Conditional MAF from nflows pieces (see module docstring for the fixes)."""

    def __init__(self, config: FlowConfig) -> None:
        super().__init__(config)
        self.flow_layers = nn.ModuleList(NflowsLayer(config) for _ in range(config.layers))

    def _forward_layer(self, index: int, x: Tensor, context: Tensor) -> tuple[Tensor, Tensor]:
        return self.flow_layers[index](x, context)

    def _inverse_layer(self, index: int, z: Tensor, context: Tensor) -> Tensor:
        layer = self.flow_layers[index]
        assert isinstance(layer, NflowsLayer)  # ModuleList items are typed as plain Modules
        return layer.inverse(z, context)
