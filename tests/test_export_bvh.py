"""BVH export: round trip through lsgan's own reader, the header, rigid bones under noise, gzip, speed."""
from __future__ import annotations

import gzip
import time
from pathlib import Path

import numpy as np
import pytest

from lsgan.data.bvh import forward_kinematics, read_bvh
from lsgan.data.skeleton import BONE_LENGTHS, JOINT_NAMES, PARENTS, bone_lengths
from lsgan.data.synthetic import generate
from lsgan.export.bvh import UNITS_PER_METRE, joints_to_bvh, write_bvh
from lsgan.motion.fit import rest_offsets, shortest_arc

LEAVES = {"head", "left_foot", "right_foot", "left_wrist", "right_wrist"}


@pytest.fixture(scope="module")
def clips() -> list[np.ndarray]:
    return [c.joints for c in generate(3, seed=0)]  # walk, run, turn-left: exact target-skeleton bones


def _read_joints(path: Path) -> np.ndarray:
    """Positions (T,22,3) in metres, SMPL order, from a BVH file via lsgan's reader."""
    bvh = read_bvh(path)
    order = [bvh.names.index(name) for name in JOINT_NAMES]
    return forward_kinematics(bvh)[:, order] / UNITS_PER_METRE


def test_round_trip_is_within_a_millimetre(clips, tmp_path):
    assert generate(1, seed=0)[0].action == "walk"
    for k, joints in enumerate(clips):
        path = write_bvh(tmp_path / f"clip{k}.bvh", joints)
        back = _read_joints(path)
        assert back.shape == joints.shape
        assert np.abs(back - joints).max() < 1e-3


def test_header_names_channels_and_frame_time(clips, tmp_path):
    joints = clips[0]
    bvh = read_bvh(write_bvh(tmp_path / "a.bvh", joints))
    assert sorted(bvh.names) == sorted(JOINT_NAMES) and len(bvh.names) == 22
    assert bvh.names[0] == "pelvis" and bvh.parents[0] == -1
    for k, name in enumerate(bvh.names):
        parent = PARENTS[JOINT_NAMES.index(name)]
        assert (bvh.parents[k] == -1) if parent < 0 else (bvh.names[bvh.parents[k]] == JOINT_NAMES[parent])
    assert bvh.channels[0] == ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
    assert all(c == ("Zrotation", "Yrotation", "Xrotation") for c in bvh.channels[1:])
    assert bvh.motion.shape == (len(joints), 6 + 3 * 21)
    assert bvh.frame_time == pytest.approx(0.05) and bvh.fps == 20.0
    text = joints_to_bvh(joints)
    assert "Frame Time: 0.05000000" in text and f"Frames: {len(joints)}" in text
    assert text.count("End Site") == len(LEAVES)
    assert read_bvh(write_bvh(tmp_path / "b.bvh", joints, fps=30)).fps == 30.0


def test_noisy_bone_lengths_round_trip_with_rigid_bones(clips, tmp_path):
    joints = clips[0] + np.random.default_rng(0).normal(0.0, 5e-4, clips[0].shape).astype(np.float32)
    assert np.ptp(bone_lengths(joints)[:, 1:], axis=0).max() > 1e-3  # the input's bones do stretch
    back = _read_joints(write_bvh(tmp_path / "noisy.bvh", joints))
    assert np.abs(back - joints).max() < 6e-3
    assert np.ptp(bone_lengths(back), axis=0).max() < 1e-6  # rigid by construction


def test_gzip_copy_reads_the_same(clips, tmp_path):
    path = write_bvh(tmp_path / "sub" / "c.bvh", clips[1])
    gz = tmp_path / "c.bvh.gz"
    gz.write_bytes(gzip.compress(path.read_bytes()))
    np.testing.assert_array_equal(read_bvh(gz).motion, read_bvh(path).motion)
    assert not list(path.parent.glob("*.tmp"))  # the atomic write left no temporary file


def test_offsets_override_sets_the_rest_pose(clips, tmp_path):
    offsets = rest_offsets(clips[0])  # same target skeleton as clips[1]
    np.testing.assert_allclose(np.linalg.norm(offsets, axis=-1), BONE_LENGTHS, atol=1e-5)
    assert offsets[4, 1] < 0 and offsets[10, 2] > 0 and offsets[18, 1] < 0  # knee down, foot forward, arm down
    path = write_bvh(tmp_path / "fixed.bvh", clips[1], offsets=offsets)
    bvh = read_bvh(path)
    order = [bvh.names.index(name) for name in JOINT_NAMES]
    np.testing.assert_allclose(bvh.offsets[order], offsets * UNITS_PER_METRE, atol=1e-5)
    assert np.abs(_read_joints(path) - clips[1]).max() < 1e-3
    with pytest.raises(ValueError):
        joints_to_bvh(clips[0], offsets=np.zeros((21, 3)))


def test_shortest_arc_handles_opposite_vectors():
    a = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    b = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    r = shortest_arc(a, b)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", r, a), b, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0)


def test_bad_input_is_rejected():
    with pytest.raises(ValueError):
        joints_to_bvh(np.zeros((5, 21, 3)))
    with pytest.raises(ValueError):
        joints_to_bvh(np.full((5, 22, 3), np.nan))
    with pytest.raises(ValueError):
        joints_to_bvh(np.zeros((5, 22, 3)) + np.arange(22)[:, None] * 0.1, fps=0)
    with pytest.raises(ValueError, match="positive and finite"):  # a Frame Time of 0 would follow
        joints_to_bvh(np.zeros((5, 22, 3)) + np.arange(22)[:, None] * 0.1, fps=float("inf"))


def test_export_is_fast(clips):
    joints = np.concatenate(clips)[:196]
    joints_to_bvh(joints)
    start = time.perf_counter()
    joints_to_bvh(joints)
    assert time.perf_counter() - start < 0.5  # ~20 ms measured; generous for loaded CI machines


def test_export_command_writes_bvh_for_joints_features_and_folders(tmp_path):
    import subprocess
    import sys

    from lsgan.data.bvh import forward_kinematics, read_bvh
    from lsgan.data.features import joints_to_features
    from lsgan.data.skeleton import JOINT_NAMES
    from lsgan.data.synthetic import generate

    clip = generate(1, seed=3)[0]
    folder = tmp_path / "gen"
    folder.mkdir()
    np.save(folder / "000_walk_joints.npy", clip.joints)
    np.save(tmp_path / "feats.npy", joints_to_features(clip.joints))

    def run(*args):
        return subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--bvh", *map(str, args)],
                              capture_output=True, text=True)

    assert run(folder, "-o", tmp_path / "bvh").returncode == 0
    bvh = read_bvh(tmp_path / "bvh" / "000_walk.bvh")
    back = forward_kinematics(bvh)[:, [bvh.names.index(n) for n in JOINT_NAMES]] / 100.0
    assert np.abs(back - clip.joints).max() < 1e-3
    assert run(tmp_path / "feats.npy", "--fps", 30, "-o", tmp_path / "f.bvh").returncode == 0
    assert abs(read_bvh(tmp_path / "f.bvh").frame_time - 1 / 30) < 1e-6
    (tmp_path / "bad.npy").write_bytes(b"junk")
    bad = run(tmp_path / "bad.npy", "-o", tmp_path / "x.bvh")
    assert bad.returncode == 1 and "bad.npy" in bad.stderr and "not a .npy" in bad.stderr
