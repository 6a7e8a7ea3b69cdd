"""Benchmark of the paper's cost claim on this machine, with paper-sized models (random weights).

1. GAN training steps/s reading latents from the cache (lsgan's design) versus the naive design that runs
   the VAE encoder on every real batch, at the same batch size in the same run; reported as a ratio.
2. Generation end to end (MiniLM text -> deep-wgan-gp generator -> paper-sized VAE decoder, 120 frames) at batch
   1 and 256, per runtime, all in the same run: torch fp32 eager (``lsgan generate``'s path, the baseline), torch
   with bf16 autocast, and onnxruntime on the fp32 and int8 graphs ``lsgan export-model --onnx --int8`` writes
   (the random-weight models are saved as runs and exported by that same code). Each figure is the median of
   repeated runs with its quartiles, timed by ``lsgan.eval.bench.time_per_motion``, the timer ``lsgan bench``
   uses. Beside each: the physical floor, the decoder's FLOPs over this CPU's peak at the precision (the peak
   measured here with a 2048-cube matrix product in that precision on all cores; for int8, the feed-forward
   and self-attention products at the int8 rate and the rest at the fp32 rate, as ``--int8`` quantises them).
   Before and after each row, the machine's int8 rate at that moment (:func:`lsgan.eval.bench.machine_rate`): the host can slow
   this machine down unseen, and a row taken then says so (``machine_speed`` in the JSON, 1.0 = the run's best).
3. With ``--quality-run GAN_RUN`` (a trained text GAN; its VAE from its cache or ``--quality-vae``): the joint
   deviation of each fast runtime from torch fp32 on the same noise, mean and max mm over 100 motions; and how far
   the joints move when the prompt embeddings turn by 1e-4 to 1e-2 (the precision any faster text encoder must
   keep: ``benchmarks/deploy.py`` prints how far the reduced-precision MiniLMs turn them).

FLOPs per clip and the diffusion comparison are measured by ``lsgan bench``.

    python benchmarks/models.py                  # CPU (and CUDA when torch sees a GPU, training only)
    python benchmarks/models.py --json out.json --steps 20 --frames 120
    python benchmarks/models.py --skip-training --quality-run runs/bandai-gan
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from lsgan.eval.bench import (PAPER_VAE, Pipeline, decoder_flops, gan_sampler, machine_rate, paper_gan,
                              peak_gflops, save_paper_runs, time_per_motion, torch_pipeline)
from lsgan.models.gan import LatentGAN, critic_loss_wgan_gp, g_loss_wgan
from lsgan.models.vae import MotionVAE
from lsgan.threads import threads_said

PAPER_GAN = paper_gan("deep-wgan-gp", cond_dim=384)


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


# ---------------------------------------------------------------------------------------------------- generation

RUNTIMES = ("torch fp32 eager", "torch bf16 autocast", "onnxruntime fp32", "onnxruntime int8")
PRECISION = dict(zip(RUNTIMES, ("fp32", "bf16", "fp32", "int8")))  # int8: the products --int8 quantises


def int8_gflop(frames: int) -> float:
    """GFLOPs per motion of the products --int8 quantises (lsgan.deploy.int8): in every layer the feed-forward
    (d -> ff -> d) and the self-attention projections (d -> 3d, d -> d); the rest of the decoder stays fp32."""
    d = PAPER_VAE.d_model
    return 2 * frames * PAPER_VAE.num_layers * (2 * d * PAPER_VAE.ff_size + 4 * d * d) / 1e9


def floor_ms(precision: str, decoder_gflop: float, frames: int, peaks: dict[str, float]) -> float:
    """The decoder's time at the CPU's peak: all of it at ``precision``, or for int8 the quantised products at
    the int8 rate and the rest at the fp32 rate."""
    if precision != "int8":
        return 1000.0 * decoder_gflop / peaks[precision]
    i8 = int8_gflop(frames)
    return 1000.0 * (i8 / peaks["int8"] + (decoder_gflop - i8) / peaks["fp32"])


def _autocast_bf16(fn: Callable) -> Callable:
    """``fn`` under torch's CPU autocast to bf16 (matrix products in bf16, sensitive operations in fp32)."""

    def run(*args, **kwargs):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            return fn(*args, **kwargs)

    return run


def onnx_pipeline(model) -> Pipeline:
    """An exported folder (lsgan.deploy.runtime) as the timer's three stages; the noise is drawn in ``sample``."""
    rng = np.random.default_rng(0)
    noise_dim = int(model.manifest["noise_dim"])

    def sample(cond: np.ndarray) -> np.ndarray:
        return model.latents(rng.standard_normal((len(cond), noise_dim), dtype=np.float32), cond)

    return Pipeline(model.embed, sample, lambda z, frames: model.decode(z, [frames] * len(z)))


def generation_pipelines(gan_run: Path, vae_run: Path, onnx_dir: Path) -> dict[str, Pipeline]:
    """Each runtime of RUNTIMES on the same models."""
    from lsgan.deploy.runtime import load
    from lsgan.models.gan import load_gan
    from lsgan.models.text import load_text_encoder
    from lsgan.models.vae import load_vae

    gan, _ = load_gan(gan_run)
    vae, _ = load_vae(vae_run)
    enc = load_text_encoder("minilm")
    fp32 = torch_pipeline(gan_sampler(gan.config.arch, gan, cond_dim=gan.config.cond_dim, text_encoder="minilm"),
                          vae, enc.encode, torch.device("cpu"))
    bf16 = Pipeline(*(_autocast_bf16(f) for f in (fp32.encode, fp32.sample, fp32.decode)))
    return dict(zip(RUNTIMES, (fp32, bf16, onnx_pipeline(load(onnx_dir, variant="fp32")),
                               onnx_pipeline(load(onnx_dir, variant="int8")))))


def bench_generation(frames: int, repeats: dict[int, int], workdir: Path) -> dict:
    """ms per motion (median, quartiles) and motions/s per runtime and batch, with the decoder's floor."""
    from lsgan.deploy.onnx_export import export_onnx

    gan_run, vae_run = save_paper_runs(workdir)
    export_onnx(gan_run, workdir / "onnx", vae=vae_run, int8=True)
    pipelines = generation_pipelines(gan_run, vae_run, workdir / "onnx")
    decoder_gflop = decoder_flops(MotionVAE(PAPER_VAE).eval(), frames) / 1e9
    peaks = {p: peak_gflops(p) for p in ("fp32", "bf16", "int8")}
    rows = []
    for name, pipeline in pipelines.items():
        for batch, reps in repeats.items():
            before = machine_rate()
            t = time_per_motion(pipeline, batch=batch, frames=frames, repeats=reps)
            rate = [before, machine_rate()]
            floor = floor_ms(PRECISION[name], decoder_gflop, frames, peaks)
            rows.append({"runtime": name, "batch": batch, **t, "motions_per_s": 1000.0 / t["total"],
                         "decoder_floor_ms": floor, "repeats": reps, "load_avg_1min": os.getloadavg()[0],
                         "machine_int8_gops": rate})
            print(f"[generation] {name:22s} b{batch:<4d} {t['total']:8.2f} ms/motion (q25 {t['total_q25']:.2f}, "
                  f"q75 {t['total_q75']:.2f}; text {t['text']:.2f} + gen {t['generator']:.3f} + dec "
                  f"{t['decoder']:.2f}) = {1000.0 / t['total']:7.1f} motions/s; decoder floor {floor:.2f} ms; "
                  f"machine {rate[0]:.0f} / {rate[1]:.0f} GOP/s", file=sys.stderr, flush=True)
    best = max([peaks["int8"]] + [x for r in rows for x in r["machine_int8_gops"]])
    for r in rows:
        r["machine_speed"] = min(r["machine_int8_gops"]) / best
    return {"frames": frames, "decoder_gflop_per_motion": decoder_gflop, "peak_gflops": peaks, "rows": rows}



def joint_deviation(gan_run: Path, vae_run: Path | None, workdir: Path, count: int = 100) -> dict:
    """Mean and max joint distance (mm) of each fast runtime from torch fp32 eager, same prompts and noise."""
    from lsgan.deploy.int8 import reference_requests
    from lsgan.deploy.onnx_export import export_onnx
    from lsgan.deploy.runtime import load
    from lsgan.generate import generate

    folder = workdir / "quality-onnx"
    manifest = export_onnx(gan_run, folder, vae=vae_run, int8=True).manifest
    requests = reference_requests(manifest, count)
    # the noise lsgan.generate draws for seed 0, given to onnxruntime too
    noise = torch.randn(count, int(manifest["noise_dim"]), generator=torch.Generator().manual_seed(0)).numpy()
    vae = vae_run or manifest["sources"]["vae"]["path"]
    joints = {name: [m.joints for m in run(gan_run, vae, requests, seed=0, device="cpu").motions]
              for name, run in (("torch fp32 eager", generate), ("torch bf16 autocast", _autocast_bf16(generate)))}
    onnx = {variant: load(folder, variant=variant) for variant in ("fp32", "int8")}
    for variant, model in onnx.items():
        joints[f"onnxruntime {variant}"] = [m.joints for m in model.generate(requests, noise=noise).motions]
    base = joints.pop("torch fp32 eager")
    out = {}
    for name, js in joints.items():
        d = _distances_mm(base, js)
        out[name] = {"mean_mm": float(d.mean()), "max_mm": float(d.max()), "motions": count}
        print(f"[quality] {name:22s} vs torch fp32: mean {d.mean():.3f} mm, max {d.max():.3f} mm over {count} "
              "motions", file=sys.stderr)
    out["embedding_turns"] = embedding_sensitivity(onnx["fp32"], requests, noise)
    return out


def _distances_mm(a: list[np.ndarray], b: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([np.linalg.norm(x - y, axis=-1).ravel() for x, y in zip(a, b)]) * 1000.0


TURNS = (1e-4, 3e-4, 1e-3, 3e-3, 1e-2)


def embedding_sensitivity(model, requests: list, noise: np.ndarray) -> list[dict]:
    """How far the joints move when the prompt embeddings turn by a distance ``d`` (a random direction per prompt,
    re-normalised to the unit sphere, as MiniLM's embeddings are), same noise: the precision a faster text encoder
    must keep. fp32 ONNX graphs of the trained GAN."""
    from lsgan.data.features import recover_from_ric

    frames = [r.frames for r in requests]

    def joints(cond: np.ndarray) -> list[np.ndarray]:
        return [recover_from_ric(f) for f in model.decode(model.latents(noise, cond), frames)]

    cond = model.conditions(requests)
    base, rng, rows = joints(cond), np.random.default_rng(0), []
    for turn in TURNS:
        step = rng.standard_normal(cond.shape).astype(np.float32)
        moved = cond + turn * step / np.linalg.norm(step, axis=1, keepdims=True)
        moved /= np.linalg.norm(moved, axis=1, keepdims=True)
        d = _distances_mm(base, joints(moved))
        rows.append({"turn": turn, "mean_mm": float(d.mean()), "max_mm": float(d.max()), "motions": len(requests)})
        print(f"[quality] embeddings turned by {turn:.0e}: joints move by {d.mean():.2f} mm mean, {d.max():.1f} max",
              file=sys.stderr)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=10, help="GAN steps per design")
    ap.add_argument("--batch", type=int, default=64, help="GAN training batch size (paper: 64)")
    ap.add_argument("--frames", type=int, default=120, help="motion length for encoding and decoding (20 fps)")
    ap.add_argument("--repeats-b1", type=int, default=50, help="timed runs per runtime at batch 1")
    ap.add_argument("--repeats-b256", type=int, default=5, help="timed runs per runtime at batch 256")
    ap.add_argument("--skip-training", action="store_true", help="only the generation figures")
    ap.add_argument("--skip-generation", action="store_true", help="only the training figures")
    ap.add_argument("--quality-run", help="a trained text GAN run: joint deviation of each runtime from torch fp32")
    ap.add_argument("--quality-vae", help="its VAE (default: the one its latent cache records)")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    report = {"machine": f"{platform.machine()} python {platform.python_version()} torch {torch.__version__}, "
                         f"{os.cpu_count()} cpus", "threads": threads_said(), "load_avg_at_start": os.getloadavg(),
              "results": []}
    with tempfile.TemporaryDirectory(prefix="lsgan-bench-") as tmp:
        if not args.skip_generation:
            report["generation"] = bench_generation(args.frames, {1: args.repeats_b1, 256: args.repeats_b256},
                                                    Path(tmp))
        if args.quality_run:
            report["quality"] = joint_deviation(Path(args.quality_run),
                                                Path(args.quality_vae) if args.quality_vae else None, Path(tmp))
    for dev in ([] if args.skip_training else devices):
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
