"""The GPU path, measured: generation time per motion, training steps and peak memory, paper-sized models.

All models have random weights and the paper's sizes: the VAE of ``recipes/humanml3d.yaml`` (MLD's VAE: 9 layers,
d 256, 4 heads, ff 1024, post-norm), deep-wgan-gp (noise 100, latent 256, hidden 512) conditioned on MiniLM's
384-d sentence embedding (the toolkit's default encoder; the paper's CLIP gives 768-d).

1. Generation, end to end as ``lsgan generate`` runs it: MiniLM text encoding (tokenisation on the CPU, the
   embeddings back on the CPU, as ``TextEncoder.encode`` returns them) + generator + VAE decoding of 120
   frames, at batch 1 and 1024, in four modes: fp32; bf16 autocast; ``torch.compile`` (default mode) of the
   generator, the decoder and the text encoder's BERT, fp32; the same compiled, under bf16 autocast.
   Wall clock per repeat with ``torch.cuda.synchronize`` after each stage; reported per motion.
2. A VAE training step as ``lsgan train-vae`` takes it (forward, MSE + KL, backward, grad-norm clip 1.0, AdamW),
   batch 128 of 196-frame windows (recipes/humanml3d.yaml: batch_size 128, max_frames 196; every frame real,
   the longest batch), fp32 and bf16 autocast (the recipe's ``amp: true``).
3. A deep-wgan-gp step as ``lsgan train-gan`` takes it: 5 critic updates (WGAN-GP, gradient penalty 10) + 1
   generator update, batch 64 (the recipe's), with the library's own ``d_step`` / ``g_step``, fp32 (as the
   library trains the GAN), eager and replayed as one CUDA graph (``lsgan.train.graphs``, the default on one GPU).

Each figure: median over repeats after a warm-up, with min and max; peak GPU memory is
``torch.cuda.max_memory_allocated`` from a reset before the configuration's models are built (weights,
optimiser state and activations of that configuration alone). Training steps are timed as a run of steps
between two synchronisations (the library's loop also reads the losses back every step; that costs little
once the GPU is the bottleneck).

    python benchmarks/gpu.py                       # prints markdown tables
    python benchmarks/gpu.py --json gpu.json       # and writes the figures
    python benchmarks/gpu.py --only generation --repeats 20

On a machine without CUDA it says so and exits 0 (nothing is measured; the test suite never runs it).
"""
from __future__ import annotations

import argparse
import gc
import json
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 120  # generated motion length (6 s at 20 fps), as lsgan bench
VAE_BATCH, VAE_FRAMES = 128, 196  # recipes/humanml3d.yaml vae.train
GAN_BATCH, CRITIC_STEPS, GP_WEIGHT = 64, 5, 10.0  # recipes/humanml3d.yaml gan.train
MODES = ("fp32", "bf16", "compiled-fp32", "compiled-bf16")


def prompts(batch: int) -> list[str]:
    """The prompts timed at ``batch`` (the same sentences as ``lsgan bench``)."""
    return [f"a person walks forward and waves the {'left' if i % 2 else 'right'} hand {i} times" for i in range(batch)]


def paper_vae_config():
    """MLD's VAE as recipes/humanml3d.yaml gives it (the ``vae: model:`` section)."""
    from lsgan.models.vae import VAEConfig
    from lsgan.recipes import build, load_recipe, section

    recipe = load_recipe(ROOT / "recipes" / "humanml3d.yaml")
    return build(VAEConfig, section(recipe, "vae").get("model"), "vae.model")


def paper_gan_config():
    from lsgan.models.gan import GANConfig

    return GANConfig(arch="deep-wgan-gp", noise_dim=100, latent_dim=256, cond="text", cond_dim=384, hidden_dim=512,
                     num_res_blocks=2, leaky_slope=0.2)


def _sync() -> None:
    torch.cuda.synchronize()


def _spread(values: list[float]) -> dict:
    return {"median": statistics.median(values), "min": min(values), "max": max(values), "n": len(values)}


def _fresh() -> None:
    gc.collect()
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()


def _peak_gib() -> float:
    return torch.cuda.max_memory_allocated() / 2**30


# ------------------------------------------------------------------------------------------------ generation


def bench_generation(mode: str, batches: tuple[int, ...], repeats: dict[int, int], dev: torch.device) -> list[dict]:
    """ms per motion (total and per stage) for each batch size in ``mode``."""
    from lsgan.models.gan import LatentGAN
    from lsgan.models.text import load_text_encoder
    from lsgan.models.vae import MotionVAE

    _fresh()
    torch.manual_seed(0)
    enc = load_text_encoder("minilm", device=dev)
    gan = LatentGAN(paper_gan_config()).to(dev).eval()
    vae = MotionVAE(paper_vae_config()).to(dev).eval()
    generator, decode = gan.generator, vae.decode
    if mode.startswith("compiled"):
        generator = torch.compile(gan.generator)
        decode = torch.compile(vae.decode)
        enc.model = torch.compile(enc.model, dynamic=True)  # prompt lengths vary: one graph for all of them
    amp = (torch.autocast("cuda", dtype=torch.bfloat16) if mode.endswith("bf16")
           else torch.autocast("cuda", enabled=False))
    noise_dim = gan.config.noise_dim
    rows = []
    for batch in batches:
        texts = prompts(batch)
        mask = torch.ones(batch, FRAMES, dtype=torch.bool, device=dev)

        def once() -> tuple[float, float, float]:
            t0 = time.perf_counter()
            cond = enc.encode(texts).to(dev)  # the encoder returns CPU float32, as generate uses it
            _sync()
            t1 = time.perf_counter()
            z = generator(torch.randn(batch, noise_dim, device=dev), cond)
            _sync()
            t2 = time.perf_counter()
            decode(z, mask)
            _sync()
            t3 = time.perf_counter()
            return t1 - t0, t2 - t1, t3 - t2

        with torch.inference_mode(), amp:
            _sync()
            t = time.perf_counter()
            once()  # the first call: compilation in the compiled modes
            first_s = time.perf_counter() - t
            for _ in range(5 if batch == 1 else 2):
                once()
            samples = [once() for _ in range(repeats[batch])]
        per = [[1000.0 * s / batch for s in sample] for sample in samples]
        total = [sum(p) for p in per]
        rows.append({
            "mode": mode, "batch": batch, "frames": FRAMES,
            "ms_per_motion": _spread(total),
            "text_ms": statistics.median(p[0] for p in per),
            "generator_ms": statistics.median(p[1] for p in per),
            "decoder_ms": statistics.median(p[2] for p in per),
            "first_call_s": first_s,
            "peak_gib": _peak_gib(),
        })
        r = rows[-1]
        print(f"  generation {mode:>13} b{batch:<5} {r['ms_per_motion']['median']:.4f} ms/motion "
              f"(text {r['text_ms']:.4f} + gen {r['generator_ms']:.4f} + dec {r['decoder_ms']:.4f}), "
              f"first call {first_s:.1f} s, peak {r['peak_gib']:.2f} GiB", file=sys.stderr, flush=True)
    del enc, gan, vae, generator, decode
    torch._dynamo.reset()
    return rows


# ------------------------------------------------------------------------------------------------ training


def bench_vae_step(mode: str, steps: int, repeats: int, dev: torch.device, frames: int = VAE_FRAMES) -> dict:
    """One VAE training step as lsgan.train.vae takes it, batch 128 x ``frames`` frames."""
    from contextlib import nullcontext

    from lsgan.models.vae import MotionVAE, vae_loss

    _fresh()
    torch.manual_seed(0)
    vae = MotionVAE(paper_vae_config()).to(dev).train()
    opt = torch.optim.AdamW(vae.parameters(), lr=1e-4, weight_decay=0.0)
    x = torch.randn(VAE_BATCH, frames, 263, device=dev)
    mask = torch.ones(VAE_BATCH, frames, dtype=torch.bool, device=dev)
    amp = torch.autocast("cuda", dtype=torch.bfloat16) if mode == "bf16" else nullcontext()

    def step() -> None:
        with amp:
            x_hat, mu, logvar = vae(x, mask)
        losses = vae_loss(x_hat.float(), x, mu.float(), logvar.float(), mask, 1e-4)
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        torch.nn.utils.clip_grad_norm_(vae.parameters(), 1.0)
        opt.step()

    times = _time_steps(step, warmup=5, steps=steps, repeats=repeats)
    out = {"what": "vae-step", "mode": mode, "batch": VAE_BATCH, "frames": frames, "ms_per_step": _spread(times),
           "peak_gib": _peak_gib(), "parameters": sum(p.numel() for p in vae.parameters())}
    print(f"  VAE step {mode}, {frames} frames: {out['ms_per_step']['median']:.2f} ms, peak {out['peak_gib']:.2f} GiB",
          file=sys.stderr, flush=True)
    del vae, opt, x
    return out


def _time_steps(step, *, warmup: int, steps: int, repeats: int) -> list[float]:
    """ms per call of ``step`` for each of ``repeats`` timed runs of ``steps`` calls, after ``warmup`` calls."""
    for _ in range(warmup):
        step()
    _sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        _sync()
        times.append(1000.0 * (time.perf_counter() - t0) / steps)
    return times


class _RandomPairs:
    """Stands in for lsgan.train.latents.LatentPairs: random standardised latents and MiniLM-like conditions."""

    def __init__(self, n: int, latent: int, cond: int, dev: torch.device) -> None:
        self.mu = torch.randn(n, latent, device=dev)
        self.sigma = 0.1 * torch.rand(n, latent, device=dev)
        self.cond = torch.nn.functional.normalize(torch.randn(n, cond, device=dev), dim=-1)

    def batch(self, b: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        i = torch.randint(len(self.mu), (b,), generator=g, device=self.mu.device)
        return self.mu[i] + self.sigma[i] * torch.randn(b, self.mu.shape[1], generator=g, device=self.mu.device), self.cond[i]


def bench_gan_step(steps: int, repeats: int, dev: torch.device, graph: bool) -> dict:
    """One deep-wgan-gp step as lsgan.train.gan takes it: 5 critic updates + 1 generator update, batch 64; eager,
    or replayed as one CUDA graph (``graph``, lsgan.train.graphs, the library's default on one GPU). The
    optimisers are capturable in both, as the library builds them on CUDA."""
    from lsgan.models.gan import LatentGAN
    from lsgan.train.gan import d_step, g_step
    from lsgan.train.graphs import GraphedStep, optimizer_options

    _fresh()
    torch.manual_seed(0)
    gan = LatentGAN(paper_gan_config()).to(dev).train()
    hp = dict(lr=1e-4, betas=(0.5, 0.9), weight_decay=0.0, **optimizer_options(dev))
    opt_d = torch.optim.AdamW(gan.discriminator.parameters(), **hp)
    opt_g = torch.optim.AdamW(gan.generator.parameters(), **hp)
    data = _RandomPairs(20_000, gan.config.latent_dim, gan.config.cond_dim, dev)
    g = torch.Generator(device=dev)

    def one(gen: torch.Generator) -> dict[str, torch.Tensor]:
        for _ in range(CRITIC_STEPS):
            d = d_step(gan, gan.discriminator, opt_d, data, GAN_BATCH, GP_WEIGHT, gen)
        return {**d, "g_loss": g_step(gan, gan.generator, opt_g, data, GAN_BATCH, gen)}

    run = GraphedStep(one) if graph else one
    seeds = iter(range(10**9))
    times = _time_steps(lambda: run(g.manual_seed(next(seeds))), warmup=10, steps=steps, repeats=repeats)
    out = {"what": "gan-step", "mode": "fp32, CUDA graph" if graph else "fp32", "arch": "deep-wgan-gp",
           "batch": GAN_BATCH, "critic_steps": CRITIC_STEPS, "ms_per_step": _spread(times), "peak_gib": _peak_gib(),
           "parameters": sum(p.numel() for p in gan.parameters())}
    print(f"  GAN step ({out['mode']}): {out['ms_per_step']['median']:.2f} ms, peak {out['peak_gib']:.3f} GiB",
          file=sys.stderr, flush=True)
    del gan, opt_d, opt_g, data, run
    return out


# ------------------------------------------------------------------------------------------------ report


def device_info() -> dict:
    p = torch.cuda.get_device_properties(0)
    info = {"device": torch.cuda.get_device_name(0), "capability": ".".join(map(str, torch.cuda.get_device_capability(0))),
            "memory_gib": p.total_memory / 2**30, "multiprocessors": p.multi_processor_count,
            "torch": torch.__version__, "cuda": torch.version.cuda, "python": platform.python_version(),
            "cpu_threads": torch.get_num_threads()}
    try:
        smi = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=20)
        info["nvidia_smi"] = smi.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        info["nvidia_smi"] = None
    return info


def _fmt(s: dict, digits: int = 3) -> str:
    return f"{s['median']:.{digits}f} ({s['min']:.{digits}f}-{s['max']:.{digits}f})"


def tables(report: dict) -> str:
    info = report["device_info"]
    lines = [f"Device: {info['device']} (torch {info['torch']}, CUDA {info['cuda']}); "
             f"median (min-max) over the repeats after warm-up.", "",
             "| generation, 120 frames | batch | ms per motion | text | generator | decoder | first call (s) | peak GiB |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in report["generation"]:
        d = 3 if r["batch"] == 1 else 4
        lines.append(f"| {r['mode']} | {r['batch']} | {_fmt(r['ms_per_motion'], d)} | {r['text_ms']:.{d}f} | "
                     f"{r['generator_ms']:.{d}f} | {r['decoder_ms']:.{d}f} | {r['first_call_s']:.1f} | {r['peak_gib']:.2f} |")
    for e in report.get("errors", []):
        lines.append(f"| {e['what']} | | failed: {e['error']} | | | | | |")
    lines += ["", "| training step | mode | batch | ms per step | steps/s | peak GiB |", "| --- | --- | ---: | ---: | ---: | ---: |"]
    for r in report["training"]:
        what = (f"VAE (paper-sized), {r['frames']} frames" if r["what"] == "vae-step"
                else f"deep-wgan-gp, {r['critic_steps']} critic + 1 generator update")
        lines.append(f"| {what} | {r['mode']} | {r['batch']} | {_fmt(r['ms_per_step'], 2)} | "
                     f"{1000.0 / r['ms_per_step']['median']:.1f} | {r['peak_gib']:.3f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("--only", choices=("generation", "training"), help="one half only")
    ap.add_argument("--modes", default=",".join(MODES), help=f"generation modes, comma-separated (default: all of {MODES})")
    ap.add_argument("--repeats", type=int, default=30, help="timed repeats at batch 1 (batch 1024: a third, at least 5)")
    ap.add_argument("--train-repeats", type=int, default=7, help="timed runs of training steps")
    ap.add_argument("--vae-frames", default=str(VAE_FRAMES),
                    help="window lengths of the timed VAE steps, comma-separated (120: recipes/bandai-gpu.yaml; empty: no VAE step)")
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("no CUDA device: benchmarks/gpu.py measures the GPU path only; nothing measured "
              "(the CPU figures come from benchmarks/models.py and lsgan bench)")
        return 0
    dev = torch.device("cuda", 0)
    torch.backends.cuda.matmul.allow_tf32 = False  # fp32 means fp32 (torch's default; said explicitly)
    torch.backends.cudnn.allow_tf32 = False
    report = {"device_info": device_info(), "generation": [], "training": [], "errors": []}
    print(f"[gpu] {report['device_info']}", file=sys.stderr, flush=True)
    if args.only != "training":
        repeats = {1: args.repeats, 1024: max(5, args.repeats // 3)}
        for mode in [m for m in args.modes.split(",") if m]:
            if mode not in MODES:
                ap.error(f"unknown mode {mode!r}; choose from {MODES}")
            try:
                report["generation"] += bench_generation(mode, (1, 1024), repeats, dev)
            except Exception as e:  # a compile failure is a finding, not the end of the run
                report["errors"].append({"what": f"generation {mode}", "error": f"{type(e).__name__}: {e}"[:500]})
                print(f"  generation {mode} failed: {type(e).__name__}: {e}", file=sys.stderr, flush=True)
                torch._dynamo.reset()
    if args.only != "generation":
        for frames in [int(f) for f in args.vae_frames.split(",") if f]:
            for mode in ("fp32", "bf16"):
                report["training"].append(bench_vae_step(mode, 10, args.train_repeats, dev, frames))
        for graph in (False, True):
            report["training"].append(bench_gan_step(20, args.train_repeats, dev, graph))
    text = tables(report)
    print(text)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
