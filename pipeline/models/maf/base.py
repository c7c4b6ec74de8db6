"""The conditional masked autoregressive flow interface shared by every backend.

Architecture (paper, "Conditional Density Estimation with Normalizing Flow"): ``L`` layers, each
``[permutation, LU linear, masked affine autoregressive transform with context]``, and a base
distribution that is a diagonal Gaussian whose mean and log-scale are produced from the context
by a 2-layer MLP. The context therefore reaches the base *and* every layer.

Direction convention (as in nflows and zuko): a layer maps *data towards base*. For a point ``x``
the flow's trajectory is ``f_0 = x, f_1, ..., f_L = z``; ``f_L`` is scored by the base, and

    log p_X(x | c) = log p_Z(f_L | c) + sum_l log |det d f_l / d f_{l-1}|.

Sampling runs the layers backwards (``f_L -> f_0``); the autoregressive inverse costs ``D``
sequential passes per layer, which is what MAF trades for a one-pass density.

Backends (``nflows_maf``, ``zuko_maf``) implement only two hooks, ``_forward_layer`` and
``_inverse_layer``; everything else (density, sampling, layer outputs, the base) lives here so
the two are the same model up to their MADE networks.
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from pipeline.errors import ConfigError
from pipeline.names import BACKENDS, Backend


# |log sigma| of the base is soft-clipped at this value (sigma in [4.5e-5, 2.2e4] in standardized
# units): never binding for a sane model, but it keeps an untrained base from producing inf.
BASE_MAX_LOG_SCALE = 10.0


@dataclass(frozen=True)
class FlowConfig:
    """Hyper-parameters of one conditional MAF.

    features: target dimension D. context_features: embedding size E (0 = unconditional).
    layers: number L of [permutation, LU linear, masked affine autoregressive] layers.
    hidden_features: width of every MADE hidden layer. made_blocks: depth of the MADE (nflows:
    number of residual blocks; zuko: number of hidden layers). base_hidden_features: width of
    the base distribution's 2-layer MLP (None: ``hidden_features``).
    max_log_scale: bound B of each affine layer's log-scale, soft-clipped as a / (1 + |a| / B)
    (zuko's parametrisation with slope e^-B). It bounds how much one layer can expand space
    when sampling (factor e^B), which is what keeps samples of an untrained flow finite.
    """

    features: int
    context_features: int
    layers: int = 5
    hidden_features: int = 32
    made_blocks: int = 2
    base_hidden_features: int | None = None
    max_log_scale: float = 3.0
    backend: Backend = "zuko"

    def __post_init__(self) -> None:
        _require(self.features >= 1, "features", self.features, "must be >= 1")
        _require(self.context_features >= 0, "context_features", self.context_features,
                 "must be >= 0")
        _require(self.layers >= 1, "layers", self.layers, "must be >= 1")
        _require(self.hidden_features >= 1, "hidden_features", self.hidden_features,
                 "must be >= 1")
        _require(self.made_blocks >= 1, "made_blocks", self.made_blocks, "must be >= 1")
        _require(self.base_hidden_features is None or self.base_hidden_features >= 1,
                 "base_hidden_features", self.base_hidden_features, "must be >= 1 or None")
        _require(self.max_log_scale > 0, "max_log_scale", self.max_log_scale, "must be > 0")
        _require(self.backend in BACKENDS, "backend", self.backend, f"must be one of {BACKENDS}")


def _require(ok: bool, field: str, value: object, rule: str) -> None:
    if not ok:
        raise ConfigError(f"FlowConfig.{field}={value!r}: {rule}")


def soft_clip(a: Tensor, bound: float) -> Tensor:
    """a / (1 + |a| / bound): the identity near 0, smoothly bounded in (-bound, bound)."""
    return a / (1.0 + a.abs() / bound)


@dataclass(frozen=True)
class FlowTrajectory:
    """Every layer's output from data to base, and the summed log |det| of the whole map.

    ``outputs[0]`` is the input x, ``outputs[l]`` the output of layer l, ``outputs[-1]`` = z.
    """

    outputs: list[Tensor]
    log_abs_det: Tensor

    @property
    def latent(self) -> Tensor:
        return self.outputs[-1]


class ConditionalDiagonalGaussian(nn.Module):
    """Base distribution N(mu(c), diag sigma(c)^2) with (mu, log sigma) = MLP_2(c).

    With ``context_features == 0`` mu and log sigma are free parameters (unconditional flow).
    """

    def __init__(self, features: int, context_features: int, hidden_features: int) -> None:
        super().__init__()
        self.features = features
        self.context_features = context_features
        if context_features > 0:
            self.net: nn.Module | None = nn.Sequential(
                nn.Linear(context_features, hidden_features), nn.ReLU(),
                nn.Linear(hidden_features, 2 * features))
        else:
            self.net = None
            self.loc = nn.Parameter(torch.zeros(features))
            self.raw_log_scale = nn.Parameter(torch.zeros(features))

    def parameters_for(self, context: Tensor) -> tuple[Tensor, Tensor]:
        """(mean (B, D), log-scale (B, D)) for a batch of contexts (B, E)."""
        if self.net is None:
            shape = (context.shape[0], self.features)
            return self.loc.expand(shape), soft_clip(self.raw_log_scale, BASE_MAX_LOG_SCALE).expand(shape)
        loc, raw = self.net(context).chunk(2, dim=-1)
        return loc, soft_clip(raw, BASE_MAX_LOG_SCALE)

    def log_prob(self, z: Tensor, context: Tensor) -> Tensor:
        loc, log_scale = self.parameters_for(context)
        standard = (z - loc) * torch.exp(-log_scale)
        log_norm = 0.5 * self.features * math.log(2 * math.pi)
        return -0.5 * standard.pow(2).sum(-1) - log_scale.sum(-1) - log_norm

    def from_standard_normal(self, eps: Tensor, context: Tensor) -> Tensor:
        """mean + scale * eps for eps (B, n, D): the reparametrised base sample."""
        loc, log_scale = self.parameters_for(context)
        return loc[:, None, :] + torch.exp(log_scale)[:, None, :] * eps


class ConditionalFlow(nn.Module, ABC):
    """Conditional MAF: density, sampling and per-layer outputs (see module docstring).

    Shapes: x (B, D), context (B, E) (E may be 0: pass ``torch.empty(B, 0)``),
    samples (B, n, D). Subclasses implement ``_forward_layer`` / ``_inverse_layer``.
    """

    def __init__(self, config: FlowConfig) -> None:
        super().__init__()
        self.config = config
        base_hidden = config.base_hidden_features or config.hidden_features
        self.base = ConditionalDiagonalGaussian(config.features, config.context_features,
                                                base_hidden)

    # --- backend hooks -------------------------------------------------------------------
    @abstractmethod
    def _forward_layer(self, index: int, x: Tensor, context: Tensor) -> tuple[Tensor, Tensor]:
        """Layer ``index`` (0-based) from data towards base: (output (B, D), log|det| (B,))."""

    @abstractmethod
    def _inverse_layer(self, index: int, z: Tensor, context: Tensor) -> Tensor:
        """Inverse of ``_forward_layer`` (base towards data)."""

    # --- public interface ----------------------------------------------------------------
    @property
    def num_layers(self) -> int:
        return self.config.layers

    def trajectory(self, x: Tensor, context: Tensor) -> FlowTrajectory:
        """f_0 = x, f_1, ..., f_L and the summed log|det| of data -> base."""
        self._check(x, context)
        outputs, total = [x], torch.zeros(x.shape[0], dtype=x.dtype, device=x.device)
        for index in range(self.num_layers):
            x, log_abs_det = self._forward_layer(index, x, context)
            outputs.append(x)
            total = total + log_abs_det
        return FlowTrajectory(outputs, total)

    def layer_outputs(self, x: Tensor, context: Tensor) -> list[Tensor]:
        """[f_0 = x, f_1, ..., f_L] from data to base (``L + 1`` tensors of shape (B, D))."""
        return self.trajectory(x, context).outputs

    def log_prob(self, x: Tensor, context: Tensor) -> Tensor:
        """log p(x | context), shape (B,)."""
        trajectory = self.trajectory(x, context)
        return self.base_log_prob(trajectory.latent, context) + trajectory.log_abs_det

    def base_log_prob(self, z: Tensor, context: Tensor) -> Tensor:
        """log p_Z(z | context) of the conditional base, shape (B,)."""
        return self.base.log_prob(z, context)

    def inverse(self, z: Tensor, context: Tensor) -> Tensor:
        """Base -> data for z (B, D)."""
        self._check(z, context)
        for index in reversed(range(self.num_layers)):
            z = self._inverse_layer(index, z, context)
        return z

    def noise_to_data(self, eps: Tensor, context: Tensor) -> Tensor:
        """Standard-normal noise (B, n, D) -> data (B, n, D) through base and flow.

        eps = (1, 0, ...) maps to the point 1 sigma along the first base axis: this is what
        the confidence-region code pushes through the flow.
        """
        if eps.dim() != 3 or eps.shape[0] != context.shape[0] or eps.shape[2] != self.config.features:
            raise ValueError(f"eps must have shape (B={context.shape[0]}, n, "
                             f"D={self.config.features}), got {tuple(eps.shape)}")
        batch, n, dim = eps.shape
        z = self.base.from_standard_normal(eps, context).reshape(batch * n, dim)
        repeated = context.repeat_interleave(n, dim=0)
        return self.inverse(z, repeated).reshape(batch, n, dim)

    def sample(self, num_samples: int, context: Tensor,
               generator: torch.Generator | None = None) -> Tensor:
        """``num_samples`` draws per context: (B, num_samples, D)."""
        eps = torch.randn((context.shape[0], num_samples, self.config.features),
                          generator=generator, dtype=context.dtype, device=context.device)
        return self.noise_to_data(eps, context)

    def _check(self, x: Tensor, context: Tensor) -> None:
        if x.dim() != 2 or x.shape[1] != self.config.features:
            raise ValueError(f"x must have shape (B, D={self.config.features}), "
                             f"got {tuple(x.shape)}")
        if (context.dim() != 2 or context.shape[0] != x.shape[0]
                or context.shape[1] != self.config.context_features):
            raise ValueError(f"context must have shape (B={x.shape[0]}, "
                             f"E={self.config.context_features}), got {tuple(context.shape)}")


def reverse_permutation(features: int) -> Tensor:
    """The permutation used between layers: reversal, so every feature is first every other
    layer (deterministic, so it needs no seed and a checkpoint rebuilds it exactly)."""
    return torch.arange(features - 1, -1, -1)


class LUParameters(nn.Module):
    """W = L U with unit-diagonal U and positive diag(L) = softplus(raw) + 1e-3.

    Identity at initialisation (as nflows' LULinear). Used by the zuko backend (nflows has its
    own ``LULinear`` with the same parametrisation).
    """

    EPS = 1e-3

    def __init__(self, features: int) -> None:
        super().__init__()
        self.features = features
        self.lower = nn.Parameter(torch.zeros(features, features))
        self.upper = nn.Parameter(torch.zeros(features, features))
        inverse_softplus_one = float(torch.log(torch.expm1(torch.tensor(1.0 - self.EPS))))
        self.raw_diagonal = nn.Parameter(torch.full((features,), inverse_softplus_one))
        self.bias = nn.Parameter(torch.zeros(features))

    def diagonal(self) -> Tensor:
        return nn.functional.softplus(self.raw_diagonal) + self.EPS

    def lu_matrix(self) -> Tensor:
        """Lower part incl. diagonal = L, strict upper part = U (zuko's LU layout)."""
        return (torch.tril(self.lower, -1) + torch.diag(self.diagonal())
                + torch.triu(self.upper, 1))
