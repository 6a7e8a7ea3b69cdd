"""Benchmark of the paper's cost claim on this machine, with paper-sized models (random weights).

1. GAN training steps/s reading latents from the cache (lsgan's design) versus the naive design that runs
   the VAE encoder on every real batch, at the same batch size in the same run; reported as a ratio.
Time per generated motion and FLOPs (GANs vs. the diffusion baseline) are measured by ``lsgan bench``.

    python benchmarks/models.py                  # CPU (and CUDA when torch sees a GPU)
    python benchmarks/models.py --json out.json --steps 20 --frames 120
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import torch

from lsgan.eval.bench import PAPER_VAE
from lsgan.models.gan import GANConfig, LatentGAN, critic_loss_wgan_gp, g_loss_wgan
from lsgan.models.vae import MotionVAE

PAPER_GAN = GANConfig(arch="deep-wgan-gp", noise_dim=100, latent_dim=256, cond="text", cond_dim=384)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench_training(device: torch.device, steps: int, batch: int, frames: int) -> dict:
    """Steps/s of deep-wgan-gp (5 critic steps) from cached latents vs. encoding every real batch with the VAE."""
    torch.manual_seed(0)
    vae = MotionVAE(PAPER_VAE).to(device).eval()
    gan = LatentGAN(PAPER_GAN).to(device)
    opt_d = torch.optim.AdamW(gan.discriminator.parameters(), lr=1e-4, betas=(0.5, 0.9))
    opt_g = torch.optim.AdamW(gan.generator.parameters(), lr=1e-4, betas=(0.5, 0.9))
    n_clips = 512
    motions = torch.randn(n_clips, frames, 263, device=device)
    lengths = torch.randint(40, frames + 1, (n_clips,), device=device)
    mask_all = torch.arange(frames, device=device)[None] < lengths[:, None]
    cond_all = torch.nn.functional.normalize(torch.randn(n_clips, 384, device=device), dim=-1)
    with torch.no_grad():
        cached = torch.cat([vae.encode(motions[i : i + 64], mask_all[i : i + 64])[0] for i in range(0, n_clips, 64)])

    def cached_batch():
        i = torch.randint(n_clips, (batch,), device=device)
        return cached[i], cond_all[i]

    def naive_batch():
        i = torch.randint(n_clips, (batch,), device=device)
        with torch.no_grad():
            mu, logvar = vae.encode(motions[i], mask_all[i])
        return mu + torch.randn_like(mu) * (0.5 * logvar).exp(), cond_all[i]

    out = {}
    for name, source in (("cached", cached_batch), ("naive_vae_every_batch", naive_batch)):
        # The critic takes 5 real batches per generator step: the naive design encodes each of them.
        real, cond = source()  # warm-up
        _gan_step_critic_only(gan, opt_d, real, cond)
        _gen_step(gan, opt_g, cond)
        _sync(device)
        t0 = time.perf_counter()
        for _ in range(steps):
            for _ in range(5):
                real, cond = source()
                _gan_step_critic_only(gan, opt_d, real, cond)
            _gen_step(gan, opt_g, cond)
        _sync(device)
        out[f"{name}_steps_per_s"] = steps / (time.perf_counter() - t0)
    out["speedup_cached_vs_naive"] = out["cached_steps_per_s"] / out["naive_vae_every_batch_steps_per_s"]
    out.update(batch=batch, frames=frames, critic_steps=5, steps=steps)
    return out


def _gan_step_critic_only(gan: LatentGAN, opt_d, real: torch.Tensor, cond: torch.Tensor) -> None:
    with torch.no_grad():
        fake = gan.generator(torch.randn(real.shape[0], gan.config.noise_dim, device=real.device), cond)
    loss = critic_loss_wgan_gp(gan.discriminator, real, fake, cond).loss
    opt_d.zero_grad(set_to_none=True)
    loss.backward()
    opt_d.step()


def _gen_step(gan: LatentGAN, opt_g, cond: torch.Tensor) -> None:
    gan.discriminator.requires_grad_(False)
    noise = torch.randn(cond.shape[0], gan.config.noise_dim, device=cond.device)
    loss = g_loss_wgan(gan.discriminator(gan.generator(noise, cond), cond))
    opt_g.zero_grad(set_to_none=True)
    loss.backward()
    gan.discriminator.requires_grad_(True)
    opt_g.step()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=10, help="GAN steps per design")
    ap.add_argument("--batch", type=int, default=64, help="GAN training batch size (paper: 64)")
    ap.add_argument("--frames", type=int, default=120, help="motion length for encoding and decoding (20 fps)")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    report = {"machine": f"{platform.machine()} python {platform.python_version()} torch {torch.__version__}",
              "threads": torch.get_num_threads(), "results": []}
    for dev in devices:
        train = bench_training(dev, args.steps, args.batch, args.frames)
        print(f"[{dev}] GAN training: cached {train['cached_steps_per_s']:.2f} steps/s, naive "
              f"{train['naive_vae_every_batch_steps_per_s']:.2f} steps/s -> x{train['speedup_cached_vs_naive']:.1f}",
              file=sys.stderr)
        report["results"].append({"device": str(dev), "training": train})
    text = json.dumps(report, indent=1)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text)
    print(text)


if __name__ == "__main__":
    main()
