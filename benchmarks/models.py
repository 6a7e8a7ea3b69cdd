"""Benchmark of the paper's cost claim on this machine, with paper-sized models (random weights).

1. GAN training steps/s reading latents from the cache (lsgan's design) versus the naive design that runs
   the VAE encoder on every real batch, at the same batch size in the same run; reported as a ratio.
2. Time per generated motion at batch 1 and 256, split into text encoding, generator and VAE decoding.

    python benchmarks/models.py                  # CPU (and CUDA when torch sees a GPU)
    python benchmarks/models.py --json out.json --steps 20 --frames 120
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import numpy as np
import torch

from lsgan.models.gan import GANConfig, LatentGAN, critic_loss_wgan_gp, g_loss_wgan
from lsgan.models.text import load_text_encoder
from lsgan.models.vae import MotionVAE, VAEConfig

PAPER_VAE = VAEConfig(latent_dim=256, d_model=256, num_layers=9, num_heads=4, ff_size=1024, dropout=0.1)
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


def bench_generation(device: torch.device, batch: int, frames: int, repeats: int) -> dict:
    """ms per motion for text encoding (MiniLM), the generator and VAE decoding, at one batch size."""
    torch.manual_seed(0)
    enc = load_text_encoder("minilm", device=device)
    gan = LatentGAN(PAPER_GAN).to(device).eval()
    vae = MotionVAE(PAPER_VAE).to(device).eval()
    prompts = [f"a person walks forward and waves the {'left' if i % 2 else 'right'} hand {i} times" for i in range(batch)]
    mask = torch.ones(batch, frames, dtype=torch.bool, device=device)
    timings = {"text_encoding": [], "generator": [], "vae_decoding": []}
    with torch.no_grad():
        for r in range(repeats + 1):
            t0 = time.perf_counter()
            cond = enc.encode(prompts).to(device)
            _sync(device)
            t1 = time.perf_counter()
            z = gan.generator(torch.randn(batch, 100, device=device), cond)
            _sync(device)
            t2 = time.perf_counter()
            vae.decode(z, mask)
            _sync(device)
            t3 = time.perf_counter()
            if r:  # the first round is a warm-up
                for k, dt in zip(timings, (t1 - t0, t2 - t1, t3 - t2)):
                    timings[k].append(1000 * dt / batch)
    med = {k: float(np.median(v)) for k, v in timings.items()}
    return {"batch": batch, "frames": frames, **{f"{k}_ms_per_motion": v for k, v in med.items()},
            "total_ms_per_motion": sum(med.values())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=10, help="GAN steps per design")
    ap.add_argument("--batch", type=int, default=64, help="GAN training batch size (paper: 64)")
    ap.add_argument("--frames", type=int, default=120, help="motion length for encoding and decoding (20 fps)")
    ap.add_argument("--repeats", type=int, default=3)
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
        gen = [bench_generation(dev, b, args.frames, args.repeats) for b in (1, 256)]
        for g in gen:
            print(f"[{dev}] generation batch {g['batch']}: {g['total_ms_per_motion']:.2f} ms/motion (text "
                  f"{g['text_encoding_ms_per_motion']:.2f}, generator {g['generator_ms_per_motion']:.3f}, "
                  f"VAE decoder {g['vae_decoding_ms_per_motion']:.2f})", file=sys.stderr)
        report["results"].append({"device": str(dev), "training": train, "generation": gen})
    text = json.dumps(report, indent=1)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text)
    print(text)


if __name__ == "__main__":
    main()
