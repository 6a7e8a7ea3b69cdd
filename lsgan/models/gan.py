"""The latent-space GANs of LS-GAN: a conditional generator z' = G(noise, c) and a discriminator/critic D(z, c).

Four variants (method.md's table), picked by ``GANConfig.arch``:

    vanilla-gan       3-FC generator, 4-FC discriminator, BCE loss (sigmoid folded into BCE-with-logits)
    vanilla-wgan-gp   same networks, the discriminator is a critic (no sigmoid), Wasserstein loss + gradient penalty
    deep-gan          the same networks with residual blocks after their first FC layer, BCE loss
    deep-wgan-gp      deep networks, Wasserstein loss + gradient penalty

Latents live in STANDARDISED space: the cache's per-dimension mean/std of the train latents are removed before
training, so the generator's output is an unbounded, roughly unit-variance Gaussian (hence no tanh) and
``destandardise`` maps it back to the VAE's latent space.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from lsgan.models.checkpoint import load_weights, unwrap

ArrayLike = Sequence[float] | np.ndarray | torch.Tensor

ARCHS = ("vanilla-gan", "vanilla-wgan-gp", "deep-gan", "deep-wgan-gp")
CONDS = ("text", "action")


@dataclass
class GANConfig:
    arch: str = "deep-wgan-gp"
    noise_dim: int = 100
    latent_dim: int = 256
    cond: str = "text"  # "text": a caption embedding of cond_dim; "action": a learnable embedding per class
    cond_dim: int = 384  # the text encoder's width
    num_actions: int = 0
    action_emb_dim: int = 10
    hidden_dim: int = 512
    num_res_blocks: int = 2  # deep variants only
    leaky_slope: float = 0.2

    def __post_init__(self) -> None:
        if self.arch not in ARCHS:
            raise ValueError(f"unknown GAN arch {self.arch!r}; choose one of {ARCHS}")
        if self.cond not in CONDS:
            raise ValueError(f"unknown condition kind {self.cond!r}; choose one of {CONDS}")

    @property
    def deep(self) -> bool:
        return self.arch.startswith("deep")

    @property
    def wgan(self) -> bool:
        return self.arch.endswith("wgan-gp")

    @property
    def blocks(self) -> int:
        """Residual blocks per network: num_res_blocks for the deep variants, none for the vanilla ones."""
        return self.num_res_blocks if self.deep else 0


class ResBlock(nn.Module):
    """x + W(LeakyReLU(LayerNorm(x))): a pre-activation residual block at the hidden width.

    LayerNorm (per sample) rather than batch norm: batch statistics would couple the samples of a batch
    and break the critic's per-sample gradient penalty.
    """

    def __init__(self, dim: int, slope: float) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.act = nn.LeakyReLU(slope)
        self.fc = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.fc(self.act(self.norm(x)))


class Condition(nn.Module):
    """The condition vector: a text embedding as given (B, cond_dim), or a learnable embedding of action ids (B,)."""

    def __init__(self, cfg: GANConfig) -> None:
        super().__init__()
        if cfg.cond == "action":
            if cfg.num_actions < 1:
                raise ValueError("cond='action' needs num_actions >= 1 (the cache's action_names)")
            self.embed = nn.Embedding(cfg.num_actions, cfg.action_emb_dim)
            self.dim = cfg.action_emb_dim
        else:
            self.embed = None
            self.dim = cfg.cond_dim

    def forward(self, c: torch.Tensor) -> torch.Tensor:
        if self.embed is None:
            return c.float()  # (B, cond_dim)
        return self.embed(c.long())  # (B, action_emb_dim)


class Generator(nn.Module):
    """z' = G(noise, c), unbounded (no tanh: VAE latents are Gaussians, not values in [-1, 1]).

    Layout, reading method.md's "3 fully connected layers, LeakyReLU before the last" literally::

        vanilla: [noise, c] -> fc1 -> fc2 -> LeakyReLU -> fc3 -> z'
        deep:    [noise, c] -> fc1 -> ResBlock x num_res_blocks -> fc2 -> LeakyReLU -> fc3 -> z'

    In the vanilla generator fc1 and fc2 compose to one (rank <= hidden_dim) linear map, so it is a one-hidden-layer
    MLP with the paper's layer count; the deep one's residual blocks (one Linear each) sit between its first two FC
    layers. With a 768-d text condition and hidden 512 that is 0.84 M / 1.36 M multiply-adds per sample (vanilla /
    deep), close to the paper's 1.581 / 2.665 GFLOPs for 2048 clips (0.77 M / 1.30 M per clip).
    """

    def __init__(self, cfg: GANConfig) -> None:
        super().__init__()
        h = cfg.hidden_dim
        self.cond = Condition(cfg)
        self.fc1 = nn.Linear(cfg.noise_dim + self.cond.dim, h)
        self.blocks = nn.ModuleList(ResBlock(h, cfg.leaky_slope) for _ in range(cfg.blocks))
        self.fc2 = nn.Linear(h, h)
        self.act = nn.LeakyReLU(cfg.leaky_slope)
        self.fc3 = nn.Linear(h, cfg.latent_dim)

    def forward(self, noise: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        x = self.fc1(torch.cat([noise, self.cond(c)], dim=-1))  # (B, H)
        for block in self.blocks:
            x = block(x)  # (B, H)
        return self.fc3(self.act(self.fc2(x)))  # (B, Z)


class Discriminator(nn.Module):
    """D(z, c) -> one score per sample (B,): a logit for the BCE GANs, an unbounded critic value for WGAN-GP.

    Layout ("4 fully connected layers, LeakyReLU"; no batch norm, which breaks the gradient penalty)::

        vanilla: [z, c] -> fc1 -> LeakyReLU -> fc2 -> LeakyReLU -> fc3 -> LeakyReLU -> fc4 -> score
        deep:    [z, c] -> fc1 -> ResBlock x num_res_blocks -> LeakyReLU -> fc2 -> ... -> fc4 -> score

    The BCE variants' sigmoid is applied inside the loss (BCE-with-logits: the same function, numerically stable).
    The condition has its own embedding here (for actions), separate from the generator's.
    """

    def __init__(self, cfg: GANConfig) -> None:
        super().__init__()
        h = cfg.hidden_dim
        self.cond = Condition(cfg)
        self.fc1 = nn.Linear(cfg.latent_dim + self.cond.dim, h)
        self.blocks = nn.ModuleList(ResBlock(h, cfg.leaky_slope) for _ in range(cfg.blocks))
        self.fc2 = nn.Linear(h, h)
        self.fc3 = nn.Linear(h, h)
        self.fc4 = nn.Linear(h, 1)
        self.act = nn.LeakyReLU(cfg.leaky_slope)

    def forward(self, z: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        x = self.fc1(torch.cat([z, self.cond(c)], dim=-1))  # (B, H)
        for block in self.blocks:
            x = block(x)  # (B, H)
        x = self.act(self.fc2(self.act(x)))  # (B, H)
        x = self.act(self.fc3(x))  # (B, H)
        return self.fc4(x).squeeze(-1)  # (B,)


# ---------------------------------------------------------------------------------------------------- losses


def d_loss_bce(real_logits: torch.Tensor, fake_logits: torch.Tensor) -> torch.Tensor:
    """-log D(real) - log(1 - D(fake)), with D = sigmoid(logits)."""
    real = F.binary_cross_entropy_with_logits(real_logits, torch.ones_like(real_logits))
    fake = F.binary_cross_entropy_with_logits(fake_logits, torch.zeros_like(fake_logits))
    return real + fake


def g_loss_bce(fake_logits: torch.Tensor) -> torch.Tensor:
    """Non-saturating generator loss -log D(fake)."""
    return F.binary_cross_entropy_with_logits(fake_logits, torch.ones_like(fake_logits))


def g_loss_wgan(fake_scores: torch.Tensor) -> torch.Tensor:
    """-E[D(fake)]."""
    return -fake_scores.mean()


class WGANLoss(NamedTuple):
    loss: torch.Tensor  # what the critic minimises
    wasserstein: torch.Tensor  # E[D(real)] - E[D(fake)], detached: the distance estimate
    gp: torch.Tensor  # E[(||grad D(x_hat)||_2 - 1)^2], detached (unweighted)


def critic_loss_wgan_gp(
    critic: nn.Module,
    real: torch.Tensor,
    fake: torch.Tensor,
    cond: torch.Tensor,
    gp_weight: float = 10.0,
    generator: torch.Generator | None = None,
) -> WGANLoss:
    """E[D(fake)] - E[D(real)] + gp_weight * E[(||grad_x D(x_hat)||_2 - 1)^2], x_hat on random real-fake segments.

    Both terms: the public reference code kept only the penalty, which trains nothing. The gradient is taken
    with respect to the latent input only (the condition is held fixed).

    ``critic`` may be wrapped in DistributedDataParallel: real and fake go through the wrapper in one forward
    pass, the interpolates through the module inside it (DDP expects one forward per backward; the penalty's
    weight gradients add into the same parameters before DDP averages them). Keeping the interpolates out of
    the real/fake pass means the double backward runs over B rows, not 3B.
    """
    b = real.shape[0]
    alpha = torch.rand(b, 1, generator=generator, device=real.device, dtype=real.dtype)  # (B, 1)
    x_hat = (alpha * real + (1 - alpha) * fake).detach().requires_grad_(True)  # (B, Z)
    d_real, d_fake = critic(torch.cat([real, fake.detach()]), torch.cat([cond, cond])).split(b)  # (B,), (B,)
    d_hat = unwrap(critic)(x_hat, cond)  # (B,)
    (grad,) = torch.autograd.grad(d_hat.sum(), x_hat, create_graph=True)  # (B, Z)
    gp = ((grad.norm(2, dim=1) - 1) ** 2).mean()
    wasserstein = d_real.mean() - d_fake.mean()
    return WGANLoss(-wasserstein + gp_weight * gp, wasserstein.detach(), gp.detach())


# ---------------------------------------------------------------------------------------------------- model


class LatentGAN(nn.Module):
    """Generator + discriminator + config; ``sample`` draws standardised latents for conditions."""

    def __init__(self, cfg: GANConfig) -> None:
        super().__init__()
        self.config = cfg
        self.generator = Generator(cfg)
        self.discriminator = Discriminator(cfg)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    @torch.no_grad()
    def sample(
        self, cond: torch.Tensor, num: int | None = None, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Latents in standardised space for conditions ``cond``: (B, cond_dim) text embeddings or (B,) action ids.

        num=None: one latent per condition -> (B, Z); num=k: k latents per condition -> (B, k, Z).
        ``generator`` (on the model's device) makes the noise reproducible.
        """
        cond = torch.as_tensor(cond, device=self.device)
        if num is not None:
            cond = cond.repeat_interleave(num, dim=0)
        noise = torch.randn(cond.shape[0], self.config.noise_dim, generator=generator, device=self.device)
        z = self.generator(noise, cond)  # (B*k, Z)
        return z if num is None else z.view(-1, num, z.shape[-1])


def destandardise(z: torch.Tensor, mean: ArrayLike, std: ArrayLike) -> torch.Tensor:
    """Standardised latents -> the VAE's latent space: z * std + mean (mean/std (Z,), as in the cache)."""
    mean = torch.as_tensor(mean, dtype=z.dtype, device=z.device)
    std = torch.as_tensor(std, dtype=z.dtype, device=z.device)
    return z * std + mean


def load_gan(
    path: str | os.PathLike, device: str | torch.device = "cpu", prefer: str = "best"
) -> tuple[LatentGAN, dict]:
    """(model in eval mode, checkpoint meta) from a checkpoint folder or a run folder (its best/, else last/).

    meta["extra"] holds latent_mean/latent_std (for ``destandardise``), vae_hash and text_encoder (to check the
    pairing with a VAE and text encoder), action_names and val_latent_fid.
    """
    weights, meta = load_weights(path, prefer=prefer, kind="gan")
    known = {f.name for f in fields(GANConfig)}
    cfg = GANConfig(**{k: v for k, v in meta["config"]["gan"].items() if k in known})
    model = LatentGAN(cfg)
    model.load_state_dict(weights, strict=True)
    return model.to(device).eval(), meta
