"""Context encoders: shapes, padding never matters, alignment-free sequence encoders, errors."""
from __future__ import annotations

import pytest
import torch

from pipeline.errors import ConfigError
from pipeline.models.encoders import (ENCODER_KINDS, EncoderConfig, TransformerEncoderConfig,
                                      build_encoder, last_real_index, relative_positions)

CHANNELS, WINDOW, EMBEDDING = 3, 6, 5



def make_encoder(kind: str, seed: int = 0):
    torch.manual_seed(seed)
    return build_encoder(EncoderConfig(kind=kind, embedding_features=EMBEDDING), CHANNELS, WINDOW)


def padded_batch():
    generator = torch.Generator().manual_seed(0)
    context = torch.randn(4, WINDOW, CHANNELS, generator=generator)
    mask = torch.ones(4, WINDOW, dtype=torch.bool)
    mask[1, :2] = False    # padded at the front
    mask[2, 4:] = False    # padded at the back
    mask[3, 1:] = False    # a single real row
    return context, mask


@pytest.mark.parametrize("kind", ENCODER_KINDS)
def test_output_shape_and_padding_values_do_not_matter(kind):
    encoder = make_encoder(kind)
    context, mask = padded_batch()
    out = encoder(context, mask)
    assert out.shape == (4, EMBEDDING) and bool(torch.isfinite(out).all())
    for filler in (1e4, float("nan")):
        changed = context.clone()
        changed[~mask] = filler
        assert torch.equal(encoder(changed, mask), out)


@pytest.mark.parametrize("kind", ["transformer", "mamba"])
def test_sequence_encoders_ignore_where_the_padding_sits(kind):
    """A window of 4 real rows: unpadded, padded at the front, or at the back -> same embedding."""
    encoder = make_encoder(kind)
    generator = torch.Generator().manual_seed(1)
    real = torch.randn(1, 4, CHANNELS, generator=generator)
    junk = torch.randn(1, 2, CHANNELS, generator=generator)
    alone = encoder(real, torch.ones(1, 4, dtype=torch.bool))
    front = encoder(torch.cat([junk, real], 1), torch.tensor([[0, 0, 1, 1, 1, 1]], dtype=torch.bool))
    back = encoder(torch.cat([real, junk], 1), torch.tensor([[1, 1, 1, 1, 0, 0]], dtype=torch.bool))
    assert torch.allclose(front, alone, atol=1e-6)
    assert torch.allclose(back, alone, atol=1e-6)


@pytest.mark.parametrize("kind", ["transformer", "mamba"])
def test_sequence_encoders_use_every_real_row(kind):
    encoder = make_encoder(kind)
    context, mask = padded_batch()
    base = encoder(context, mask)
    for row in range(WINDOW):
        changed = context.clone()
        changed[0, row] += 1.0
        assert not torch.allclose(encoder(changed, mask)[0], base[0], atol=1e-6), row


def test_transformer_layout_is_the_papers():
    encoder = make_encoder("transformer")
    assert len(encoder.encoder.layers) == 4 and len(encoder.decoder.layers) == 4
    assert encoder.encoder.layers[0].linear1.out_features == 64
    assert encoder.decoder.layers[0].dropout.p == 0.0


def test_transformer_decoder_look_ahead_mask_is_causal():
    """Decoder position j (start token + rows < j) must not read later decoder tokens: with the
    encoder memory held fixed, changing row 3 leaves decoder outputs 0..3 unchanged."""
    encoder = make_encoder("transformer")
    context = torch.randn(1, WINDOW, CHANNELS)
    memory = torch.randn(1, WINDOW, encoder.d_model)

    def decode(ctx):
        tokens = torch.cat([encoder.start_token.expand(1, 1, -1), encoder.decoder_input(ctx)], 1)
        look_ahead = torch.ones(WINDOW + 1, WINDOW + 1, dtype=torch.bool).triu(1)
        return encoder.decoder(tokens, memory, tgt_mask=look_ahead)

    changed = context.clone()
    changed[0, 3] += 1.0
    before, after = decode(context), decode(changed)
    assert torch.allclose(before[:, :4], after[:, :4], atol=1e-6)   # tokens 0..3 = start, rows 0..2
    assert not torch.allclose(before[:, 4], after[:, 4], atol=1e-6)


def test_mask_helpers():
    mask = torch.tensor([[0, 1, 1, 0], [1, 1, 1, 1]], dtype=torch.bool)
    assert last_real_index(mask).tolist() == [2, 3]
    assert relative_positions(mask)[0, 1:3].tolist() == [0, 1]


@pytest.mark.parametrize("kind", ENCODER_KINDS)
def test_bad_windows_are_rejected(kind):
    encoder = make_encoder(kind)
    context, mask = padded_batch()
    empty = mask.clone()
    empty[2] = False
    with pytest.raises(ValueError, match="at least one real row"):
        encoder(context, empty)
    with pytest.raises(ValueError, match="C=3"):
        encoder(context[..., :2], mask)


def test_mlp_needs_its_window_length():
    with pytest.raises(ValueError, match="windows of 6 rows"):
        make_encoder("mlp")(torch.zeros(2, 4, CHANNELS), torch.ones(2, 4, dtype=torch.bool))


def test_encoder_config_validation():
    with pytest.raises(ConfigError, match="kind"):
        EncoderConfig(kind="gru")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="divisible"):
        EncoderConfig(transformer=TransformerEncoderConfig(d_model=30, heads=4))
