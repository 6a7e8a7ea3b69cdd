"""The decoder's time filter and skeleton (lsgan.models.decoder_head): properties, and a real training run
through both (every decoded motion on the data's bones, saved and loaded with the weights)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lsgan.data.features import joints_to_features, recover_from_ric
from lsgan.data.shards import ClipRecord, write_shard
from lsgan.data.skeleton import TARGET_OFFSETS
from lsgan.models.decoder_head import smooth_time
from lsgan.data.bones import bone_lengths, on_skeleton, root_frame_joints, skeleton_lengths
from lsgan.models.vae import MotionVAE, VAEConfig, load_vae
from lsgan.train.vae import VAETrainConfig, train_vae
from test_vae import _walk

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = VAEConfig(d_model=32, num_layers=1, num_heads=4, ff_size=64, latent_dim=32, dropout=0.0, max_len=196,
                 smooth_output=1, rigid_output=True)
LENGTHS = torch.tensor(np.linalg.norm(TARGET_OFFSETS[1:], axis=-1), dtype=torch.float64)


def _mask(lengths: list[int], T: int) -> torch.Tensor:
    return torch.arange(T)[None] < torch.tensor(lengths)[:, None]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.01, 10.0))
def test_every_bone_gets_the_skeletons_length_and_nothing_else_moves(seed, scale):
    """Whatever the decoder says (random features, any scale), the projected joints have exactly the skeleton's
    bones, in the root's frame and in the world's; the root and every other feature are untouched."""
    g = torch.Generator().manual_seed(seed)
    f = torch.randn(3, 7, 263, generator=g, dtype=torch.float64) * scale
    out = on_skeleton(f, LENGTHS)
    assert torch.allclose(bone_lengths(root_frame_joints(out)), LENGTHS.expand(3, 7, 21), atol=1e-9)
    assert torch.allclose(bone_lengths(recover_from_ric(out)), LENGTHS.expand(3, 7, 21), atol=1e-9)
    assert torch.equal(out[..., :4], f[..., :4]) and torch.equal(out[..., 67:], f[..., 67:])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_a_motion_already_on_the_skeleton_is_left_as_it_is(seed):
    """Features of joints posed on the skeleton (random bone directions): the projection changes them by float
    rounding only, and the skeleton read back from them is the one they were posed on."""
    g = torch.Generator().manual_seed(seed)
    f = torch.randn(5, 263, generator=g, dtype=torch.float64)
    posed = on_skeleton(f, LENGTHS)
    assert torch.allclose(on_skeleton(posed, LENGTHS), posed, atol=1e-12)
    assert torch.allclose(skeleton_lengths(posed).double(), LENGTHS, atol=1e-6)


def test_a_zero_length_bone_takes_the_skeletons_length_upwards():
    f = torch.zeros(1, 263, dtype=torch.float64)  # every joint at the root
    j = root_frame_joints(on_skeleton(f, LENGTHS))[0]
    assert torch.allclose(bone_lengths(j), LENGTHS) and torch.all(j[1:, 1] > 0) and torch.all(j[:, [0, 2]] == 0)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), lengths=st.lists(st.integers(1, 12), min_size=1, max_size=4),
       passes=st.integers(1, 3))
def test_the_filter_never_reads_padding_and_keeps_a_constant(seed, lengths, passes):
    g = torch.Generator().manual_seed(seed)
    T = 12
    mask = _mask(lengths, T)
    x = torch.randn(len(lengths), T, 4, generator=g)
    noisy = torch.where(mask[..., None], x, torch.full_like(x, float("nan")))
    out = smooth_time(noisy, mask, passes)
    assert torch.equal(out[mask], smooth_time(x, mask, passes)[mask])  # NaN in padding reaches no real frame
    assert out[~mask].isnan().all()  # and padding comes out as it went in
    const = torch.ones(len(lengths), T, 4) * 3.5
    assert torch.allclose(smooth_time(const, mask, passes), const)


def test_one_pass_removes_the_frame_to_frame_alternation_and_keeps_a_ramp():
    mask = _mask([20], 20)
    alternating = (-1.0) ** torch.arange(20.0)[None, :, None]
    assert smooth_time(alternating, mask, 1)[0, 1:-1].abs().max() == 0
    ramp = torch.arange(20.0)[None, :, None]
    assert torch.equal(smooth_time(ramp, mask, 1)[0, 1:-1], ramp[0, 1:-1])


@pytest.mark.parametrize("bad", [-1, 9, 1.5, True])
def test_config_rejects_a_bad_pass_count(bad):
    with pytest.raises(ValueError, match="smooth_output"):
        VAEConfig(smooth_output=bad)


def test_an_unset_skeleton_decodes_to_nan_not_to_a_plausible_motion():
    vae = MotionVAE(TINY).eval()
    with torch.no_grad():
        assert vae.decode(torch.zeros(1, 32), _mask([10], 10)).isnan().any()


def _walks() -> list[np.ndarray]:
    """Joints of three short walks (test_vae's), on the training skeleton once they are features."""
    return [_walk(40 + 4 * k, 0.6 + 0.2 * k, 0.8, 0.4, 0.1 * k) for k in range(3)]


@pytest.fixture(scope="module")
def shard(tmp_path_factory) -> str:
    feats = joints_to_features(_walks())
    clips = [ClipRecord(f"t{k}-{i}", f, "train") for k in range(3) for i, f in enumerate(feats)]
    clips += [ClipRecord(f"v{i}", f, "val") for i, f in enumerate(feats)]
    path = tmp_path_factory.mktemp("head") / "walks.h5"
    write_shard(path, clips, source="test", action_names=[], provenance={})
    return str(path)


def test_a_trained_vae_decodes_every_motion_onto_the_datas_bones(shard, tmp_path):
    """A real run through the head: the skeleton it stores is the data's; any latent, even far outside the
    prior, decodes to joints whose bones keep those lengths in every frame, and the validation log says 0 mm."""
    cfg = VAETrainConfig(lr=2e-3, batch_size=8, max_steps=20, val_every=10, ckpt_every=10, log_every=10,
                         unit_length=1, seed=0)
    train_vae(shard, tmp_path, model=TINY, train=cfg, device="cpu", progress=False)
    vae, meta = load_vae(tmp_path)
    data_joints = recover_from_ric(joints_to_features(_walks())[0])
    assert torch.allclose(vae.head.lengths, bone_lengths(torch.as_tensor(data_joints[0])).float(), atol=1e-5)
    assert np.array_equal(vae.head.mean.numpy(), meta["mean"]) and np.array_equal(vae.head.std.numpy(), meta["std"])
    z = torch.randn(4, 32, generator=torch.Generator().manual_seed(1)) * 5
    with torch.no_grad():
        x = vae.decode(z, _mask([40, 33, 12, 3], 40))
    joints = recover_from_ric(x[0].double() * torch.as_tensor(meta["std"]).double() + torch.as_tensor(meta["mean"]))
    assert torch.allclose(bone_lengths(joints).float(), vae.head.lengths.expand(40, 21), atol=1e-4)
    assert (x[2, 12:] == 0).all() and (x[3, 3:] == 0).all()
    log = (tmp_path / "log.csv").read_text().splitlines()
    col = log[0].split(",").index("val_bone_std_mm")
    assert all(float(r.split(",")[col]) < 0.01 for r in log[1:] if r.split(",")[col])


def test_decoding_without_the_head_is_the_plain_decoder():
    """smooth_output 0 and rigid_output false add no module and no weights: checkpoints of before load as they were."""
    plain = MotionVAE(replace(TINY, smooth_output=0, rigid_output=False))
    assert plain.head is None and not any(k.startswith("head.") for k in plain.state_dict())


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_numpy_and_torch_put_features_on_the_skeleton_alike(seed):
    """One implementation for the decoder (torch) and a timeline's seams (numpy): the same numbers from both,
    with per-frame lengths as a seam uses them."""
    rng = np.random.default_rng(seed)
    f = rng.normal(size=(6, 263))
    per_frame = np.abs(rng.normal(0.2, 0.05, size=(6, 21))) + 0.01
    for lengths in (LENGTHS.numpy(), per_frame):
        np.testing.assert_allclose(on_skeleton(f, lengths), on_skeleton(torch.from_numpy(f), torch.from_numpy(lengths))
                                   .numpy(), atol=1e-12)
    np.testing.assert_allclose(skeleton_lengths(f), skeleton_lengths(torch.from_numpy(f)).numpy(), atol=1e-6)


def test_a_resume_on_other_data_decodes_on_that_datas_skeleton(shard, tmp_path):
    """Resumed on a shard of other statistics and bones, the head takes the new normalisation and skeleton (they are
    measured every run, not restored), so the checkpoint holds one normalisation and decodes rigid motion."""
    feats = [f.copy() for f in joints_to_features(_walks())]
    for f in feats:  # the root-relative joints and the root's height 20% larger: every bone 20% longer
        f[:, 3:67] *= 1.2
    other = tmp_path / "big.h5"
    write_shard(other, [ClipRecord(f"t{i}", f, "train") for i, f in enumerate(feats)]
                + [ClipRecord(f"v{i}", f, "val") for i, f in enumerate(feats)], source="test", action_names=[],
                provenance={})
    cfg = VAETrainConfig(lr=2e-3, batch_size=8, max_steps=6, val_every=3, ckpt_every=3, log_every=3, unit_length=1)
    train_vae(shard, tmp_path / "run", model=TINY, train=cfg, device="cpu", progress=False)
    first = load_vae(tmp_path / "run", prefer="last")[0].head.lengths.clone()
    train_vae(str(other), tmp_path / "run", model=TINY, train=replace(cfg, max_steps=12), device="cpu",
              progress=False, resume=True)
    vae, meta = load_vae(tmp_path / "run", prefer="last")
    assert meta["step"] == 12 and torch.allclose(vae.head.lengths, first * 1.2, rtol=1e-4)
    assert np.array_equal(vae.head.mean.numpy(), meta["mean"]) and np.array_equal(vae.head.std.numpy(), meta["std"])
    with torch.no_grad():
        x = vae.decode(torch.randn(2, 32, generator=torch.Generator().manual_seed(0)), _mask([30, 30], 30))
    f = x.double() * torch.from_numpy(meta["std"]).double() + torch.from_numpy(meta["mean"]).double()
    assert torch.allclose(bone_lengths(recover_from_ric(f)).float(), vae.head.lengths.expand(2, 30, 21), atol=1e-4)
