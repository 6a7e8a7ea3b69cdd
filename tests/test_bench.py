"""lsgan bench's cost figures against hand counts: the paper-sized generators at CLIP's 768-d condition, CLIP
ViT-L/14's text tower, attention on the CPU, and end to end as the sum of its parts."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from lsgan.eval import bench
from lsgan.models.vae import MotionVAE, VAEConfig

pytest.importorskip("transformers")

NOISE, COND, H, Z = 100, 768, 512, 256  # the paper's noise, CLIP ViT-L/14's width, hidden width, latent


def test_paper_models_match_the_recipe():
    from lsgan.models.diffusion import DiffusionConfig
    from lsgan.recipes import build, load_recipe

    recipe = load_recipe("humanml3d")

    def shape(cfg: VAEConfig) -> dict:  # the initialisation is a training setting: bench's weights are random
        return {k: v for k, v in dataclasses.asdict(cfg).items() if k != "init"}

    assert shape(bench.PAPER_VAE) == shape(build(VAEConfig, recipe["vae"]["model"]))
    assert not bench.PAPER_VAE.norm_first and bench.PAPER_VAE.max_len == 256
    gan = {k: v for k, v in recipe["gan"]["model"].items() if k != "arch"}
    assert {k: gan[k] for k in bench.PAPER_GAN} == bench.PAPER_GAN
    assert recipe["text_encoder"] == bench.PAPER_TEXT_ENCODER and bench.PAPER_COND_DIM == COND
    diffusion = build(DiffusionConfig, recipe["diffusion"]["model"])
    assert {k: getattr(diffusion, k) for k in bench.PAPER_DIFFUSION} == bench.PAPER_DIFFUSION


# Linear layers of the generators, 2 x in x out FLOPs per clip (biases, norms and activations are not counted).
HAND_GENERATOR_FLOPS = {
    # fc1 [noise, c] -> H, two residual blocks H -> H, fc2 H -> H, fc3 H -> Z
    "deep-wgan-gp": 2 * ((NOISE + COND) * H + 2 * H * H + H * H + H * Z),
    # the LS-GAN authors' widths: fc1 [noise, c] -> 2H, fc2 2H -> H, fc3 H -> Z
    "vanilla-wgan-gp": 2 * ((NOISE + COND) * 2 * H + 2 * H * H + H * Z),
}


@pytest.mark.parametrize("arch", bench.PAPER_GANS)
def test_paper_generator_flops_at_condition_768_match_a_hand_count(arch):
    samplers, _ = bench.bench_samplers(steps=1)
    sampler = next(s for s in samplers if s.name == arch)
    assert sampler.cond_dim == COND and sampler.text_encoder == "clip-vit-l-14"
    assert bench.generator_flops(sampler) == HAND_GENERATOR_FLOPS[arch]
    assert bench.gflops_2048(sampler, torch.device("cpu")) == pytest.approx(2048 * HAND_GENERATOR_FLOPS[arch] / 1e9)


def test_deep_generator_is_the_issues_5_58_gflops_per_2048_clips():
    assert 2048 * HAND_GENERATOR_FLOPS["deep-wgan-gp"] / 1e9 == pytest.approx(5.578, abs=1e-3)


def test_clip_tower_is_vit_l14_and_its_count_matches_its_main_matmuls():
    """Hand count: per layer q, k, v, out (4 d^2 per token), the MLP (2 d f per token), and the attention products
    QK^T and AV (2 T^2 d); then the projection (d p) on the pooled token. torch's counter adds nothing else (norms,
    activations, embedding lookups are not counted), so the two agree to within 0.1%."""
    from lsgan.models.text import clip_l14_text_tower

    cfg = clip_l14_text_tower().config
    sizes = (cfg.num_hidden_layers, cfg.hidden_size, cfg.num_attention_heads, cfg.intermediate_size,
             cfg.max_position_embeddings, cfg.projection_dim, cfg.vocab_size)
    assert sizes == (12, 768, 12, 3072, 77, 768, 49408)
    layers, d, f, t, p = 12, 768, 3072, 77, 768
    macs = layers * (t * (4 * d * d + 2 * d * f) + 2 * t * t * d) + d * p
    assert bench.clip_text_flops() == pytest.approx(2 * macs, rel=1e-3)
    assert 2 * macs / 1e9 == pytest.approx(13.30, abs=0.01)


def test_attention_is_counted_on_the_cpu():
    q, k, v = (torch.randn(2, 4, 10, 8) for _ in range(3))
    flops = bench.count_flops(lambda: torch.nn.functional.scaled_dot_product_attention(q, k, v))
    assert flops == 2 * (2 * 2 * 4 * 10 * 10 * 8)  # QK^T and AV, each B H T T D multiply-adds


def test_decoder_count_is_linear_in_the_batch():
    vae = MotionVAE(VAEConfig()).eval()
    assert bench.decoder_flops(vae, 40, clips=1) == bench.decoder_flops(vae, 40, clips=3) > 0


def test_end_to_end_is_the_sum_of_its_parts():
    torch.manual_seed(0)
    samplers = [bench.gan_sampler("deep-wgan-gp"), bench.diffusion_sampler(steps=2, guidance=7.5)]
    vae = MotionVAE(VAEConfig()).eval()
    rows = bench.run_bench(samplers, vae=vae, devices=["cpu"], frames=40, repeats=1)
    text = bench.clip_text_flops() / 1e9
    decoder = bench.decoder_flops(vae, 40) / 1e9
    gan, diffusion = rows
    assert gan.generator_gflops_clip * 1e9 == HAND_GENERATOR_FLOPS["deep-wgan-gp"]
    assert diffusion.generator_gflops_clip > 10 * gan.generator_gflops_clip
    for r in rows:
        assert r.text_gflops_clip == pytest.approx(text, rel=1e-12)
        assert r.decoder_gflops_clip == pytest.approx(decoder, rel=1e-12)
        parts = r.text_gflops_clip + r.generator_gflops_clip + r.decoder_gflops_clip
        assert r.e2e_gflops_clip == pytest.approx(parts, rel=1e-12)
        assert r.e2e_gflops_2048 == pytest.approx(2048 * parts, rel=1e-12)
        assert r.gflops_2048 == pytest.approx(2048 * r.generator_gflops_clip, rel=1e-12)
        assert r.cond_dim == COND and r.text_encoder_counted.startswith("clip-vit-l-14")
        assert r.text_encoder_timed == "minilm (384-d, zero-padded to 768)"
        assert r.ms_per_motion_b1 > 0 and r.ms_per_motion_b256 > 0 and r.ms_decoder_b256 > 0
    assert gan.e2e_gflops_clip_null_text == gan.e2e_gflops_clip  # no guidance, no empty prompt
    assert diffusion.e2e_gflops_clip_null_text == pytest.approx(diffusion.e2e_gflops_clip + text, rel=1e-12)
    table = bench.format_table(rows)
    assert "PER CLIP" in table and "2048 clips" in table and "minilm (384-d, zero-padded to 768)" in table
    assert "deep-wgan-gp vs mld-diffusion (2 DDIM steps, cfg 7.5): the generator is x" in table
    old_keys = {"model", "gflops_2048", "ms_per_motion_b1", "ms_per_motion_b256", "device"}
    assert old_keys <= set(bench.rows_as_dicts(rows)[0]) == {f.name for f in dataclasses.fields(bench.BenchRow)}


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_peak_rate_counts_two_n_cubed_operations_per_product(precision, monkeypatch):
    """The rate is 2 n^3 over the best product's seconds (the probe the benchmarks take before and after each row):
    with a clock that advances 1 ms per read (a timed product reads it twice), a 64-cube product rates 2 * 64^3 /
    1e-3; the real probe gives a finite positive rate."""
    laps = iter(range(10**6))
    monkeypatch.setattr(bench.time, "perf_counter", lambda: next(laps) * 1e-3)  # a product: two reads, 1 ms apart
    assert bench.peak_gflops(precision, n=64, reps=2) == pytest.approx(2 * 64**3 / 1e-3 / 1e9)
    monkeypatch.undo()
    rate = bench.machine_rate()
    assert 0 < rate < float("inf")
