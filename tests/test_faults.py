"""Interrupted work resumes to the identical result.

Each row stops a real ``lsgan`` process at a named fault point (``lsgan.faults``: the process sends itself
SIGINT, as Ctrl-C does, or SIGKILL) and runs the same command again (with ``--resume`` where the command has
one). The result must equal an uninterrupted run's: byte for byte for a shard and a latent cache, tensor for
tensor for the weights of a training run (the cache records its inputs' paths as given, so the reference
uses the same absolute paths). No temporary file may be left behind, and Ctrl-C exits 130 with
one line that says how to go on.
"""
from __future__ import annotations

import signal
import subprocess
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
    else:
        assert out.returncode == 130, out.stderr
        assert "interrupted" in out.stderr and "Traceback" not in out.stderr


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
PREPROCESS_FAULTS = ["preprocess.chunk@1", "preprocess.chunk@2:SIGKILL", "preprocess.write@1",
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


@pytest.mark.parametrize("fault", ["train.step@3", "train.step@3:SIGKILL", "checkpoint.write@2",
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
