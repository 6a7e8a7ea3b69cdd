"""Train a latent GAN from the latent cache alone (the VAE is never loaded).

One training step = ``critic_steps`` discriminator updates, then one generator update, each on a fresh batch of
(condition, latent) pairs from the train split: text -> (caption embedding, its clip's latent), action ->
(action id, latent). Latents are standardised per dimension with the cache's train statistics; with
real_latents="sample" each step draws z ~ N(mu, exp(logvar)) instead of using mu.

Every ``eval_every`` steps the generator is scored by a latent-space FID on the validation conditions (fixed
noise, so evaluations are comparable); ``out/best/`` keeps the lowest one, ``out/last/`` (with the optimiser
state) is written every ``ckpt_every`` steps and at the end.

Randomness of step s on rank r comes from a generator seeded by (seed, r, s) alone, so a resumed run continues
exactly as an uninterrupted one. Under torchrun each rank draws its own batches (rank-seeded sampling) of
batch_size / world_size pairs; generator and critic are wrapped in DistributedDataParallel (the critic's
gradient penalty is a double backward, which DDP handles: see ``critic_loss_wgan_gp``); rank 0 writes checkpoints
and logs. The loop itself (schedule, resume, NaN stop, DDP set-up) is :mod:`lsgan.train.loop`'s.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from lsgan.models.gan import (
    GANConfig,
    LatentGAN,
    critic_loss_wgan_gp,
    d_loss_bce,
    g_loss_bce,
    g_loss_wgan,
    load_gan,
)
from lsgan.train.common import seed_everything
from lsgan.train.graphs import optimizer_options
from lsgan.train.latents import (
    LatentPairs,
    LatentTrainConfig,
    latent_summary,
    latent_trainer,
    open_cache,
)
from lsgan.train.loop import Env, fit, launch

__all__ = ["GANTrainConfig", "train_gan", "load_gan"]


@dataclass
class GANTrainConfig(LatentTrainConfig):
    """With the schedule, batch and latent-FID settings of :class:`lsgan.train.latents.LatentTrainConfig`."""

    betas: tuple[float, float] = (0.5, 0.9)
    critic_steps: int | None = None  # discriminator updates per generator update; None: 5 for WGAN-GP, 1 for BCE
    gp_weight: float = 10.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.critic_steps is not None and self.critic_steps < 1:
            raise ValueError("critic_steps must be >= 1 (or None for the variant's default)")

    def critic_steps_for(self, gan: GANConfig) -> int:
        return self.critic_steps or (5 if gan.wgan else 1)


# ---------------------------------------------------------------------------------------------------- steps


def d_step(model: LatentGAN, d_net, opt, data: LatentPairs, b: int, gp_weight: float, g: torch.Generator) -> dict:
    """One discriminator/critic update; returns its (detached) losses."""
    real, c = data.batch(b, g)  # (b, Z), (b, ...)
    noise = torch.randn(b, model.config.noise_dim, generator=g, device=real.device)
    with torch.no_grad():
        fake = model.generator(noise, c)  # (b, Z)
    if model.config.wgan:
        out = critic_loss_wgan_gp(d_net, real, fake, c, gp_weight, generator=g)
        loss, stats = out.loss, {"wasserstein": out.wasserstein, "gp": out.gp}
    else:
        logits = d_net(torch.cat([real, fake]), torch.cat([c, c]))  # (2b,): one forward pass, as DDP expects
        loss, stats = d_loss_bce(*logits.split(b)), {}
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return {"d_loss": loss.detach(), **stats}


def g_step(model: LatentGAN, g_net, opt, data: LatentPairs, b: int, g: torch.Generator) -> torch.Tensor:
    """One generator update through the frozen, unwrapped discriminator (no weight gradients, nothing to sync)."""
    _, c = data.batch(b, g)
    noise = torch.randn(b, model.config.noise_dim, generator=g, device=data.mu.device)
    model.discriminator.requires_grad_(False)
    scores = model.discriminator(g_net(noise, c), c)  # (b,)
    loss = g_loss_wgan(scores) if model.config.wgan else g_loss_bce(scores)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    model.discriminator.requires_grad_(True)
    opt.step()
    return loss.detach()


# ---------------------------------------------------------------------------------------------------- training


def train_gan(cache: str | os.PathLike, out: str | os.PathLike, *, gan: GANConfig | None = None,
              train: GANTrainConfig | None = None, device: str = "auto", resume: bool = False, force: bool = False,
              progress: bool = True, expect_vae_hash: str | None = None,
              expect_text_encoder: str | None = None) -> dict:
    """Train a latent GAN on ``cache``, writing ``out/last``, ``out/best`` and ``out/log.csv``; returns a summary.

    expect_vae_hash / expect_text_encoder: refuse (StaleCache) a cache made with another VAE or text encoder.
    resume: continue from ``out/last`` at its step (an existing run is never overwritten without it).
    """
    gan, train = gan or GANConfig(), train or GANTrainConfig()

    def body(env: Env) -> dict:
        with warnings.catch_warnings():
            # DDP notes that the double backward hands the critic's (1, H) output weight a gradient with other
            # (equivalent) strides than its bucket view: a performance remark about one tiny tensor.
            warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
            return _train(env, Path(cache), gan, train, expect_vae_hash, expect_text_encoder)

    return launch("train_gan", out, device=device, resume=resume, force=force, progress=progress, body=body)


def _train(env: Env, cache_path: Path, gan: GANConfig, train: GANTrainConfig, expect_vae_hash: str | None,
           expect_text_encoder: str | None) -> dict:
    gan, prev, data = open_cache(env, cache_path, gan, train, "gan", expect_vae_hash, expect_text_encoder)
    critic_steps = train.critic_steps_for(gan)
    seed_everything(train.seed)
    model = LatentGAN(gan).to(env.device)
    hp = dict(lr=train.lr, betas=train.betas, weight_decay=train.weight_decay, **optimizer_options(env.device))
    opt_g = torch.optim.AdamW(model.generator.parameters(), **hp)
    opt_d = torch.optim.AdamW(model.discriminator.parameters(), **hp)
    g_net, d_net = env.ddp(model.generator), env.ddp(model.discriminator)

    def step(g: torch.Generator) -> dict[str, torch.Tensor]:
        for _ in range(critic_steps):
            d_stats = d_step(model, d_net, opt_d, data.pairs, data.batch, train.gp_weight, g)
        return {**d_stats, "g_loss": g_step(model, g_net, opt_g, data.pairs, data.batch, g)}

    config = {"gan": asdict(gan), "train": asdict(train)}
    t = latent_trainer(env, "gan", f"gan {gan.arch}", model, config, {"opt_g": opt_g, "opt_d": opt_d}, step, data,
                       train.seed, train.cuda_graph)
    p = fit(env, t, train.schedule(), prev)
    return latent_summary(env, p, data, config) | {"critic_steps": critic_steps}
