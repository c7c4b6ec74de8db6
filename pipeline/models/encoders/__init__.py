"""Context encoders: (B, R, C) observation windows with a padding mask -> (B, E) embeddings.

Every encoder is an ``nn.Module`` with ``forward(context (B, R, C), mask (B, R) bool) -> (B, E)``;
inputs are already standardized; True in ``mask`` marks a real row, and padding rows never
influence the output (their values are zeroed and they are masked out of attention / the scan).

Padding convention: the real rows of a window are *contiguous* (no gaps). The sequence encoders
(transformer, Mamba) measure positions from the first real row and read the embedding at the
last real row, so a window padded at the front, padded at the back, or not padded at all gives
the same embedding. The MLP sees absolute row positions, so it must be trained and used with one
alignment (the dataset's).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor, nn

from pipeline.errors import ConfigError

EncoderKind = Literal["mlp", "transformer", "mamba"]
ENCODER_KINDS: tuple[EncoderKind, ...] = ("mlp", "transformer", "mamba")


@dataclass(frozen=True)
class MLPEncoderConfig:
    """MLP over the flattened window (values of padded rows zeroed, plus the mask channel)."""

    hidden_features: int = 64
    hidden_layers: int = 2


@dataclass(frozen=True)
class TransformerEncoderConfig:
    """Encoder-decoder transformer after Wu et al. (2020), used as an embedding.

    feedforward_features 64 (not PyTorch's 2048): at d_model 32 the default width made a
    training step ~7x slower for no accuracy gain at these window lengths (docs/models.md).
    dropout 0 keeps train and eval outputs identical (the flows are small and rarely overfit
    through the encoder; context noise is the paper's regulariser).
    """

    d_model: int = 32
    heads: int = 4
    encoder_layers: int = 4
    decoder_layers: int = 4
    feedforward_features: int = 64
    dropout: float = 0.0


@dataclass(frozen=True)
class MambaEncoderConfig:
    """Selective SSM (Mamba) blocks in plain PyTorch.

    d_state N, expand (d_inner = expand * d_model), conv_kernel of the causal depthwise
    convolution, dt_rank (None: ceil(d_model / 16)); the step sizes Delta are initialised
    log-uniform in [dt_min, dt_max] (Gu & Dao 2023). Any sequence length works.
    Defaults (d_state 4, expand 1, 2 layers) are the reduced sizes: at batch 512 one training
    step took 32 ms against 89 ms with d_state 8, expand 2 (docs/models.md).
    """

    d_model: int = 32
    layers: int = 2
    d_state: int = 4
    expand: int = 1
    conv_kernel: int = 4
    dt_rank: int | None = None
    dt_min: float = 1e-3
    dt_max: float = 1e-1


@dataclass(frozen=True)
class EncoderConfig:
    """Which encoder and its sizes. ``embedding_features`` = E = the flow's context size."""

    kind: EncoderKind = "mlp"
    embedding_features: int = 6
    mlp: MLPEncoderConfig = field(default_factory=MLPEncoderConfig)
    transformer: TransformerEncoderConfig = field(default_factory=TransformerEncoderConfig)
    mamba: MambaEncoderConfig = field(default_factory=MambaEncoderConfig)

    def __post_init__(self) -> None:
        if self.kind not in ENCODER_KINDS:
            raise ConfigError(f"EncoderConfig.kind={self.kind!r}: must be one of {ENCODER_KINDS}")
        if self.embedding_features < 1:
            raise ConfigError(f"EncoderConfig.embedding_features={self.embedding_features}: "
                              "must be >= 1")
        if self.transformer.d_model % self.transformer.heads:
            raise ConfigError(f"TransformerEncoderConfig.d_model={self.transformer.d_model} must "
                              f"be divisible by heads={self.transformer.heads}")


def check_window(context: Tensor, mask: Tensor, channels: int) -> None:
    """Shapes (B, R, C) / (B, R) bool, C = ``channels``, and at least one real row per window."""
    if context.dim() != 3 or context.shape[2] != channels:
        raise ValueError(f"context must have shape (B, R, C={channels}), got {tuple(context.shape)}")
    if mask.shape != context.shape[:2] or mask.dtype != torch.bool:
        raise ValueError(f"mask must be a bool tensor of shape {tuple(context.shape[:2])}, "
                         f"got {mask.dtype} {tuple(mask.shape)}")
    if not bool(mask.any(dim=1).all()):
        empty = torch.nonzero(~mask.any(dim=1)).flatten()[:5].tolist()
        raise ValueError(f"every window needs at least one real row; windows {empty} have none")


def zero_padding(context: Tensor, mask: Tensor) -> Tensor:
    """Padded rows set to exactly 0, whatever they held (NaN included)."""
    return torch.where(mask[..., None], context, torch.zeros((), dtype=context.dtype))


def last_real_index(mask: Tensor) -> Tensor:
    """(B,) index of the last True of each row of ``mask`` (B, R)."""
    positions = torch.arange(mask.shape[1], device=mask.device).expand_as(mask)
    return torch.where(mask, positions, -1).max(dim=1).values


def relative_positions(mask: Tensor) -> Tensor:
    """Position of each row counted from the window's first real row (0 for rows before it)."""
    return (mask.long().cumsum(dim=1) - 1).clamp(min=0)


def gather_rows(sequence: Tensor, index: Tensor) -> Tensor:
    """sequence (B, R, F), index (B,) -> (B, F)."""
    return sequence[torch.arange(sequence.shape[0], device=sequence.device), index]


def build_encoder(config: EncoderConfig, context_channels: int, window: int) -> nn.Module:
    """An encoder for windows of at most ``window`` rows of ``context_channels`` channels."""
    if config.kind == "mlp":
        from pipeline.models.encoders.mlp import MLPEncoder
        return MLPEncoder(context_channels, window, config.embedding_features, config.mlp)
    if config.kind == "transformer":
        from pipeline.models.encoders.transformer import TransformerEncoder
        return TransformerEncoder(context_channels, config.embedding_features, config.transformer)
    from pipeline.models.encoders.mamba import MambaEncoder
    return MambaEncoder(context_channels, config.embedding_features, config.mamba)


__all__ = ["ENCODER_KINDS", "check_window", "gather_rows", "last_real_index",
           "relative_positions", "zero_padding", "EncoderConfig", "EncoderKind", "MLPEncoderConfig",
           "MambaEncoderConfig", "TransformerEncoderConfig", "build_encoder"]
