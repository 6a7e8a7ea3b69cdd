"""The 263-d representation against reference outputs of the original HumanML3D code."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from lsgan.data.features import (
    FOOT_CONTACT,
    GROUPS,
    joints_to_features,
    mirror_features,
    recover_from_ric,
    recover_from_rot,
    group_std,
)
from lsgan.data.skeleton import BONE_LENGTHS, MIRROR_PAIRS, TARGET_OFFSETS, bone_lengths, mirror_joints

CASES = ("rigid_scaled", "noisy", "mirrored_reversed")


@pytest.fixture(scope="module")
def reference(hml_fixtures):
    return np.load(hml_fixtures / "reference_features.npz")


def test_target_offsets_match_reference(reference):
    np.testing.assert_array_equal(TARGET_OFFSETS, reference["target_offsets"])


@pytest.mark.parametrize("case", CASES)
def test_features_match_reference_in_every_slice(reference, case):
    ours = joints_to_features(reference[f"{case}/joints_in"])
    ref = reference[f"{case}/features"]
    assert ours.shape == ref.shape == (169, 263)
    assert ours.dtype == np.float32
    for g in GROUPS:
        err = np.abs(ours[:, g] - ref[:, g]).max()
        assert err <= 1e-4, f"{case} slice {g}: max abs error {err:.2e}"
    np.testing.assert_array_equal(ours[:, FOOT_CONTACT], ref[:, FOOT_CONTACT])


@pytest.mark.parametrize("case", CASES)
def test_recovered_joints_match_reference(reference, case):
    feats = joints_to_features(reference[f"{case}/joints_in"])
    ref = reference[f"{case}/recovered_joints"]
    assert np.abs(recover_from_ric(feats) - ref).max() <= 1e-4
    assert np.abs(recover_from_rot(feats) - ref).max() <= 1e-4


def test_recover_from_ric_matches_new_joints(hml_fixtures):
    vecs = np.load(hml_fixtures / "new_joint_vecs" / "012314.npy")
    joints = np.load(hml_fixtures / "new_joints" / "012314.npy")
    assert np.abs(recover_from_ric(vecs) - joints).max() <= 1e-5
    # The torch path gives the same joints (it is used on batches during training).
    rec_t = recover_from_ric(torch.from_numpy(vecs)[None].repeat(2, 1, 1))
    assert rec_t.shape == (2, 170, 22, 3)
    assert torch.abs(rec_t - torch.from_numpy(joints)).max().item() <= 1e-5


def test_batched_equals_one_by_one(reference):
    clips = [reference[f"{c}/joints_in"][: 60 + 30 * i] for i, c in enumerate(CASES)]
    batched = joints_to_features(clips)
    for clip, feats in zip(clips, batched):
        np.testing.assert_allclose(feats, joints_to_features(clip), atol=1e-6)
        assert feats.shape == (len(clip) - 1, 263)


def test_features_are_invariant_to_placement_and_heading(reference):
    joints = reference["noisy/joints_in"].astype(np.float64)
    angle = 1.1
    rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    moved = joints @ rot.T + np.array([3.0, 0.5, -2.0])
    np.testing.assert_allclose(joints_to_features(moved), joints_to_features(joints), atol=2e-4)


def test_recovered_joints_have_target_bone_lengths(reference):
    feats = joints_to_features(reference["noisy/joints_in"])
    np.testing.assert_allclose(bone_lengths(recover_from_rot(feats))[:, 1:], np.broadcast_to(BONE_LENGTHS[1:], (169, 21)), atol=1e-5)


def test_mirror_joints_swaps_sides_and_is_an_involution(reference):
    joints = reference["noisy/joints_in"]
    m = mirror_joints(joints)
    for a, b in MIRROR_PAIRS:
        np.testing.assert_array_equal(m[:, a, 0], -joints[:, b, 0])
        np.testing.assert_array_equal(m[:, a, 1:], joints[:, b, 1:])
    np.testing.assert_array_equal(mirror_joints(m), joints)


def test_mirror_features_swap_the_sides_of_the_motion(reference):
    feats = joints_to_features(reference["noisy/joints_in"])
    mirrored = mirror_features(feats)
    # Left wrist height of the mirror = right wrist height of the original (heights are mirror-invariant).
    j, jm = recover_from_ric(feats)[:-1], recover_from_ric(mirrored)
    # Within 2 cm: the target skeleton is slightly asymmetric, so the mirror is retargeted.
    np.testing.assert_allclose(jm[..., 20, 1], j[..., 21, 1], atol=2e-2)
    # Turning reverses: the yaw rates are anti-correlated and the total turn changes sign.
    assert np.corrcoef(feats[1:-1, 0], mirrored[1:, 0])[0, 1] < -0.95
    assert abs(feats[:-1, 0].sum() + mirrored[:, 0].sum()) < 0.05 * abs(feats[:, 0]).sum()


def test_group_std_is_constant_per_group(hml_fixtures):
    std = np.load(hml_fixtures / "Std.npy")
    np.testing.assert_allclose(group_std(std), std, rtol=1e-5)
    raw = np.random.default_rng(0).uniform(0.1, 1.0, 263)
    grouped = group_std(raw)
    for g in GROUPS:
        assert np.allclose(grouped[g], raw[g].mean())


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match=r"\(T, 22, 3\)"):
        joints_to_features(np.zeros((10, 24, 3)))
    with pytest.raises(ValueError, match="at least 2 frames"):
        joints_to_features(np.zeros((1, 22, 3)))
