"""Cost of generation (``lsgan bench``): FLOPs for 2048 clips and measured time per motion, per model.

FLOPs are counted by PyTorch's ``FlopCounterMode`` on the real forward passes (the generator once; the
denoiser over every sampling step, both halves of classifier-free guidance included) for a batch of
``FLOP_BATCH`` clips and scaled to 2048: every operation is per sample, so the count is exactly linear in
the batch (a test checks this). Time per motion is measured end to end, as a user waits for it: text
encoding + generator or denoiser + VAE decoding, at batch 1 and 256, median of ``repeats`` runs after a
warm-up. Models are paper-sized with random weights unless checkpoints are given.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from lsgan.models.gan import GANConfig, LatentGAN
from lsgan.models.vae import MotionVAE, VAEConfig

CLIPS = 2048
FLOP_BATCH = 32
PAPER_VAE = VAEConfig(latent_dim=256, d_model=256, num_layers=9, num_heads=4, ff_size=1024, dropout=0.1)
PAPER_GANS = ("deep-wgan-gp", "vanilla-wgan-gp")
# MLD's denoiser (configs/modules/denoiser.yaml): 9 layers, width 256, 4 heads, ff 1024, one 256-d latent token.
PAPER_DIFFUSION = dict(latent_dim=256, d_model=256, num_layers=9, num_heads=4, ff_size=1024, dropout=0.1,
                       norm_first=False, cond="text", cond_dim=384)


@dataclass
class BenchRow:
    """One line of the table; the JSON keys are the field names."""

    model: str
    gflops_2048: float
    ms_per_motion_b1: float
    ms_per_motion_b256: float
    device: str


@dataclass
class Sampler:
    """A latent generator as the benchmark sees it: ``sample(cond) -> latents (B, Z)`` for embeddings (B, D)."""

    name: str
    sample: Callable[[torch.Tensor], torch.Tensor]
    cond_dim: int
    to: Callable[[torch.device], None]


def count_flops(fn: Callable[[], object]) -> int:
    """Floating-point operations of one call of ``fn`` (PyTorch's count: a multiply-add is 2).

    Transformer layers in eval mode take a fused fast path that the counter does not see, so it is switched off
    while counting (the arithmetic is the same)."""
    fastpath = torch.backends.mha.get_fastpath_enabled()
    torch.backends.mha.set_fastpath_enabled(False)
    try:
        with FlopCounterMode(display=False) as counter, torch.no_grad():
            fn()
    finally:
        torch.backends.mha.set_fastpath_enabled(fastpath)
    return int(counter.get_total_flops())


def gan_sampler(arch: str, gan: LatentGAN | None = None, cond_dim: int = 384) -> Sampler:
    """The generator of a GAN (paper-sized, random weights, when ``gan`` is None)."""
    model = gan if gan is not None else LatentGAN(GANConfig(arch=arch, noise_dim=100, latent_dim=256, cond="text",
                                                             cond_dim=cond_dim))
    model.eval()
    noise_dim = model.config.noise_dim

    def sample(cond: torch.Tensor) -> torch.Tensor:
        return model.generator(torch.randn(cond.shape[0], noise_dim, device=cond.device), cond)

    return Sampler(arch, sample, model.config.cond_dim, lambda d: model.to(d))


def diffusion_sampler(model=None, *, steps: int, guidance: float, name: str = "mld-diffusion") -> Sampler:
    """A latent-diffusion model (paper-sized, random weights, when None) sampled with DDIM over ``steps`` steps
    and classifier-free ``guidance`` (two denoiser passes per step unless guidance is 1)."""
    from lsgan.models.diffusion import DiffusionConfig, LatentDiffusion

    model = (model if model is not None else LatentDiffusion(DiffusionConfig(**PAPER_DIFFUSION))).eval()

    def sample(cond: torch.Tensor) -> torch.Tensor:
        g = torch.Generator(device="cpu").manual_seed(0)
        return model.sample(cond, generator=g, steps=steps, guidance=guidance)

    return Sampler(f"{name} ({steps} DDIM steps, cfg {guidance:g})", sample, model.config.cond_dim,
                   lambda d: model.to(d))


def bench_samplers(*, gans=(), diffusion=None, vae=None, steps: int = 50, guidance: float = 7.5,
                   ) -> tuple[list[Sampler], MotionVAE | None]:
    """The samplers ``lsgan bench`` times: the given checkpoints, or paper-sized GANs and MLD denoiser."""
    from lsgan.generate import load_generator

    samplers = []
    for path in gans:
        model, _ = load_generator(path)
        if model.config.cond != "text":
            raise ValueError(f"{path}: bench times text-conditioned generators; this one is {model.config.cond}")
        samplers.append(gan_sampler(model.config.arch, model) if hasattr(model, "generator") else
                        diffusion_sampler(model, steps=steps, guidance=guidance, name=Path(str(path)).name))
    if not gans:
        samplers = [gan_sampler(arch) for arch in PAPER_GANS]
    if diffusion is not None:
        model, _ = load_generator(diffusion)
        samplers.append(diffusion_sampler(model, steps=steps, guidance=guidance, name=Path(str(diffusion)).name))
    elif not gans:
        samplers.append(diffusion_sampler(steps=steps, guidance=guidance))
    decoder = None
    if vae is not None:
        from lsgan.models.vae import load_vae

        decoder, _ = load_vae(vae)
    return samplers, decoder


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def gflops_2048(sampler: Sampler, device: torch.device) -> float:
    """GFLOPs of sampling 2048 latents (counted on FLOP_BATCH clips, scaled exactly)."""
    cond = torch.nn.functional.normalize(torch.randn(FLOP_BATCH, sampler.cond_dim, device=device), dim=-1)
    return count_flops(lambda: sampler.sample(cond)) * (CLIPS / FLOP_BATCH) / 1e9


def ms_per_motion(sampler: Sampler, vae: MotionVAE, encode: Callable[[list[str]], torch.Tensor],
                  device: torch.device, *, batch: int, frames: int, repeats: int) -> float:
    """Median wall time per motion of text encoding + sampling + VAE decoding at ``batch``."""
    prompts = [f"a person walks forward and waves the {'left' if i % 2 else 'right'} hand {i} times"
               for i in range(batch)]
    mask = torch.ones(batch, frames, dtype=torch.bool, device=device)
    samples = []
    with torch.no_grad():
        for r in range(repeats + 1):
            _sync(device)
            t0 = time.perf_counter()
            z = sampler.sample(encode(prompts).to(device))
            vae.decode(z, mask)
            _sync(device)
            if r:  # round 0 warms up
                samples.append(1000.0 * (time.perf_counter() - t0) / batch)
    return float(np.median(samples))


def run_bench(samplers: list[Sampler], *, vae: MotionVAE | None = None, devices: list[str] | None = None,
              frames: int = 120, repeats: int = 3, text_encoder: str = "minilm",
              progress: Callable[[str], None] | None = None) -> list[BenchRow]:
    """One row per sampler and device: FLOPs for 2048 clips, ms per motion at batch 1 and 256."""
    from lsgan.models.text import load_text_encoder

    devices = devices or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    torch.manual_seed(0)
    decoder = (vae if vae is not None else MotionVAE(PAPER_VAE)).eval()
    rows = []
    for dev_name in devices:
        device = torch.device(dev_name)
        enc = load_text_encoder(text_encoder, device=device)
        decoder.to(device)
        for sampler in samplers:
            sampler.to(device)
            if progress:
                progress(f"[{device}] {sampler.name}")
            flops = gflops_2048(sampler, device)
            times = [ms_per_motion(sampler, decoder, enc.encode, device, batch=b, frames=frames, repeats=repeats)
                     for b in (1, 256)]
            rows.append(BenchRow(sampler.name, flops, times[0], times[1], str(device)))
    return rows


def format_table(rows: list[BenchRow]) -> str:
    """Markdown table of the rows, with each model's FLOPs and time relative to the first row's."""
    lines = ["| model | device | GFLOPs (2048 clips) | ms/motion b1 | ms/motion b256 | FLOPs vs first | time b1 vs first |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        base = next(b for b in rows if b.device == r.device)
        lines.append(f"| {r.model} | {r.device} | {r.gflops_2048:.2f} | {r.ms_per_motion_b1:.2f} | "
                     f"{r.ms_per_motion_b256:.2f} | x{r.gflops_2048 / base.gflops_2048:.1f} | "
                     f"x{r.ms_per_motion_b1 / base.ms_per_motion_b1:.2f} |")
    return "\n".join(lines)


def rows_as_dicts(rows: list[BenchRow]) -> list[dict]:
    return [asdict(r) for r in rows]
