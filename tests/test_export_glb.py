"""Tests for the hand-written glTF 2.0 binary exporter (lsgan.export.glb)."""
from __future__ import annotations

import numpy as np
import pytest
from gltf_reader import accessor, frame_count, parse, skinned_vertices, validate, world_matrices

from lsgan.data.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS
from lsgan.data.synthetic import generate
from lsgan.motion.fit import CHILDREN
from lsgan.export.glb import joints_to_glb, write_glb


@pytest.fixture(scope="module")
def clips():
    return generate(2, seed=0)


def _joint_nodes(doc: dict) -> dict[str, int]:
    return {n["name"]: i for i, n in enumerate(doc["nodes"]) if n.get("name") in JOINT_NAMES}


def _animated_positions(doc: dict, blob: bytes) -> np.ndarray:
    """World positions (T,22,3) of the joint nodes, by FK over the node tree with the sampled channels."""
    index = [_joint_nodes(doc)[name] for name in JOINT_NAMES]
    return np.stack([world_matrices(doc, blob, t)[index, :3, 3] for t in range(frame_count(doc, blob))])


def test_glb_container_and_json(clips):
    joints = clips[0].joints
    frames = joints.shape[0]
    doc, blob = parse(joints_to_glb(joints, fps=20.0, name="walk"))
    assert doc["asset"] == {"version": "2.0", "generator": "lsgan"}
    index = _joint_nodes(doc)
    assert sorted(index) == sorted(JOINT_NAMES)
    parent = {c: i for i, n in enumerate(doc["nodes"]) for c in n.get("children", [])}
    for k, joint_name in enumerate(JOINT_NAMES):
        if PARENTS[k] >= 0:
            assert parent[index[joint_name]] == index[JOINT_NAMES[PARENTS[k]]]
        assert "mesh" not in doc["nodes"][index[joint_name]]  # the joints are a skin's, not rigid meshes
    root = doc["scenes"][doc["scene"]]["nodes"]
    assert len(root) == 2 and doc["nodes"][root[0]]["children"] == [index["pelvis"]]
    (skin,) = doc["skins"]
    mesh_node = doc["nodes"][root[1]]
    assert mesh_node["skin"] == 0 and "children" not in mesh_node and "translation" not in mesh_node
    assert skin["joints"] == [index[n] for n in JOINT_NAMES] and skin["skeleton"] == index["pelvis"]

    (anim,) = doc["animations"]
    paths = [(ch["target"]["node"], ch["target"]["path"]) for ch in anim["channels"]]
    assert sorted(n for n, p in paths if p == "rotation") == sorted(index.values())
    assert [n for n, p in paths if p == "translation"] == [index["pelvis"]]
    assert len(paths) == NUM_JOINTS + 1
    for sampler in anim["samplers"]:
        assert sampler["interpolation"] == "LINEAR"
        assert doc["accessors"][sampler["input"]]["count"] == frames
        assert doc["accessors"][sampler["output"]]["count"] == frames
        times = accessor(doc, blob, sampler["input"])
        np.testing.assert_allclose(times, np.arange(frames) / 20.0, atol=1e-6)
        acc = doc["accessors"][sampler["input"]]
        assert acc["min"] == [pytest.approx(0.0)] and acc["max"] == [pytest.approx((frames - 1) / 20.0)]
    for ch in anim["channels"]:
        if ch["target"]["path"] == "rotation":
            quat = accessor(doc, blob, anim["samplers"][ch["sampler"]]["output"])
            np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, atol=1e-5)

    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            pos = doc["accessors"][prim["attributes"]["POSITION"]]
            values = accessor(doc, blob, prim["attributes"]["POSITION"])
            np.testing.assert_allclose(pos["min"], values.min(axis=0))
            np.testing.assert_allclose(pos["max"], values.max(axis=0))
            normals = accessor(doc, blob, prim["attributes"]["NORMAL"])
            np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)
            assert accessor(doc, blob, prim["indices"]).max() < pos["count"]
    assert len(doc["materials"]) == 1


@pytest.mark.parametrize("clip_index", [0, 1])
def test_animation_reproduces_joints(clips, clip_index):
    joints = clips[clip_index].joints
    doc, blob = parse(joints_to_glb(joints, fps=20.0))
    error = np.abs(_animated_positions(doc, blob) - joints).max()
    assert error < 1e-3, error


@pytest.mark.parametrize("clip_index", [0, 1])
def test_skinned_mesh_follows_the_joints(clips, clip_index):
    """glTF's skinning formula puts every joint's sphere (its first 42 vertices, an icosphere) around that joint
    at every frame, and the bones' capsules between the joints they join."""
    joints = clips[clip_index].joints
    doc, blob = parse(joints_to_glb(joints, fps=20.0))
    mesh_node = doc["scenes"][0]["nodes"][1]
    prim = doc["meshes"][0]["primitives"][0]
    bound = accessor(doc, blob, prim["attributes"]["JOINTS_0"])[:, 0]
    weights = accessor(doc, blob, prim["attributes"]["WEIGHTS_0"])
    np.testing.assert_array_equal(weights[:, 0], 1.0)
    assert sorted(set(bound.tolist())) == list(range(NUM_JOINTS))
    for frame in (0, len(joints) // 2, len(joints) - 1):
        verts = skinned_vertices(doc, blob, frame, mesh_node=mesh_node)
        for k in range(NUM_JOINTS):
            sphere = verts[np.flatnonzero(bound == k)[:42]]
            assert np.abs(sphere.mean(axis=0) - joints[frame, k]).max() < 1e-3
            assert np.linalg.norm(sphere - joints[frame, k], axis=1).max() < 0.021  # JOINT_RADIUS, placed right
        verts_of = {k: verts[np.flatnonzero(bound == k)[42:]] for k in range(NUM_JOINTS)}
        for c, p in enumerate(PARENTS):  # each bone's capsule lies along the segment from its joint to the child
            if p < 0 or len(CHILDREN[p]) != 1:
                continue
            seg = joints[frame, c] - joints[frame, p]
            rel = verts_of[p] - joints[frame, p]
            along = rel @ seg / (seg @ seg)
            assert along.min() > -0.1 and along.max() < 1.1


def test_write_glb_loads_in_trimesh(tmp_path, clips):
    trimesh = pytest.importorskip("trimesh")
    path = write_glb(tmp_path / "out" / "clip.glb", clips[0].joints, fps=30.0)
    assert path.exists() and not list(path.parent.glob("*.tmp"))
    scene = trimesh.load(path, force="scene")
    assert len(scene.geometry) == 1  # one skinned mesh
    assert set(JOINT_NAMES) <= set(scene.graph.nodes)
    doc, _ = parse(path.read_bytes())
    assert doc["extras"]["fps"] == 30.0


@pytest.mark.parametrize("bad", [np.zeros((5, 21, 3)), np.zeros((22, 3)), np.zeros((0, 22, 3))])
def test_bad_shape_raises(bad):
    with pytest.raises(ValueError):
        joints_to_glb(bad)


def test_nan_and_bad_fps_raise(clips):
    joints = clips[0].joints.copy()
    with pytest.raises(ValueError):
        joints_to_glb(joints, fps=0.0)
    joints[3, 4, 1] = np.nan
    with pytest.raises(ValueError):
        joints_to_glb(joints)


def test_export_command_writes_glb(tmp_path):
    import subprocess
    import sys

    from lsgan.data.synthetic import generate

    folder = tmp_path / "gen"
    folder.mkdir()
    for i, clip in enumerate(generate(2, seed=1)):
        np.save(folder / f"{i:03d}_clip_joints.npy", clip.joints)
    out = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--glb", str(folder), "-o", str(tmp_path / "glb")],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    files = sorted(p.name for p in (tmp_path / "glb").iterdir())
    assert files == [".lsgan-outputs.json", "000_clip.glb", "001_clip.glb"]  # the registry of what lsgan wrote
    assert (tmp_path / "glb" / "000_clip.glb").read_bytes()[:4] == b"glTF"
    both = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--glb", "--bvh", str(folder), "-o", "x"],
                          capture_output=True, text=True)
    assert both.returncode != 0 and "choose one format" in both.stderr


def test_khronos_validator_reports_no_errors_or_warnings(tmp_path):
    from lsgan.export.glb import gltf_document, pack_glb

    path = tmp_path / "walk.glb"
    write_glb(path, generate(1, seed=0)[0].joints)
    report = validate(path)
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"]

    # The check can fail: a POSITION accessor without its required bounds is an error for the validator.
    doc, blob = gltf_document(generate(1, seed=0)[0].joints, fps=20.0, name="broken")
    position = doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    doc["accessors"][position].pop("min")
    (tmp_path / "broken.glb").write_bytes(pack_glb(doc, blob))
    assert validate(tmp_path / "broken.glb")["errors"] > 0
