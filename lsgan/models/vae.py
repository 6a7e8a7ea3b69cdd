"""MLD's skip-transformer motion VAE: a motion (T,263) <-> one Gaussian latent z (Z,).

With ``time_tokens: k`` (not MLD's) z is k vectors of Z/k, each summarising one k-th of the motion's frames (the mean
of the encoder's outputs there) and entering the decoder's queries of those frames (linearly between neighbouring
tokens' centres) as well as its memory: the latent varies over the motion's time, so a decoder can place a gait's
steps, which the one-vector latent's decoder averages away (docs/results.md). The GAN still generates one Z vector.

Encoder: Linear(263->d), two learned distribution tokens prepended, positional encoding, a skip
transformer over [mu_token, logvar_token, frames] with padded frames masked out; the outputs at the two
tokens are mu and log-variance. Decoder: T query tokens (zeros + positional encoding) self-attend (padded
frames masked) and cross-attend to z as a one-token memory; Linear(d->263); optionally a time filter and the
data's skeleton (:mod:`lsgan.models.decoder_head`, not MLD's); padded frames set to zero. In eval
mode that cross-attention is computed once per motion, not per frame (:func:`one_token_cross`): the same features,
12.6% fewer FLOPs for the paper-sized decoder.

Skip transformer (MLD): (L-1)/2 input blocks, 1 middle block, (L-1)/2 output blocks; output block i
takes [h, activations of input block L/2-i] (2d) projected back to d, then a final LayerNorm.
Layers are pre-norm (``norm_first=True``, the default): it trains stably without warm-up and pairs with
the final LayerNorm; ``norm_first=False`` gives MLD's post-norm layers. ``init="xavier"`` gives MLD's
initialisation (``SkipTransformer.reset_xavier``); the default keeps torch's, which the CPU recipes were tuned with.

Code defaults are small (quick runs, tests); the paper's sizes (9 layers, d=256, ff=1024) live in recipes.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from lsgan.models.attention import attend
from lsgan.models.checkpoint import checkpoint_reader, load_weights
from lsgan.models.decoder_head import DecoderHead
from lsgan.models.dropout import DecoderLayer, EncoderLayer


@dataclass
class VAEConfig:
    nfeats: int = 263
    latent_dim: int = 256  # Z: what the GAN generates
    time_tokens: int = 0  # 0: MLD's one latent vector; k: z is k vectors of latent_dim/k, each for 1/k of the motion
    d_model: int = 128
    num_layers: int = 3  # per encoder and per decoder; odd (input blocks + middle + output blocks)
    num_heads: int = 4
    ff_size: int = 256
    dropout: float = 0.1
    activation: str = "gelu"
    position_embedding: str = "learned"  # "learned" | "sine"
    max_len: int = 1024  # longest motion (frames) the positional encoding covers
    norm_first: bool = True  # pre-norm layers (False: MLD's post-norm)
    init: str = "default"  # "default": torch's initialisation; "xavier": MLD's (see SkipTransformer.reset_xavier)
    smooth_output: int = 0  # passes of a [1,2,1]/4 time filter on the decoded features (lsgan.models.decoder_head)
    rigid_output: bool = False  # decoded joints on the training data's bone lengths (lsgan.models.decoder_head)

    def __post_init__(self) -> None:
        if self.num_layers < 1 or self.num_layers % 2 == 0:
            raise ValueError(f"num_layers must be odd (input blocks, a middle block, output blocks), got {self.num_layers}")
        if type(self.time_tokens) is not int or self.time_tokens < 0 or \
                (self.time_tokens and self.latent_dim % self.time_tokens):
            raise ValueError(f"time_tokens must be 0 or a whole divisor of latent_dim ({self.latent_dim}), "
                             f"got {self.time_tokens!r}")
        if self.d_model % self.num_heads:
            raise ValueError(f"d_model ({self.d_model}) must be divisible by num_heads ({self.num_heads})")
        if self.position_embedding not in ("learned", "sine"):
            raise ValueError(f"position_embedding must be 'learned' or 'sine', got {self.position_embedding!r}")
        if self.position_embedding == "sine" and self.d_model % 2:
            raise ValueError(f"a sine position code needs an even d_model, got {self.d_model}")
        if self.init not in ("default", "xavier"):
            raise ValueError(f"init must be 'default' or 'xavier', got {self.init!r}")
        if type(self.smooth_output) is not int or not 0 <= self.smooth_output <= 8:
            raise ValueError(f"smooth_output must be an integer from 0 to 8 (filter passes), got {self.smooth_output!r}")
        if not isinstance(self.rigid_output, bool):
            raise ValueError(f"rigid_output must be true or false, got {self.rigid_output!r}")


class PositionalEncoding(nn.Module):
    """Adds a position code to (B,T,d): a learned table or fixed sinusoids."""

    def __init__(self, d: int, max_len: int, kind: str) -> None:
        super().__init__()
        if kind == "learned":
            self.table = nn.Parameter(torch.rand(max_len, d))  # MLD: uniform [0,1); O(1) like the sinusoids
        else:
            pos = torch.arange(max_len, dtype=torch.float32)[:, None]
            freq = torch.exp(torch.arange(0, d, 2, dtype=torch.float32) * (-math.log(10000.0) / d))
            table = torch.zeros(max_len, d)
            table[:, 0::2] = torch.sin(pos * freq)
            table[:, 1::2] = torch.cos(pos * freq)
            self.register_buffer("table", table, persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[1] > self.table.shape[0]:
            raise ValueError(f"sequence of {x.shape[1]} positions, the positional encoding covers {self.table.shape[0]} (max_len)")
        return x + self.table[: x.shape[1]].to(x.dtype)


class SkipTransformer(nn.Module):
    """MLD's U-shaped stack: input blocks, a middle block, output blocks fed [h, skip] -> Linear(2d->d)."""

    def __init__(self, make_layer, num_layers: int, d: int) -> None:
        super().__init__()
        n = (num_layers - 1) // 2
        self.input_blocks = nn.ModuleList(make_layer() for _ in range(n))
        self.middle_block = make_layer()
        self.output_blocks = nn.ModuleList(make_layer() for _ in range(n))
        self.skip_proj = nn.ModuleList(nn.Linear(2 * d, d) for _ in range(n))
        self.norm = nn.LayerNorm(d)

    @torch.no_grad()
    def reset_xavier(self) -> None:
        """MLD's init: xavier-uniform on every matrix of the stack, the rest as torch made it.

        As MLD's SkipTransformerEncoder/Decoder._reset_parameters (mld/models/operator/cross_attention.py): every
        parameter with more than one dimension (attention in/out projections, feed-forward and skip projection
        weights); biases and LayerNorms keep torch's values, and nothing outside the stack is touched (MLD's
        skel_embedding and final_layer keep torch's Linear init, its distribution tokens randn, its learned
        positions uniform [0, 1)).
        """
        for p in self.parameters():
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    def forward(self, h: torch.Tensor, *args, apply=None, **kwargs) -> torch.Tensor:
        """h (B,S,d) -> (B,S,d); args/kwargs go to every layer (memory, padding mask), or ``apply(layer, h)`` runs
        each layer instead."""
        apply = apply or (lambda layer, x: layer(x, *args, **kwargs))
        skips = []
        for block in self.input_blocks:
            h = apply(block, h)
            skips.append(h)
        h = apply(self.middle_block, h)
        for block, proj in zip(self.output_blocks, self.skip_proj):
            h = apply(block, proj(torch.cat([h, skips.pop()], dim=-1)))  # (B,S,2d) -> (B,S,d)
        return self.norm(h)


def one_token_cross(attn: nn.MultiheadAttention, memory: torch.Tensor) -> torch.Tensor:
    """Cross-attention to a one-token memory (B,1,d) -> (B,1,d), the same for every query.

    Softmax over a single key is exactly 1, so each query receives that key's value whatever the query is:
    out_proj(v_proj(memory)). The query and key projections, and the per-frame value and output products,
    are skipped (2 of the ~15 d x d products per frame and layer at ff = 4d).
    """
    d = attn.embed_dim
    bias = None if attn.in_proj_bias is None else attn.in_proj_bias[2 * d :]
    return attn.out_proj(F.linear(memory, attn.in_proj_weight[2 * d :], bias))  # (B,1,d)


def self_attention(attn: nn.MultiheadAttention, x: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """``attn(x, x, x, key_padding_mask=~keep)`` (B,T,d) -> (B,T,d) in eval mode, by :func:`attend`.

    torch's own inference path for a padding mask runs a masked softmax that took a third of the demo decoder's
    time on the CPU; the fused kernel gives the same values to float rounding (~1e-6) and exports to ONNX as
    plain products and a softmax. ``keep`` (B,T) is True on real frames; every sequence has one at least, so no
    row of scores is all masked, and the mask goes in as an additive bias (a boolean one makes the exporter
    guard every (B,heads,T,T) softmax against all-masked rows, a tenth of the int8 decoder's time at batch 1).
    """
    B, T, d = x.shape
    heads = attn.num_heads
    qkv = F.linear(x, attn.in_proj_weight, attn.in_proj_bias).view(B, T, 3, heads, d // heads)
    bias = x.new_zeros(B, 1, 1, T).masked_fill(~keep[:, None, None, :], float("-inf"))  # 0 on real frames
    return attn.out_proj(attend(*qkv.unbind(2), bias))  # q, k, v (B,T,heads,d/heads) -> (B,T,d)


def decoder_layer_one_token(layer: nn.TransformerDecoderLayer, h: torch.Tensor, memory: torch.Tensor,
                            pad: torch.Tensor) -> torch.Tensor:
    """``layer(h, memory, tgt_key_padding_mask=pad)`` in eval mode for a one-token memory, with the cross-attention
    computed once per sequence (:func:`one_token_cross`) and the self-attention by :func:`self_attention`.
    Pre-norm and post-norm layers alike."""
    if layer.training:
        raise RuntimeError("the one-token decoder path is for inference (dropout would act per frame)")
    keep = ~pad

    def self_attn(x: torch.Tensor) -> torch.Tensor:
        return self_attention(layer.self_attn, x, keep)

    def feed_forward(x: torch.Tensor) -> torch.Tensor:
        return layer.linear2(layer.activation(layer.linear1(x)))

    cross = one_token_cross(layer.multihead_attn, memory)  # (B,1,d)
    if layer.norm_first:
        h = h + self_attn(layer.norm1(h))
        h = h + cross
        return h + feed_forward(layer.norm3(h))
    h = layer.norm1(h + self_attn(h))
    h = layer.norm2(h + cross)
    return layer.norm3(h + feed_forward(h))


class MotionVAE(nn.Module):
    """x (B,T,263) normalised features + mask (B,T) True on real frames <-> z (B,Z)."""

    def __init__(self, config: VAEConfig) -> None:
        super().__init__()
        self.config = c = config
        d = c.d_model
        self.skel_embed = nn.Linear(c.nfeats, d)
        self.dist_tokens = nn.Parameter(torch.randn(2, d))  # [mu token, logvar token]
        self.enc_pos = PositionalEncoding(d, c.max_len + 2, c.position_embedding)
        self.dec_pos = PositionalEncoding(d, c.max_len, c.position_embedding)
        layer = dict(d_model=d, nhead=c.num_heads, dim_feedforward=c.ff_size, dropout=c.dropout,
                     activation=c.activation, batch_first=True, norm_first=c.norm_first)
        self.encoder = SkipTransformer(lambda: EncoderLayer(**layer), c.num_layers, d)
        self.decoder = SkipTransformer(lambda: DecoderLayer(**layer), c.num_layers, d)
        w = c.latent_dim // max(c.time_tokens, 1)  # one token's width
        same = w == d
        self.to_mu = nn.Identity() if same else nn.Linear(d, w)
        self.to_logvar = nn.Identity() if same else nn.Linear(d, w)
        self.from_latent = nn.Identity() if same else nn.Linear(w, d)
        self.final = nn.Linear(d, c.nfeats)
        use_head = c.smooth_output or c.rigid_output
        self.head = DecoderHead(c.nfeats, c.smooth_output, c.rigid_output) if use_head else None
        if c.init == "xavier":
            self.encoder.reset_xavier()
            self.decoder.reset_xavier()

    def encode(self, x: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B,T,263), (B,T) -> mu (B,Z), logvar (B,Z). Padded frames never reach a real token."""
        B = x.shape[0]
        x = x.masked_fill(~mask[..., None], 0.0)  # garbage (even NaN) in padding cannot leak through 0-weights
        h = self.skel_embed(x)  # (B,T,d)
        h = torch.cat([self.dist_tokens.expand(B, -1, -1).to(h.dtype), h], dim=1)  # (B,2+T,d)
        h = self.enc_pos(h)
        pad = torch.cat([mask.new_zeros(B, 2), ~mask], dim=1)  # (B,2+T) True = ignore
        h = self.encoder(h, src_key_padding_mask=pad)  # (B,2+T,d)
        k = self.config.time_tokens
        if k:
            seg = segment_weights(mask, k)  # (B,T,k)
            pooled = torch.einsum("btk,btd->bkd", seg, h[:, 2:]) / seg.sum(1).clamp_min(1.0)[..., None]  # (B,k,d)
            return self.to_mu(pooled).reshape(B, -1), self.to_logvar(pooled).reshape(B, -1)
        return self.to_mu(h[:, 0]), self.to_logvar(h[:, 1])

    def decode(self, z: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """z (B,Z), mask (B,T) -> (B,T,263), exactly zero on padded frames."""
        B, T = mask.shape
        k = self.config.time_tokens
        memory = self.from_latent(z.reshape(B, max(k, 1), -1))  # (B,k,d)
        queries = self.dec_pos(memory.new_zeros(B, T, self.config.d_model))  # (B,T,d)
        if k:
            queries = queries + torch.einsum("btk,bkd->btd", interpolation_weights(mask, k), memory)
        if self.training or k:
            h = self.decoder(queries, memory, tgt_key_padding_mask=~mask)  # (B,T,d)
        else:  # the same function, the one-token cross-attention computed once per motion
            h = self.decoder(queries, apply=lambda layer, x: decoder_layer_one_token(layer, x, memory, ~mask))
        x = self.final(h)  # (B,T,263)
        if self.head is not None:
            x = self.head(x, mask)
        return x.masked_fill(~mask[..., None], 0.0)

    def forward(self, x: torch.Tensor, mask: torch.Tensor, sample: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Reconstruction (B,T,263), mu, logvar; z = mu + sigma * eps when sampling, else mu."""
        mu, logvar = self.encode(x, mask)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if sample else mu
        return self.decode(z, mask), mu, logvar


def segment_weights(mask: torch.Tensor, k: int) -> torch.Tensor:
    """(B,T) -> (B,T,k): 1 where frame t of a motion of L frames lies in its j-th k-th (floor(t k / L) = j), 0 on
    padding: which frames each time token of :class:`MotionVAE` summarises."""
    lengths = mask.sum(1, keepdim=True).clamp_min(1)  # (B,1)
    t = torch.arange(mask.shape[1], device=mask.device)[None]
    seg = torch.minimum(t * k // lengths, torch.full_like(t, k - 1))  # (B,T)
    tokens = torch.arange(k, device=mask.device)
    return ((seg[..., None] == tokens) & mask[..., None]).to(torch.float32)  # comparisons: exports to ONNX as is


def interpolation_weights(mask: torch.Tensor, k: int) -> torch.Tensor:
    """(B,T) -> (B,T,k): frame t's linear weights (summing to 1; 0 on padding) between the two time tokens whose
    segment centres enclose it; before the first centre and after the last, that token alone."""
    lengths = mask.sum(1, keepdim=True).clamp_min(1).to(torch.float32)
    u = (torch.arange(mask.shape[1], device=mask.device)[None] + 0.5) * k / lengths - 0.5  # (B,T) token coordinate
    u = u.clamp(0, k - 1)
    tokens = torch.arange(k, device=mask.device, dtype=torch.float32)
    w = (1 - (u[..., None] - tokens).abs()).clamp_min(0)  # hat functions: (1 - a) at floor(u), a at floor(u) + 1
    return w * mask[..., None]


def vae_loss(x_hat: torch.Tensor, x: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor, mask: torch.Tensor,
             kl_weight: float) -> dict[str, torch.Tensor]:
    """MSE over the real frames' features + kl_weight * KL(q(z|x) || N(0,I)).

    KL is averaged over the batch and the latent dimensions, as MLD's KLLoss does, so the paper's weight
    (1e-4) means the same thing here.
    """
    m = mask[..., None].to(x.dtype)
    recon = ((x_hat - x) ** 2 * m).sum() / (m.sum() * x.shape[-1]).clamp_min(1.0)
    kl = (-0.5 * (1 + logvar - mu**2 - logvar.exp())).mean()
    return {"total": recon + kl_weight * kl, "recon": recon, "kl": kl}


@checkpoint_reader
def load_vae(path: str | os.PathLike, device: str | torch.device = "cpu", prefer: str = "best") -> tuple[MotionVAE, dict]:
    """A trained VAE (eval mode) from a checkpoint folder or run folder, and its meta.

    meta is the checkpoint's config.json plus ``mean``/``std`` (263,) float32: the normalisation the
    VAE was trained with, so decoding needs no shard.
    """
    state, meta = load_weights(path, prefer=prefer, kind="vae")
    model = MotionVAE(VAEConfig(**meta["config"]["model"]))
    model.load_state_dict(state)
    extra = meta.get("extra", {})
    rigid = model.head is not None and model.head.rigid
    meta["mean"] = _finite(extra, "mean", model.config.nfeats)
    meta["std"] = _finite(extra, "std", model.config.nfeats, positive=rigid)
    if rigid:
        lengths = _finite(extra, "bone_lengths", model.head.lengths.numel(), positive=True)
        model.head.set_skeleton(torch.from_numpy(meta["mean"]), torch.from_numpy(meta["std"]), torch.from_numpy(lengths))
    return model.to(device).eval(), meta


def _finite(extra: dict, key: str, size: int, positive: bool = False) -> np.ndarray:
    """``extra[key]`` as ``size`` float32 values, each finite (and > 0 if ``positive``), or a ValueError saying
    what is wrong (the checkpoint reader names the file)."""
    if key not in extra:
        raise ValueError(f"its config has no {key!r}")
    values = np.asarray(extra[key], np.float32).reshape(-1)
    if values.size != size or not np.isfinite(values).all() or (positive and (values <= 0).any()):
        raise ValueError(f"its {key!r} is not {size} finite{' positive' if positive else ''} numbers")
    return values
