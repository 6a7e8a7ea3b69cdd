"""Running the real ``lsgan`` command in a subprocess, and a tiny recipe for a whole pipeline in seconds."""
from __future__ import annotations

import atexit
import contextlib
import functools
import hashlib
import io
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
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


# Environment variables that the libraries tests/zygote.py has imported read when they load: a command that sets
# one differently from the first zygote gets a zygote of its own.
_READ_AT_IMPORT = ("OMP_", "MKL_", "KMP_", "OPENBLAS", "PYTHON", "LD_", "TORCH", "CUDA", "HDF5", "H5PY")


def forked_lsgan(*args, cwd: Path, env: dict | None = None, preexec_fn=None, timeout: float = 600,
                 preload: tuple[str, ...] = (), headroom: int | None = None) -> subprocess.CompletedProcess:
    """:func:`lsgan`, in a process forked from tests/zygote.py, which has torch, numpy, scipy and h5py imported
    already and nothing of lsgan: the same command in a process of its own, about two seconds sooner. For the
    bad-input tables, which run hundreds of refused commands. A command whose environment changes what those
    libraries read when they load (OMP_NUM_THREADS, ...) gets a zygote started under it; one with a ``preexec_fn``
    runs through :func:`lsgan`. Children of one zygote share
    its string-hash seed, so tests of determinism across processes use :func:`lsgan`. ``preload``: modules the
    child imports before the command; ``headroom``: then its address space is capped at what it maps plus this
    many bytes (a reader's allocation beyond it is a MemoryError, not the machine's memory)."""
    if preexec_fn is not None:
        if preload or headroom is not None:
            raise ValueError("preload and headroom are for forked commands, which take no preexec_fn")
        return lsgan(*args, cwd=cwd, env=env, preexec_fn=preexec_fn)
    full_env = {k: v for k, v in os.environ.items() if k not in ("LSGAN_DEBUG", "LSGAN_FAULT")}
    full_env.update({"OMP_NUM_THREADS": "1", **(env or {})})
    zygote = _zygote(tuple(sorted((k, v) for k, v in full_env.items() if k.startswith(_READ_AT_IMPORT))))
    argv = [str(a) for a in args]
    with tempfile.TemporaryDirectory(prefix="lsgan-run-") as d:
        streams = {name: Path(d) / name for name in ("stdout", "stderr")}
        for path in streams.values():
            path.touch()
        request = {"args": argv, "cwd": str(cwd), "env": full_env, "preload": list(preload), "headroom": headroom,
                   **{k: str(v) for k, v in streams.items()}}
        zygote.proc.stdin.write((json.dumps(request) + "\n").encode())
        zygote.proc.stdin.flush()
        pid = zygote.reply(60)["pid"]
        try:
            status = zygote.reply(timeout)["status"]
        except subprocess.TimeoutExpired:
            os.kill(pid, signal.SIGKILL)
            zygote.reply(60)
            raise subprocess.TimeoutExpired(["lsgan", *argv], timeout) from None
        return subprocess.CompletedProcess(["lsgan", *argv], status, streams["stdout"].read_text(),
                                           streams["stderr"].read_text())


class _Zygote:
    """tests/zygote.py running with ``loading`` as the variables its libraries read when they load, and its replies
    read line by line from the pipe (no read-ahead)."""

    def __init__(self, loading: dict[str, str]) -> None:
        env = {k: v for k, v in os.environ.items() if not k.startswith(_READ_AT_IMPORT)}
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name("zygote.py"))],
                                     env={**env, **loading}, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        atexit.register(self.proc.kill)

    def reply(self, timeout: float) -> dict:
        line, fd, end = b"", self.proc.stdout.fileno(), time.monotonic() + timeout
        while not line.endswith(b"\n"):
            if not select.select([fd], [], [], max(end - time.monotonic(), 0))[0]:
                raise subprocess.TimeoutExpired("zygote", timeout)
            got = os.read(fd, 1)
            if not got:
                raise RuntimeError(f"tests/zygote.py exited with {self.proc.wait()}")
            line += got
        return json.loads(line)


@functools.cache
def _zygote(loading: tuple[tuple[str, str], ...]) -> _Zygote:
    """The zygote whose libraries loaded under these variables (one per distinct set the tests use)."""
    return _Zygote(dict(loading))


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
