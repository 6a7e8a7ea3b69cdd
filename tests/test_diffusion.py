"""The latent-diffusion baseline: schedule, DDIM (closed forms), guidance, training, checkpoints, generate, CLI."""
from __future__ import annotations

import csv
import json
import math
import re
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from lsgan.outputs import OutputError
import torch

from lsgan.models.cache import StaleCache, read_latent_cache, write_latent_cache
from lsgan.models.checkpoint import read_meta, save_checkpoint, weights_hash
from lsgan.models.diffusion import (
    DiffusionConfig,
    LatentDiffusion,
    alphas_cumprod,
    ddim_timesteps,
    destandardise,
    load_diffusion,
)
from lsgan.train.diffusion import DiffusionTrainConfig, train_diffusion

sys.path.insert(0, str(Path(__file__).parent))
from test_gan import SMALL as GAN_SMALL  # noqa: E402
from test_gan import D, Z, toy_cache  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

SMALL = dict(latent_dim=Z, cond_dim=D, d_model=32, num_layers=3, num_heads=4, ff_size=64, dropout=0.0)


def quick(**kw) -> DiffusionTrainConfig:
    base = dict(lr=1e-3, batch_size=64, max_steps=20, eval_every=10, ckpt_every=10, log_every=5, fid_samples=256,
                eval_steps=5)
    return DiffusionTrainConfig(**(base | kw))


@pytest.fixture(scope="module")
def text_cache(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cache") / "text.h5"
    toy_cache(path)
    return path


# ---------------------------------------------------------------------------------------------------- schedule


def test_schedule_matches_the_formula() -> None:
    cfg = DiffusionConfig()
    ac = alphas_cumprod(cfg).numpy()
    betas = np.linspace(0.00085**0.5, 0.012**0.5, 1000) ** 2  # scaled_linear (MLD's scheduler.yaml)
    np.testing.assert_allclose(ac, np.cumprod(1 - betas), rtol=1e-12)
    assert ac[0] == pytest.approx(1 - 0.00085) and ac[-1] == pytest.approx(0.004660, abs=2e-6)
    lin = alphas_cumprod(DiffusionConfig(beta_schedule="linear", beta_start=1e-4, beta_end=0.02)).numpy()
    np.testing.assert_allclose(lin, np.cumprod(1 - np.linspace(1e-4, 0.02, 1000)), rtol=1e-12)
    buffer = LatentDiffusion(DiffusionConfig(**SMALL)).alphas_cumprod
    assert buffer.dtype == torch.float32 and torch.allclose(buffer.double(), torch.as_tensor(ac), rtol=1e-6)


def test_ddim_timesteps_follow_diffusers_leading_spacing() -> None:
    pairs = ddim_timesteps(50, 1000)  # MLD: DDIMScheduler(steps_offset=1, set_alpha_to_one=False), 50 steps
    assert len(pairs) == 50 and pairs[0] == (981, 961) and pairs[-1] == (1, -19)
    assert all(t - p == 20 for t, p in pairs)
    assert ddim_timesteps(1, 1000) == [(1, -999)]
    every = ddim_timesteps(1000, 1000)  # t = 1000 is clamped to 999, which the next step already is
    assert len(every) == 999 and every[0] == (999, 998) and every[-1] == (1, 0)
    with pytest.raises(ValueError, match="steps"):
        ddim_timesteps(0, 1000)


class GaussianOracle(torch.nn.Module):
    """The exact E[eps | z_t] for data z_0 ~ N(m, diag(s^2)): sqrt(1-a)(z_t - sqrt(a) m) / (a s^2 + 1 - a)."""

    def __init__(self, ac: torch.Tensor, m: torch.Tensor, s: torch.Tensor) -> None:
        super().__init__()
        self.ac, self.m, self.s = ac.double(), m.double(), s.double()
        self.anchor = torch.nn.Parameter(torch.zeros(1))  # gives the model a device

    def forward(self, z, t, cond, drop=None):
        a = self.ac[t][:, None]
        return ((1 - a).sqrt() * (z.double() - a.sqrt() * self.m) / (a * self.s**2 + 1 - a)).float()


def oracle_model(m: torch.Tensor, s: torch.Tensor) -> LatentDiffusion:
    model = LatentDiffusion(DiffusionConfig(**(SMALL | dict(latent_dim=len(m)))))
    model.denoiser = GaussianOracle(model.alphas_cumprod, m, s)
    return model.eval()


def test_ddim_with_an_oracle_denoiser_is_exact_for_a_point_mass() -> None:
    # Data = one point m: every step's z_0 estimate is m and DDIM (eta 0) keeps the noise estimate fixed, so the
    # output is sqrt(a_0) m + sqrt(1 - a_0) (z_T - sqrt(a_T') m) / sqrt(1 - a_T'), a_T' at the first DDIM step.
    m = torch.tensor([1.5, -2.0, 0.0, 0.7], dtype=torch.float64)
    model = oracle_model(m, torch.zeros(4))
    ac = model.alphas_cumprod.double()
    z_T = torch.randn(64, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for steps in (1, 7, 50):
        t_first = ddim_timesteps(steps, 1000)[0][0]
        expect = ac[0].sqrt() * m + (1 - ac[0]).sqrt() * (z_T - ac[t_first].sqrt() * m) / (1 - ac[t_first]).sqrt()
        out = model.sample(torch.zeros(64, D), noise=z_T.float(), steps=steps, guidance=1.0, eta=0.0)
        torch.testing.assert_close(out.double(), expect, atol=2e-4, rtol=0)


@pytest.mark.parametrize("steps,eta", [(50, 0.0), (1000, 0.0), (1000, 1.0)])
def test_ddim_with_an_oracle_denoiser_recovers_a_gaussian(steps: int, eta: float) -> None:
    # Data N(m, s^2) per dimension, started from the exact marginal at the first timestep. With the exact noise
    # estimate a DDIM step (eta 0) is affine: z' - sqrt(a') m = k (z - sqrt(a) m) with
    # k = (sqrt(a' a) s^2 + sqrt((1 - a')(1 - a))) / (a s^2 + 1 - a), so the output is Gaussian with mean sqrt(a_0) m
    # (MLD's last step lands on a_0) and std sqrt(a_T s^2 + 1 - a_T) prod k: a little below the data's
    # sqrt(a_0 s^2 + 1 - a_0) where s != 1 (Cauchy-Schwarz), converging to it as the steps shrink. eta 1 with
    # all 1000 steps is DDPM's ancestral sampler, which must land on the data's too. (From N(0, I) instead of the
    # exact marginal, the means come out biased by about -sqrt(a_T) m s: the scaled_linear schedule ends at
    # a_T = 0.0047, not 0; MLD samples the same way.)
    m = torch.tensor([1.0, -0.5, 3.0, 0.0], dtype=torch.float64)
    s = torch.tensor([0.2, 1.0, 2.0, 0.5], dtype=torch.float64)
    model = oracle_model(m, s)
    ac = model.alphas_cumprod.double()
    n = 20_000 if steps == 50 else 4000
    g = torch.Generator().manual_seed(1)
    pairs = ddim_timesteps(steps, 1000)
    a_T = ac[pairs[0][0]]
    z_T = a_T.sqrt() * m + (a_T * s**2 + 1 - a_T).sqrt() * torch.randn(n, 4, generator=g, dtype=torch.float64)
    out = model.sample(torch.zeros(n, D), generator=g, noise=z_T.float(), steps=steps, guidance=1.0, eta=eta).double()
    data_std = (ac[0] * s**2 + 1 - ac[0]).sqrt()
    std = (a_T * s**2 + 1 - a_T).sqrt()
    for t, t_prev in pairs:
        a, a_prev = ac[t], ac[max(t_prev, 0)]
        std = std * ((a_prev * a).sqrt() * s**2 + ((1 - a_prev) * (1 - a)).sqrt()) / (a * s**2 + 1 - a)
    assert ((out.mean(0) - ac[0].sqrt() * m).abs() < 4 * data_std / math.sqrt(n) + 2e-3).all(), out.mean(0)
    torch.testing.assert_close(out.std(0), std if eta == 0 else data_std, rtol=0.03, atol=0)
    if steps == 1000:
        torch.testing.assert_close(out.std(0), data_std, rtol=0.03, atol=0)


def test_recipes_build_the_diffusion_configs() -> None:
    from lsgan.recipes import RECIPES, build, load_recipe, section

    found = {}
    for path in sorted(RECIPES.glob("*.yaml")):
        r = section(load_recipe(path), "diffusion")
        if r:
            found[path.stem] = (build(DiffusionConfig, section(r, "model")),
                                build(DiffusionTrainConfig, section(r, "train")))
    assert {"humanml3d", "humanact12", "bandai", "demo"} <= set(found)
    mld, train = found["humanml3d"]  # MLD's HumanML3D settings
    assert (mld.d_model, mld.num_layers, mld.num_heads, mld.ff_size, mld.dropout) == (256, 9, 4, 1024, 0.1)
    assert (mld.beta_schedule, mld.beta_start, mld.beta_end) == ("scaled_linear", 0.00085, 0.012)
    assert mld.train_timesteps == 1000
    assert (mld.sample_steps, mld.guidance_scale, mld.cond_mask_prob, mld.prediction) == (50, 7.5, 0.1, "epsilon")
    assert train.lr == 1e-4 and found["humanact12"][0].cond == "action"


# ---------------------------------------------------------------------------------------------------- denoiser


@pytest.mark.parametrize("cond", ["text", "action"])
def test_shapes_and_the_null_condition(cond: str) -> None:
    cfg = DiffusionConfig(**(SMALL | dict(cond=cond, num_actions=5)))
    model = LatentDiffusion(cfg).eval()
    c1 = torch.randn(7, D) if cond == "text" else torch.randint(0, 5, (7,))
    c2 = torch.randn(7, D) if cond == "text" else (c1 + 1) % 5
    z, t = torch.randn(7, Z), torch.randint(0, 1000, (7,))
    assert model.denoiser(z, t, c1).shape == (7, Z)
    assert not torch.allclose(model.denoiser(z, t, c1), model.denoiser(z, t, c2))
    null = torch.ones(7, dtype=torch.bool)
    torch.testing.assert_close(model.denoiser(z, t, c1, null), model.denoiser(z, t, c2, null))  # condition ignored
    assert model.sample(c1, steps=3).shape == (7, Z)
    assert model.sample(c1, num=3, steps=3).shape == (7, 3, Z)


def test_guidance_one_is_the_conditional_prediction() -> None:
    model = LatentDiffusion(DiffusionConfig(**SMALL)).eval()
    with torch.no_grad():
        model.denoiser.null_cond.normal_()  # a trained-looking null token
    z, c = torch.randn(6, Z), torch.randn(6, D)
    t = torch.full((6,), 500)
    with torch.no_grad():
        cond = model.denoiser(z, t, c)
        uncond = model.denoiser(z, t, c, torch.ones(6, dtype=torch.bool))
        assert torch.equal(model.predict(z, 500, c, 1.0), cond)
        torch.testing.assert_close(model.predict(z, 500, c, 1.0 + 1e-12), cond)  # the two-half path, w = 1
        torch.testing.assert_close(model.predict(z, 500, c, 0.0), uncond, atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(model.predict(z, 500, c, 7.5), uncond + 7.5 * (cond - uncond), atol=1e-5, rtol=1e-5)


def test_sampling_is_deterministic_under_a_seed() -> None:
    model = LatentDiffusion(DiffusionConfig(**(SMALL | dict(dropout=0.1)))).eval()
    c = torch.randn(5, D)
    for eta in (0.0, 1.0):
        a = model.sample(c, generator=torch.Generator().manual_seed(3), steps=8, eta=eta)
        b = model.sample(c, generator=torch.Generator().manual_seed(3), steps=8, eta=eta)
        other = model.sample(c, generator=torch.Generator().manual_seed(4), steps=8, eta=eta)
        assert torch.equal(a, b) and not torch.allclose(a, other)


# ---------------------------------------------------------------------------------------------------- training


def test_training_lowers_the_loss_and_the_latent_fid(text_cache: Path, tmp_path: Path) -> None:
    result = train_diffusion(text_cache, tmp_path / "run", diffusion=DiffusionConfig(**SMALL),
                             train=quick(max_steps=400, eval_every=200, ckpt_every=400, log_every=50, eval_steps=10),
                             device="cpu", progress=False)
    history = dict(result["fid_history"])
    assert result["eval_split"] == "val" and sorted(history) == [0, 200, 400]
    assert history[400] < 0.2 * history[0], history
    assert result["best_val_latent_fid"] == min(history.values())
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    losses = [float(r["loss"]) for r in rows if r.get("loss")]
    assert losses[-1] < 0.7 * losses[0], losses
    best = read_meta(tmp_path / "run", "best")["extra"]["val_latent_fid"]
    assert best == pytest.approx(result["best_val_latent_fid"])


def test_action_conditioning(tmp_path: Path) -> None:
    centres = toy_cache(tmp_path / "act.h5", k=2, actions=True)
    train_diffusion(tmp_path / "act.h5", tmp_path / "run", diffusion=DiffusionConfig(**(SMALL | dict(cond="action"))),
                    train=quick(max_steps=300, eval_every=300, ckpt_every=300), device="cpu", progress=False)
    model, meta = load_diffusion(tmp_path / "run")
    assert model.config.num_actions == 2 and meta["extra"]["action_names"] == ["a0", "a1"]

    def class_means(guidance: float) -> torch.Tensor:
        g = torch.Generator().manual_seed(0)
        z = model.sample(torch.tensor([0, 1]), num=300, generator=g, steps=20, guidance=guidance)
        return destandardise(z, meta["extra"]["latent_mean"], meta["extra"]["latent_std"]).mean(1).double()  # (2, Z)

    plain, guided = class_means(1.0), class_means(3.0)
    err = torch.cdist(plain, torch.as_tensor(centres))  # (generated action, true centre)
    gap = np.linalg.norm(centres[0] - centres[1])
    assert err[0, 0] < 0.2 * gap and err[1, 1] < 0.2 * gap, err
    # guidance > 1 extrapolates away from the unconditional prediction: the classes move apart
    assert (guided[0] - guided[1]).norm() > 1.1 * (plain[0] - plain[1]).norm()


def test_checkpoint_round_trip(tmp_path: Path) -> None:
    for cfg in (DiffusionConfig(**SMALL), DiffusionConfig(**(SMALL | dict(cond="action", num_actions=4)))):
        model = LatentDiffusion(cfg)
        save_checkpoint(tmp_path / cfg.cond, model=model, kind="diffusion", config={"diffusion": asdict(cfg)}, step=3)
        loaded, meta = load_diffusion(tmp_path / cfg.cond)
        assert loaded.config == cfg and meta["step"] == 3 and not loaded.training
        for (k, a), (k2, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
            assert k == k2 and torch.equal(a, b)
        c = torch.randn(5, D) if cfg.cond == "text" else torch.arange(5) % 4
        za = model.eval().sample(c, generator=torch.Generator().manual_seed(1), steps=5)
        zb = loaded.sample(c, generator=torch.Generator().manual_seed(1), steps=5)
        assert torch.equal(za, zb)
    from lsgan.models.gan import GANConfig, LatentGAN

    save_checkpoint(tmp_path / "gan", model=LatentGAN(GANConfig(**GAN_SMALL)), kind="gan", config={}, step=0)
    with pytest.raises(ValueError, match="not a 'diffusion'"):
        load_diffusion(tmp_path / "gan")


def test_run_meta_matches_the_gans(text_cache: Path, tmp_path: Path) -> None:
    from lsgan.models.gan import GANConfig
    from lsgan.train.gan import GANTrainConfig, train_gan

    train_diffusion(text_cache, tmp_path / "diff", diffusion=DiffusionConfig(**SMALL), train=quick(max_steps=4),
                    device="cpu", progress=False)
    train_gan(text_cache, tmp_path / "gan", gan=GANConfig(arch="vanilla-gan", **GAN_SMALL),
              train=GANTrainConfig(max_steps=2, fid_samples=64), device="cpu", progress=False)
    meta, gan_meta = read_meta(tmp_path / "diff"), read_meta(tmp_path / "gan")
    assert meta["kind"] == "diffusion" and set(meta["extra"]) == set(gan_meta["extra"])
    cache = read_latent_cache(text_cache)
    assert meta["extra"]["vae_hash"] == "vae-a" and meta["extra"]["text_encoder"] == "toy-encoder"
    assert np.allclose(meta["extra"]["latent_mean"], cache.mean) and np.allclose(meta["extra"]["latent_std"], cache.std)
    assert meta["config"]["train"]["max_steps"] == 4 and meta["config"]["diffusion"]["cond_dim"] == D


def test_resume_continues_exactly(text_cache: Path, tmp_path: Path) -> None:
    cfg = DiffusionConfig(**(SMALL | dict(dropout=0.1)))  # dropout: the global RNG must be restored too
    train_diffusion(text_cache, tmp_path / "whole", diffusion=cfg, train=quick(), device="cpu", progress=False)
    train_diffusion(text_cache, tmp_path / "split", diffusion=cfg, train=quick(max_steps=10), device="cpu",
                    progress=False)
    with pytest.raises(OutputError, match="--resume"):
        train_diffusion(text_cache, tmp_path / "split", diffusion=cfg, train=quick(), device="cpu", progress=False)
    resumed = train_diffusion(text_cache, tmp_path / "split", diffusion=cfg, train=quick(), device="cpu",
                              progress=False, resume=True)
    assert resumed["step"] == 20 and [s for s, _ in resumed["fid_history"]] == [20]
    a, _ = load_diffusion(tmp_path / "whole", prefer="last")
    b, _ = load_diffusion(tmp_path / "split", prefer="last")
    for (k, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(x, y), k


def test_stale_cache_is_refused(text_cache: Path, tmp_path: Path) -> None:
    kw = dict(diffusion=DiffusionConfig(**SMALL), train=quick(max_steps=2), device="cpu", progress=False)
    with pytest.raises(StaleCache, match="another VAE"):
        train_diffusion(text_cache, tmp_path / "a", expect_vae_hash="vae-b", **kw)
    with pytest.raises(StaleCache, match="text encoder"):
        train_diffusion(text_cache, tmp_path / "b", expect_text_encoder="clip-vit-l-14", **kw)
    train_diffusion(text_cache, tmp_path / "c", expect_vae_hash="vae-a", expect_text_encoder="toy-encoder", **kw)
    other = tmp_path / "other.h5"
    toy_cache(other, vae_hash="vae-b")
    with pytest.raises(StaleCache, match="another VAE"):
        train_diffusion(other, tmp_path / "c", resume=True, **kw)


# ---------------------------------------------------------------------------------------------------- generate, CLI

TINY = """
diffusion:
  model: {d_model: 32, num_layers: 3, num_heads: 4, ff_size: 64, dropout: 0.0, sample_steps: 6, guidance_scale: 2.5}
  train: {lr: 1.0e-3, batch_size: 32, max_steps: 30, eval_every: 15, ckpt_every: 15, log_every: 5, fid_samples: 64,
          eval_steps: 3}
"""
PROMPTS = ["a person walks forward", "someone waves the right hand", "a person jumps"]


def lsgan(*args, cwd):
    return subprocess.run([sys.executable, "-m", "lsgan.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd)


def random_vae(path: Path, seed: int) -> Path:
    from lsgan.models.vae import MotionVAE, VAEConfig

    torch.manual_seed(seed)
    cfg = VAEConfig(latent_dim=Z, d_model=32, num_layers=1, num_heads=2, ff_size=64, dropout=0.0, max_len=200)
    extra = {"mean": np.zeros(263).tolist(), "std": np.full(263, 0.05).tolist()}
    save_checkpoint(path / "best", model=MotionVAE(cfg), kind="vae", config={"model": asdict(cfg)}, step=0, extra=extra)
    return path


@pytest.fixture(scope="module")
def setup(tmp_path_factory) -> Path:
    """A random tiny VAE, a cache of its hash with real MiniLM caption embeddings, and a diffusion run from the CLI."""
    from lsgan.models.text import load_text_encoder

    d = tmp_path_factory.mktemp("diffusion-e2e")
    vae = random_vae(d / "vae", 0)
    enc = load_text_encoder("minilm")
    emb = enc.encode(PROMPTS).numpy()
    rng = np.random.default_rng(0)
    n = 150
    label = np.arange(n) % 3
    write_latent_cache(
        d / "cache.h5", names=[f"c{i}" for i in range(n)], splits=["val" if i % 5 == 0 else "train" for i in range(n)],
        actions=np.full(n, -1), lengths=np.full(n, 60), mu=rng.normal(0, 2, (3, Z))[label] + rng.normal(size=(n, Z)),
        logvar=np.full((n, Z), -4.0), caption_clip=np.arange(n), caption_text=[PROMPTS[i] for i in label],
        caption_embedding=emb[label], action_names=[], vae_hash=weights_hash(vae), vae_path=str(vae),
        text_encoder=enc.id,
    )
    (d / "tiny.yaml").write_text(TINY)
    out = lsgan("train-diffusion", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--out", "diff", cwd=d)
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stderr.strip().splitlines()[-1])["step"] == 30
    return d


def test_cli_train_diffusion_and_generate(setup: Path) -> None:
    assert read_meta(setup / "diff")["config"]["diffusion"]["cond_dim"] == 384  # taken from the cache
    args = ["generate", "--gan", "diff", "--vae", "vae", "--text", PROMPTS[0], "--text", PROMPTS[1], "--frames", 48,
            "--num", 2, "--steps", 4, "--guidance", 3.0, "--seed"]
    first = lsgan(*args, 3, "-o", "out1", cwd=setup)
    assert first.returncode == 0, first.stderr
    assert "ms per motion" in first.stderr
    again, other = lsgan(*args, 3, "-o", "out2", cwd=setup), lsgan(*args, 4, "-o", "out3", cwd=setup)
    assert again.returncode == 0 and other.returncode == 0
    manifest = json.loads((setup / "out1" / "manifest.json").read_text())
    assert manifest["generator"]["kind"] == "diffusion" and manifest["generator"]["sha256"]
    assert (manifest["generator"]["steps"], manifest["generator"]["guidance"]) == (4, 3.0)
    assert len(manifest["motions"]) == 4
    assert set(manifest["timings_s"]) == {"text_encoding", "generator", "vae_decoding"}
    for m in manifest["motions"]:
        joints = np.load(setup / "out1" / m["joints"])
        assert np.load(setup / "out1" / m["features"]).shape == (48, 263) and joints.shape == (48, 22, 3)
        assert np.isfinite(joints).all()
        np.testing.assert_array_equal(joints, np.load(setup / "out2" / m["joints"]))
    first_joints = np.load(setup / "out1" / manifest["motions"][0]["joints"])
    assert not np.array_equal(first_joints, np.load(setup / "out3" / manifest["motions"][0]["joints"]))
    from click.testing import CliRunner

    from lsgan.cli import main

    for cmd in ("train-diffusion", "generate"):
        help_text = CliRunner().invoke(main, [cmd, "--help"]).output
        assert "Examples:" in help_text and "diffusion" in help_text


def test_generate_api_with_a_diffusion_checkpoint(setup: Path) -> None:
    from lsgan.generate import Request, generate, load_generator, sample_latents

    requests = [Request(text=p, frames=40 + 8 * i) for i, p in enumerate(PROMPTS)]
    a = generate(setup / "diff", setup / "vae", requests, num=2, seed=5, device="cpu", batch_size=256)
    b = generate(setup / "diff", setup / "vae", requests, num=2, seed=5, device="cpu", batch_size=1)
    assert a.kind == "diffusion" and a.sampling == {"steps": 6, "guidance": 2.5, "eta": 0.0}  # the config's
    assert [len(m.features) for m in a.motions] == [40, 40, 48, 48, 56, 56]
    for x, y in zip(a.motions, b.motions):  # the motions do not depend on the batch size
        np.testing.assert_allclose(x.joints, y.joints, atol=1e-4)
    z = sample_latents(setup / "diff", requests, num=2, seed=5, device="cpu")
    model, meta = load_generator(setup / "diff")
    assert z.shape == (6, Z) and meta["kind"] == "diffusion" and isinstance(model, LatentDiffusion)
    np.testing.assert_array_equal(z, sample_latents(setup / "diff", requests, num=2, seed=5, device="cpu"))
    few = generate(setup / "diff", setup / "vae", requests[:1], seed=5, device="cpu", steps=2, guidance=1.0)
    assert few.sampling["steps"] == 2 and not np.allclose(few.motions[0].features, a.motions[0].features)
    with pytest.raises(ValueError, match="not a generator"):
        load_generator(setup / "vae")


def test_a_diffusion_model_is_steered_through_its_latent(setup: Path) -> None:
    """Control with a diffusion checkpoint: its sampled latent is optimised (no noise steps), the root then closed
    onto the path, and the keyframe's miss shrinks against the unsteered motion's."""
    from lsgan.constraints import Constraints, path_points
    from lsgan.control import ControlSettings
    from lsgan.generate import Request, generate_loaded, load_models

    loaded = load_models(setup / "diff", setup / "vae", device="cpu")
    req = [Request(text=PROMPTS[0], frames=40)]
    free = generate_loaded(loaded, req, seed=1, steps=2).motions[0].joints
    wrist = np.full((22, 3), np.nan, np.float32)
    wrist[21] = free[30, 21] + [0.3, 0.2, 0.0]
    settings = ControlSettings(20, lr=0.1)
    g = generate_loaded(loaded, req, seed=1, steps=2, constraints=Constraints(40, keyframes={30: wrist}),
                        control_settings=settings)
    assert g.timings_s["control"] > 0 and g.control["settings"]["noise_steps"] == 20
    assert g.motions[0].control["keyframes_m"]["max"] < 0.8 * np.linalg.norm(free[30, 21] - wrist[21])
    path = Constraints(40, path=path_points(np.array([[0, 0, 0], [1.9, 0.5, 1.0]]), 40))
    g = generate_loaded(loaded, req, seed=1, steps=2, constraints=path, control_settings=settings)
    assert g.motions[0].control["path_m"]["max"] < 1e-3


def test_a_stale_cache_is_refused_by_the_cli(setup: Path, tmp_path: Path) -> None:
    other = random_vae(tmp_path / "vae2", 1)
    stale = lsgan("train-diffusion", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--vae", other,
                  "--out", tmp_path / "d2", cwd=setup)
    assert stale.returncode == 1 and "another VAE" in stale.stderr
    mismatch = lsgan("generate", "--gan", "diff", "--vae", other, "--text", "walk", "-o", tmp_path / "o", cwd=setup)
    assert mismatch.returncode == 1 and "another VAE" in mismatch.stderr


DDP_SCRIPT = """
import os, sys
import lsgan.train.diffusion as td
from lsgan.models.diffusion import DiffusionConfig

built = []
class Recorded(td.LatentDiffusion):
    def __init__(self, cfg):
        super().__init__(cfg)
        built.append(self)
td.LatentDiffusion = Recorded

cache, out = sys.argv[1:3]
result = td.train_diffusion(cache, out, diffusion=DiffusionConfig(**{small}), train=td.DiffusionTrainConfig(**{train}),
                            device="cpu", progress=False)
digest = sum(float(p.double().sum()) * (i + 1) for i, p in enumerate(built[0].state_dict().values()))
open(f"{{out}}/digest{{os.environ['RANK']}}.txt", "w").write(repr(digest))
assert result["step"] == 6, result
"""


@pytest.mark.slow
def test_torchrun_two_processes(tmp_path: Path) -> None:
    import os

    toy_cache(tmp_path / "c.h5", k=2, per=20)
    script = tmp_path / "run.py"
    train = dict(lr=1e-3, batch_size=16, max_steps=6, eval_every=3, ckpt_every=3, log_every=2, fid_samples=64,
                 eval_steps=2)
    script.write_text(DDP_SCRIPT.format(small=SMALL | dict(dropout=0.1), train=train))
    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", str(script),
           str(tmp_path / "c.h5"), str(out)]
    proc = subprocess.run(cmd, env=dict(os.environ, OMP_NUM_THREADS="1"), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert read_meta(out, "last")["step"] == 6 and (out / "best").is_dir() and (out / "log.csv").exists()
    digests = [(out / f"digest{r}.txt").read_text() for r in range(2)]
    assert digests[0] == digests[1], digests  # DDP keeps the ranks' weights identical (they draw different batches)


@pytest.mark.parametrize("values, phrase", [
    ({"beta_start": 1.0, "beta_end": 1.0}, "beta_start (1.0) must be below beta_end (1.0)"),
    ({"beta_start": 0.5, "beta_end": 0.001}, "beta_start (0.5) must be below beta_end (0.001)"),
    ({"sample_steps": 5000, "train_timesteps": 10}, "sample_steps (5000) is more than train_timesteps (10)"),
])
def test_a_schedule_that_cannot_run_is_refused_with_its_section(values, phrase):
    """Settings within their bounds that no schedule can run (the second hostile review) are refused when the
    recipe is read, naming the section, not by scipy or at generation."""
    from lsgan.recipes import build

    with pytest.raises(ValueError, match=re.escape(f"r.yaml: diffusion.model: {phrase}")):
        build(DiffusionConfig, values, "r.yaml: diffusion.model")
