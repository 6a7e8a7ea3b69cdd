"""train-vae -> encode-latents -> train-gan -> generate through the real CLI, on tiny configs."""
from __future__ import annotations

import json
import subprocess
import sys

import h5py
import numpy as np
import pytest

TINY = """
vae:
  model: {latent_dim: 32, d_model: 32, num_layers: 1, num_heads: 2, ff_size: 64, dropout: 0.0, max_len: 200}
  train: {batch_size: 16, max_steps: 12, val_every: 6, ckpt_every: 6, log_every: 3, lr: 1.0e-3, val_batches: 2}
gan:
  model: {arch: deep-wgan-gp, latent_dim: 32, hidden_dim: 64, noise_dim: 16}
  train: {batch_size: 16, max_steps: 12, eval_every: 6, ckpt_every: 6, log_every: 3, fid_samples: 64, critic_steps: 2}
"""


def lsgan(*args, cwd):
    out = subprocess.run([sys.executable, "-m", "lsgan.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd)
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("pipeline")
    (d / "tiny.yaml").write_text(TINY)
    steps = [
        ("preprocess", "--source", "synthetic", "--num-clips", 60, "-o", "synth.h5"),
        ("train-vae", "--data", "synth.h5", "--recipe", "tiny.yaml", "--out", "vae"),
        ("encode-latents", "--data", "synth.h5", "--vae", "vae", "-o", "cache.h5"),
        ("train-gan", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--out", "gan"),
    ]
    for step in steps:
        out = lsgan(*step, cwd=d)
        assert out.returncode == 0, f"{step[0]} failed:\n{out.stderr[-3000:]}"
    return d


def test_cache_holds_latents_and_caption_embeddings(run):
    with h5py.File(run / "cache.h5", "r") as f:
        n = len(f["clips/name"])
        assert f["latents/mu"].shape == (n, 32) and f["latents/logvar"].shape == (n, 32)
        m = len(f["captions/text"])
        assert m >= n and f["captions/embedding"].shape == (m, 384)
        assert f.attrs["text_encoder"].startswith("minilm:") and len(f.attrs["vae_hash"]) == 64
        assert set(f["clips/split"].asstr()[()]) <= {"train", "val", "test"}


def test_generate_writes_motions_and_is_deterministic(run):
    args = ["generate", "--gan", "gan", "--vae", "vae", "--text", "a person walks forward", "--text", "someone waves",
            "--frames", 48, "--num", 2, "--seed", 3]
    first = lsgan(*args, "-o", "out1", cwd=run)
    assert first.returncode == 0, first.stderr
    assert "ms per motion" in first.stderr
    again = lsgan(*args, "-o", "out2", cwd=run)
    other = lsgan(*args[:-1], 4, "-o", "out3", cwd=run)
    assert again.returncode == 0 and other.returncode == 0
    manifest = json.loads((run / "out1" / "manifest.json").read_text())
    assert len(manifest["motions"]) == 4 and manifest["seed"] == 3
    assert manifest["vae"]["sha256"] and manifest["gan"]["sha256"]
    for m in manifest["motions"]:
        feats = np.load(run / "out1" / m["features"])
        joints = np.load(run / "out1" / m["joints"])
        assert feats.shape == (48, 263) and joints.shape == (48, 22, 3) and np.isfinite(joints).all()
        np.testing.assert_array_equal(joints, np.load(run / "out2" / m["joints"]))
    first_joints = np.load(run / "out1" / manifest["motions"][0]["joints"])
    assert not np.array_equal(first_joints, np.load(run / "out3" / manifest["motions"][0]["joints"]))


def test_prompts_file_with_lengths(run):
    (run / "prompts.txt").write_text("a person jumps#40\n\nsomeone kicks with the left leg\n")
    out = lsgan("generate", "--gan", "gan", "--vae", "vae", "--prompts", "prompts.txt", "--seconds", 3, "-o", "outp", cwd=run)
    assert out.returncode == 0, out.stderr
    frames = [m["frames"] for m in json.loads((run / "outp" / "manifest.json").read_text())["motions"]]
    assert frames == [40, 60]


def test_a_stale_cache_is_refused(run, tmp_path):
    import shutil

    shutil.copytree(run / "vae", tmp_path / "vae2")
    out = lsgan("train-vae", "--data", run / "synth.h5", "--recipe", run / "tiny.yaml", "--out", tmp_path / "vae2",
                "--resume", "--max-steps", 18, cwd=run)
    assert out.returncode == 0, out.stderr
    changed = tmp_path / "vae2" / "last"  # trained on after the cache was encoded
    stale = lsgan("train-gan", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--vae", changed,
                  "--out", tmp_path / "gan2", cwd=run)
    assert stale.returncode == 1 and "another VAE" in stale.stderr
    mismatch = lsgan("generate", "--gan", "gan", "--vae", changed, "--text", "walk", "-o", tmp_path / "o", cwd=run)
    assert mismatch.returncode == 1 and "another VAE" in mismatch.stderr


def test_help_of_model_commands_has_examples(run):
    for cmd in ("train-vae", "encode-latents", "train-gan", "generate"):
        out = lsgan(cmd, "--help", cwd=run)
        assert out.returncode == 0 and "Examples:" in out.stdout


def test_generated_motion_exports_validate_and_reimport(run):
    """A generated motion as a user exports it: GLB (Khronos validator) and BVH (our importer) agree."""
    from gltf_reader import frame_count, node_index, parse, validate, world_matrices

    from lsgan.data.bvh import forward_kinematics, read_bvh
    from lsgan.data.skeleton import JOINT_NAMES

    out = lsgan("generate", "--gan", "gan", "--vae", "vae", "--text", "a person waves", "--frames", 40, "-o", "gen",
                cwd=run)
    assert out.returncode == 0, out.stderr
    for fmt in ("glb", "bvh"):
        done = lsgan("export", f"--{fmt}", "gen", "-o", f"gen-{fmt}", cwd=run)
        assert done.returncode == 0, done.stderr
    (glb,), (bvh_path,) = sorted((run / "gen-glb").glob("*.glb")), sorted((run / "gen-bvh").glob("*.bvh"))
    report = validate(glb)
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"]
    doc, blob = parse(glb.read_bytes())
    index = [node_index(doc)[n] for n in JOINT_NAMES]
    from_glb = np.stack([world_matrices(doc, blob, t)[index, :3, 3] for t in range(frame_count(doc, blob))])
    bvh = read_bvh(bvh_path)
    from_bvh = forward_kinematics(bvh)[:, [bvh.names.index(n) for n in JOINT_NAMES]] / 100.0
    assert np.abs(from_bvh - from_glb).max() < 1e-3  # both files pose the same rigid skeleton
    generated = np.load(next((run / "gen").glob("*_joints.npy")))
    assert from_glb.shape == generated.shape
    assert np.abs(from_glb[:, 0] - generated[:, 0]).max() < 1e-3  # the root path is kept exactly
