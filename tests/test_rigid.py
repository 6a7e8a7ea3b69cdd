"""One motion of record (lsgan.motion.rigid): a generated motion is made rigid once, right after decoding, and every
output shows that motion: ``generate``'s ``_joints.npy``, ``export --glb|--bvh`` and what ``lsgan serve`` sends.
The model tests run on 100 motions of a really trained tiny model (conftest's ``serve_models``)."""
from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from cli_runs import lsgan
from gltf_reader import frame_count, node_index, parse, world_matrices

from lsgan.data.bvh import forward_kinematics, read_bvh
from lsgan.data.features import joints_to_features, recover_from_ric
from lsgan.data.skeleton import BONE_LENGTHS, JOINT_NAMES, PARENTS, bone_lengths
from lsgan.data.synthetic import generate as synthetic_clips
from lsgan.motion.rigid import make_rigid

MM = 1e-3
PROMPTS = ["a person walks forward#60", "someone waves the left hand#48", "a man jumps#80", "a woman squats down#40",
           "a person turns around twice#100"]


def recovered_clip(seed: int = 0) -> np.ndarray:
    """Joints (T,22,3) of a synthetic clip through its features: rigid, on the training skeleton."""
    return recover_from_ric(joints_to_features(synthetic_clips(1, seed=seed)[0].joints)).astype(np.float64)


def stretched(joints: np.ndarray, seed: int = 0) -> np.ndarray:
    """``joints`` with every bone's length scaled by a random factor per frame (0.8-1.2), as a decoder's drift; every
    bone keeps its direction."""
    rng = np.random.default_rng(seed)
    parents = list(PARENTS)
    bones = joints[:, 1:] - joints[:, parents[1:]]
    bones = bones * rng.uniform(0.8, 1.2, size=bones.shape[:2] + (1,))
    out = joints.copy()
    for k in range(1, len(parents)):  # parents first
        out[:, k] = out[:, parents[k]] + bones[:, k - 1]
    return out


def test_a_rigid_motion_is_kept() -> None:
    """A motion that is already rigid (a training clip's joints) comes back as it is."""
    j = recovered_clip()
    np.testing.assert_allclose(make_rigid(j), j, atol=1e-5, rtol=0)


def test_bones_get_one_length_and_keep_their_directions() -> None:
    raw = stretched(recovered_clip(1))
    lengths = bone_lengths(raw)
    rigid = make_rigid(raw).astype(np.float64)
    got = bone_lengths(rigid)
    assert np.abs(got - np.median(lengths, axis=0)).max() < 1e-5  # each motion's median, in every frame
    np.testing.assert_allclose(rigid[:, 0], raw[:, 0], atol=1e-6)  # the root is where it was
    single = [k for k in range(1, 22) if list(PARENTS).count(PARENTS[k]) == 1]  # the bones with no sibling
    def direction(j: np.ndarray) -> np.ndarray:
        bones = j[:, single] - j[:, [PARENTS[k] for k in single]]
        return bones / np.linalg.norm(bones, axis=-1, keepdims=True)

    assert np.sum(direction(rigid) * direction(raw), axis=-1).min() > 1 - 1e-9
    trained = bone_lengths(make_rigid(raw, BONE_LENGTHS).astype(np.float64))
    assert np.abs(trained - BONE_LENGTHS).max() < 1e-5  # the training skeleton when asked


def test_batched_equals_one_by_one_and_bad_frames_stay() -> None:
    a, b = stretched(recovered_clip(2)[:50], 3), stretched(recovered_clip(3)[:50], 4)
    both = make_rigid(np.stack([a, b]))
    np.testing.assert_array_equal(both[0], make_rigid(a))
    np.testing.assert_array_equal(both[1], make_rigid(b))
    a[7, 3] = np.nan
    got = make_rigid(a)
    assert np.isnan(got[7, 3]).all() and np.isfinite(np.delete(got, 7, axis=0)).all()
    with pytest.raises(ValueError, match="joints must be"):
        make_rigid(np.zeros((10, 21, 3)))


# ---- a trained tiny model: generate, export, serve ------------------------------------------------------------------

def glb_joints(data: bytes) -> np.ndarray:
    """World positions (T,22,3) of the GLB's joint nodes at every frame."""
    doc, blob = parse(data)
    index = [node_index(doc)[n] for n in JOINT_NAMES]
    return np.stack([world_matrices(doc, blob, t)[index, :3, 3] for t in range(frame_count(doc, blob))])


def bvh_joints(path: Path) -> np.ndarray:
    """Positions (T,22,3) in metres by FK of a written BVH (lsgan's reader)."""
    bvh = read_bvh(path)
    return forward_kinematics(bvh)[:, [bvh.names.index(n) for n in JOINT_NAMES]] / 100.0


def assert_rigid(joints: np.ndarray) -> None:
    lengths = bone_lengths(np.asarray(joints, np.float64))
    assert (lengths.max(axis=0) - lengths.min(axis=0)).max() < 1e-4


@pytest.fixture(scope="module")
def made(serve_models: Path, tmp_path_factory) -> Path:
    """100 motions (5 prompts x 20, 40-100 frames) with their decoded joints, and their GLB and BVH exports (feet as
    generated: ``--fix-feet`` is a deliberate edit of the motion)."""
    d = tmp_path_factory.mktemp("rigid")
    (d / "p.txt").write_text("\n".join(PROMPTS) + "\n")
    steps = [("generate", "--gan", "gan", "--vae", "vae", "--prompts", d / "p.txt", "--num", 20, "--seed", 5,
              "--raw-joints", "-o", d / "gen"),
             ("export", "--glb", d / "gen", "--no-fix-feet", "-o", d / "glb"),
             ("export", "--bvh", d / "gen", "--no-fix-feet", "-o", d / "bvh")]
    for step in steps:
        res = lsgan(*step, cwd=serve_models)
        assert res.returncode == 0, res.stderr
    return d


@pytest.mark.slow
def test_joints_glb_and_bvh_are_one_rigid_motion(made: Path) -> None:
    """Every joint of every frame of the GLB and the BVH within 1 mm of ``_joints.npy``, whose bones keep one length
    (1e-4 m); ``_joints_raw.npy`` holds the decoded joints, of which ``_joints.npy`` is the rigid motion."""
    entries = json.loads((made / "gen" / "manifest.json").read_text())["motions"]
    assert len(entries) == 100
    for e in entries:
        joints, raw = np.load(made / "gen" / e["joints"]), np.load(made / "gen" / e["raw_joints"])
        stem = e["joints"].removesuffix("_joints.npy")
        assert_rigid(joints)
        np.testing.assert_array_equal(raw, recover_from_ric(np.load(made / "gen" / e["features"])))
        np.testing.assert_allclose(joints, make_rigid(raw), atol=1e-6, rtol=0)
        assert np.abs(glb_joints((made / "glb" / f"{stem}.glb").read_bytes()) - joints).max() < MM, stem
        assert np.abs(bvh_joints(made / "bvh" / f"{stem}.bvh") - joints).max() < MM, stem
    assert sorted(p.name for p in (made / "glb").glob("*.glb")) == sorted(
        e["joints"].replace("_joints.npy", ".glb") for e in entries)  # the raw joints are not exported


@pytest.mark.slow
def test_the_server_sends_the_rigid_motion_in_every_format(serve_models: Path, tmp_path: Path) -> None:
    """``/v1/motions/ID.npy`` equals ``generate``'s ``_joints.npy`` for the same seed and is rigid; the served GLB
    and BVH pose it within 1 mm at every joint and frame."""
    from serve_client import Server

    res = lsgan("generate", "--gan", "gan", "--vae", "vae", "--text", "a man jumps", "--frames", 56, "--num", 2,
                "--seed", 9, "-o", tmp_path / "gen", cwd=serve_models)
    assert res.returncode == 0, res.stderr
    entries = json.loads((tmp_path / "gen" / "manifest.json").read_text())["motions"]
    s = Server("--gan", "gan", "--vae", "vae", cwd=serve_models)
    try:
        out = s.generate(text="a man jumps", frames=56, num=2, seed=9)
        for motion, e in zip(out["motions"], entries):
            joints = np.load(io.BytesIO(s.request("GET", motion["urls"]["npy"])[2]), allow_pickle=False)
            np.testing.assert_allclose(joints, np.load(tmp_path / "gen" / e["joints"]), atol=1e-5, rtol=0)
            assert_rigid(joints)
            assert np.abs(glb_joints(s.request("GET", motion["urls"]["glb"])[2]) - joints).max() < MM
            (tmp_path / "m.bvh").write_bytes(s.request("GET", motion["urls"]["bvh"])[2])
            assert np.abs(bvh_joints(tmp_path / "m.bvh") - joints).max() < MM
    finally:
        assert s.stop() == 0, s.stderr
