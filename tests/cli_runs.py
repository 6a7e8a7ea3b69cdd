"""Running the real ``lsgan`` command in a subprocess, and a tiny recipe for a whole pipeline in seconds."""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

TINY_RECIPE = """
vae:
  model: {latent_dim: 16, d_model: 16, num_layers: 1, num_heads: 2, ff_size: 32, dropout: 0.0, max_len: 200}
  train: {batch_size: 8, max_steps: 6, val_every: 2, ckpt_every: 2, log_every: 2, lr: 1.0e-3, val_batches: 1}
gan:
  model: {arch: deep-wgan-gp, latent_dim: 16, hidden_dim: 32, noise_dim: 8}
  train: {batch_size: 8, max_steps: 6, eval_every: 2, ckpt_every: 2, log_every: 2, fid_samples: 32, critic_steps: 1}
"""


def lsgan(*args, cwd: Path, env: dict | None = None, fault: str | None = None) -> subprocess.CompletedProcess:
    """``lsgan ARGS`` on one thread, without the caller's debug or fault settings unless given here."""
    full_env = {k: v for k, v in os.environ.items() if k not in ("LSGAN_DEBUG", "LSGAN_FAULT")}
    full_env.update({"OMP_NUM_THREADS": "1", **(env or {})})
    if fault:
        full_env["LSGAN_FAULT"] = fault
    return subprocess.run([sys.executable, "-m", "lsgan.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=full_env, timeout=600)


TINY_PIPELINE = [
    ("preprocess", "--source", "synthetic", "--num-clips", 40, "-o", "synth.h5"),
    ("train-vae", "--data", "synth.h5", "--recipe", "tiny.yaml", "--out", "vae"),
    ("encode-latents", "--data", "synth.h5", "--vae", "vae", "-o", "cache.h5"),
    ("train-gan", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--out", "gan"),
]


def tiny_pipeline(d: Path, *more: tuple) -> Path:
    """TINY_RECIPE's pipeline in ``d`` (tiny.yaml, synth.h5, vae/, cache.h5, gan/), then the steps ``more``."""
    (d / "tiny.yaml").write_text(TINY_RECIPE)
    for step in [*TINY_PIPELINE, *more]:
        out = lsgan(*step, cwd=d)
        assert out.returncode == 0, f"{step[0]} failed:\n{out.stderr[-3000:]}"
    return d


def snapshot(*folders: Path) -> dict[Path, str]:
    """SHA-256 of every file under the folders."""
    return {p: hashlib.sha256(p.read_bytes()).hexdigest()
            for f in folders for p in sorted(f.rglob("*")) if p.is_file()}
