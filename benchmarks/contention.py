"""Slowdown of each stage beside CPU-bound competitors, under torch's default threads and under lsgan's policy.

One process tree, one run: every stage (a paper-sized VAE training step on 8 clips, a deep-wgan-gp GAN step at
batch 64 with its five critic steps, VAE encoding of 64 windows (encode-latents' batch), generation end to end at
batch 1 and 256 in torch and in onnxruntime on the int8 export of the same paper-sized models) is timed with the
machine otherwise idle, then beside 1 and then 3 competitor processes (pure-Python busy loops, children of this
one).
Each cell is the median of repeated runs (at least ``--min-reps`` and ``--min-seconds``) after a warm-up, which
also gives lsgan's policy time to see the competitors.

Policies: ``torch`` is what lsgan did before its thread policy (torch's default: one thread per core, for every
workload); ``lsgan`` is :class:`lsgan.threads.ThreadPolicy` set up as the command behind the stage sets it up (a
training run decides its count when it starts, beside the competitors already running, and keeps it; encoding
tunes it and follows the load; generation follows the load), updated before each run. For the onnxruntime stages
``torch`` is the runtime's sessions before they followed the load (every core, fixed when the model was loaded on
the idle machine, no spin-waiting) and ``lsgan`` its sessions now (every core, spin-waiting up to
``lsgan.deploy.runtime.SPIN_US`` only while other processes leave every core free). Printed per stage: idle ms,
slowdown beside 1 and 3 competitors per policy, and lsgan's idle time against torch's. Fair shares on 2 cores: x1.5 beside one competitor, x2.5 beside three.

    python benchmarks/contention.py                       # both policies, 0/1/3 competitors
    python benchmarks/contention.py --policies torch      # one policy only
    python benchmarks/contention.py --json contention.json --stages gan_step,generate_b1
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager, nullcontext
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from lsgan.eval.bench import PAPER_GANS, PAPER_VAE, bench_prompts, gan_sampler, save_paper_runs, torch_pipeline
from lsgan.models.gan import GANConfig, LatentGAN, critic_loss_wgan_gp, g_loss_wgan
from lsgan.models.text import load_text_encoder
from lsgan.models.vae import MotionVAE
from lsgan.threads import LARGE_BATCH, ThreadPolicy, run_threads, usable_cpus
from lsgan.train.vae import mld_vae_loss

FRAMES = 120


def vae_step(batch: int = 8) -> Callable[[], None]:
    """One training step of the paper-sized VAE (MLD's loss) on ``batch`` clips of FRAMES frames."""
    vae = MotionVAE(PAPER_VAE).train()
    opt = torch.optim.AdamW(vae.parameters(), lr=1e-4)
    x = torch.randn(batch, FRAMES, 263)
    mask = torch.ones(batch, FRAMES, dtype=torch.bool)
    mean, std = torch.zeros(263), torch.ones(263)

    def run() -> None:
        x_hat, mu, logvar = vae(x, mask)
        loss = mld_vae_loss(x_hat, x, mu, logvar, mask, 1e-4, mean, std)["total"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return run


def gan_step(batch: int = 64) -> Callable[[], None]:
    """One deep-wgan-gp generator step with its five critic steps (paper-sized, text condition)."""
    gan = LatentGAN(GANConfig(arch=PAPER_GANS[0], cond="text", cond_dim=384))
    opt_d = torch.optim.AdamW(gan.discriminator.parameters(), lr=1e-4, betas=(0.5, 0.9))
    opt_g = torch.optim.AdamW(gan.generator.parameters(), lr=1e-4, betas=(0.5, 0.9))
    real, cond = torch.randn(batch, 256), torch.nn.functional.normalize(torch.randn(batch, 384), dim=-1)

    def run() -> None:
        for _ in range(5):
            with torch.no_grad():
                fake = gan.generator(torch.randn(batch, 100), cond)
            loss = critic_loss_wgan_gp(gan.discriminator, real, fake, cond).loss
            opt_d.zero_grad(set_to_none=True)
            loss.backward()
            opt_d.step()
        gan.discriminator.requires_grad_(False)
        loss = g_loss_wgan(gan.discriminator(gan.generator(torch.randn(batch, 100), cond), cond))
        opt_g.zero_grad(set_to_none=True)
        loss.backward()
        gan.discriminator.requires_grad_(True)
        opt_g.step()

    return run


def encode(batch: int = 64) -> Callable[[], None]:
    """VAE encoding of ``batch`` windows of FRAMES frames, as ``lsgan encode-latents`` does."""
    vae = MotionVAE(PAPER_VAE).eval()
    x, mask = torch.randn(batch, FRAMES, 263), torch.ones(batch, FRAMES, dtype=torch.bool)

    def run() -> None:
        with torch.no_grad():
            vae.encode(x, mask)

    return run


def generate(batch: int) -> Callable[[], None]:
    """Text (MiniLM) -> deep-wgan-gp generator -> VAE decoder for ``batch`` prompts, as ``lsgan bench`` times it."""
    vae = MotionVAE(PAPER_VAE).eval()
    sampler = gan_sampler(PAPER_GANS[0], cond_dim=384, text_encoder="minilm")
    enc = load_text_encoder("minilm")

    pipeline = torch_pipeline(sampler, vae, enc.encode, torch.device("cpu"))

    def run() -> None:
        with torch.no_grad():
            pipeline.decode(pipeline.sample(pipeline.encode(bench_prompts(batch))), FRAMES)

    return run


@lru_cache(maxsize=1)
def _int8_export() -> tempfile.TemporaryDirectory:
    """The paper-sized random-weight runs exported with ``--int8`` (once per process; removed at exit)."""
    from lsgan.deploy.onnx_export import export_onnx

    tmp = tempfile.TemporaryDirectory(prefix="lsgan-contention-")
    gan_run, vae_run = save_paper_runs(Path(tmp.name))
    export_onnx(gan_run, Path(tmp.name) / "onnx", vae=vae_run, int8=True)
    return tmp


def generate_onnx(batch: int) -> dict[str, Callable[[], int]]:
    """The int8 export's text encoder -> generator -> decoder for ``batch`` prompts, per policy (see the module);
    each run returns the intra-op threads it used."""
    from lsgan.deploy.runtime import load
    from lsgan.generation import Request

    folder = Path(_int8_export().name) / "onnx"
    models = {"torch": load(folder, variant="int8", threads=usable_cpus(), spin_us=0),
              "lsgan": load(folder, variant="int8")}

    def runner(model) -> Callable[[], int]:
        def run() -> int:
            model.generate([Request(text=t, frames=FRAMES) for t in bench_prompts(batch)])
            return model.threads
        return run

    return {policy: runner(model) for policy, model in models.items()}


# stage: (how lsgan sets its threads there, the setup). "train": the count decided when the run starts and kept
# (lsgan.threads.run_threads); "tune": encode-latents' loop, tuned and re-decided as the load changes; "large" /
# "small": generation of a batch of >= LARGE_BATCH motions or fewer; "onnx": the
# ONNX runtime's own sessions, one setup per policy.
STAGES: dict[str, tuple[str, Callable[[], Callable[[], None]]]] = {
    "vae_step": ("train", vae_step),
    "gan_step": ("train", gan_step),
    "encode": ("tune", encode),
    "generate_b1": ("large" if 1 >= LARGE_BATCH else "small", lambda: generate(1)),
    "generate_b256": ("large" if 256 >= LARGE_BATCH else "small", lambda: generate(256)),
    "onnx_int8_b1": ("onnx", lambda: generate_onnx(1)),
    "onnx_int8_b256": ("onnx", lambda: generate_onnx(256)),
}


@contextmanager
def competitors(n: int):
    """``n`` busy-loop child processes for the duration of the block."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        time.sleep(0.5 if n else 0.0)
        yield
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


def lsgan_policy(mode: str) -> ThreadPolicy:
    """lsgan's policy as the command behind the stage sets it up."""
    if mode == "train":
        return ThreadPolicy(threads=run_threads())
    return ThreadPolicy(tune=mode == "tune", large=mode == "large")


def measure(run: Callable[[], int | None], policy: str, mode: str, *, min_reps: int, min_seconds: float,
            max_reps: int, max_seconds: float, warmup_seconds: float) -> tuple[list[float], set[int]]:
    """Times (ms) of ``run`` under ``policy`` after at least ``warmup_seconds`` of warm-up (at least 3 runs, and no
    more once ``max_seconds`` have passed), and the thread counts used (torch's, or what ``run`` returns)."""
    default = torch.get_num_threads()
    ctx = lsgan_policy(mode) if policy == "lsgan" and mode != "onnx" else nullcontext()
    times, threads = [], set()
    with ctx as pol:
        t_end = time.perf_counter() + warmup_seconds
        while True:
            if pol:
                pol.update()
            run()
            if time.perf_counter() >= t_end and not (pol and pol.tuning):
                break
        start = time.perf_counter()
        while len(times) < max_reps and (len(times) < min_reps or time.perf_counter() - start < min_seconds):
            if len(times) >= 3 and time.perf_counter() - start > max_seconds:
                break
            if pol:
                pol.update()
            t0 = time.perf_counter()
            used = run()
            times.append(1000.0 * (time.perf_counter() - t0))
            threads.add(torch.get_num_threads() if used is None else used)
    torch.set_num_threads(default)
    return times, threads


def run_contention(stages: list[str], policies: list[str], counts: tuple[int, ...], rounds: int = 1,
                   **timing) -> dict:
    """{stage: {policy: {competitors: cell}}} for every stage, policy and competitor count. With ``rounds`` 2 the
    policies are measured in the order A B, then B A (each round a full cell), and the runs pooled: neither
    gains from going first."""
    runs = {name: STAGES[name][1]() for name in stages}
    out: dict = {name: {p: {} for p in policies} for name in stages}
    for n in counts:
        with competitors(n):
            load = os.getloadavg()[0]
            for name in stages:
                pooled: dict[str, tuple[list[float], set[int]]] = {p: ([], set()) for p in policies}
                for r in range(rounds):
                    for p in (policies if r % 2 == 0 else policies[::-1]):
                        run = runs[name][p] if isinstance(runs[name], dict) else runs[name]
                        times, threads = measure(run, p, STAGES[name][0], **timing)
                        pooled[p][0].extend(times)
                        pooled[p][1].update(threads)
                for p in policies:
                    times, threads = pooled[p]
                    q25, med, q75 = (float(q) for q in np.percentile(times, [25, 50, 75]))
                    out[name][p][n] = {"median_ms": med, "q25_ms": q25, "q75_ms": q75, "runs": len(times),
                                       "threads": sorted(threads), "load_avg_1min": load}
                    print(f"  {n} competitor(s) {name:14s} {p:6s} {med:9.1f} ms (q25 {q25:.1f}, q75 {q75:.1f}, "
                          f"{len(times)} runs, threads {sorted(threads)})", file=sys.stderr, flush=True)
    return out


def table(results: dict, policies: list[str], counts: tuple[int, ...]) -> str:
    """Markdown: idle ms and slowdown ratios per stage and policy."""
    head = ["stage"] + [f"{p} idle ms" for p in policies]
    head += [f"{p} x{n}" for p in policies for n in counts if n]
    if "lsgan" in policies and "torch" in policies:
        head.append("lsgan idle / torch idle")
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for name, by_policy in results.items():
        idle = {p: by_policy[p][0]["median_ms"] for p in policies}
        row = [name] + [f"{idle[p]:.1f}" for p in policies]
        row += [f"{by_policy[p][n]['median_ms'] / idle[p]:.2f}" for p in policies for n in counts if n]
        if "lsgan" in policies and "torch" in policies:
            row.append(f"{idle['lsgan'] / idle['torch']:.2f}")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stages", default=",".join(STAGES), help="comma-separated: " + ", ".join(STAGES))
    ap.add_argument("--policies", default="torch,lsgan", help="comma-separated: torch, lsgan")
    ap.add_argument("--min-reps", type=int, default=7)
    ap.add_argument("--max-reps", type=int, default=40)
    ap.add_argument("--min-seconds", type=float, default=3.0)
    ap.add_argument("--max-seconds", type=float, default=60.0, help="stop a cell after this (and 3 runs)")
    ap.add_argument("--warmup-seconds", type=float, default=1.0)
    ap.add_argument("--competitors", default="0,1,3", help="comma-separated counts; 0 (idle) must be among them")
    ap.add_argument("--rounds", type=int, default=1, help="2: measure the policies A B then B A, pooled")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    if any(os.environ.get(v) for v in ("LSGAN_THREADS", "OMP_NUM_THREADS")):
        sys.exit("error: unset LSGAN_THREADS and OMP_NUM_THREADS: they fix the thread count this compares")
    stages, policies = args.stages.split(","), args.policies.split(",")
    unknown = [s for s in stages if s not in STAGES] + [p for p in policies if p not in ("torch", "lsgan")]
    if unknown:
        sys.exit(f"error: unknown stage or policy: {', '.join(unknown)}")
    print(f"load average before: {os.getloadavg()}, {os.cpu_count()} cpus, torch {torch.__version__}, "
          f"default threads {torch.get_num_threads()}", file=sys.stderr)
    counts = tuple(int(c) for c in args.competitors.split(","))
    if 0 not in counts:
        sys.exit("error: --competitors must include 0: the ratios are against the idle machine")
    results = run_contention(stages, policies, counts, args.rounds, min_reps=args.min_reps, min_seconds=args.min_seconds,
                             max_reps=args.max_reps, max_seconds=args.max_seconds,
                             warmup_seconds=args.warmup_seconds)
    print(table(results, policies, counts))
    if args.json:
        report = {"machine": f"{platform.machine()} {os.cpu_count()} cpus, torch {torch.__version__}",
                  "competitors": list(counts), "rounds": args.rounds, "results": results}
        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
