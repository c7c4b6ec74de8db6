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

from torch import nn

from pipeline.models.encoders.config import (ENCODER_KINDS, EncoderConfig, EncoderKind,
                                             MambaEncoderConfig, MLPEncoderConfig,
                                             TransformerEncoderConfig)
from pipeline.models.encoders.window import (check_window, gather_rows, last_real_index,
                                             relative_positions, zero_padding)


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


__all__ = ["ENCODER_KINDS", "EncoderConfig", "EncoderKind", "MLPEncoderConfig",
           "MambaEncoderConfig", "TransformerEncoderConfig", "build_encoder", "check_window",
           "gather_rows", "last_real_index", "relative_positions", "zero_padding"]
