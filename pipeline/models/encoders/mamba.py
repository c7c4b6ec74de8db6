"""Mamba (selective state-space model, Gu & Dao 2023) context encoder in plain PyTorch.

One mixer, per channel d of the inner width and state index n:

    u = SiLU(causal depthwise conv(W_in x))            (short convolution, kernel ``conv_kernel``)
    Delta_t = softplus(W_dt (W_x u_t)[:dt_rank] + b_dt)  B_t, C_t = (W_x u_t)[dt_rank:]  (selection)
    h_t = exp(Delta_t A) h_{t-1} + (exp(Delta_t A) - 1) / A * B_t u_t
                                                         (exact zero-order hold of
                                                          h' = A h + B u for diagonal A; the
                                                          Mamba reference code uses Delta*B,
                                                          its first-order approximation)
    y_t = C_t . h_t + D u_t,   out = W_out (y * SiLU(z)),  z = gate half of W_in x.

Blocks are pre-norm residual (x + mixer(RMSNorm(x))); the encoder ends with an RMSNorm and a
linear projection of the last real row to the flow's context size.

Initialisation (published minimal implementations leave these at PyTorch defaults, which makes
A and Delta meaningless at the start of training):
- A = -exp(A_log), A_log = log(1..N) for every channel (S4D-real);
- D = 1;
- b_dt = softplus^{-1}(dt) with dt log-uniform in [dt_min, dt_max], so the initial step sizes
  span two decades of time scales; W_dt uniform in +-dt_rank^{-1/2}.

Scans: ``selective_scan`` (used for training) is a Hillis-Steele associative scan over the pairs
(decay, input) with (a1, b1) o (a2, b2) = (a1 a2, a2 b1 + b2): ceil(log2 L) vectorised steps, any
length L, and only products of decays <= 1 (no exp of positive cumulative sums, so it is
stable). ``selective_scan_sequential`` is the step-by-step recurrence kept as the reference.

Padding: padded rows are zeroed before the convolution (so they cannot leak into neighbouring
real rows through the kernel) and get Delta = 0, i.e. decay 1 and no input: the state passes
through them unchanged. With contiguous real rows the embedding at the last real row therefore
equals that of the unpadded window, wherever the padding sits.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from pipeline.models.encoders.config import MambaEncoderConfig
from pipeline.models.encoders.window import check_window, gather_rows, last_real_index, zero_padding


def _discretize(u: Tensor, delta: Tensor, A: Tensor, B: Tensor) -> tuple[Tensor, Tensor]:
    """Zero-order hold: (decay exp(Delta A), input (exp(Delta A) - 1) / A * B u), (b, L, d, n).

    A < 0 strictly (A = -exp(A_log)), so the division is safe; expm1 keeps it accurate for
    small Delta A (where it tends to Delta B u) and Delta = 0 gives decay 1 and input 0.
    """
    delta_A = delta[..., None] * A
    decay = torch.exp(delta_A)
    drive = torch.expm1(delta_A) / A * (u[..., None] * B[:, :, None, :])
    return decay, drive


def selective_scan(u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, D: Tensor) -> Tensor:
    """Parallel (associative) selective scan. u, delta (b, L, d); A (d, n); B, C (b, L, n);
    D (d,) -> y (b, L, d). h_{-1} = 0."""
    decay, state = _discretize(u, delta, A, B)
    length, offset = u.shape[1], 1
    while offset < length:
        # Element t absorbs the summary of (t - 2 offset, t - offset]: h = a_t h_prev + b_t.
        state = torch.cat([state[:, :offset],
                           decay[:, offset:] * state[:, :-offset] + state[:, offset:]], dim=1)
        decay = torch.cat([decay[:, :offset], decay[:, offset:] * decay[:, :-offset]], dim=1)
        offset *= 2
    return torch.einsum("bldn,bln->bld", state, C) + u * D


def selective_scan_sequential(u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor,
                              D: Tensor) -> Tensor:
    """Reference recurrence h_t = exp(Delta_t A) h_{t-1} + Delta_t B_t u_t, one step at a time."""
    decay, drive = _discretize(u, delta, A, B)
    h = torch.zeros_like(drive[:, 0])
    outputs = []
    for t in range(u.shape[1]):
        h = decay[:, t] * h + drive[:, t]
        outputs.append(torch.einsum("bdn,bn->bd", h, C[:, t]))
    return torch.stack(outputs, dim=1) + u * D


class MambaMixer(nn.Module):
    """The selective SSM mixer (module docstring), (b, L, d_model) + mask -> (b, L, d_model)."""

    def __init__(self, d_model: int, config: MambaEncoderConfig) -> None:
        super().__init__()
        d_inner = config.expand * d_model
        self.d_state = config.d_state
        self.dt_rank = config.dt_rank or math.ceil(d_model / 16)
        self.in_proj = nn.Linear(d_model, 2 * d_inner)
        self.conv = nn.Conv1d(d_inner, d_inner, config.conv_kernel, groups=d_inner,
                              padding=config.conv_kernel - 1)
        self.x_proj = nn.Linear(d_inner, self.dt_rank + 2 * config.d_state, bias=False)
        self.dt_proj = nn.Linear(self.dt_rank, d_inner)
        self.A_log = nn.Parameter(torch.log(torch.arange(1, config.d_state + 1, dtype=torch.float32))
                                  .repeat(d_inner, 1))
        self.D = nn.Parameter(torch.ones(d_inner))
        self.out_proj = nn.Linear(d_inner, d_model)
        self._init_dt(config.dt_min, config.dt_max)

    def _init_dt(self, dt_min: float, dt_max: float) -> None:
        with torch.no_grad():
            bound = self.dt_rank ** -0.5
            self.dt_proj.weight.uniform_(-bound, bound)
            log_dt = torch.empty_like(self.dt_proj.bias).uniform_(math.log(dt_min), math.log(dt_max))
            dt = log_dt.exp().clamp(min=1e-4)
            self.dt_proj.bias.copy_(dt + torch.log(-torch.expm1(-dt)))  # softplus^{-1}(dt)

    def ssm_inputs(self, x: Tensor, mask: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """(u, delta, B, C, gate) of the scan for input x (b, L, d_model)."""
        u, gate = self.in_proj(x).chunk(2, dim=-1)
        u = u * mask[..., None]
        u = self.conv(u.transpose(1, 2))[..., : x.shape[1]].transpose(1, 2)  # causal: drop tail
        u = F.silu(u)
        dt, B, C = self.x_proj(u).split([self.dt_rank, self.d_state, self.d_state], dim=-1)
        delta = F.softplus(self.dt_proj(dt)) * mask[..., None]
        return u, delta, B, C, gate

    def forward(self, x: Tensor, mask: Tensor, sequential: bool = False) -> Tensor:
        u, delta, B, C, gate = self.ssm_inputs(x, mask)
        scan = selective_scan_sequential if sequential else selective_scan
        y = scan(u, delta, -torch.exp(self.A_log), B, C, self.D)
        return self.out_proj(y * F.silu(gate))


class MambaBlock(nn.Module):
    def __init__(self, d_model: int, config: MambaEncoderConfig) -> None:
        super().__init__()
        self.norm = nn.RMSNorm(d_model)
        self.mixer = MambaMixer(d_model, config)

    def forward(self, x: Tensor, mask: Tensor, sequential: bool = False) -> Tensor:
        return x + self.mixer(self.norm(x), mask, sequential)


class MambaEncoder(nn.Module):
    """(B, R, C) window + mask -> (B, E): Mamba blocks, RMSNorm, last real row, projection."""

    def __init__(self, channels: int, embedding_features: int, config: MambaEncoderConfig) -> None:
        super().__init__()
        self.channels = channels
        self.input = nn.Linear(channels, config.d_model)
        self.blocks = nn.ModuleList(MambaBlock(config.d_model, config) for _ in range(config.layers))
        self.norm = nn.RMSNorm(config.d_model)
        self.output = nn.Linear(config.d_model, embedding_features)

    def sequence(self, context: Tensor, mask: Tensor, sequential: bool = False) -> Tensor:
        """Normalised per-row features (B, R, d_model); row k depends on rows <= k only."""
        check_window(context, mask, self.channels)
        x = self.input(zero_padding(context, mask))
        for block in self.blocks:
            x = block(x, mask, sequential)
        return self.norm(x)

    def forward(self, context: Tensor, mask: Tensor, sequential: bool = False) -> Tensor:
        features = self.sequence(context, mask, sequential)
        return self.output(gather_rows(features, last_real_index(mask)))
