"""Transformer context encoder after Wu et al. (2020), "Deep Transformer Models for Time Series
Forecasting", used as in the paper to produce an embedding rather than a sequence.

Layout (paper, "Generating Conditional Embeddings"):
- encoder: input layer (linear C -> d_model), sinusoidal positional encoding, 4 encoder layers
  (self-attention + feed-forward);
- decoder: input layer, 4 decoder layers (masked self-attention + attention over the encoder
  output + feed-forward), output layer (linear d_model -> E).
- "one-position offset and look-ahead masking": the decoder input is the window shifted right by
  one position behind a learned start token (token j+1 carries row j), and a causal mask stops
  position j from attending to later positions. The embedding is the decoder output at the last
  real row, which has seen the start token and every real row, so nothing is read beyond the
  window.

Padding: padded rows are zeroed, excluded as attention keys (``key_padding_mask`` for the encoder,
the decoder self-attention and the cross-attention), and positions are counted from the first real
row, so the embedding does not depend on where the padding sits (contiguous real rows assumed).
No query ever sees only masked keys (encoder queries see every real row; decoder queries see the
start token), so no NaN arises from a fully masked softmax.
"""
from __future__ import annotations

import math
from typing import TypedDict

import torch
from torch import Tensor, nn

from pipeline.models.encoders.config import TransformerEncoderConfig
from pipeline.models.encoders.window import check_window, gather_rows, last_real_index, relative_positions, zero_padding


def sinusoidal_encoding(positions: Tensor, d_model: int) -> Tensor:
    """Vaswani et al. positional encoding at integer ``positions`` (B, R) -> (B, R, d_model)."""
    frequencies = torch.exp(torch.arange(0, d_model, 2, dtype=torch.float32)
                            * (-math.log(10000.0) / d_model)).to(positions.device)
    angles = positions[..., None].float() * frequencies
    encoding = torch.zeros(*positions.shape, d_model, device=positions.device)
    encoding[..., 0::2] = torch.sin(angles)
    encoding[..., 1::2] = torch.cos(angles[..., : d_model // 2])
    return encoding


class _LayerOptions(TypedDict):
    """The keyword arguments shared by the encoder and decoder layers."""

    d_model: int
    nhead: int
    dim_feedforward: int
    dropout: float
    batch_first: bool


class TransformerEncoder(nn.Module):
    """(B, R, C) window + mask -> (B, E) embedding (see module docstring)."""

    def __init__(self, channels: int, embedding_features: int,
                 config: TransformerEncoderConfig) -> None:
        super().__init__()
        self.channels, self.d_model = channels, config.d_model
        self.encoder_input = nn.Linear(channels, config.d_model)
        self.decoder_input = nn.Linear(channels, config.d_model)
        self.start_token = nn.Parameter(torch.zeros(config.d_model))
        layer_options = _LayerOptions(d_model=config.d_model, nhead=config.heads,
                                      dim_feedforward=config.feedforward_features,
                                      dropout=config.dropout, batch_first=True)
        # enable_nested_tensor=False: the nested-tensor fast path drops padded positions and
        # returns zeros there, which would make eval and train outputs differ in layout.
        self.encoder = nn.TransformerEncoder(nn.TransformerEncoderLayer(**layer_options),
                                             config.encoder_layers, enable_nested_tensor=False)
        self.decoder = nn.TransformerDecoder(nn.TransformerDecoderLayer(**layer_options),
                                             config.decoder_layers)
        self.output = nn.Linear(config.d_model, embedding_features)

    def forward(self, context: Tensor, mask: Tensor) -> Tensor:
        check_window(context, mask, self.channels)
        context = zero_padding(context, mask)
        positions = relative_positions(mask)
        padding = ~mask

        memory = self.encoder_input(context) + sinusoidal_encoding(positions, self.d_model)
        memory = self.encoder(memory, src_key_padding_mask=padding)

        # Decoder tokens: [start, row_0, ..., row_{R-1}]; start sits at position 0, row j at the
        # relative position of row j plus one.
        batch, rows = mask.shape
        start = self.start_token.expand(batch, 1, self.d_model)
        tokens = torch.cat([start, self.decoder_input(context)], dim=1)
        token_positions = torch.cat([torch.zeros_like(positions[:, :1]),
                                     positions + mask.long()], dim=1)
        tokens = tokens + sinusoidal_encoding(token_positions, self.d_model)
        token_padding = torch.cat([torch.zeros_like(padding[:, :1]), padding], dim=1)
        # Boolean look-ahead mask (True = may not attend), the same type as the padding masks.
        look_ahead = torch.ones(rows + 1, rows + 1, dtype=torch.bool, device=mask.device).triu(1)
        decoded = self.decoder(tokens, memory, tgt_mask=look_ahead,
                               tgt_key_padding_mask=token_padding,
                               memory_key_padding_mask=padding)
        return self.output(gather_rows(decoded, last_real_index(mask) + 1))
