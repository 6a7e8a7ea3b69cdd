"""An independent reader of our GLB files for tests: container checks, accessors, animated node transforms,
linear blend skinning, and the Khronos validator."""
from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

DTYPES = {5126: np.float32, 5121: np.uint8, 5123: np.uint16, 5125: np.uint32}
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
VALIDATOR = Path(__file__).resolve().parents[1] / "tools" / "gltf-validate"


def parse(data: bytes) -> tuple[dict, bytes]:
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


def accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """The array behind accessor ``index`` ((count,width), or (count,) for scalars)."""
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    assert view["byteOffset"] % 4 == 0
    width = WIDTHS[acc["type"]]
    arr = np.frombuffer(blob, dtype=DTYPES[acc["componentType"]], count=acc["count"] * width,
                        offset=view["byteOffset"] + acc.get("byteOffset", 0))
    assert arr.nbytes <= view["byteLength"]
    return arr.reshape(acc["count"], width) if width > 1 else arr


def node_index(doc: dict) -> dict[str, int]:
    return {n["name"]: i for i, n in enumerate(doc["nodes"]) if "name" in n}


def world_matrices(doc: dict, blob: bytes, frame: int) -> np.ndarray:
    """World 4x4 matrices (N,4,4) of every node at animation sample ``frame`` (FK over the node tree)."""
    anim = doc["animations"][0]
    nodes = doc["nodes"]
    tracks: dict[tuple[int, str], np.ndarray] = {}
    for ch in anim["channels"]:
        out = accessor(doc, blob, anim["samplers"][ch["sampler"]]["output"]).astype(np.float64)
        tracks[ch["target"]["node"], ch["target"]["path"]] = out[frame]
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}
    world: dict[int, np.ndarray] = {}

    def transform(i: int) -> np.ndarray:
        if i not in world:
            m = np.eye(4)
            m[:3, :3] = Rotation.from_quat(tracks.get((i, "rotation"), nodes[i].get("rotation", [0, 0, 0, 1]))).as_matrix()
            m[:3, 3] = tracks.get((i, "translation"), nodes[i].get("translation", [0, 0, 0]))
            world[i] = transform(parent[i]) @ m if i in parent else m
        return world[i]

    return np.stack([transform(i) for i in range(len(nodes))])


def frame_count(doc: dict, blob: bytes) -> int:
    anim = doc["animations"][0]
    return int(doc["accessors"][anim["samplers"][0]["input"]]["count"])


def skinned_vertices(doc: dict, blob: bytes, frame: int, mesh_node: int = 0) -> np.ndarray:
    """Vertices (V,3) of the skinned mesh on ``mesh_node`` at sample ``frame``, by glTF's skinning formula."""
    node = doc["nodes"][mesh_node]
    skin = doc["skins"][node["skin"]]
    prim = doc["meshes"][node["mesh"]]["primitives"][0]
    rest = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
    joints = accessor(doc, blob, prim["attributes"]["JOINTS_0"]).astype(np.int64)
    weights = accessor(doc, blob, prim["attributes"]["WEIGHTS_0"]).astype(np.float64)
    ibm = accessor(doc, blob, skin["inverseBindMatrices"]).astype(np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
    world = world_matrices(doc, blob, frame)[skin["joints"]] @ ibm  # (J,4,4)
    homog = np.concatenate([rest, np.ones((len(rest), 1))], axis=1)
    per_joint = np.einsum("vkij,vj->vki", world[joints], homog)[..., :3]  # (V,4,3)
    return (weights[..., None] * per_joint).sum(axis=1)


def validate(path: Path) -> dict:
    """The Khronos glTF-Validator's summary of ``path`` (skips the test when it is not installed)."""
    if shutil.which("node") is None or not (VALIDATOR / "node_modules" / "gltf-validator").exists():
        pytest.skip("the Khronos glTF-Validator is not installed: run `npm install` in tools/gltf-validate (CI does)")
    out = subprocess.run(["node", str(VALIDATOR / "validate.js"), str(path)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)
