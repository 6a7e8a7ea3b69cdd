"""Train the latent-diffusion baseline (MLD's denoiser) from the latent cache alone, like ``train_gan``.

One step: a batch of (condition, latent) train pairs (latents standardised with the cache's statistics; with
real_latents="sample", z ~ N(mu, exp(logvar)) as MLD's diffusion stage draws it from the frozen VAE), uniform
timesteps, noise, the condition replaced by the null token with probability ``cond_mask_prob`` (for
classifier-free guidance), and the MSE between the denoiser's prediction and the noise. AdamW (MLD: lr 1e-4 and
torch's other defaults, weight decay 0.01).

Every ``eval_every`` steps the model is scored by the same latent-space FID on the validation conditions as the
GANs, from DDIM samples with ``eval_steps`` steps and guidance ``eval_guidance`` (default: the model's) and fixed
noise; ``out/best/`` keeps the lowest, ``out/last/`` (with the optimiser state) is written every ``ckpt_every``
steps and at the end. The randomness of step s on rank r comes from (seed, r, s) alone, so ``resume`` continues
exactly; under torchrun the denoiser runs in DistributedDataParallel and rank 0 writes. The loop itself is
:mod:`lsgan.train.loop`'s.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from lsgan.models.diffusion import (
    DiffusionConfig,
    LatentDiffusion,
    diffusion_loss,
    load_diffusion,
)
from lsgan.train.common import seed_everything
from lsgan.train.graphs import optimizer_options
from lsgan.train.latents import LatentTrainConfig, latent_summary, latent_trainer, open_cache
from lsgan.train.loop import Env, fit, launch

__all__ = ["DiffusionTrainConfig", "load_diffusion", "train_diffusion"]


@dataclass
class DiffusionTrainConfig(LatentTrainConfig):
    """With the schedule, batch and latent-FID settings of :class:`lsgan.train.latents.LatentTrainConfig`."""

    weight_decay: float = 0.01  # torch's AdamW default, which MLD keeps
    eval_steps: int = 10  # DDIM steps of the samples scored by the latent FID (fewer than sampling's, for speed)
    eval_guidance: float | None = None  # None: the model's guidance_scale

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.eval_steps < 1:
            raise ValueError("eval_steps must be >= 1")


def train_diffusion(cache: str | os.PathLike, out: str | os.PathLike, *, diffusion: DiffusionConfig | None = None,
                    train: DiffusionTrainConfig | None = None, device: str = "auto", resume: bool = False,
                    force: bool = False, progress: bool = True, expect_vae_hash: str | None = None,
                    expect_text_encoder: str | None = None) -> dict:
    """Train the denoiser on ``cache`` as :func:`lsgan.train.gan.train_gan` trains a GAN (the same run folder, checks
    of the cache's VAE and text encoder, and ``resume``); its summary adds ``eval_sampling``."""
    diffusion, train = diffusion or DiffusionConfig(), train or DiffusionTrainConfig()
    return launch("train_diffusion", out, device=device, resume=resume, force=force, progress=progress,
                  body=lambda env: _train(env, Path(cache), diffusion, train, expect_vae_hash, expect_text_encoder))


def _train(env: Env, cache_path: Path, cfg: DiffusionConfig, train: DiffusionTrainConfig,
           expect_vae_hash: str | None, expect_text_encoder: str | None) -> dict:
    cfg, prev, data = open_cache(env, cache_path, cfg, train, "diffusion", expect_vae_hash, expect_text_encoder)
    seed_everything(train.seed)
    model = LatentDiffusion(cfg).to(env.device)
    opt = torch.optim.AdamW(model.parameters(), lr=train.lr, betas=train.betas, weight_decay=train.weight_decay,
                            **optimizer_options(env.device))
    net = env.ddp(model.denoiser)

    def step(g: torch.Generator) -> dict[str, torch.Tensor]:
        z0, c = data.pairs.batch(data.batch, g)
        loss = diffusion_loss(model, z0, c, g, net=net)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"loss": loss.detach()}

    sampling = {"steps": train.eval_steps, "guidance": train.eval_guidance, "eta": 0.0}
    config = {"diffusion": asdict(cfg), "train": asdict(train)}
    t = latent_trainer(env, "diffusion", "diffusion", model, config, {"opt": opt}, step, data, train.seed,
                       train.cuda_graph, **sampling)
    p = fit(env, t, train.schedule(), prev)
    return latent_summary(env, p, data, config) | {"eval_sampling": sampling}
