"""A latent-diffusion baseline (MLD, CVPR 2023) on the same latents as the GANs, for a like-for-like comparison.

The denoiser is MLD's ``mld_denoiser`` with ``arch: trans_enc``: a skip transformer (the VAE's U-shaped stack)
over three tokens, [noisy latent, timestep, condition], whose output at the latent token is the prediction of
the noise (``prediction="epsilon"``, MLD's setting) or of the clean latent (``"sample"``, MLD's
PREDICT_EPSILON false, which converges far faster on small CPU budgets: see recipes/bandai.yaml). Training follows
DDPM: z_t = sqrt(a_t) z_0 + sqrt(1 - a_t) eps with t uniform in [0, T), a_t = prod_{s<=t} (1 - beta_s), and the
"scaled_linear" betas (linear in sqrt(beta) from 0.00085 to 0.012, T = 1000). Sampling is DDIM with ``steps``
steps, the timesteps spaced as diffusers' DDIMScheduler does in MLD's config (``steps_offset: 1``,
``set_alpha_to_one: false``: t = 981, 961, ..., 1 for 50 steps, and the last step lands on a_0, not 1).

Classifier-free guidance: with probability ``cond_mask_prob`` a training example's condition token is replaced
by a learned null token; sampling mixes eps = eps_null + w (eps_cond - eps_null), both halves in one batch.

Latents live in the same STANDARDISED space as the GANs' (the cache's train mean/std removed; see gan.py), so
``destandardise`` and the checkpoint's meta are shared with them.

Where this departs from MLD's code (facts checked against ChenFengYe/motion-latent-diffusion):
- the latent enters and leaves through Linear maps (MLD uses the raw 256-d latent as its token, which needs
  d_model == latent_dim and reads the prediction straight off the final LayerNorm, which normalises every
  predicted noise vector over its features before a fixed gain and bias; MotionLCM-V2's authors name the same
  defect);
- the text embedding is projected by a Linear (MLD: ReLU then Linear, flagged "todo debug why relu" there;
  the ReLU discards the negative half of the embedding's coordinates);
- the null condition is one learned token for text and actions alike (MLD: the CLIP embedding of "" for
  text, a zero action embedding for actions); our text condition is a cached embedding, and "" is not cached;
- the sinusoidal timestep code is d_model wide (MLD: the text encoder's width for text, which is only a
  width before the same Linear-SiLU-Linear MLP).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn

from lsgan.models.checkpoint import checkpoint_reader, load_weights
from lsgan.models.dropout import EncoderLayer
from lsgan.models.gan import destandardise  # noqa: F401  (re-exported: the same latent space as the GANs')
from lsgan.models.vae import PositionalEncoding, SkipTransformer

CONDS = ("text", "action")
SCHEDULES = ("scaled_linear", "linear")
PREDICTIONS = ("epsilon", "sample")


@dataclass
class DiffusionConfig:
    latent_dim: int = 256
    d_model: int = 128
    num_layers: int = 3  # odd: input blocks, a middle block, output blocks (MLD: 9)
    num_heads: int = 4
    ff_size: int = 256
    dropout: float = 0.1
    activation: str = "gelu"
    norm_first: bool = True  # pre-norm layers (False: MLD's post-norm)
    cond: str = "text"  # "text": a caption embedding of cond_dim; "action": a learnable embedding per class
    cond_dim: int = 384  # the text encoder's width
    num_actions: int = 0
    train_timesteps: int = 1000
    beta_schedule: str = "scaled_linear"
    beta_start: float = 0.00085
    beta_end: float = 0.012
    prediction: str = "epsilon"  # what the denoiser predicts: the noise (MLD) or the clean latent
    cond_mask_prob: float = 0.1  # classifier-free guidance: the share of training examples without condition
    guidance_scale: float = 7.5  # sampling defaults, overridable per call
    sample_steps: int = 50
    eta: float = 0.0  # DDIM's stochasticity: 0 deterministic, 1 DDPM's posterior variance

    def __post_init__(self) -> None:
        if self.cond not in CONDS:
            raise ValueError(f"unknown condition kind {self.cond!r}; choose one of {CONDS}")
        if self.beta_schedule not in SCHEDULES:
            raise ValueError(f"unknown beta_schedule {self.beta_schedule!r}; choose one of {SCHEDULES}")
        if self.prediction not in PREDICTIONS:
            raise ValueError(f"unknown prediction {self.prediction!r}; choose one of {PREDICTIONS}")
        if self.num_layers < 1 or self.num_layers % 2 == 0:
            raise ValueError(f"num_layers must be odd (input blocks, a middle block, output blocks), "
                             f"got {self.num_layers}")
        if self.d_model % self.num_heads or self.d_model % 2:
            raise ValueError(f"d_model ({self.d_model}) must be even and divisible by num_heads ({self.num_heads})")
        if not 0.0 <= self.cond_mask_prob < 1.0:
            raise ValueError(f"cond_mask_prob must be in [0, 1), got {self.cond_mask_prob}")
        if not self.beta_start < self.beta_end < 1.0:
            raise ValueError(f"beta_start ({self.beta_start}) must be below beta_end ({self.beta_end}), and both "
                             "below 1")
        if self.sample_steps > self.train_timesteps:
            raise ValueError(f"sample_steps ({self.sample_steps}) is more than train_timesteps "
                             f"({self.train_timesteps})")


# ---------------------------------------------------------------------------------------------------- schedule


def alphas_cumprod(cfg: DiffusionConfig) -> torch.Tensor:
    """a_t = prod_{s<=t} (1 - beta_s), t = 0..T-1, float64. scaled_linear: sqrt(beta) linear (Stable Diffusion, MLD)."""
    T = cfg.train_timesteps
    if cfg.beta_schedule == "scaled_linear":
        betas = torch.linspace(cfg.beta_start**0.5, cfg.beta_end**0.5, T, dtype=torch.float64) ** 2
    else:
        betas = torch.linspace(cfg.beta_start, cfg.beta_end, T, dtype=torch.float64)
    return torch.cumprod(1.0 - betas, dim=0)


def ddim_timesteps(steps: int, train_timesteps: int) -> list[tuple[int, int]]:
    """(t, t_prev) pairs, noisiest first: diffusers' DDIM "leading" spacing with steps_offset 1, as MLD runs it.

    t = k * (T // steps) + 1 for k = steps-1 .. 0, clamped to T-1 (a clamped step that repeats the next is dropped);
    t_prev is the next t, and t - T // steps after the last (negative: the sampler then uses a_0, set_alpha_to_one
    false).
    """
    if not 1 <= steps <= train_timesteps:
        raise ValueError(f"steps must be in 1..{train_timesteps} (the training timesteps), got {steps}")
    ratio = train_timesteps // steps
    ts: list[int] = []
    for k in reversed(range(steps)):
        t = min(k * ratio + 1, train_timesteps - 1)
        if not ts or ts[-1] != t:
            ts.append(t)
    return list(zip(ts, ts[1:] + [ts[-1] - ratio]))


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal code of timesteps (B,) -> (B, dim): [cos, sin] of t * max_period^(-i / (dim/2)).

    MLD's get_timestep_embedding with flip_sin_to_cos=True and freq_shift=0.
    """
    half = dim // 2
    freq = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    angle = t.float()[:, None] * freq[None]  # (B, half)
    return torch.cat([torch.cos(angle), torch.sin(angle)], dim=-1)


# ---------------------------------------------------------------------------------------------------- denoiser


class LatentDenoiser(nn.Module):
    """MLD's trans_enc denoiser: prediction (B, Z) = f(z_t, t, c), or f(z_t, t, null) where ``drop`` is True."""

    def __init__(self, cfg: DiffusionConfig) -> None:
        super().__init__()
        d = cfg.d_model
        self.latent_in = nn.Linear(cfg.latent_dim, d)
        self.time_mlp = nn.Sequential(nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))  # MLD's TimestepEmbedding
        if cfg.cond == "action":
            if cfg.num_actions < 1:
                raise ValueError("cond='action' needs num_actions >= 1 (the cache's action_names)")
            self.cond_embed: nn.Module = nn.Embedding(cfg.num_actions, d)
        else:
            self.cond_embed = nn.Linear(cfg.cond_dim, d)
        self.null_cond = nn.Parameter(torch.zeros(d))  # the classifier-free guidance's "no condition" token
        self.pos = PositionalEncoding(d, 3, "learned")  # MLD: learned, uniform-initialised
        layer = {"d_model": d, "nhead": cfg.num_heads, "dim_feedforward": cfg.ff_size, "dropout": cfg.dropout,
                 "activation": cfg.activation, "batch_first": True, "norm_first": cfg.norm_first}
        self.encoder = SkipTransformer(lambda: EncoderLayer(**layer), cfg.num_layers, d)
        self.latent_out = nn.Linear(d, cfg.latent_dim)
        self.d_model = d

    def forward(self, z: torch.Tensor, t: torch.Tensor, cond: torch.Tensor,
                drop: torch.Tensor | None = None) -> torch.Tensor:
        time = self.time_mlp(timestep_embedding(t, self.d_model))  # (B, d)
        c = self.cond_embed(cond.long() if isinstance(self.cond_embed, nn.Embedding) else cond.float())  # (B, d)
        if drop is not None:
            c = torch.where(drop[:, None], self.null_cond.to(c.dtype).expand_as(c), c)  # (B, d)
        h = torch.stack([self.latent_in(z), time, c], dim=1)  # (B, 3, d): MLD's order, latent token first
        h = self.encoder(self.pos(h))  # (B, 3, d)
        return self.latent_out(h[:, 0])  # (B, Z)


# ---------------------------------------------------------------------------------------------------- model


def _randn(shape: tuple[int, ...], generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
    """Normal noise drawn on the generator's own device (a CPU generator works for a CUDA model), then moved."""
    where = generator.device if generator is not None else device
    return torch.randn(shape, generator=generator, device=where).to(device)


class LatentDiffusion(nn.Module):
    """Denoiser + noise schedule + config; ``sample`` draws standardised latents for conditions by DDIM."""

    def __init__(self, cfg: DiffusionConfig) -> None:
        super().__init__()
        self.config = cfg
        self.denoiser = LatentDenoiser(cfg)
        self.register_buffer("alphas_cumprod", alphas_cumprod(cfg).float(), persistent=False)  # (T,)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def add_noise(self, z0: torch.Tensor, t: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
        """z_t = sqrt(a_t) z_0 + sqrt(1 - a_t) eps for timesteps t (B,)."""
        a = self.alphas_cumprod[t][:, None]  # (B, 1)
        return a.sqrt() * z0 + (1 - a).sqrt() * eps

    def predict(self, z: torch.Tensor, t: int, cond: torch.Tensor, guidance: float) -> torch.Tensor:
        """The denoiser's prediction at timestep t with classifier-free ``guidance`` (1: the conditional one only).

        Otherwise eps_null + guidance (eps_cond - eps_null), both halves in one batch of 2B.
        """
        if guidance == 1.0:
            return self.denoiser(z, torch.full((len(z),), t, device=z.device), cond)
        b = len(z)
        drop = torch.arange(2 * b, device=z.device) < b  # first half: the null condition
        out = self.denoiser(torch.cat([z, z]), torch.full((2 * b,), t, device=z.device), torch.cat([cond, cond]), drop)
        uncond, conditional = out.split(b)
        return uncond + guidance * (conditional - uncond)

    @torch.no_grad()
    def sample(
        self,
        cond: torch.Tensor,
        num: int | None = None,
        generator: torch.Generator | None = None,
        *,
        steps: int | None = None,
        guidance: float | None = None,
        eta: float | None = None,
        noise: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Latents in standardised space for conditions ``cond``: (B, cond_dim) text embeddings or (B,) action ids.

        num=None: one latent per condition -> (B, Z); num=k: k per condition -> (B, k, Z). ``steps`` DDIM steps,
        classifier-free ``guidance`` and ``eta`` default to the config's. ``generator`` (any device) makes the
        noise reproducible; ``noise`` (B*k, Z) gives the starting z_T instead of drawing it.
        """
        cfg, dev = self.config, self.device
        steps = cfg.sample_steps if steps is None else steps
        guidance = cfg.guidance_scale if guidance is None else guidance
        eta = cfg.eta if eta is None else eta
        cond = torch.as_tensor(cond, device=dev)
        if num is not None:
            cond = cond.repeat_interleave(num, dim=0)
        z = _randn((len(cond), cfg.latent_dim), generator, dev) if noise is None else noise.to(dev)
        ac = self.alphas_cumprod
        for t, t_prev in ddim_timesteps(steps, cfg.train_timesteps):
            a, a_prev = ac[t], ac[max(t_prev, 0)]
            pred = self.predict(z, t, cond, guidance)
            if cfg.prediction == "epsilon":
                eps, z0 = pred, (z - (1 - a).sqrt() * pred) / a.sqrt()
            else:
                eps, z0 = (z - a.sqrt() * pred) / (1 - a).sqrt(), pred
            sigma = eta * ((1 - a_prev) / (1 - a) * (1 - a / a_prev)).sqrt()
            z = a_prev.sqrt() * z0 + (1 - a_prev - sigma**2).clamp_min(0).sqrt() * eps
            if eta > 0:
                z = z + sigma * _randn(tuple(z.shape), generator, dev)
        return z if num is None else z.view(-1, num, z.shape[-1])


def diffusion_loss(model: LatentDiffusion, z0: torch.Tensor, cond: torch.Tensor, generator: torch.Generator,
                   net: nn.Module | None = None) -> torch.Tensor:
    """MSE between the denoiser's prediction and its target (the noise, or z_0) at uniform random timesteps.

    ``net``: the denoiser as called (e.g. wrapped in DistributedDataParallel); default ``model.denoiser``.
    """
    cfg, b = model.config, len(z0)
    t = torch.randint(cfg.train_timesteps, (b,), generator=generator, device=z0.device)
    eps = torch.randn(z0.shape, generator=generator, device=z0.device)
    drop = torch.rand(b, generator=generator, device=z0.device) < cfg.cond_mask_prob
    pred = (net or model.denoiser)(model.add_noise(z0, t, eps), t, cond, drop)
    return F.mse_loss(pred, eps if cfg.prediction == "epsilon" else z0)


@checkpoint_reader
def load_diffusion(
    path: str | os.PathLike, device: str | torch.device = "cpu", prefer: str = "best"
) -> tuple[LatentDiffusion, dict]:
    """(model in eval mode, checkpoint meta) from a checkpoint folder or a run folder (its best/, else last/).

    meta["extra"] holds the same keys as a GAN's: latent_mean/latent_std, vae_hash, text_encoder, action_names,
    val_latent_fid.
    """
    weights, meta = load_weights(path, prefer=prefer, kind="diffusion")
    known = {f.name for f in fields(DiffusionConfig)}
    cfg = DiffusionConfig(**{k: v for k, v in meta["config"]["diffusion"].items() if k in known})
    model = LatentDiffusion(cfg)
    model.load_state_dict(weights, strict=True)
    return model.to(device).eval(), meta
