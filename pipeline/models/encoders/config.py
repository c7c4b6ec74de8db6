"""The context encoders' configs: which encoder (``EncoderConfig.kind``) and each one's settings."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

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
