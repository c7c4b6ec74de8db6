"""Plain-PyTorch Mamba: parallel scan == recurrence, exact ZOH, causality, padding, init."""
from __future__ import annotations

import math

import pytest
import torch

from pipeline.models.encoders import EncoderConfig, MambaEncoderConfig, build_encoder
from pipeline.models.encoders.mamba import (MambaMixer, selective_scan,
                                            selective_scan_sequential)



def random_scan_inputs(length: int, seed: int = 0, d: int = 3, n: int = 4):
    g = torch.Generator().manual_seed(seed)
    kw = dict(generator=g, dtype=torch.float64)
    u = torch.randn(2, length, d, **kw)
    delta = torch.rand(2, length, d, **kw) * 2.0
    A = -torch.rand(d, n, **kw) * 3 - 0.1
    B, C = torch.randn(2, length, n, **kw), torch.randn(2, length, n, **kw)
    D = torch.randn(d, **kw)
    return u, delta, A, B, C, D


@pytest.mark.parametrize("length", [1, 2, 5, 7, 16, 33])
def test_parallel_scan_equals_recurrence(length):
    """Any length (no multiple-of-chunk requirement), float64, to 1e-12."""
    inputs = random_scan_inputs(length, seed=length)
    assert torch.allclose(selective_scan(*inputs), selective_scan_sequential(*inputs),
                          atol=1e-12, rtol=1e-12)


def test_zero_order_hold_is_exact_for_constant_input():
    """h' = a h + b u with constant u from h(0) = 0 has h(T) = (e^{aT} - 1)/a * b u; the
    discretised scan with step Delta must hit it at T = (k+1) Delta for every k."""
    a, b, c, u0, dt, steps = -0.7, 1.3, 1.0, 0.9, 0.25, 12
    u = torch.full((1, steps, 1), u0, dtype=torch.float64)
    delta = torch.full((1, steps, 1), dt, dtype=torch.float64)
    A = torch.tensor([[a]], dtype=torch.float64)
    B = torch.full((1, steps, 1), b, dtype=torch.float64)
    C = torch.full((1, steps, 1), c, dtype=torch.float64)
    y = selective_scan(u, delta, A, B, C, torch.zeros(1, dtype=torch.float64))[0, :, 0]
    times = dt * torch.arange(1, steps + 1, dtype=torch.float64)
    assert torch.allclose(y, c * torch.expm1(a * times) / a * b * u0, atol=1e-13)


def make_encoder(seed: int = 0, **sizes):
    torch.manual_seed(seed)
    config = EncoderConfig(kind="mamba", embedding_features=4,
                           mamba=MambaEncoderConfig(d_model=16, **sizes))
    return build_encoder(config, 3, 8).double()


def test_encoder_parallel_and_sequential_scans_agree():
    encoder = make_encoder(d_state=4, expand=2, layers=2)
    context = torch.randn(3, 11, 3, dtype=torch.float64)
    mask = torch.ones(3, 11, dtype=torch.bool)
    mask[1, 7:] = False
    assert torch.allclose(encoder(context, mask), encoder(context, mask, sequential=True),
                          atol=1e-12)


def test_output_at_step_k_ignores_later_inputs():
    encoder = make_encoder()
    context = torch.randn(1, 9, 3, dtype=torch.float64)
    mask = torch.ones(1, 9, dtype=torch.bool)
    before = encoder.sequence(context, mask)
    for k in (0, 3, 7):
        changed = context.clone()
        changed[:, k + 1:] = torch.randn(1, 8 - k, 3, dtype=torch.float64) * 5
        after = encoder.sequence(changed, mask)
        assert torch.equal(after[:, : k + 1], before[:, : k + 1])
        assert not torch.allclose(after[:, k + 1], before[:, k + 1])


def test_variable_length_windows_match_their_unpadded_versions():
    """A batch of windows of lengths 2..6 padded to 6 (front and back) embeds each one exactly
    as the window alone."""
    encoder = make_encoder()
    g = torch.Generator().manual_seed(3)
    lengths = [2, 3, 6, 4]
    context = torch.randn(4, 6, 3, generator=g, dtype=torch.float64)
    mask = torch.zeros(4, 6, dtype=torch.bool)
    starts = [0, 3, 0, 1]
    for i, (start, n) in enumerate(zip(starts, lengths)):
        mask[i, start:start + n] = True
    batch = encoder(context, mask)
    for i, (start, n) in enumerate(zip(starts, lengths)):
        alone = encoder(context[i:i + 1, start:start + n], torch.ones(1, n, dtype=torch.bool))
        assert torch.allclose(batch[i], alone[0], atol=1e-12), i


def test_initialisation_follows_mamba():
    torch.manual_seed(0)
    config = MambaEncoderConfig(d_model=16, d_state=6, expand=2, dt_min=1e-3, dt_max=1e-1)
    mixer = MambaMixer(16, config)
    A = -torch.exp(mixer.A_log)
    assert torch.allclose(A, -torch.arange(1, 7, dtype=torch.float32).expand(32, 6))  # S4D-real
    assert torch.equal(mixer.D, torch.ones(32))
    dt = torch.nn.functional.softplus(mixer.dt_proj.bias.detach())
    assert float(dt.min()) >= 1e-3 * (1 - 1e-4) and float(dt.max()) <= 1e-1 * (1 + 1e-4)
    # log-uniform: the logs of 32 draws spread over most of [log 1e-3, log 1e-1]
    spread = float(dt.log().max() - dt.log().min())
    assert spread > 0.6 * (math.log(1e-1) - math.log(1e-3))
