"""Multi-head attention over per-head tensors, shared by the VAE's decoder and MiniLM.

In eager torch it is ``scaled_dot_product_attention`` (the fused CPU kernel). When torch exports a graph it is
spelled out as two products and a softmax with the keys transposed in one step: the exporter's own lowering of the
fused op transposes them by a Reshape, Transpose, Reshape chain per layer, which onnxruntime runs as copies and
cannot fold into the product (on the paper-sized int8 decoder, 4.6% of its time at 32 motions). The two forms agree
to float rounding (~2e-6).
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """q, k, v (B,T,heads,dh) and an additive bias broadcast to (B,heads,T,T) -> (B,T,heads*dh)."""
    B, T, heads, dh = q.shape
    q, v = q.transpose(1, 2), v.transpose(1, 2)  # (B,heads,T,dh)
    if torch.compiler.is_exporting():
        scores = q @ k.permute(0, 2, 3, 1) * (1.0 / math.sqrt(dh)) + bias  # (B,heads,T,T)
        out = torch.softmax(scores, dim=-1) @ v
    else:
        out = F.scaled_dot_product_attention(q, k.transpose(1, 2), v, attn_mask=bias)  # (B,heads,T,dh)
    return out.transpose(1, 2).reshape(B, T, heads * dh)
