"""lsgan evaluate / bench / plot-latents end to end through the real CLI, on tiny trained models.

One module fixture trains, on 360 synthetic clips: a VAE, a text GAN, an action GAN, a text diffusion model,
a text-motion evaluator and an action classifier (tiny configs, a few seconds each).
"""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

TINY = """
vae:
  model: {latent_dim: 32, d_model: 32, num_layers: 1, num_heads: 2, ff_size: 64, dropout: 0.0, max_len: 200}
  train: {batch_size: 16, max_steps: 40, val_every: 20, ckpt_every: 20, log_every: 10, lr: 1.0e-3, val_batches: 2}
gan:
  model: {arch: deep-wgan-gp, latent_dim: 32, hidden_dim: 64, noise_dim: 16}
  train: {batch_size: 32, max_steps: 40, eval_every: 20, ckpt_every: 20, log_every: 10, fid_samples: 64, critic_steps: 2}
diffusion:
  model: {latent_dim: 32, d_model: 32, num_layers: 1, num_heads: 2, ff_size: 64, dropout: 0.0, sample_steps: 5}
  train: {batch_size: 32, max_steps: 40, eval_every: 20, ckpt_every: 20, log_every: 10, fid_samples: 64, eval_steps: 3}
evaluator:
  text:
    model: {movement_hidden: 64, movement_latent: 64, motion_hidden: 64, embed_dim: 64, text_hidden: 64}
    train: {lr: 2.0e-3, batch_size: 32, max_steps: 40, val_every: 20, ckpt_every: 20, log_every: 10}
  action:
    model: {hidden_size: 32}
    train: {lr: 2.0e-3, batch_size: 32, max_steps: 40, val_every: 20, ckpt_every: 20, log_every: 10}
"""


def lsgan(*args, cwd):
    return subprocess.run([sys.executable, "-m", "lsgan.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("evaluate")
    (d / "tiny.yaml").write_text(TINY)
    steps = [
        ("preprocess", "--source", "synthetic", "--num-clips", 360, "-o", "synth.h5"),
        ("train-vae", "--data", "synth.h5", "--recipe", "tiny.yaml", "--out", "vae"),
        ("encode-latents", "--data", "synth.h5", "--vae", "vae", "-o", "cache.h5"),
        ("train-gan", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--out", "gan"),
        ("train-gan", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--cond", "action", "--out", "act-gan"),
        ("train-diffusion", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--out", "diffusion"),
        ("train-evaluator", "--data", "synth.h5", "--recipe", "tiny.yaml", "--kind", "text", "--out", "evaluator"),
        ("train-evaluator", "--data", "synth.h5", "--recipe", "tiny.yaml", "--kind", "action", "--out", "classifier"),
    ]
    for step in steps:
        out = lsgan(*step, cwd=d)
        assert out.returncode == 0, f"{step[0]} failed:\n{out.stderr[-3000:]}"
    return d


def test_text_to_motion_table(run):
    out = lsgan("evaluate", "--gan", "gan", "--gan", "mld=diffusion", "--vae", "vae", "--data", "synth.h5",
                "--evaluator", "evaluator", "--replications", 2, "--mm-captions", 4, "--mm-samples", 10,
                "--steps", 3, "-o", "t2m", cwd=run)
    assert out.returncode == 0, out.stderr[-3000:]
    table = json.loads((run / "t2m.json").read_text())
    assert set(table["rows"]) == {"Real", "gan", "mld"}
    real, gan = table["rows"]["Real"], table["rows"]["gan"]
    for row in (real, gan):
        top = [row[f"r_precision_top{k}"]["mean"] for k in (1, 2, 3)]
        assert 0 <= top[0] <= top[1] <= top[2] <= 1
        assert len(row["fid"]["values"]) == 2 and row["fid"]["ci95"] >= 0
    assert real["r_precision_top3"]["mean"] > 3 / 32 * 2  # the trained evaluator matches real pairs well
    assert real["fid"]["mean"] < gan["fid"]["mean"]  # two real draws agree better than 40-step models
    assert "multimodality" in gan and "multimodality" not in real
    for row in table["rows"].values():  # what animators read, for every row
        assert 0 <= row["foot_skating_ratio"]["mean"] <= 1 and len(row["foot_skating_ratio"]["values"]) == 2
        assert row["penetration_m"]["mean"] >= 0 and row["floating_m"]["mean"] >= 0 and row["jerk_m_s3"]["mean"] > 0
    assert real["foot_skating_ratio"]["mean"] < 0.1 and real["penetration_m"]["mean"] < 0.01  # planted synthetic feet
    assert table["info"]["fid_reference"] == "separate"
    small = [n for n in table["notes"] if n.startswith(f"FID from {table['info']['windows']} motions per draw")]
    assert len(small) == 1 and "biased upward" in small[0]  # a synthetic test split: fewer windows than dimensions
    markdown = (run / "t2m.md").read_text()
    assert "Skating ↓" in markdown and "Jerk (m/s³) →" in markdown
    assert "| Real |" in markdown and "±" in markdown and "R-P top3" in markdown
    assert "| mld |" in out.stdout


def test_vae_reconstruction_table(run):
    out = lsgan("evaluate", "--vae-only", "--vae", "vae", "--data", "synth.h5", "--evaluator", "evaluator",
                "-o", "vae-table", cwd=run)
    assert out.returncode == 0, out.stderr[-3000:]
    row = json.loads((run / "vae-table.json").read_text())["rows"]["VAE"]
    assert set(row) >= {"ape_root", "ape_traj", "ape_mean_pose", "ape_mean_joints", "ave_root", "mpjpe", "fid"}
    assert 0 < row["mpjpe"]["mean"] < 2.0 and row["ape_mean_joints"]["mean"] > 0


def test_action_table(run):
    out = lsgan("evaluate", "--action", "--gan", "act-gan", "--vae", "vae", "--data", "synth.h5", "--evaluator",
                "classifier", "--replications", 2, "--samples", 60, "--min-frames", 16, "-o", "act", cwd=run)
    assert out.returncode == 0, out.stderr[-3000:]
    rows = json.loads((run / "act.json").read_text())["rows"]
    assert set(rows) == {"Real", "act-gan"}
    assert rows["Real"]["accuracy"]["mean"] > rows["act-gan"]["accuracy"]["mean"] - 1.0  # both defined
    assert rows["Real"]["fid"]["mean"] < 1e-6  # the real draw against itself
    assert rows["act-gan"]["fid"]["mean"] > 0
    assert not json.loads((run / "act.json").read_text())["notes"]  # 60 motions in the classifier's 30-d features


def test_bench_counts_flops_and_times(run):
    out = lsgan("bench", "--gan", "gan", "--diffusion", "diffusion", "--vae", "vae", "--steps", 4, "--repeats", 1,
                "--frames", 40, "--device", "cpu", "--json", "bench.json", cwd=run)
    assert out.returncode == 0, out.stderr[-3000:]
    rows = json.loads((run / "bench.json").read_text())
    assert all({"model", "gflops_2048", "ms_per_motion_b1", "ms_per_motion_b256", "device"} <= set(r) for r in rows)
    gan, diffusion = rows
    assert gan["model"] == "deep-wgan-gp" and "4 DDIM steps" in diffusion["model"]
    assert diffusion["gflops_2048"] > gan["gflops_2048"] > 0
    for r in rows:  # checkpoints made with MiniLM: MiniLM is what is counted end to end
        assert r["text_encoder_counted"].startswith("minilm") and r["cond_dim"] == 384 and r["text_gflops_clip"] > 0
        parts = r["text_gflops_clip"] + r["generator_gflops_clip"] + r["decoder_gflops_clip"]
        assert r["e2e_gflops_clip"] == pytest.approx(parts) and r["e2e_gflops_2048"] == pytest.approx(2048 * parts)
    assert all(r["ms_per_motion_b1"] > 0 and r["ms_per_motion_b256"] > 0 and r["device"] == "cpu" for r in rows)


def test_flop_count_is_linear_in_the_batch_and_scales_with_steps():
    from lsgan.eval.bench import count_flops, diffusion_sampler, gan_sampler

    torch.manual_seed(0)
    gan = gan_sampler("vanilla-wgan-gp")
    cond = torch.randn(8, gan.cond_dim)
    assert count_flops(lambda: gan.sample(torch.cat([cond, cond]))) == 2 * count_flops(lambda: gan.sample(cond))
    two, four = (diffusion_sampler(steps=s, guidance=7.5) for s in (2, 4))
    assert count_flops(lambda: four.sample(cond)) == pytest.approx(2 * count_flops(lambda: two.sample(cond)),
                                                                  rel=0.01)
    unguided = diffusion_sampler(steps=2, guidance=1.0)
    assert count_flops(lambda: two.sample(cond)) == pytest.approx(2 * count_flops(lambda: unguided.sample(cond)),
                                                                 rel=0.01)


def test_plot_latents_png(run):
    from PIL import Image

    out = lsgan("plot-latents", "--cache", "cache.h5", "--gan", "gan", "--per-class", 8, "-o", "fig/latents.png",
                cwd=run)
    assert out.returncode == 0, out.stderr[-3000:]
    img = np.asarray(Image.open(run / "fig" / "latents.png").convert("RGB"), dtype=np.int16)
    assert img.shape[0] > 400 and img.reshape(-1, 3).std(axis=0).max() > 10
    coloured = (np.abs(img[..., 0] - img[..., 2]) > 60).mean()  # the tab10 markers, not just black text
    assert coloured > 0.001


def test_evaluate_errors_are_clear(run):
    out = lsgan("evaluate", "--gan", "gan", "--vae", "vae", "--data", "synth.h5", "-o", "x", cwd=run)
    assert out.returncode == 2 and "--evaluator is required" in out.stderr
    out = lsgan("evaluate", "--gan", "gan", "--vae", "vae", "--data", "synth.h5", "--evaluator", "evaluator",
                "--split", "nope", "-o", "x", cwd=run)
    assert out.returncode == 1 and "error:" in out.stderr and "nope" in out.stderr


def test_flop_count_sees_the_transformer_fast_path():
    """In eval mode torch's transformer layers take a fused path the counter would miss: counts must agree."""
    from lsgan.eval.bench import count_flops, diffusion_sampler

    torch.manual_seed(0)
    sampler = diffusion_sampler(steps=1, guidance=1.0)
    cond = torch.randn(4, sampler.cond_dim)
    d = 256  # paper width: per pass at least the 9 layers' feed-forward matmuls (2 x 256 x 1024 x 2 flops)
    assert count_flops(lambda: sampler.sample(cond)) >= 4 * 9 * 2 * (2 * d * 1024 * 2)
