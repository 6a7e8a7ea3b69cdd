"""The VAE's objective (lsgan.train.vae_loss), its learning-rate schedule and the bone-length figures."""
from __future__ import annotations

import csv
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lsgan.data.features import joints_to_features
from lsgan.data.skeleton import PARENTS, bone_lengths as np_bone_lengths
from lsgan.models.checkpoint import load_weights
from lsgan.motion.quality import bone_variation, quality_metrics
from lsgan.train.vae import VAETrainConfig, mld_vae_loss, reconstruction_errors, train_vae
from lsgan.data.bones import bone_lengths
from lsgan.train.vae_loss import CONTACT_JOINTS, LossWeights, kinematic_terms, vae_objective
from test_vae import TINY, _walk, shard  # noqa: F401  (the fixture)

pytestmark = pytest.mark.usefixtures("one_thread")


def _joints(seed: int, B: int = 2, T: int = 12) -> torch.Tensor:
    g = np.random.default_rng(seed)
    return torch.from_numpy(np.stack([_walk(T, 1.0 + 0.3 * b, 1.0, 0.4, 0.2 * b) for b in range(B)])
                            + 0.001 * g.standard_normal((B, T, 22, 3)))  # float64: accelerations are fps^2 x rounding


def _no_contact(j: torch.Tensor) -> torch.Tensor:
    return torch.zeros(j.shape[:2] + (4,), dtype=j.dtype)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10**6), shift=st.tuples(*[st.floats(-2, 2)] * 3))
def test_a_constant_shift_moves_only_the_joint_term(seed, shift):
    """Every joint moved by one vector on every frame: the same velocities, accelerations and bones."""
    j = _joints(seed)
    mask = torch.ones(j.shape[:2], dtype=torch.bool)
    terms = kinematic_terms(j + torch.tensor(shift, dtype=j.dtype), j, mask, _no_contact(j))
    for name in ("velocity", "accel", "bones"):
        assert float(terms[name]) == pytest.approx(0.0, abs=1e-4), name
    if max(map(abs, shift)) > 1e-3:
        assert float(terms["joints"]) > 0


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10**6), real=st.integers(4, 12))
def test_padded_frames_do_not_count(seed, real):
    """Whatever the padding holds, the terms of the real frames are the terms of the motion cut to them."""
    j, g = _joints(seed), torch.Generator().manual_seed(seed)
    j_hat = j + 0.01 * torch.randn(j.shape, generator=g, dtype=j.dtype)
    mask = torch.zeros(j.shape[:2], dtype=torch.bool)
    mask[:, :real] = True
    junk = j_hat.clone()
    junk[:, real:] = 100 * torch.randn(junk[:, real:].shape, generator=g, dtype=j.dtype)
    contacts = (torch.rand(j.shape[:2] + (4,), generator=g) > 0.5).to(j.dtype)
    padded = kinematic_terms(junk, j, mask, contacts)
    cut = kinematic_terms(j_hat[:, :real], j[:, :real], mask[:, :real], contacts[:, :real])
    for name in cut:
        assert float(padded[name]) == pytest.approx(float(cut[name]), rel=1e-5, abs=1e-7), name


def test_each_term_measures_what_it_says():
    j = _joints(0, B=1, T=10)
    mask = torch.ones(1, 10, dtype=torch.bool)
    stretched = j.clone()
    stretched[:, :, 21] += (j[:, :, 21] - j[:, :, PARENTS[21]]) * 0.1  # the right forearm 10% longer
    forearm = float(np.linalg.norm(j[0, :, 21] - j[0, :, PARENTS[21]], axis=-1).mean())
    terms = kinematic_terms(stretched, j, mask, _no_contact(j))
    assert float(terms["bones"]) == pytest.approx(0.1 * forearm / 21, rel=1e-3)
    assert np.allclose(bone_lengths(j).numpy(), np_bone_lengths(j.numpy())[..., 1:], atol=1e-6)
    jitter = j.clone()
    jitter[:, 5, 3, 0] += 0.01  # one joint, one frame, 1 cm: 0.2 m/s over two pairs, 4 m/s^2 over three triples
    terms = kinematic_terms(jitter, j, mask, _no_contact(j))
    assert float(terms["velocity"]) == pytest.approx(2 * 0.2 / (9 * 22), rel=1e-3)
    assert float(terms["accel"]) == pytest.approx((4 + 8 + 4) / (8 * 22), rel=1e-3)
    sliding = j.clone()
    sliding[:, :, list(CONTACT_JOINTS)] = j[:, :1, list(CONTACT_JOINTS)]  # the feet still, then sliding at 1 m/s
    sliding[:, :, list(CONTACT_JOINTS), 2] += torch.arange(10.0)[None, :, None] * 0.05
    down = torch.ones(1, 10, 4, dtype=j.dtype)
    assert float(kinematic_terms(sliding, sliding, mask, down)["contact"]) == pytest.approx(1.0, rel=1e-4)
    assert float(kinematic_terms(sliding, sliding, mask, 0 * down)["contact"]) == 0.0


def test_the_objective_adds_the_weighted_terms_and_mld_is_one_setting():
    raw = torch.from_numpy(joints_to_features(_walk(30, 1.2, 1.0, 0.4, 0.3))).float()[None]  # (1,T,263)
    mean, std = raw[0].mean(0), raw[0].std(0) + 0.1
    x = (raw - mean) / std
    x_hat = x + 0.05 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0))
    mu, logvar, mask = torch.zeros(1, 1, 8), torch.zeros(1, 1, 8), torch.ones(1, x.shape[1], dtype=torch.bool)
    w = LossWeights("smoothl1", joints=1.0, velocity=0.5, accel=0.02, bones=5.0, contact=0.5)
    out = vae_objective(x_hat, x, mu, logvar, mask, w, mean, std)
    added = out["recon"] + sum(getattr(w, k) * out[f"recon_{k}"] for k in ("joints", "velocity", "accel", "bones",
                                                                          "contact")) + w.kl * out["kl"]
    assert float(out["total"]) == pytest.approx(float(added), rel=1e-6)
    assert all(float(out[f"recon_{k}"]) > 0 for k in ("joints", "velocity", "accel", "bones"))
    mld = mld_vae_loss(x_hat, x, mu, logvar, mask, 1e-4, mean, std)
    assert set(mld) == {"total", "recon", "recon_joints", "kl"}
    assert float(mld["total"]) == pytest.approx(float(out["recon"] + out["recon_joints"]), rel=1e-6)
    assert VAETrainConfig(loss="mld").weights() == LossWeights("smoothl1", joints=1.0)
    assert not VAETrainConfig().weights().uses_joints
    assert VAETrainConfig(joint_weight=0.25).weights() == LossWeights("mse", joints=0.25)


def test_the_learning_rate_schedules():
    cfg = VAETrainConfig(lr=1e-3, max_steps=110, warmup_steps=10, lr_schedule="cosine")
    assert [cfg.lr_at(s) for s in (0, 4, 9)] == pytest.approx([1e-4, 5e-4, 1e-3])
    assert cfg.lr_at(10) == pytest.approx(1e-3) and cfg.lr_at(60) == pytest.approx(5e-4)
    assert cfg.lr_at(109) == pytest.approx(1e-3 * 0.5 * (1 + math.cos(math.pi * 99 / 100)))
    lrs = [cfg.lr_at(s) for s in range(10, 110)]
    assert all(a >= b for a, b in zip(lrs, lrs[1:]))
    assert replace(cfg, lr_schedule="constant").lr_at(100) == 1e-3
    for bad in (dict(lr_schedule="linear"), dict(bone_weight=-1.0), dict(velocity_weight=math.nan),
                dict(joint_weight=math.inf), dict(loss="mld", joint_weight=0.5)):
        with pytest.raises(ValueError):
            VAETrainConfig(**bad)


def test_a_resume_inside_the_warm_up_continues_the_schedule_and_the_new_terms(shard, tmp_path):
    """The learning rate comes from AdamW's restored step count: 6 steps then 12 == 12 uninterrupted steps."""
    cfg = VAETrainConfig(lr=1e-3, batch_size=4, max_steps=6, val_every=3, ckpt_every=6, log_every=3, seed=3,
                         loss="mld", velocity_weight=0.5, accel_weight=0.02, bone_weight=5.0, contact_weight=0.5,
                         warmup_steps=9)
    train_vae(shard, tmp_path / "a", model=TINY, train=cfg, device="cpu", progress=False)
    resumed = train_vae(shard, tmp_path / "a", model=TINY, train=replace(cfg, max_steps=12), device="cpu",
                        resume=True, progress=False)
    straight = train_vae(shard, tmp_path / "b", model=TINY, train=replace(cfg, max_steps=12), device="cpu",
                         progress=False)
    assert resumed == straight
    wa, wb = load_weights(tmp_path / "a", prefer="last")[0], load_weights(tmp_path / "b", prefer="last")[0]
    assert all(torch.equal(wa[k], wb[k]) for k in wb)
    rows = list(csv.DictReader(open(tmp_path / "b" / "log.csv")))
    assert [float(r["lr"]) for r in rows] == pytest.approx([1e-3 / 3, 2e-3 / 3, 1e-3, 1e-3])  # each row's last update
    assert {"recon_velocity", "recon_accel", "recon_bones", "recon_contact", "val_mpjpe_rel_m",
            "val_bone_std_mm"} <= set(rows[0])


def test_bone_variation_is_zero_for_a_rigid_motion_and_the_std_of_a_stretch():
    rigid = _walk(40, 1.0, 1.0, 0.4, 0.3)
    assert bone_variation(rigid) == pytest.approx(0.0, abs=1e-6)
    stretched = rigid.copy()
    amp = 0.01 * np.sin(np.arange(40) * 2 * np.pi / 10)  # the left toe moves 1 cm along its bone and back
    bone = rigid[:, 10] - rigid[:, PARENTS[10]]
    stretched[:, 10] += bone / np.linalg.norm(bone, axis=-1, keepdims=True) * amp[:, None]
    assert bone_variation(stretched) == pytest.approx(amp.std() * 1000 / 21, rel=1e-6)
    assert quality_metrics([rigid, stretched])["bone_std_mm"] == pytest.approx(amp.std() * 1000 / 42, rel=1e-6)


def test_validation_figures_match_the_quality_functions():
    """reconstruction_errors' bone figure is quality.bone_variation over the real frames of each motion."""
    raw = np.stack([joints_to_features(_walk(24, 1.0 + 0.2 * b, 1.0, 0.4, 0.2)) for b in range(2)])
    x = torch.from_numpy(raw).float()
    noisy = x + 0.02 * torch.randn(x.shape, generator=torch.Generator().manual_seed(1))
    mask = torch.ones(x.shape[:2], dtype=torch.bool)
    mask[1, 15:] = False
    zero, one = torch.zeros(x.shape[-1]), torch.ones(x.shape[-1])
    got = reconstruction_errors(noisy, x, mask, zero, one)
    from lsgan.data.features import recover_from_ric

    joints = [recover_from_ric(noisy[0].numpy()), recover_from_ric(noisy[1, :15].numpy())]
    assert got["motions"] == 2 and got["frames"] == x.shape[1] + 15
    assert got["bone_std_mm"] / 2 == pytest.approx(quality_metrics(joints)["bone_std_mm"], rel=1e-4)
    assert reconstruction_errors(x, x, mask, zero, one)["mpjpe_rel_m"] == 0.0


def test_a_resume_that_changes_the_objective_says_so(shard, tmp_path, capsys):
    cfg = VAETrainConfig(lr=1e-3, batch_size=4, max_steps=4, val_every=4, ckpt_every=4, log_every=2, seed=3,
                         loss="mld", bone_weight=1.0, lr_schedule="cosine")
    train_vae(shard, tmp_path, model=TINY, train=cfg, device="cpu", progress=False)
    capsys.readouterr()
    train_vae(shard, tmp_path, model=TINY, train=replace(cfg, max_steps=6), device="cpu", resume=True, progress=False)
    said = capsys.readouterr().err
    assert "max_steps 4 -> 6 (the cosine now ends there)" in said and "bone_weight" not in said
    train_vae(shard, tmp_path, model=TINY, train=replace(cfg, max_steps=8, lr_schedule="constant", bone_weight=2.0),
              device="cpu", resume=True, progress=False)
    said = capsys.readouterr().err
    assert "bone_weight 1.0 -> 2.0" in said and "lr_schedule 'cosine' -> 'constant'" in said


@pytest.mark.parametrize("frames", [1, 2, 3])
def test_windows_too_short_for_a_velocity_or_acceleration_still_train(frames):
    """A window of 1 frame has no velocity and one of 2 no acceleration: those terms are 0, not an error."""
    x = torch.randn(2, frames, 263, generator=torch.Generator().manual_seed(frames))
    x_hat = (x + 0.1).requires_grad_()
    mask = torch.ones(2, frames, dtype=torch.bool)
    w = LossWeights("smoothl1", joints=1.0, velocity=1.0, accel=1.0, bones=1.0, contact=1.0)
    out = vae_objective(x_hat, x, torch.zeros(2, 4), torch.zeros(2, 4), mask, w, torch.zeros(263), torch.ones(263))
    out["total"].backward()
    out = {k: float(v.detach()) for k, v in out.items()}
    assert torch.isfinite(x_hat.grad).all() and out["recon"] > 0
    assert (out["recon_velocity"] == 0) == (frames < 2) and (out["recon_accel"] == 0) == (frames < 3)


def test_a_contact_label_is_its_frame_and_the_next():
    """Frame t's contact label (features 259:263) is computed from the pair (t, t+1): the term reads it there."""
    j = _joints(0, B=1, T=6)
    still = j.clone()
    still[:, :, list(CONTACT_JOINTS)] = j[:, :1, list(CONTACT_JOINTS)]
    still[:, 3:, list(CONTACT_JOINTS), 0] += 0.05  # the feet jump 5 cm between frames 2 and 3, nowhere else
    mask = torch.ones(1, 6, dtype=torch.bool)
    label = torch.zeros(1, 6, 4, dtype=j.dtype)
    label[:, 2] = 1.0  # frame 2's label: the pair (2, 3)
    assert float(kinematic_terms(still, still, mask, label)["contact"]) == pytest.approx(0.05 * 20, rel=1e-6)
    label = torch.zeros(1, 6, 4, dtype=j.dtype)
    label[:, 3] = 1.0  # the pair (3, 4): the feet are still
    assert float(kinematic_terms(still, still, mask, label)["contact"]) == pytest.approx(0.0, abs=1e-9)


def test_squared_terms_average_the_squared_error():
    """kinematic='squared': one 1 cm jitter gives (0.2 m/s)^2 on two pairs, (4, 8, 4 m/s^2)^2 on three triples."""
    j = _joints(0, B=1, T=10)
    jitter = j.clone()
    jitter[:, 5, 3, 0] += 0.01
    mask = torch.ones(1, 10, dtype=torch.bool)
    terms = kinematic_terms(jitter, j, mask, _no_contact(j), kinematic="squared")
    assert float(terms["velocity"]) == pytest.approx(2 * 0.2**2 / (9 * 22), rel=1e-3)
    assert float(terms["accel"]) == pytest.approx((16 + 64 + 16) / (8 * 22), rel=1e-3)
    assert VAETrainConfig(kinematic_loss="squared").weights().kinematic == "squared"
    with pytest.raises(ValueError, match="kinematic_loss"):
        VAETrainConfig(kinematic_loss="l1")


def test_every_row_of_the_fidelity_benchmark_is_a_valid_config_over_the_bandai_recipe():
    """The ablation's rows override the recipe: a row that inherits a recipe value it contradicts (the joint
    weight with MLD's loss) would only fail an hour into a benchmark run."""
    from importlib.util import module_from_spec, spec_from_file_location

    from lsgan.models.vae import VAEConfig
    from lsgan.recipes import configs, load_recipe

    spec = spec_from_file_location("fidelity", Path(__file__).resolve().parents[1] / "benchmarks" / "fidelity.py")
    fidelity = module_from_spec(spec)
    spec.loader.exec_module(fidelity)
    recipe = load_recipe("bandai")
    for name, (_, train, model) in fidelity.ROWS.items():
        _, cfg = configs(recipe, "vae", VAEConfig, VAETrainConfig, model_overrides=model, train_overrides=train)
        own = train.get("joint_weight", recipe["vae"]["train"].get("joint_weight", 0.0))
        assert cfg.weights().joints == (1.0 if cfg.loss == "mld" else own), name
