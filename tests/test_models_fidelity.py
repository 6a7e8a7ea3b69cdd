"""The models as the paper and its sources build them: the vanilla GANs layer by layer, MLD's VAE init, the recipes."""
from __future__ import annotations

import math
from dataclasses import asdict

import pytest
import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from lsgan.models.checkpoint import save_checkpoint
from lsgan.models.diffusion import DiffusionConfig
from lsgan.models.gan import GANConfig, LatentGAN, load_gan
from lsgan.models.vae import MotionVAE, VAEConfig
from lsgan.recipes import build, load_recipe, section
from lsgan.train.vae import VAETrainConfig

pytestmark = pytest.mark.usefixtures("one_thread")

SMALL = dict(noise_dim=8, hidden_dim=64, latent_dim=16, cond_dim=12)


def trace(module: nn.Module, *inputs: torch.Tensor) -> list[str]:
    """The Linear and LeakyReLU layers a forward pass runs through, in order: 'Linear(in->out)' or 'LeakyReLU'."""
    calls: list[str] = []

    def hook(m: nn.Module, args, out) -> None:
        calls.append(f"Linear({m.in_features}->{m.out_features})" if isinstance(m, nn.Linear) else "LeakyReLU")

    handles = [m.register_forward_hook(hook) for m in module.modules() if isinstance(m, (nn.Linear, nn.LeakyReLU))]
    try:
        module(*inputs)
    finally:
        for h in handles:
            h.remove()
    return calls


# ------------------------------------------------------------------------------------------------ vanilla GANs


@pytest.mark.parametrize("arch", ["vanilla-gan", "vanilla-wgan-gp"])
def test_vanilla_networks_are_the_papers_layer_by_layer(arch: str) -> None:
    # the authors' gan_architecture.py at hidden 512: G in->1024->512->Z, D in->1024->512->256->1, LeakyReLU after
    # every layer but the last (the paper: "leaky ReLU in all layers preceding the final layer")
    model = LatentGAN(GANConfig(arch=arch, noise_dim=100, latent_dim=256, cond_dim=768, hidden_dim=512))
    c, noise = torch.randn(3, 768), torch.randn(3, 100)
    assert trace(model.generator, noise, c) == [
        "Linear(868->1024)", "LeakyReLU", "Linear(1024->512)", "LeakyReLU", "Linear(512->256)"]
    assert trace(model.discriminator, torch.randn(3, 256), c) == [
        "Linear(1024->1024)", "LeakyReLU", "Linear(1024->512)", "LeakyReLU", "Linear(512->256)", "LeakyReLU",
        "Linear(256->1)"]


def test_the_leaky_slope_is_the_configured_one() -> None:
    g = LatentGAN(GANConfig(arch="vanilla-gan", leaky_slope=0.01, **SMALL)).generator
    slopes = {m.negative_slope for m in g.modules() if isinstance(m, nn.LeakyReLU)}
    assert slopes == {0.01}
    with torch.no_grad():  # the function really bends: a negative pre-activation is scaled by the slope
        x = torch.randn(5, 8 + 12)
        h = g.fc1(x)
        expect = g.fc3(torch.nn.functional.leaky_relu(g.fc2(torch.nn.functional.leaky_relu(h, 0.01)), 0.01))
        torch.testing.assert_close(g(x[:, :8], x[:, 8:]), expect)
        assert (h < 0).any()


def test_the_vanilla_generator_is_the_papers_flop_count() -> None:
    # The paper prints 1.581 G for the vanilla GAN: THOP multiply-accumulates at batch 1024 (method.md). Our vanilla
    # generator at a 768-d CLIP condition: 868*1024 + 1024*512 + 512*256 = 1,544,192 multiply-adds per clip.
    g = LatentGAN(GANConfig(arch="vanilla-gan", noise_dim=100, latent_dim=256, cond_dim=768, hidden_dim=512)).generator
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        g(torch.randn(1024, 100), torch.randn(1024, 768))
    macs = counter.get_total_flops() // 2
    assert macs == 1024 * (868 * 1024 + 1024 * 512 + 512 * 256)
    assert round(macs / 1e9, 3) == 1.581


def test_deep_networks_compute_what_their_checkpoints_were_trained_as() -> None:
    # deep: fc1 -> pre-activation residual blocks (no LeakyReLU in between) -> fc2 -> LeakyReLU -> fc3, all H wide;
    # a deep checkpoint written before the vanilla fix must load and give the same function
    g = LatentGAN(GANConfig(arch="deep-wgan-gp", **SMALL)).generator
    assert [tuple(p.shape) for p in g.parameters()] == [
        (64, 20), (64,), (64,), (64,), (64, 64), (64,), (64,), (64,), (64, 64), (64,), (64, 64), (64,), (16, 64),
        (16,)]
    noise, c = torch.randn(6, 8), torch.randn(6, 12)
    with torch.no_grad():
        x = g.fc1(torch.cat([noise, c], -1))
        for b in g.blocks:
            x = x + b.fc(torch.nn.functional.leaky_relu(b.norm(x), 0.2))
        torch.testing.assert_close(g(noise, c), g.fc3(torch.nn.functional.leaky_relu(g.fc2(x), 0.2)))


def test_an_old_vanilla_checkpoint_is_refused_by_name(tmp_path) -> None:
    cfg = GANConfig(arch="vanilla-gan", **SMALL)
    old = LatentGAN(cfg)
    old.generator.fc1 = nn.Linear(20, 64)  # the layout before the fix: H wide throughout
    old.generator.fc2 = nn.Linear(64, 64)
    save_checkpoint(tmp_path / "old", model=old, kind="gan", config={"gan": asdict(cfg)}, step=1)
    with pytest.raises(ValueError, match="before the vanilla networks followed the paper"):
        load_gan(tmp_path / "old")


# ---------------------------------------------------------------------------------------------------- VAE init


def _stack_matrices(vae: MotionVAE) -> dict[str, torch.Tensor]:
    return {n: p for n, p in vae.named_parameters() if n.startswith(("encoder.", "decoder.")) and p.dim() > 1}


def test_xavier_init_is_mlds() -> None:
    # MLD's SkipTransformerEncoder/Decoder._reset_parameters: xavier_uniform_ on every parameter with dim > 1 of the
    # skip stacks; biases, LayerNorms and everything outside the stacks keep torch's init.
    cfg = VAEConfig(d_model=64, num_layers=3, num_heads=4, ff_size=256, latent_dim=64, max_len=64)
    torch.manual_seed(0)
    default = MotionVAE(cfg)
    torch.manual_seed(0)
    xavier = MotionVAE(VAEConfig(**(asdict(cfg) | {"init": "xavier"})))
    mats = _stack_matrices(xavier)
    assert any(n.endswith("self_attn.in_proj_weight") for n in mats) and any("skip_proj" in n for n in mats)
    assert any(n.endswith("multihead_attn.out_proj.weight") for n in mats)  # the decoder's cross-attention too
    for name, w in mats.items():
        fan_out, fan_in = w.shape
        bound = math.sqrt(6.0 / (fan_in + fan_out))
        assert w.abs().max() <= bound and w.abs().max() > 0.95 * bound, name
        assert w.std().item() == pytest.approx(bound / math.sqrt(3), rel=0.08), name
    # linear2 (ff 256 -> d 64): torch's default bound is 1/sqrt(256) = 0.0625, xavier's sqrt(6/320) = 0.137
    w = default.state_dict()["encoder.middle_block.linear2.weight"]
    assert w.abs().max() <= 1 / 16 < 0.137 * 0.95
    for (name, a), b in zip(default.state_dict().items(), xavier.state_dict().values()):
        if name not in mats:
            assert torch.equal(a, b), name  # nothing else moved


def test_init_option_is_checked_and_defaults_to_torchs() -> None:
    assert VAEConfig().init == "default"
    with pytest.raises(ValueError, match="init must be"):
        VAEConfig(init="kaiming")


# ------------------------------------------------------------------------------------------------------ recipes


@pytest.mark.parametrize("name", ["humanml3d", "humanact12"])
def test_paper_recipes_use_mlds_vae_loss_and_init(name: str) -> None:
    vae = section(load_recipe(name), "vae")
    assert build(VAEConfig, vae["model"]).init == "xavier"
    train = build(VAETrainConfig, vae["train"])
    assert (train.loss, train.kl_weight, train.lr) == ("mld", 1e-4, 1e-4)
    assert train.weight_decay == 0.01  # MLD's AdamW(lr=...) keeps torch's default weight decay


@pytest.mark.parametrize("name", ["demo", "bandai", "bandai-gpu"])
def test_cpu_recipes_keep_the_default_init(name: str) -> None:
    assert build(VAEConfig, section(load_recipe(name), "vae")["model"]).init == "default"


def test_diffusion_recipes_follow_mlds_released_configs() -> None:
    hml = section(load_recipe("humanml3d"), "diffusion")
    assert hml["train"]["batch_size"] == 64  # MLD's README: --batch_size 64 (over TRAIN.BATCH_SIZE 128)
    act = build(DiffusionConfig, section(load_recipe("humanact12"), "diffusion")["model"])
    assert (act.sample_steps, act.eta, act.guidance_scale) == (50, 0.0, 7.5)  # modules_humanact12/scheduler.yaml


@pytest.mark.parametrize("name", ["humanml3d-vanilla-gan", "humanml3d-vanilla-wgan-gp"])
def test_vanilla_recipes_are_the_authors_networks(name: str) -> None:
    cfg = build(GANConfig, section(load_recipe(name), "gan")["model"])
    assert (cfg.hidden_dim, cfg.leaky_slope, cfg.cond_dim) == (512, 0.01, 768)
    assert cfg.widths("G") == (1024, 512) and cfg.widths("D") == (1024, 512, 256)
