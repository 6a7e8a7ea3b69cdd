"""Latent GANs: shapes, losses (no tanh, both WGAN-GP terms), learning a toy conditional target, checkpoints."""
from __future__ import annotations

import csv
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from lsgan import outputs
from lsgan.outputs import OutputError
import torch

from lsgan.models.cache import StaleCache, read_latent_cache, write_latent_cache
from lsgan.models.checkpoint import load_state, read_meta, save_checkpoint
from lsgan.models.gan import (
    ARCHS,
    GANConfig,
    LatentGAN,
    critic_loss_wgan_gp,
    d_loss_bce,
    destandardise,
    g_loss_bce,
    load_gan,
)
from lsgan.train.common import TrainingDiverged
from lsgan.train.gan import GANTrainConfig, train_gan

pytestmark = pytest.mark.usefixtures("one_thread")

Z, D = 16, 8  # toy latent and text widths
SMALL = dict(noise_dim=8, hidden_dim=64, latent_dim=Z, cond_dim=D)



def toy_cache(path: Path, *, k: int = 3, per: int = 100, actions: bool = False, seed: int = 0,
              splits: tuple[str, ...] = ("val", "train", "train", "train", "train"),
              vae_hash: str = "vae-a") -> np.ndarray:
    """k conditions (random unit text vectors or action ids), each tied to a Gaussian cluster; returns centres."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(0, 1.5, (k, Z))
    texts = rng.normal(size=(k, D))
    texts /= np.linalg.norm(texts, axis=1, keepdims=True)
    n = k * per
    label = np.repeat(np.arange(k), per)
    mu = centres[label] + 0.5 * rng.normal(size=(n, Z))
    write_latent_cache(
        path, names=[f"c{i}" for i in range(n)], splits=[splits[i % len(splits)] for i in range(n)],
        actions=label if actions else np.full(n, -1), lengths=np.full(n, 60), mu=mu,
        logvar=np.full((n, Z), np.log(0.01)), caption_clip=np.arange(n), caption_text=[f"move {c}" for c in label],
        caption_embedding=texts[label], action_names=[f"a{i}" for i in range(k)] if actions else [],
        vae_hash=vae_hash, text_encoder="toy-encoder",
    )
    return centres


@pytest.fixture(scope="module")
def text_cache(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cache") / "text.h5"
    toy_cache(path)
    return path


@pytest.fixture(scope="module")
def action_cache(tmp_path_factory) -> tuple[Path, np.ndarray]:
    path = tmp_path_factory.mktemp("cache") / "action.h5"
    return path, toy_cache(path, k=2, actions=True)


def quick(**kw) -> GANTrainConfig:
    base = dict(lr=1e-3, batch_size=64, max_steps=20, eval_every=10, ckpt_every=10, log_every=5, fid_samples=256)
    return GANTrainConfig(**(base | kw))


# ---------------------------------------------------------------------------------------------------- networks


@pytest.mark.parametrize("arch", ARCHS)
@pytest.mark.parametrize("cond", ["text", "action"])
def test_shapes(arch: str, cond: str) -> None:
    cfg = GANConfig(arch=arch, cond=cond, num_actions=5, **SMALL)
    model = LatentGAN(cfg)
    c = torch.randn(7, D) if cond == "text" else torch.randint(0, 5, (7,))
    z = model.generator(torch.randn(7, cfg.noise_dim), c)
    assert z.shape == (7, Z)
    assert model.discriminator(z, c).shape == (7,)
    assert model.sample(c).shape == (7, Z)
    assert model.sample(c, num=3).shape == (7, 3, Z)
    assert len(model.generator.blocks) == (2 if arch.startswith("deep") else 0)
    names = {type(m).__name__ for m in model.modules()}
    assert not names & {"Tanh", "Sigmoid", "BatchNorm1d"}


def test_default_sizes() -> None:
    cfg = GANConfig()
    model = LatentGAN(cfg)
    z = model.sample(torch.randn(4, 384))
    assert z.shape == (4, 256)
    assert model.generator.fc1.in_features == 100 + 384
    assert model.discriminator.fc1.in_features == 256 + 384


def test_generator_output_is_unbounded() -> None:
    model = LatentGAN(GANConfig(arch="vanilla-gan", **SMALL))
    with torch.no_grad():
        model.generator.fc3.weight.mul_(50)
    z = model.sample(torch.randn(64, D))
    assert z.abs().max() > 3  # a tanh would keep it inside (-1, 1)


def test_action_embedding_is_learnable_and_matters() -> None:
    model = LatentGAN(GANConfig(arch="deep-wgan-gp", cond="action", num_actions=3, **SMALL))
    assert model.generator.cond.embed.weight.requires_grad
    noise = torch.randn(5, 8)
    a = model.generator(noise, torch.zeros(5, dtype=torch.long))
    b = model.generator(noise, torch.ones(5, dtype=torch.long))
    assert not torch.allclose(a, b)


# ---------------------------------------------------------------------------------------------------- losses


class LinearCritic(torch.nn.Module):
    """D(z, c) = w . z: its gradient with respect to z is w everywhere."""

    def __init__(self, w: torch.Tensor) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(w)

    def forward(self, z: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return z @ self.w


def test_wgan_gp_loss_has_the_wasserstein_term() -> None:
    torch.manual_seed(0)
    w = torch.randn(Z)
    w /= w.norm()
    critic = LinearCritic(w)
    real, fake, c = torch.randn(32, Z), torch.randn(32, Z), torch.randn(32, D)
    a = critic_loss_wgan_gp(critic, real, fake, c)
    b = critic_loss_wgan_gp(critic, real + 2.0 * w, fake, c)  # D(real) rises by 2, the penalty stays 0
    assert a.gp < 1e-10 and b.gp < 1e-10
    assert b.loss.item() == pytest.approx(a.loss.item() - 2.0, abs=1e-4)
    assert a.wasserstein.item() == pytest.approx((critic(real, c).mean() - critic(fake, c).mean()).item(), abs=1e-5)


def test_gradient_penalty() -> None:
    torch.manual_seed(0)
    w = torch.randn(Z)
    real, fake, c = torch.randn(32, Z), torch.randn(32, Z), torch.randn(32, D)
    unit = critic_loss_wgan_gp(LinearCritic(w / w.norm()), real, fake, c)
    steep = critic_loss_wgan_gp(LinearCritic(3 * w / w.norm()), real, fake, c, gp_weight=10.0)
    assert unit.gp < 1e-10
    assert steep.gp.item() == pytest.approx(4.0, rel=1e-4)  # (||grad|| - 1)^2 = (3 - 1)^2
    assert steep.loss.item() == pytest.approx(-steep.wasserstein.item() + 40.0, rel=1e-4)
    # the penalty trains the critic: its gradient reaches the critic's weights
    critic = LinearCritic(3 * w / w.norm())
    critic_loss_wgan_gp(critic, real, real, c).loss.backward()  # Wasserstein term 0: the gradient is the penalty's
    assert critic.w.grad.norm() > 1.0


def test_bce_losses() -> None:
    sure = torch.full((8,), 20.0)
    assert d_loss_bce(sure, -sure) < 1e-6
    assert d_loss_bce(-sure, sure) > 20
    fake = torch.full((8,), -10.0, requires_grad=True)  # D is sure these are fake
    g_loss_bce(fake).backward()
    assert fake.grad.abs().sum() > 0.99  # non-saturating: -log D(fake) still has a gradient of ~1 in total


# ---------------------------------------------------------------------------------------------------- training


@pytest.mark.parametrize("arch", ARCHS)
def test_each_variant_learns_the_toy_target(arch: str, text_cache: Path, tmp_path: Path) -> None:
    wgan = arch.endswith("wgan-gp")
    result = train_gan(
        text_cache, tmp_path / "run", gan=GANConfig(arch=arch, **SMALL),
        train=quick(max_steps=250 if wgan else 500, eval_every=50, ckpt_every=1000, fid_samples=512),
        device="cpu", progress=False,
    )
    history = dict(result["fid_history"])
    assert result["eval_split"] == "val" and result["step"] == max(history)
    start, end = history[0], history[result["step"]]
    assert end < 0.5 * start, history
    assert result["best_val_latent_fid"] <= end
    best = read_meta(tmp_path / "run", "best")["extra"]["val_latent_fid"]
    assert best == pytest.approx(result["best_val_latent_fid"])
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    assert {"d_loss", "g_loss", "latent_fid"} <= set(rows[0])
    assert ("wasserstein" in rows[0]) == wgan and ("gp" in rows[0]) == wgan


def test_action_conditioning(action_cache: tuple[Path, np.ndarray], tmp_path: Path) -> None:
    cache, centres = action_cache
    train_gan(cache, tmp_path / "run", gan=GANConfig(arch="vanilla-wgan-gp", cond="action", **SMALL),
              train=quick(max_steps=250, eval_every=250, ckpt_every=250), device="cpu", progress=False)
    model, meta = load_gan(tmp_path / "run")
    assert model.config.num_actions == 2 and meta["extra"]["action_names"] == ["a0", "a1"]
    g = torch.Generator().manual_seed(0)
    z = destandardise(model.sample(torch.tensor([0, 1]), num=500, generator=g), meta["extra"]["latent_mean"],
                      meta["extra"]["latent_std"]).mean(1)  # (2, Z) in the cache's latent space
    err = torch.cdist(z.double(), torch.as_tensor(centres))  # (generated action, true centre)
    gap = np.linalg.norm(centres[0] - centres[1])
    assert err[0, 0] < 0.25 * gap and err[1, 1] < 0.25 * gap, err
    assert (z[0] - z[1]).norm() > 0.5 * gap


def test_config_follows_the_cache(text_cache: Path, tmp_path: Path) -> None:
    cfg = GANConfig(arch="vanilla-gan", noise_dim=8, hidden_dim=32)  # latent_dim 256, cond_dim 384: not the cache's
    result = train_gan(text_cache, tmp_path / "run", gan=cfg, train=quick(max_steps=2), device="cpu", progress=False)
    gan = result["config"]["gan"]
    assert (gan["latent_dim"], gan["cond_dim"]) == (Z, D)
    assert any("cond_dim 384" in n for n in result["notes"])
    with pytest.raises(ValueError, match="no clip in the cache has an action"):
        train_gan(text_cache, tmp_path / "act", gan=GANConfig(cond="action", **SMALL), train=quick(), device="cpu",
                  progress=False)


def test_eval_falls_back_to_test_split(tmp_path: Path) -> None:
    toy_cache(tmp_path / "c.h5", per=20, splits=("test", "train", "train"))
    result = train_gan(tmp_path / "c.h5", tmp_path / "run", gan=GANConfig(arch="vanilla-gan", **SMALL),
                       train=quick(max_steps=2), device="cpu", progress=False)
    assert result["eval_split"] == "test"
    assert any("test split" in n for n in result["notes"])


def test_checkpoint_round_trip(tmp_path: Path) -> None:
    text = GANConfig(arch="deep-wgan-gp", **SMALL)
    action = GANConfig(arch="vanilla-gan", cond="action", num_actions=4, **SMALL)
    for cfg in (text, action):
        model = LatentGAN(cfg)
        save_checkpoint(tmp_path / cfg.arch, model=model, kind="gan", config={"gan": asdict(cfg)}, step=3)
        loaded, meta = load_gan(tmp_path / cfg.arch)
        assert loaded.config == cfg and meta["step"] == 3 and not loaded.training
        for (k, a), (k2, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
            assert k == k2 and torch.equal(a, b)
        c = torch.randn(5, D) if cfg.cond == "text" else torch.arange(5) % 4
        za = model.sample(c, generator=torch.Generator().manual_seed(1))
        zb = loaded.sample(c, generator=torch.Generator().manual_seed(1))
        assert torch.equal(za, zb)


def test_run_checkpoint_meta(text_cache: Path, tmp_path: Path) -> None:
    train_gan(text_cache, tmp_path / "run", gan=GANConfig(arch="vanilla-gan", **SMALL), train=quick(max_steps=10),
              device="cpu", progress=False)
    model, meta = load_gan(tmp_path / "run")
    cache = read_latent_cache(text_cache)
    extra = meta["extra"]
    assert meta["kind"] == "gan" and extra["vae_hash"] == "vae-a" and extra["text_encoder"] == "toy-encoder"
    assert np.allclose(extra["latent_mean"], cache.mean) and np.allclose(extra["latent_std"], cache.std)
    assert math.isfinite(extra["val_latent_fid"]) and Path(extra["cache"]) == text_cache.resolve()
    assert meta["config"]["train"]["max_steps"] == 10
    z = torch.zeros(1, Z)
    assert np.allclose(destandardise(z, extra["latent_mean"], extra["latent_std"]).numpy()[0], cache.mean)


def test_resume_continues_exactly(text_cache: Path, tmp_path: Path) -> None:
    gan = GANConfig(arch="deep-wgan-gp", **SMALL)
    whole = train_gan(text_cache, tmp_path / "whole", gan=gan, train=quick(max_steps=20), device="cpu", progress=False)
    train_gan(text_cache, tmp_path / "split", gan=gan, train=quick(max_steps=10), device="cpu", progress=False)
    with pytest.raises(OutputError, match="--resume"):
        train_gan(text_cache, tmp_path / "split", gan=gan, train=quick(max_steps=20), device="cpu", progress=False)
    resumed = train_gan(text_cache, tmp_path / "split", gan=gan, train=quick(max_steps=20), device="cpu",
                        progress=False, resume=True)
    assert resumed["step"] == whole["step"] == 20
    assert [s for s, _ in resumed["fid_history"]] == [20]  # continued at step 10, no new step-0 evaluation
    a, _ = load_gan(tmp_path / "whole", prefer="last")
    b, meta = load_gan(tmp_path / "split", prefer="last")
    assert meta["step"] == 20
    for (k, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(x, y), k
    steps = [int(r["step"]) for r in csv.DictReader(open(tmp_path / "split" / "log.csv"))]
    assert steps == [0, 5, 10, 15, 20]


def test_a_run_saved_before_the_shared_loop_resumes_exactly(text_cache: Path, tmp_path: Path) -> None:
    """A state.pt in train_gan's own earlier layout (best_fid, one torch RNG state; the step and FID in config.json)."""
    gan = GANConfig(arch="vanilla-wgan-gp", **SMALL)
    train_gan(text_cache, tmp_path / "old", gan=gan, train=quick(max_steps=10), device="cpu", progress=False)
    state = load_state(tmp_path / "old")
    torch.save({"opt_g": state["opt_g"], "opt_d": state["opt_d"], "best_fid": state["best"],
                "rng": state["rng"][0]["torch"]}, tmp_path / "old" / "last" / "state.pt")
    outputs.record(tmp_path / "old" / "last")  # as the earlier version recorded its checkpoint
    resumed = train_gan(text_cache, tmp_path / "old", gan=gan, train=quick(), device="cpu", progress=False, resume=True)
    straight = train_gan(text_cache, tmp_path / "new", gan=gan, train=quick(), device="cpu", progress=False)
    assert resumed["best_val_latent_fid"] == straight["best_val_latent_fid"]
    assert resumed["last_val_latent_fid"] == straight["last_val_latent_fid"]
    a, _ = load_gan(tmp_path / "old", prefer="last")
    b, _ = load_gan(tmp_path / "new", prefer="last")
    for (k, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(x, y), k


def test_stale_cache_is_refused(text_cache: Path, tmp_path: Path) -> None:
    kw = dict(gan=GANConfig(arch="vanilla-gan", **SMALL), train=quick(max_steps=2), device="cpu", progress=False)
    with pytest.raises(StaleCache, match="another VAE"):
        train_gan(text_cache, tmp_path / "a", expect_vae_hash="vae-b", **kw)
    with pytest.raises(StaleCache, match="text encoder"):
        train_gan(text_cache, tmp_path / "b", expect_text_encoder="clip-vit-l-14", **kw)
    train_gan(text_cache, tmp_path / "c", expect_vae_hash="vae-a", expect_text_encoder="toy-encoder", **kw)
    # resuming a run on latents of another VAE
    other = tmp_path / "other.h5"
    toy_cache(other, vae_hash="vae-b")
    with pytest.raises(StaleCache, match="another VAE"):
        train_gan(other, tmp_path / "c", resume=True, **kw)


def test_divergence_stops_and_keeps_the_last_good_checkpoint(text_cache: Path, tmp_path: Path) -> None:
    gan = GANConfig(arch="vanilla-wgan-gp", **SMALL)
    train_gan(text_cache, tmp_path / "run", gan=gan, train=quick(max_steps=10), device="cpu", progress=False)
    with pytest.raises(TrainingDiverged, match="is (nan|inf|-inf) at step"):
        train_gan(text_cache, tmp_path / "run", gan=gan, train=quick(max_steps=100, lr=1e30), device="cpu",
                  progress=False, resume=True)
    assert read_meta(tmp_path / "run", "last")["step"] == 10
    model, _ = load_gan(tmp_path / "run", prefer="last")
    assert all(torch.isfinite(p).all() for p in model.parameters())
