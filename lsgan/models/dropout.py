"""Dropout whose masks are cheap to draw on the CPU, and torch's transformer layers that use it when training.

torch draws a dropout mask with one call of its CPU generator per element (``bernoulli_``): in a training step of
the Bandai recipe's VAE that is 31% of the step (30 masks: the attention weights and the residual branches;
docs/results.md). Here each 64-bit word of the generator makes four 16-bit draws, compared with a threshold, so an
element is dropped with probability round(p * 65536) / 65536 (p within 1/131072) and the kept ones are scaled by
the inverse of the keep probability, as torch's dropout does. The masks come from torch's default generator, so
``torch.manual_seed`` and a saved RNG state make a run repeat exactly.

The layers are ``nn.TransformerEncoderLayer`` and ``nn.TransformerDecoderLayer`` with the same parameters (a
checkpoint of either loads in the other) and torch's own code in eval mode; training replaces only the draws, for
batched, non-empty inputs with at most a (B,S) padding mask: any other call (unbatched or empty inputs, attention
masks, causal hints) is torch's own code, with its values and its errors. On a GPU torch's fused dropout is already
cheap, and the layers are torch's there too.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

LEVELS = 1 << 16  # 16-bit draws


def keep_mask(shape: torch.Size | tuple[int, ...], p: float, device: torch.device | str = "cpu") -> torch.Tensor:
    """A bool mask of ``shape``, each element False with probability round(p * 65536) / 65536, from torch's
    default generator (four 16-bit draws per 64-bit word)."""
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"dropout probability has to be between 0 and 1, but got {p}")
    dropped = round(p * LEVELS)
    if dropped >= LEVELS:
        return torch.zeros(shape, dtype=torch.bool, device=device)
    n = math.prod(shape)
    words = torch.randint(-(1 << 63), (1 << 63) - 1, ((n + 3) // 4,), dtype=torch.int64, device=device)
    draws = words.view(torch.int16)[:n]  # uniform on [-32768, 32767]
    return (draws >= dropped - LEVELS // 2).view(shape)


def dropout(x: torch.Tensor, p: float, training: bool = True) -> torch.Tensor:
    """``F.dropout(x, p, training)`` with :func:`keep_mask`'s draws on the CPU; torch's own elsewhere."""
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"dropout probability has to be between 0 and 1, but got {p}")
    if not training or p == 0.0:
        return x
    if x.device.type != "cpu":
        return F.dropout(x, p, training)
    dropped = round(p * LEVELS)
    if dropped >= LEVELS:
        return x * 0.0  # as torch: still in the graph, NaN stays NaN
    scale = keep_mask(x.shape, p, x.device).to(x.dtype).mul_(LEVELS / (LEVELS - dropped))  # 0 or 1/keep
    return x * scale


class Dropout(nn.Dropout):
    """``nn.Dropout`` drawing its masks by :func:`dropout`."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return dropout(x, self.p, self.training)


def attention(attn: nn.MultiheadAttention, x: torch.Tensor, memory: torch.Tensor,
              key_padding_mask: torch.Tensor | None) -> torch.Tensor:
    """``attn(x, memory, memory, key_padding_mask=...)`` (batch first) with its attention weights dropped by
    :func:`dropout`: x (B,T,d), memory (B,S,d), key_padding_mask (B,S) True = ignore -> (B,T,d)."""
    B, T, d = x.shape
    heads = attn.num_heads
    w, b = attn.in_proj_weight.chunk(3), (attn.in_proj_bias.chunk(3) if attn.in_proj_bias is not None else (None,) * 3)
    q = F.linear(x, w[0], b[0]).view(B, T, heads, -1).transpose(1, 2)  # (B,heads,T,dh)
    k, v = (F.linear(memory, w[i], b[i]).view(B, memory.shape[1], heads, -1).transpose(1, 2) for i in (1, 2))
    scores = q @ k.transpose(-2, -1) * (1.0 / math.sqrt(q.shape[-1]))  # (B,heads,T,S)
    if key_padding_mask is not None:  # bool (True = ignore) or torch's additive form of it (0 / -inf)
        pad = key_padding_mask[:, None, None, :]
        scores = scores.masked_fill(pad, float("-inf")) if pad.dtype == torch.bool else scores + pad
    weights = torch.softmax(scores, dim=-1)
    if key_padding_mask is not None and (hidden := _all_masked(key_padding_mask)).any():
        weights = weights.masked_fill(hidden[:, None, None, None], 0.0)  # as torch: a query that sees no key gets 0
    weights = dropout(weights, attn.dropout, attn.training)
    return attn.out_proj((weights @ v).transpose(1, 2).reshape(B, T, d))


def _all_masked(key_padding_mask: torch.Tensor) -> torch.Tensor:
    """(B,) True where every key is hidden (a bool mask's True, an additive mask's -inf)."""
    hidden = key_padding_mask if key_padding_mask.dtype == torch.bool else key_padding_mask == float("-inf")
    return hidden.all(dim=-1)


def _cheap(layer: nn.Module, attn: nn.MultiheadAttention, x: torch.Tensor, memory: torch.Tensor, attn_mask,
           key_padding_mask, is_causal: bool) -> bool:
    """Whether this call takes the cheap draws: training on the CPU, batch first, non-empty (B,T,d) and (B,S,d),
    no attention mask or causal hint, a (B,S) bool or float padding mask. Anything else is torch's own code, with
    torch's errors."""
    plain = (layer.training and x.device.type == "cpu" and attn.batch_first and attn._qkv_same_embed_dim
             and attn_mask is None and not is_causal and x.dim() == memory.dim() == 3 and x.numel() and memory.numel()
             and x.shape[0] == memory.shape[0])
    return bool(plain) and (key_padding_mask is None or (
        (key_padding_mask.dtype == torch.bool or key_padding_mask.is_floating_point())
        and tuple(key_padding_mask.shape) == (memory.shape[0], memory.shape[1])))


class _CheapDraws:
    """What both layers share: cheap ``nn.Dropout`` modules, and the self-attention drawing its masks cheaply."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        for name in ("dropout", "dropout1", "dropout2", "dropout3"):
            old = getattr(self, name, None)
            if isinstance(old, nn.Dropout):
                setattr(self, name, Dropout(old.p))

    def _sa_block(self, x, attn_mask, key_padding_mask, is_causal=False):
        if not _cheap(self, self.self_attn, x, x, attn_mask, key_padding_mask, is_causal):
            return super()._sa_block(x, attn_mask, key_padding_mask, is_causal)
        return self.dropout1(attention(self.self_attn, x, x, key_padding_mask))


class EncoderLayer(_CheapDraws, nn.TransformerEncoderLayer):
    """``nn.TransformerEncoderLayer`` whose dropout masks are :func:`keep_mask`'s on the CPU."""


class DecoderLayer(_CheapDraws, nn.TransformerDecoderLayer):
    """``nn.TransformerDecoderLayer`` whose dropout masks are :func:`keep_mask`'s on the CPU."""

    def _mha_block(self, x, mem, attn_mask, key_padding_mask, is_causal=False):
        if not _cheap(self, self.multihead_attn, x, mem, attn_mask, key_padding_mask, is_causal):
            return super()._mha_block(x, mem, attn_mask, key_padding_mask, is_causal)
        return self.dropout2(attention(self.multihead_attn, x, mem, key_padding_mask))
