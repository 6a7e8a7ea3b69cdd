"""Interrupted work resumes to the identical result.

Each row stops a real ``lsgan`` process at a named fault point (``lsgan.faults``: the process sends itself
SIGINT, as Ctrl-C does, SIGTERM, as a job scheduler's stop does, or SIGKILL) and runs the same command again (with ``--resume`` where the command has
one). The result must equal an uninterrupted run's: byte for byte for a shard and a latent cache, tensor for
tensor for the weights of a training run (the cache records its inputs' paths as given, so the reference
uses the same absolute paths). No temporary file may be left behind, and Ctrl-C exits 130 (SIGTERM 143) with
one line that says how to go on, with no blank line before it.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from cli_runs import TINY_RECIPE, lsgan

from lsgan.models.checkpoint import weights_hash

pytestmark = pytest.mark.slow


def leftovers(folder: Path) -> list[str]:
    """Hidden temporaries and staging folders anywhere under ``folder`` (the registry is expected)."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")
                  if (p.name.startswith(".") and p.name != ".lsgan-outputs.json") or p.name.endswith(".parts"))


def check_stopped(out: subprocess.CompletedProcess, fault: str) -> None:
    if fault.endswith(":SIGKILL"):
        assert out.returncode == -signal.SIGKILL, out.stderr
        return
    word, code = ("terminated", 143) if fault.endswith(":SIGTERM") else ("interrupted", 130)
    assert out.returncode == code, out.stderr
    assert "Traceback" not in out.stderr
    lines = out.stderr.replace("\r", "\n").split("\n")
    said = [i for i, line in enumerate(lines) if line.startswith(word)]
    assert len(said) == 1 and (said[0] == 0 or lines[said[0] - 1].strip()), out.stderr  # one, no blank line before


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """Uninterrupted reference runs: a shard, a VAE, a latent cache and a GAN."""
    d = tmp_path_factory.mktemp("faults")
    (d / "tiny.yaml").write_text(TINY_RECIPE)
    for step in [PREPROCESS + ["-o", "ref.h5"], ["train-vae", "--data", "ref.h5", "--recipe", "tiny.yaml", "--out", "vae"],
                 ["encode-latents", "--data", d / "ref.h5", "--vae", d / "vae", "-o", "cache.h5", "--batch-size", 8],
                 ["train-gan", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--out", "gan"]]:
        out = lsgan(*step, cwd=d)
        assert out.returncode == 0, out.stderr
    return d


PREPROCESS = ["preprocess", "--source", "synthetic", "--num-clips", 60, "--mirror"]
PREPROCESS_FAULTS = ["preprocess.chunk@1", "preprocess.chunk@1:SIGTERM", "preprocess.chunk@2:SIGKILL", "preprocess.write@1",
                     "preprocess.write@2:SIGKILL", "preprocess.report", "preprocess.report:SIGKILL"]


@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.parametrize("fault", PREPROCESS_FAULTS)
def test_preprocess_resumes_to_the_same_shard(base: Path, tmp_path: Path, fault: str, workers: int) -> None:
    if workers == 2 and not fault.startswith("preprocess.chunk"):
        pytest.skip("the final write happens in the main process alone: one worker count covers it")
    args = PREPROCESS + ["-o", tmp_path / "s.h5", "--workers", workers]
    check_stopped(lsgan(*args, cwd=tmp_path, fault=fault), fault)
    assert not (tmp_path / "s.h5").exists() or fault.startswith("preprocess.report")
    out = lsgan(*args, "--resume", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "s.h5").read_bytes() == (base / "ref.h5").read_bytes()
    assert leftovers(tmp_path) == []


def test_preprocess_resumes_after_a_worker_dies(base: Path, tmp_path: Path) -> None:
    """A worker killed mid-chunk (the OOM killer's way) stops the run with one line naming it (the pool used to
    hang, and its message named nothing); --resume then gives the uninterrupted shard. The installed script, as a
    user runs it: spawned workers import its main module (a worker that took SIGTERM as the program does hung)."""
    args = PREPROCESS + ["-o", tmp_path / "s.h5", "--workers", 2]
    env = {k: v for k, v in os.environ.items() if k not in ("LSGAN_DEBUG", "LSGAN_FAULT")}
    out = subprocess.run([str(Path(sys.executable).with_name("lsgan")), *map(str, args)], capture_output=True,
                         text=True, cwd=tmp_path, timeout=300,
                         env={**env, "OMP_NUM_THREADS": "1", "LSGAN_FAULT": "preprocess.worker@2:SIGKILL"})
    assert out.returncode == 1, out.stderr
    assert out.stderr.strip().splitlines()[-1] == (f"error: {tmp_path / 's.h5.parts'}: a worker process died (killed, "
                                                    "or out of memory?); the finished chunks are kept there: run the "
                                                    "same command with --resume")
    out = lsgan(*args, "--resume", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "s.h5").read_bytes() == (base / "ref.h5").read_bytes()
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("fault", ["train.step@3", "train.step@3:SIGTERM", "train.step@3:SIGKILL", "checkpoint.write@2",
                                   "checkpoint.write@2:SIGKILL"])
def test_vae_training_resumes_to_the_same_weights(base: Path, tmp_path: Path, fault: str) -> None:
    args = ["train-vae", "--data", base / "ref.h5", "--recipe", base / "tiny.yaml", "--out", tmp_path / "vae"]
    check_stopped(lsgan(*args, cwd=tmp_path, fault=fault), fault)
    out = lsgan(*args, "--resume", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    for sub in ("last", "best"):
        assert weights_hash(tmp_path / "vae" / sub) == weights_hash(base / "vae" / sub), sub
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("fault", ["train.step@4", "checkpoint.write@3:SIGKILL"])
def test_gan_training_resumes_to_the_same_weights(base: Path, tmp_path: Path, fault: str) -> None:
    args = ["train-gan", "--cache", base / "cache.h5", "--recipe", base / "tiny.yaml", "--out", tmp_path / "gan"]
    check_stopped(lsgan(*args, cwd=tmp_path, fault=fault), fault)
    out = lsgan(*args, "--resume", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert weights_hash(tmp_path / "gan" / "last") == weights_hash(base / "gan" / "last")
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize("fault", ["encode.batch", "cache.write", "cache.write:SIGKILL"])
def test_encode_rerun_gives_the_same_cache(base: Path, tmp_path: Path, fault: str) -> None:
    args = ["encode-latents", "--data", base / "ref.h5", "--vae", base / "vae", "-o", tmp_path / "cache.h5",
            "--batch-size", 8]
    check_stopped(lsgan(*args, cwd=tmp_path, fault=fault), fault)
    assert not (tmp_path / "cache.h5").exists()
    out = lsgan(*args, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "cache.h5").read_bytes() == (base / "cache.h5").read_bytes()
    assert leftovers(tmp_path) == []
