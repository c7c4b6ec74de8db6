"""MLP over the flattened observation window."""
from __future__ import annotations

import torch
from torch import Tensor, nn

from pipeline.models.encoders.config import MLPEncoderConfig
from pipeline.models.encoders.window import check_window, zero_padding


class MLPEncoder(nn.Module):
    """Flatten [values with padded rows zeroed, mask channel] of the R rows -> MLP -> (B, E).

    The mask channel lets the network tell a real zero observation from padding. Windows
    shorter than ``window`` rows must be padded to ``window`` by the caller (the dataset does).
    """

    def __init__(self, channels: int, window: int, embedding_features: int,
                 config: MLPEncoderConfig) -> None:
        super().__init__()
        self.channels, self.window = channels, window
        layers: list[nn.Module] = []
        width = window * (channels + 1)
        for _ in range(config.hidden_layers):
            layers += [nn.Linear(width, config.hidden_features), nn.ReLU()]
            width = config.hidden_features
        layers.append(nn.Linear(width, embedding_features))
        self.net = nn.Sequential(*layers)

    def forward(self, context: Tensor, mask: Tensor) -> Tensor:
        check_window(context, mask, self.channels)
        if context.shape[1] != self.window:
            raise ValueError(f"the MLP encoder was built for windows of {self.window} rows, "
                             f"got {context.shape[1]} (pad shorter windows with mask=False)")
        rows = torch.cat([zero_padding(context, mask), mask[..., None].to(context.dtype)], dim=-1)
        return self.net(rows.flatten(1))
