"""What every context encoder does with a window: its shape checked, padded rows zeroed, the
positions of its real rows (the package docstring's padding convention)."""
from __future__ import annotations

import torch
from torch import Tensor

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
