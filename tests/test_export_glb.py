"""Tests for the hand-written glTF 2.0 binary exporter (lsgan.export.glb)."""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lsgan.data.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS
from lsgan.data.synthetic import generate
from lsgan.export.glb import joints_to_glb, write_glb

_DTYPES = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


@pytest.fixture(scope="module")
def clips():
    return generate(2, seed=0)


def _parse(data: bytes) -> tuple[dict, bytes]:
    """Split GLB bytes into (JSON dict, BIN chunk), checking the container layout."""
    magic, version, total = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and total == len(data) and total % 4 == 0
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON" and json_len % 4 == 0
    doc = json.loads(data[20:20 + json_len].decode("utf-8"))
    bin_len, bin_type = struct.unpack_from("<I4s", data, 20 + json_len)
    assert bin_type == b"BIN\0" and bin_len % 4 == 0
    assert 28 + json_len + bin_len == total
    blob = data[28 + json_len:]
    assert doc["buffers"][0]["byteLength"] <= bin_len
    return doc, blob


def _accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    assert view["byteOffset"] % 4 == 0
    width = _WIDTHS[acc["type"]]
    dtype = _DTYPES[acc["componentType"]]
    arr = np.frombuffer(blob, dtype=dtype, count=acc["count"] * width,
                        offset=view["byteOffset"] + acc.get("byteOffset", 0))
    assert arr.nbytes <= view["byteLength"]
    return arr.reshape(acc["count"], width) if width > 1 else arr


def _joint_nodes(doc: dict) -> dict[str, int]:
    return {n["name"]: i for i, n in enumerate(doc["nodes"]) if n.get("name") in JOINT_NAMES}


def _animated_positions(doc: dict, blob: bytes) -> np.ndarray:
    """World positions (T,22,3) of the joint nodes, by FK over the node tree with the sampled channels."""
    anim = doc["animations"][0]
    nodes = [dict(n) for n in doc["nodes"]]
    tracks: dict[tuple[int, str], np.ndarray] = {}
    for ch in anim["channels"]:
        sampler = anim["samplers"][ch["sampler"]]
        tracks[ch["target"]["node"], ch["target"]["path"]] = _accessor(doc, blob, sampler["output"]).astype(np.float64)
    frames = next(iter(tracks.values())).shape[0]
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}
    index = _joint_nodes(doc)
    out = np.empty((frames, NUM_JOINTS, 3))
    for t in range(frames):
        world: dict[int, np.ndarray] = {}

        def transform(i: int) -> np.ndarray:
            if i not in world:
                m = np.eye(4)
                rot = tracks.get((i, "rotation"), [nodes[i].get("rotation", [0, 0, 0, 1])] * frames)[t]
                m[:3, :3] = Rotation.from_quat(rot).as_matrix()
                m[:3, 3] = tracks.get((i, "translation"), [nodes[i].get("translation", [0, 0, 0])] * frames)[t]
                world[i] = transform(parent[i]) @ m if i in parent else m
            return world[i]

        for k, joint_name in enumerate(JOINT_NAMES):
            out[t, k] = transform(index[joint_name])[:3, 3]
    return out


def test_glb_container_and_json(clips):
    joints = clips[0].joints
    frames = joints.shape[0]
    doc, blob = _parse(joints_to_glb(joints, fps=20.0, name="walk"))
    assert doc["asset"] == {"version": "2.0", "generator": "lsgan"}
    index = _joint_nodes(doc)
    assert sorted(index) == sorted(JOINT_NAMES)
    parent = {c: i for i, n in enumerate(doc["nodes"]) for c in n.get("children", [])}
    for k, joint_name in enumerate(JOINT_NAMES):
        if PARENTS[k] >= 0:
            assert parent[index[joint_name]] == index[JOINT_NAMES[PARENTS[k]]]
        assert "mesh" in doc["nodes"][index[joint_name]]
    root = doc["scenes"][doc["scene"]]["nodes"]
    assert len(root) == 1 and doc["nodes"][root[0]]["children"] == [index["pelvis"]]

    (anim,) = doc["animations"]
    paths = [(ch["target"]["node"], ch["target"]["path"]) for ch in anim["channels"]]
    assert sorted(n for n, p in paths if p == "rotation") == sorted(index.values())
    assert [n for n, p in paths if p == "translation"] == [index["pelvis"]]
    assert len(paths) == NUM_JOINTS + 1
    for sampler in anim["samplers"]:
        assert sampler["interpolation"] == "LINEAR"
        assert doc["accessors"][sampler["input"]]["count"] == frames
        assert doc["accessors"][sampler["output"]]["count"] == frames
        times = _accessor(doc, blob, sampler["input"])
        np.testing.assert_allclose(times, np.arange(frames) / 20.0, atol=1e-6)
        acc = doc["accessors"][sampler["input"]]
        assert acc["min"] == [pytest.approx(0.0)] and acc["max"] == [pytest.approx((frames - 1) / 20.0)]
    for ch in anim["channels"]:
        if ch["target"]["path"] == "rotation":
            quat = _accessor(doc, blob, anim["samplers"][ch["sampler"]]["output"])
            np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, atol=1e-5)

    for mesh in doc["meshes"]:
        for prim in mesh["primitives"]:
            pos = doc["accessors"][prim["attributes"]["POSITION"]]
            values = _accessor(doc, blob, prim["attributes"]["POSITION"])
            np.testing.assert_allclose(pos["min"], values.min(axis=0))
            np.testing.assert_allclose(pos["max"], values.max(axis=0))
            normals = _accessor(doc, blob, prim["attributes"]["NORMAL"])
            np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)
            assert _accessor(doc, blob, prim["indices"]).max() < pos["count"]
    assert len(doc["materials"]) == 1


@pytest.mark.parametrize("clip_index", [0, 1])
def test_animation_reproduces_joints(clips, clip_index):
    joints = clips[clip_index].joints
    doc, blob = _parse(joints_to_glb(joints, fps=20.0))
    error = np.abs(_animated_positions(doc, blob) - joints).max()
    assert error < 1e-3, error


def test_write_glb_loads_in_trimesh(tmp_path, clips):
    trimesh = pytest.importorskip("trimesh")
    path = write_glb(tmp_path / "out" / "clip.glb", clips[0].joints, fps=30.0)
    assert path.exists() and not list(path.parent.glob("*.tmp"))
    scene = trimesh.load(path, force="scene")
    assert len(scene.geometry) == NUM_JOINTS
    assert set(JOINT_NAMES) <= set(scene.graph.nodes)
    doc, _ = _parse(path.read_bytes())
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
    assert files == ["000_clip.glb", "001_clip.glb"]
    assert (tmp_path / "glb" / "000_clip.glb").read_bytes()[:4] == b"glTF"
    both = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--glb", "--bvh", str(folder), "-o", "x"],
                          capture_output=True, text=True)
    assert both.returncode != 0 and "choose one format" in both.stderr


VALIDATOR = Path(__file__).resolve().parents[1] / "tools" / "gltf-validate"


def test_khronos_validator_reports_no_errors_or_warnings(tmp_path):
    import shutil
    import subprocess

    from lsgan.data.synthetic import generate

    if shutil.which("node") is None or not (VALIDATOR / "node_modules" / "gltf-validator").exists():
        pytest.skip("the Khronos glTF-Validator is not installed: run `npm install` in tools/gltf-validate (CI does)")
    path = tmp_path / "walk.glb"
    from lsgan.export.glb import write_glb

    write_glb(path, generate(1, seed=0)[0].joints)
    out = subprocess.run(["node", str(VALIDATOR / "validate.js"), str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"]

    # The check can fail: a POSITION accessor without its required bounds is an error for the validator.
    from lsgan.export.glb import gltf_document, pack_glb

    doc, blob = gltf_document(generate(1, seed=0)[0].joints, fps=20.0, name="broken")
    position = doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    doc["accessors"][position].pop("min")
    (tmp_path / "broken.glb").write_bytes(pack_glb(doc, blob))
    bad = subprocess.run(["node", str(VALIDATOR / "validate.js"), str(tmp_path / "broken.glb")], capture_output=True,
                         text=True, timeout=120)
    assert json.loads(bad.stdout)["errors"] > 0
