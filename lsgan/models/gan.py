"""The latent-space GANs of LS-GAN: a conditional generator z' = G(noise, c) and a discriminator/critic D(z, c).

Four variants (method.md's table), picked by ``GANConfig.arch``:

    vanilla-gan       3-FC generator, 4-FC discriminator, LeakyReLU after every hidden layer, BCE loss (sigmoid
                      folded into BCE-with-logits); the LS-GAN authors' widths (docs/fidelity.md)
    vanilla-wgan-gp   same networks, the discriminator is a critic (no sigmoid), Wasserstein loss + gradient penalty
    deep-gan          FC networks with residual blocks after their first FC layer, BCE loss
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

from lsgan.models.checkpoint import checkpoint_reader, load_weights, unwrap

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
    hidden_dim: int = 512  # H: deep networks are H wide; vanilla ones taper 2H -> H (G), 2H -> H -> H/2 (D)
    num_res_blocks: int = 2  # deep variants only
    leaky_slope: float = 0.2  # the LS-GAN authors' nn.LeakyReLU() is torch's default, 0.01

    def __post_init__(self) -> None:
        if self.arch not in ARCHS:
            raise ValueError(f"unknown GAN arch {self.arch!r}; choose one of {ARCHS}")
        if self.cond not in CONDS:
            raise ValueError(f"unknown condition kind {self.cond!r}; choose one of {CONDS}")
        if self.hidden_dim < 2:
            raise ValueError(f"hidden_dim must be at least 2, got {self.hidden_dim}")

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

    def widths(self, net: str) -> tuple[int, ...]:
        """Hidden widths of the generator ("G": fc1, fc2) or discriminator ("D": fc1, fc2, fc3).

        Vanilla: the LS-GAN authors' taper (gan_architecture.py: G 1024, 512; D 1024, 512, 256 for H = 512);
        deep: H throughout (our residual design, not the authors').
        """
        h = self.hidden_dim
        if self.deep:
            return (h, h) if net == "G" else (h, h, h)
        return (2 * h, h) if net == "G" else (2 * h, h, h // 2)


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

    Layout (H = hidden_dim)::

        vanilla: [noise, c] -> fc1 (2H) -> LeakyReLU -> fc2 (H) -> LeakyReLU -> fc3 -> z'
        deep:    [noise, c] -> fc1 (H) -> ResBlock x num_res_blocks -> fc2 (H) -> LeakyReLU -> fc3 -> z'

    The vanilla one is the paper's "3 fully connected layers" with leaky ReLU in all layers preceding the final
    one, at the LS-GAN authors' widths (1024, 512 for H = 512). The deep one's first FC layer feeds pre-activation
    residual blocks directly (``act1`` is the identity there), as its checkpoints were trained.
    Cost at a 768-d condition: 1.544 M multiply-adds per clip (vanilla), 1.362 M (deep); FLOPs are twice that
    (`lsgan bench`: 3.09 M, 2.72 M). The vanilla count times 1024 is the paper's "1.581 G" (THOP MACs,
    docs/fidelity.md).
    """

    def __init__(self, cfg: GANConfig) -> None:
        super().__init__()
        w1, w2 = cfg.widths("G")
        self.cond = Condition(cfg)
        self.fc1 = nn.Linear(cfg.noise_dim + self.cond.dim, w1)
        self.act1 = nn.Identity() if cfg.deep else nn.LeakyReLU(cfg.leaky_slope)
        self.blocks = nn.ModuleList(ResBlock(w1, cfg.leaky_slope) for _ in range(cfg.blocks))
        self.fc2 = nn.Linear(w1, w2)
        self.act = nn.LeakyReLU(cfg.leaky_slope)
        self.fc3 = nn.Linear(w2, cfg.latent_dim)

    def forward(self, noise: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        x = self.act1(self.fc1(torch.cat([noise, self.cond(c)], dim=-1)))  # (B, W1)
        for block in self.blocks:
            x = block(x)  # (B, W1)
        return self.fc3(self.act(self.fc2(x)))  # (B, W2) -> (B, Z)


class Discriminator(nn.Module):
    """D(z, c) -> one score per sample (B,): a logit for the BCE GANs, an unbounded critic value for WGAN-GP.

    Layout (H = hidden_dim; no batch norm, which breaks the gradient penalty)::

        vanilla: [z, c] -> fc1 (2H) -> LeakyReLU -> fc2 (H) -> LeakyReLU -> fc3 (H/2) -> LeakyReLU -> fc4 -> score
        deep:    [z, c] -> fc1 (H) -> ResBlock x num_res_blocks -> LeakyReLU -> fc2 (H) -> ... -> fc4 -> score

    The vanilla one is the paper's "4 fully connected layers" at the LS-GAN authors' widths (1024, 512, 256 for
    H = 512). The BCE variants' sigmoid is applied inside the loss (BCE-with-logits: the same function, numerically
    stable). The condition has its own embedding here (for actions), separate from the generator's.
    """

    def __init__(self, cfg: GANConfig) -> None:
        super().__init__()
        w1, w2, w3 = cfg.widths("D")
        self.cond = Condition(cfg)
        self.fc1 = nn.Linear(cfg.latent_dim + self.cond.dim, w1)
        self.blocks = nn.ModuleList(ResBlock(w1, cfg.leaky_slope) for _ in range(cfg.blocks))
        self.fc2 = nn.Linear(w1, w2)
        self.fc3 = nn.Linear(w2, w3)
        self.fc4 = nn.Linear(w3, 1)
        self.act = nn.LeakyReLU(cfg.leaky_slope)

    def forward(self, z: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        x = self.fc1(torch.cat([z, self.cond(c)], dim=-1))  # (B, W1)
        for block in self.blocks:
            x = block(x)  # (B, W1)
        x = self.act(self.fc2(self.act(x)))  # (B, W2)
        x = self.act(self.fc3(x))  # (B, W3)
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


@checkpoint_reader
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
    try:
        model.load_state_dict(weights, strict=True)
    except RuntimeError as e:
        if cfg.deep or "size mismatch" not in str(e):
            raise
        raise ValueError(f"{path}: a {cfg.arch} checkpoint from before the vanilla networks followed the paper "
                         "(LeakyReLU after every hidden layer, widths 2H/H and 2H/H/H/2); train it again") from e
    return model.to(device).eval(), meta
