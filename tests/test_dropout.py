"""The cheap dropout masks (lsgan.models.dropout): torch's dropout in distribution and in the layers' arithmetic."""
from __future__ import annotations

import math
import re
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from lsgan.models.diffusion import DiffusionConfig, LatentDenoiser
from lsgan.models.dropout import DecoderLayer, EncoderLayer, LEVELS, dropout, keep_mask
from lsgan.models.vae import MotionVAE, VAEConfig

ROOT = Path(__file__).resolve().parents[1]
LAYER = dict(d_model=32, nhead=4, dim_feedforward=64, activation="gelu", batch_first=True)


@settings(max_examples=25, deadline=None)
@given(p=st.floats(0.0, 1.0), seed=st.integers(0, 2**31 - 1))
def test_masks_drop_at_the_rate_asked_and_keep_the_mean(p, seed):
    torch.manual_seed(seed)
    n = 1 << 16
    kept = keep_mask((n // 64, 64), p).float().mean().item()
    q = 1 - round(p * LEVELS) / LEVELS  # the keep probability, p to 1/65536
    assert abs(q - (1 - p)) <= 0.5 / LEVELS + 1e-12
    assert abs(kept - q) <= 6 * math.sqrt(q * (1 - q) / n) + 1e-9
    out = dropout(torch.ones(n), p)
    scaled = out[out != 0]
    assert torch.allclose(scaled, torch.full_like(scaled, 1 / q if q else 0.0), rtol=1e-6)  # kept ones: 1 / keep
    assert abs(len(scaled) / n - q) <= 6 * math.sqrt(q * (1 - q) / n) + 1e-9


def test_masks_repeat_under_a_seed_and_differ_without():
    torch.manual_seed(7)
    a = keep_mask((5, 33), 0.3)
    state = torch.get_rng_state()
    b = keep_mask((5, 33), 0.3)
    torch.set_rng_state(state)
    assert torch.equal(b, keep_mask((5, 33), 0.3))
    torch.manual_seed(7)
    assert torch.equal(a, keep_mask((5, 33), 0.3)) and not torch.equal(a, b)


def test_eval_and_p_zero_are_the_identity():
    x = torch.randn(4, 9)
    assert dropout(x, 0.5, training=False) is x and dropout(x, 0.0) is x
    assert torch.equal(dropout(x, 1.0), torch.zeros_like(x))


def _pair(cls, ref, p, norm_first, seed=1):
    torch.manual_seed(seed)
    ours = cls(dropout=p, norm_first=norm_first, **LAYER)
    torch.manual_seed(seed)
    theirs = ref(dropout=p, norm_first=norm_first, **LAYER)
    assert ours.state_dict().keys() == theirs.state_dict().keys()
    ours.load_state_dict(theirs.state_dict())
    return ours, theirs


@pytest.mark.parametrize("norm_first", [True, False])
@pytest.mark.parametrize("train", [True, False])
def test_layers_compute_torchs_layers(norm_first, train):
    """Without drops (training, p=0: our attention) and in eval mode at any p (torch's own code), the layers give
    torch's values for padded batches; the padding mask as torch's encoder passes it (additive) and as the decoder
    does (bool)."""
    p = 0.0 if train else 0.3
    x, mem = torch.randn(3, 7, 32), torch.randn(3, 2, 32)
    pad = torch.zeros(3, 7, dtype=torch.bool)
    pad[0, 5:], pad[2, 1:] = True, True
    mem_pad = torch.tensor([[False, True], [False, False], [False, True]])
    for cls, ref, call in ((EncoderLayer, nn.TransformerEncoderLayer, lambda m: m(x, src_key_padding_mask=pad)),
                           (DecoderLayer, nn.TransformerDecoderLayer,
                            lambda m: m(x, mem, tgt_key_padding_mask=pad, memory_key_padding_mask=mem_pad))):
        ours, theirs = _pair(cls, ref, p, norm_first)
        ours.train(train), theirs.train(train)
        with torch.no_grad():
            a, b = call(ours), call(theirs)
        assert (a - b)[~pad].abs().max() < 1e-5


def test_training_layers_drop_attention_weights_from_the_seed():
    """At p = 0.5 the training layers' outputs move with the masks (attention weights included: with the residual
    and feed-forward dropouts removed, the output still varies) and repeat under a seed."""
    layer = EncoderLayer(dropout=0.5, **LAYER).train()
    for name in ("dropout", "dropout1", "dropout2"):
        setattr(layer, name, nn.Identity())
    x = torch.randn(2, 6, 32)
    torch.manual_seed(3)
    a = layer(x)
    b = layer(x)
    torch.manual_seed(3)
    assert torch.equal(a, layer(x)) and not torch.allclose(a, b)


def test_the_models_build_every_transformer_layer_here():
    """One code path: the VAE's and the denoiser's layers are these, and nothing in lsgan builds torch's own."""
    vae = MotionVAE(VAEConfig(d_model=32, num_heads=4, ff_size=64))
    den = LatentDenoiser(DiffusionConfig(latent_dim=32, d_model=32, num_heads=4, ff_size=64, cond_dim=8))
    for model in (vae, den):
        layers = [m for m in model.modules() if isinstance(m, (nn.TransformerEncoderLayer, nn.TransformerDecoderLayer))]
        assert layers and all(type(m) in (EncoderLayer, DecoderLayer) for m in layers)
    built = re.compile(r"nn\.Transformer(Encoder|Decoder)Layer\(")
    others = [str(f.relative_to(ROOT)) for f in (ROOT / "lsgan").rglob("*.py") if built.search(f.read_text())]
    assert others == [], others


def _enc(x, **kw):
    return lambda m: m(x, **kw)


def _dec(x, mem, **kw):
    return lambda m: m(x, mem, **kw)


_X, _MEM = torch.randn(2, 5, 32), torch.randn(2, 3, 32)
_ALL = torch.tensor([[False] * 5, [True] * 5])  # the second sample: every key hidden
CALLS = {  # what a user may hand torch's layers in training; ours must answer as torch does (values or error)
    "a sample with every key padded (encoder)": (EncoderLayer, _enc(_X, src_key_padding_mask=_ALL)),
    "a sample with every frame padded (decoder)": (DecoderLayer, _dec(_X, _MEM, tgt_key_padding_mask=_ALL)),
    "a memory with every key padded": (DecoderLayer, _dec(_X, _MEM, memory_key_padding_mask=torch.tensor(
        [[False] * 3, [True] * 3]))),
    "unbatched (S, E)": (EncoderLayer, _enc(torch.randn(7, 32))),
    "unbatched decoder": (DecoderLayer, _dec(torch.randn(7, 32), torch.randn(3, 32))),
    "no samples": (EncoderLayer, _enc(torch.randn(0, 7, 32))),
    "no frames": (EncoderLayer, _enc(torch.randn(3, 0, 32))),
    "an empty memory": (DecoderLayer, _dec(_X, torch.randn(2, 0, 32))),
    "causal hint without a mask": (EncoderLayer, _enc(_X, is_causal=True)),
    "causal decoder hint without a mask": (DecoderLayer, _dec(_X, _MEM, tgt_is_causal=True)),
    "an integer memory mask": (DecoderLayer, _dec(_X, _MEM, memory_key_padding_mask=torch.zeros(2, 3, dtype=torch.int64))),
    "a memory mask of the wrong shape": (DecoderLayer, _dec(_X, _MEM, memory_key_padding_mask=torch.zeros(1, 3, dtype=torch.bool))),
    "a causal mask": (EncoderLayer, _enc(_X, src_mask=nn.Transformer.generate_square_subsequent_mask(5), is_causal=True)),
}


@pytest.mark.parametrize("case", sorted(CALLS))
def test_training_layers_answer_odd_calls_as_torchs(case):
    """Without drops (p=0) our training layers give torch's values, shapes and errors for each odd call."""
    cls, call = CALLS[case]
    ref = nn.TransformerEncoderLayer if cls is EncoderLayer else nn.TransformerDecoderLayer
    ours, theirs = _pair(cls, ref, 0.0, norm_first=True)
    ours.train(), theirs.train()
    outcomes = []
    for layer in (ours, theirs):
        try:
            outcomes.append(call(layer))
        except (RuntimeError, ValueError, AssertionError) as e:
            outcomes.append(type(e))
    a, b = outcomes
    if isinstance(b, type):
        assert a is b, f"{case}: torch raises {b.__name__}, ours gave {a if isinstance(a, type) else a.shape}"
    else:
        assert not isinstance(a, type), f"{case}: ours raised {a.__name__}"
        assert a.shape == b.shape and torch.allclose(a, b, atol=1e-5, equal_nan=True), case


@pytest.mark.parametrize("p", [-0.1, 1.5, float("nan")])
def test_impossible_probabilities_are_refused(p):
    with pytest.raises(ValueError, match="between 0 and 1"):
        dropout(torch.ones(3), p)
    with pytest.raises(ValueError, match="between 0 and 1"):
        keep_mask((3,), p)


def test_dropping_everything_stays_in_the_graph():
    x = torch.tensor([1.0, float("nan"), 2.0], requires_grad=True)
    out = dropout(x, 1.0)
    assert out.requires_grad and torch.isnan(out[1]) and out[0] == 0 == out[2]
    out.nansum().backward()
    assert torch.equal(x.grad, torch.zeros(3))
