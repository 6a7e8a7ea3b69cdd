"""Running the real ``lsgan`` command in a subprocess, and a tiny recipe for a whole pipeline in seconds."""
from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

TINY_RECIPE = """
vae:
  model: {latent_dim: 16, d_model: 16, num_layers: 1, num_heads: 2, ff_size: 32, dropout: 0.0, max_len: 200,
          smooth_output: 1, rigid_output: true}
  train: {batch_size: 8, max_steps: 6, val_every: 2, ckpt_every: 2, log_every: 2, lr: 1.0e-3, val_batches: 1}
gan:
  model: {arch: deep-wgan-gp, latent_dim: 16, hidden_dim: 32, noise_dim: 8}
  train: {batch_size: 8, max_steps: 6, eval_every: 2, ckpt_every: 2, log_every: 2, fid_samples: 32, critic_steps: 1}
"""


def lsgan(*args, cwd: Path, env: dict | None = None, fault: str | None = None,
          preexec_fn=None) -> subprocess.CompletedProcess:
    """``lsgan ARGS`` on one thread, without the caller's debug or fault settings unless given here; ``preexec_fn``
    runs in the child before lsgan starts (e.g. to set a resource limit)."""
    full_env = {k: v for k, v in os.environ.items() if k not in ("LSGAN_DEBUG", "LSGAN_FAULT")}
    full_env.update({"OMP_NUM_THREADS": "1", **(env or {})})
    if fault:
        full_env["LSGAN_FAULT"] = fault
        preexec_fn = functools.partial(_at_default_sigint, preexec_fn)
    return subprocess.run([sys.executable, "-m", "lsgan.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=full_env, timeout=600, preexec_fn=preexec_fn)


def _at_default_sigint(then: Callable[[], None] | None) -> None:
    """In the child: SIGINT at its default, as in a terminal (pytest run in the background ignores it, and so would
    every lsgan it starts, so that a fault's Ctrl-C would go unseen); then ``then``."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    if then is not None:
        then()


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


def linked_pipeline(models: Path, d: Path, *more: tuple) -> Path:
    """conftest's session pipeline (``serve_models``: tiny.yaml, synth.h5, vae/, cache.h5, gan/) hard-linked into
    ``d`` (no training again; lsgan replaces files, never edits them), then the steps ``more`` run in ``d``."""
    for name in ("tiny.yaml", "synth.h5", "cache.h5", "vae", "gan"):
        src = models / name
        if src.is_dir():
            shutil.copytree(src, d / name, copy_function=os.link)
        else:
            os.link(src, d / name)
    for step in more:
        out = lsgan(*step, cwd=d)
        assert out.returncode == 0, f"{step[0]} failed:\n{out.stderr[-3000:]}"
    return d


def snapshot(*folders: Path) -> dict[Path, str]:
    """SHA-256 of every file under the folders."""
    return {p: hashlib.sha256(p.read_bytes()).hexdigest()
            for f in folders for p in sorted(f.rglob("*")) if p.is_file()}


def run_here(cwd: Path, *args) -> tuple[int, str]:
    """``lsgan ARGS`` in this process (click's entry point, as the script calls it), in ``cwd``: exit code and
    stderr. Much faster than :func:`lsgan` for many short commands."""
    from lsgan.cli import main

    err, here = io.StringIO(), os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                main.main(args=[str(a) for a in args], prog_name="lsgan")
                code = 0
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        os.chdir(here)
    return code, err.getvalue()
