"""Export (T,22,3) joint positions as an animated glTF 2.0 binary (.glb), written by hand.

The file holds a "lsgan_motion" root node whose only child is the pelvis; below it one node per SMPL joint
(named after ``JOINT_NAMES``, children per ``PARENTS``) whose rest translation is the fitted rest offset
(:func:`lsgan.export.bvh.rest_offsets`, metres) and whose rest rotation is the first frame's pose. Every
joint node carries a rigid (not skinned) mesh: a small octahedron marking the joint and one octahedral bone
towards each child (leaves get a stub of ``STUB_FRACTION`` of their own bone). One animation at the motion's
fps has a LINEAR rotation channel per joint (the IK of :func:`lsgan.export.bvh.joint_rotations`, as unit
x,y,z,w quaternions) and a translation channel for the pelvis. glTF's conventions (right-handed, +Y up,
+Z forward, metres) are lsgan's, so nothing is converted.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lsgan.data.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS
from lsgan.export.bvh import CHILDREN, joint_rotations, rest_offsets
from lsgan.io import atomic_file

GLB_MAGIC = 0x46546C67  # b"glTF" little endian
CHUNK_JSON = 0x4E4F534A  # b"JSON"
CHUNK_BIN = 0x004E4942  # b"BIN\0"
ROOT_NAME = "lsgan_motion"
JOINT_RADIUS = 0.02  # metres, half-diagonal of the joint marker octahedron
BONE_WIDTH = 0.12  # bone half-width as a fraction of its length
BONE_MAX_WIDTH = 0.03  # metres
STUB_FRACTION = 0.5
FLOAT, UINT8, UINT16, UINT32 = 5126, 5121, 5123, 5125
COMPONENT = {np.dtype(np.float32): FLOAT, np.dtype(np.uint8): UINT8, np.dtype(np.uint16): UINT16,
             np.dtype(np.uint32): UINT32}
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


def _octahedron(base: np.ndarray, tip: np.ndarray, width: float, waist: float) -> np.ndarray:
    """Triangles (8,3,3) of an octahedron from ``base`` to ``tip`` with its square waist at ``waist`` (0..1)."""
    axis = tip - base
    unit = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(unit[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(unit, helper)
    u /= np.linalg.norm(u)
    v = np.cross(unit, u)
    centre = base + waist * axis
    ring = [centre + width * d for d in (u, v, -u, -v)]
    tris = []
    for i in range(4):
        a, b = ring[i], ring[(i + 1) % 4]
        tris.append([base, b, a])
        tris.append([tip, a, b])
    return np.array(tris)


def _joint_triangles(k: int, offsets: np.ndarray) -> np.ndarray:
    """Triangles (N,3,3) of joint ``k``'s mesh in its own frame: the joint marker and its bones."""
    origin = np.zeros(3)
    r = JOINT_RADIUS
    parts = [_octahedron(origin - [0.0, r, 0.0], origin + [0.0, r, 0.0], r, 0.5)]
    targets = [offsets[c] for c in CHILDREN[k]] or [offsets[k] * STUB_FRACTION]
    for target in targets:
        length = float(np.linalg.norm(target))
        if length > 1e-6:
            parts.append(_octahedron(origin, target, min(BONE_WIDTH * length, BONE_MAX_WIDTH), 0.2))
    return np.concatenate(parts)


def _flat_mesh(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unshared positions (3N,3), outward face normals (3N,3) and uint16 indices (3N,) of convex-part triangles."""
    tris = tris.astype(np.float64)
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    positions = tris.reshape(-1, 3).astype(np.float32)
    normals = np.repeat(normals, 3, axis=0).astype(np.float32)
    return positions, normals, np.arange(len(positions), dtype=np.uint16)


def _hemisphere_continuous(quat: np.ndarray) -> np.ndarray:
    """Flip quaternions (T,K,4) so consecutive frames lie in the same hemisphere (short LINEAR paths)."""
    q = quat.copy()
    for t in range(1, len(q)):
        flip = np.einsum("ki,ki->k", q[t], q[t - 1]) < 0
        q[t, flip] *= -1
    return q


class _Builder:
    """Accumulates the BIN chunk, bufferViews and accessors of one glTF file."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, data: np.ndarray, kind: str, *, target: int | None = None, bounds: bool = False) -> int:
        """Append ``data`` (float32, uint8/16/32) as one bufferView + accessor; returns the accessor index."""
        data = np.ascontiguousarray(data)
        self.blob.extend(b"\0" * (-len(self.blob) % 4))
        view = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": data.nbytes}
        if target is not None:
            view["target"] = target
        self.blob.extend(data.tobytes())
        self.views.append(view)
        component = COMPONENT[data.dtype]
        width = 1 if data.ndim == 1 else data.shape[1]
        accessor = {"bufferView": len(self.views) - 1, "componentType": component, "count": int(data.shape[0]),
                    "type": kind}
        if bounds:
            flat = data.reshape(data.shape[0], width)
            cast = float if component == FLOAT else int
            accessor["min"] = [cast(x) for x in flat.min(axis=0)]
            accessor["max"] = [cast(x) for x in flat.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def _validate(joints: np.ndarray, fps: float) -> np.ndarray:
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 3 or j.shape[1:] != (NUM_JOINTS, 3) or j.shape[0] == 0:
        raise ValueError(f"joints must be (T,{NUM_JOINTS},3) with T > 0, got {j.shape}")
    if not np.isfinite(j).all():
        raise ValueError("joints hold NaN or infinite values")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive and finite, got {fps}")
    return j


def gltf_document(joints: np.ndarray, *, fps: float = 20.0, name: str = "motion") -> tuple[dict, bytes]:
    """The glTF JSON (dict) and its binary buffer for joint positions (T,22,3) in metres."""
    j = _validate(joints, fps)
    frames = j.shape[0]
    offsets = rest_offsets(j)
    rot = joint_rotations(j, offsets)
    quat = Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat().reshape(frames, NUM_JOINTS, 4)
    quat = _hemisphere_continuous(quat).astype(np.float32)
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    builder = _Builder()

    material = {"name": "lsgan_skeleton", "doubleSided": False,
                "pbrMetallicRoughness": {"baseColorFactor": [0.85, 0.55, 0.2, 1.0],
                                         "metallicFactor": 0.0, "roughnessFactor": 0.7}}
    meshes, nodes = [], [{"name": ROOT_NAME, "children": [1]}]
    for k in range(NUM_JOINTS):
        positions, normals, indices = _flat_mesh(_joint_triangles(k, offsets))
        attributes = {"POSITION": builder.add(positions, "VEC3", target=ARRAY_BUFFER, bounds=True),
                      "NORMAL": builder.add(normals, "VEC3", target=ARRAY_BUFFER)}
        index_acc = builder.add(indices, "SCALAR", target=ELEMENT_ARRAY_BUFFER, bounds=True)
        meshes.append({"name": f"{JOINT_NAMES[k]}_bone",
                       "primitives": [{"attributes": attributes, "indices": index_acc, "material": 0, "mode": 4}]})
        translation = j[0, 0] if PARENTS[k] < 0 else offsets[k]
        node = {"name": JOINT_NAMES[k], "mesh": k,
                "translation": [float(x) for x in translation.astype(np.float32)],
                "rotation": [float(x) for x in quat[0, k]]}
        if CHILDREN[k]:
            node["children"] = [c + 1 for c in CHILDREN[k]]
        nodes.append(node)

    times = (np.arange(frames, dtype=np.float64) / fps).astype(np.float32)
    time_acc = builder.add(times, "SCALAR", bounds=True)
    samplers, channels = [], []
    for k in range(NUM_JOINTS):
        samplers.append({"input": time_acc, "output": builder.add(quat[:, k], "VEC4"), "interpolation": "LINEAR"})
        channels.append({"sampler": k, "target": {"node": k + 1, "path": "rotation"}})
    pelvis = j[:, 0].astype(np.float32)
    samplers.append({"input": time_acc, "output": builder.add(pelvis, "VEC3"), "interpolation": "LINEAR"})
    channels.append({"sampler": NUM_JOINTS, "target": {"node": 1, "path": "translation"}})

    extras = {"fps": float(fps), "frames": frames, "units": "metres", "up": "+Y", "forward": "+Z"}
    return _finish(builder, name=name, scene_nodes=[0], nodes=nodes, meshes=meshes, materials=[material],
                   animation={"name": name, "samplers": samplers, "channels": channels}, extras=extras)


def _finish(builder: _Builder, *, name: str, scene_nodes: list[int], nodes: list[dict], meshes: list[dict],
            materials: list[dict], animation: dict, extras: dict, skins: list[dict] | None = None,
            ) -> tuple[dict, bytes]:
    """The glTF JSON of a one-scene, one-animation file, and the padded BIN chunk."""
    builder.blob.extend(b"\0" * (-len(builder.blob) % 4))
    doc = {
        "asset": {"version": "2.0", "generator": "lsgan"},
        "scene": 0,
        "scenes": [{"name": name, "nodes": scene_nodes}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "animations": [animation],
        "accessors": builder.accessors,
        "bufferViews": builder.views,
        "buffers": [{"byteLength": len(builder.blob)}],
        "extras": extras,
    }
    if skins:
        doc["skins"] = skins
    return doc, bytes(builder.blob)


def pack_glb(doc: dict, blob: bytes) -> bytes:
    """A GLB container: 12-byte header, JSON chunk (space padded), BIN chunk (zero padded), all 4-byte aligned."""
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    blob = blob + b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(text) + (8 + len(blob) if blob else 0)
    out = [struct.pack("<III", GLB_MAGIC, 2, total), struct.pack("<II", len(text), CHUNK_JSON), text]
    if blob:
        out += [struct.pack("<II", len(blob), CHUNK_BIN), blob]
    return b"".join(out)


def joints_to_glb(joints: np.ndarray, *, fps: float = 20.0, name: str = "motion") -> bytes:
    """GLB bytes (animated skeleton) for joint positions (T,22,3) in metres, Y up, +Z forward."""
    return pack_glb(*gltf_document(joints, fps=fps, name=name))


def write_glb(path: str | Path, joints: np.ndarray, *, fps: float = 20.0, name: str | None = None) -> Path:
    """Write :func:`joints_to_glb` to ``path`` atomically (a temporary file beside it, then os.replace)."""
    path = Path(path)
    data = joints_to_glb(joints, fps=fps, name=name or path.stem)
    with atomic_file(path) as fh:
        fh.write(data)
    return path


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (V,3); vertices in no face get +Y."""
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    return np.where(length > 1e-12, normals / np.maximum(length, 1e-12), [0.0, 1.0, 0.0])


def _top4_weights(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 4 largest skinning weights per vertex, renormalised to sum to 1, and their joint indices.

    Unused slots get weight 0 and joint index 0 (glTF ignores joints with zero weight)."""
    idx = np.argsort(-weights, axis=1)[:, :4]
    w = np.take_along_axis(weights, idx, axis=1).astype(np.float64)
    w = np.where(w > 1e-6, w, 0.0)
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    idx = np.where(w > 0, idx, 0)
    w = w.astype(np.float32)
    w[:, 0] += 1.0 - w.sum(axis=1)  # float32 rounding: the sum is exactly 1 to within one ulp
    dtype = np.uint8 if weights.shape[1] < 256 else np.uint16
    return idx.astype(dtype), w


def body_gltf_document(fit, model, *, name: str = "motion") -> tuple[dict, bytes]:
    """glTF JSON and buffer of a fitted body: ONE skinned mesh and the model's skeleton, animated.

    ``fit`` is a :class:`lsgan.export.body.BodyFit`, ``model`` the :class:`lsgan.data.body_model.BodyModel`
    it was fitted with. Nodes: the mesh (scene root, skinned), then "lsgan_body" holding the J joint nodes
    named after the model's joints. The mesh is the rest mesh with the fitted betas; glTF skinning is
    linear blend skinning, so the pose-dependent corrective shapes of SMPL are left out. Joints beyond
    the 22 of the motion (hands, jaw, eyes) stay at rest.
    """
    poses = np.asarray(fit.poses, dtype=np.float64).reshape(len(fit.poses), model.num_joints, 3)
    frames, fps = poses.shape[0], float(fit.fps)
    rest = model.rest_joints(fit.betas).astype(np.float64)
    vertices = model.rest_vertices(fit.betas).astype(np.float64)
    quat = Rotation.from_rotvec(poses.reshape(-1, 3)).as_quat().reshape(frames, model.num_joints, 4)
    quat = _hemisphere_continuous(quat).astype(np.float32)
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    builder = _Builder()

    joint_ids, weights = _top4_weights(model.weights)
    index_dtype = np.uint16 if len(vertices) < 65535 else np.uint32
    attributes = {
        "POSITION": builder.add(vertices.astype(np.float32), "VEC3", target=ARRAY_BUFFER, bounds=True),
        "NORMAL": builder.add(_vertex_normals(vertices, model.faces).astype(np.float32), "VEC3",
                              target=ARRAY_BUFFER),
        "JOINTS_0": builder.add(joint_ids, "VEC4", target=ARRAY_BUFFER),
        "WEIGHTS_0": builder.add(weights, "VEC4", target=ARRAY_BUFFER),
    }
    indices = builder.add(model.faces.reshape(-1).astype(index_dtype), "SCALAR", target=ELEMENT_ARRAY_BUFFER,
                          bounds=True)
    material = {"name": "lsgan_body", "pbrMetallicRoughness": {"baseColorFactor": [0.62, 0.66, 0.74, 1.0],
                                                              "metallicFactor": 0.0, "roughnessFactor": 0.8}}
    mesh = {"name": f"{model.model_type}_body",
            "primitives": [{"attributes": attributes, "indices": indices, "material": 0, "mode": 4}]}

    first = 2  # node index of joint 0: node 0 is the skinned mesh, node 1 the skeleton root
    nodes: list[dict] = [{"name": "body", "mesh": 0, "skin": 0}, {"name": "lsgan_body", "children": [first]}]
    pelvis = (rest[0] + np.asarray(fit.trans, dtype=np.float64)).astype(np.float32)
    for k, joint_name in enumerate(model.joint_names):
        parent = int(model.parents[k])
        translation = pelvis[0] if parent < 0 else (rest[k] - rest[parent]).astype(np.float32)
        node = {"name": joint_name, "translation": [float(x) for x in translation],
                "rotation": [float(x) for x in quat[0, k]]}
        children = [first + c for c in np.flatnonzero(model.parents == k) if c > 0]
        if children:
            node["children"] = [int(c) for c in children]
        nodes.append(node)
    inverse_bind = np.tile(np.eye(4, dtype=np.float32), (model.num_joints, 1, 1))
    inverse_bind[:, 3, :3] = -rest  # column-major storage: the translation sits in the last 4 floats
    skin = {"name": f"{model.model_type}_skeleton", "skeleton": first,
            "joints": list(range(first, first + model.num_joints)),
            "inverseBindMatrices": builder.add(inverse_bind.reshape(-1, 16), "MAT4")}

    times = (np.arange(frames, dtype=np.float64) / fps).astype(np.float32)
    time_acc = builder.add(times, "SCALAR", bounds=True)
    samplers, channels = [], []
    for k in range(NUM_JOINTS):
        samplers.append({"input": time_acc, "output": builder.add(quat[:, k], "VEC4"), "interpolation": "LINEAR"})
        channels.append({"sampler": k, "target": {"node": first + k, "path": "rotation"}})
    samplers.append({"input": time_acc, "output": builder.add(pelvis, "VEC3"), "interpolation": "LINEAR"})
    channels.append({"sampler": NUM_JOINTS, "target": {"node": first, "path": "translation"}})

    extras = {"fps": fps, "frames": frames, "units": "metres", "up": "+Y", "forward": "+Z",
              "body_model": model.model_type, "gender": model.gender,
              "betas": [float(b) for b in fit.betas], "fit_mean_error_mm": fit.mean_error_mm,
              "fit_max_error_mm": fit.max_joint_error_mm}
    return _finish(builder, name=name, scene_nodes=[0, 1], nodes=nodes, meshes=[mesh], materials=[material],
                   animation={"name": name, "samplers": samplers, "channels": channels}, extras=extras,
                   skins=[skin])


def write_body_glb(path: str | Path, fit, model, *, name: str | None = None) -> Path:
    """Write :func:`body_gltf_document` as a GLB to ``path`` atomically."""
    path = Path(path)
    data = pack_glb(*body_gltf_document(fit, model, name=name or path.stem))
    with atomic_file(path) as fh:
        fh.write(data)
    return path
