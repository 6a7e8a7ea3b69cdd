"""Export (T,22,3) joint positions as an animated glTF 2.0 binary (.glb), written by hand.

The file holds a "lsgan_motion" root node whose only child is the pelvis; below it one node per SMPL joint
(named after ``JOINT_NAMES``, children per ``PARENTS``) whose rest translation is the fitted rest offset
(:func:`lsgan.motion.fit.rest_offsets`, metres) and whose rest rotation is the first frame's pose. The joint
nodes are the joints of a glTF skin: one skinned mesh (a scene root node, "lsgan_skeleton") made of trimesh
primitives, an icosphere at every joint and a capsule along every bone of at least ``MIN_BONE_M`` (leaves get a
stub of ``STUB_FRACTION`` of their own bone), each vertex bound to one joint, so Blender and engines import an
armature. One animation at the motion's fps has a LINEAR rotation channel per joint (the IK of :func:`lsgan.export.bvh.joint_rotations`,
as unit x,y,z,w quaternions) and a translation channel for the pelvis. glTF's conventions (right-handed, +Y
up, +Z forward, metres) are lsgan's, so nothing is converted. :func:`skeleton_document` builds this file for
any hierarchy: a user's rig (:func:`lsgan.export.retarget.rig_gltf_document`) gets the same nodes, skin, mesh and
animation, at its own rest pose.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lsgan.data.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS
from lsgan.export.bvh import checked_motion, joint_rotations
from lsgan.motion.fit import rest_offsets
from lsgan.io import atomic_file

GLB_MAGIC = 0x46546C67  # b"glTF" little endian
CHUNK_JSON = 0x4E4F534A  # b"JSON"
CHUNK_BIN = 0x004E4942  # b"BIN\0"
ROOT_NAME = "lsgan_motion"
JOINT_RADIUS = 0.02  # metres, the joint spheres
BONE_RADIUS = 0.06  # bone capsule radius as a fraction of its length
BONE_MAX_RADIUS = 0.015  # metres
STUB_FRACTION = 0.5
MIN_BONE_M = 1e-3  # shorter bones (character-creator twist and share bones) get no capsule: it would be degenerate
FLOAT, UINT8, UINT16, UINT32 = 5126, 5121, 5123, 5125
COMPONENT = {np.dtype(np.float32): FLOAT, np.dtype(np.uint8): UINT8, np.dtype(np.uint16): UINT16,
             np.dtype(np.uint32): UINT32}
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963


def bone_targets(parents, offsets: np.ndarray, end_sites=(), moving=()) -> list[list[np.ndarray]]:
    """Per joint, the vectors (in its own frame) its bone capsules run along: to each child (not to one in
    ``moving``, whose animated translation would stretch the bone), else to its End Sites ``(joint, offset)``,
    else a stub of ``STUB_FRACTION`` of its own bone."""
    parents = np.asarray(parents)
    tips = {k: [np.asarray(o, dtype=np.float64) for j, o in end_sites if j == k] for k in range(len(parents))}
    out = []
    for k in range(len(parents)):
        children = np.flatnonzero(parents == k)
        if len(children):
            out.append([offsets[c] for c in children if c not in moving])
        else:
            out.append([o for o in tips[k] if np.linalg.norm(o) > 1e-6] or [offsets[k] * STUB_FRACTION])
    return out


def _bone_parts(targets: list[np.ndarray]) -> list:
    """trimesh primitives of one joint in its own frame: an icosphere at the joint and a capsule along each
    target vector (see :func:`bone_targets`)."""
    import trimesh

    parts = [trimesh.creation.icosphere(subdivisions=1, radius=JOINT_RADIUS)]
    for target in targets:
        length = float(np.linalg.norm(target))
        if length < MIN_BONE_M:
            continue
        radius = min(BONE_RADIUS * length, BONE_MAX_RADIUS)
        capsule = trimesh.creation.capsule(height=max(length - 2 * radius, 1e-4), radius=radius, count=[8, 8])
        place = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], target / length)  # 4x4: +Z onto the bone
        place[:3, 3] = target / 2  # capsules are centred on the origin
        parts.append(capsule.apply_transform(place))
    return parts


def _rest_world(parents, rest: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """(J,4,4) world matrices of the joint nodes in the bind pose: rest translations (a root's is its position)
    and rotations ``quat`` (J,4), parents listed first."""
    world = np.zeros((len(parents), 4, 4))
    for k, parent in enumerate(parents):
        local = np.eye(4)
        local[:3, :3] = Rotation.from_quat(quat[k]).as_matrix()
        local[:3, 3] = rest[k]
        world[k] = local if parent < 0 else world[parent] @ local
    return world


def skeleton_mesh(targets: list[list[np.ndarray]], world: np.ndarray) -> dict[str, np.ndarray]:
    """The skinned skeleton mesh in the bind pose ``world`` (J,4,4): positions (V,3), normals (V,3), faces
    (F,3), joint (V,) of each vertex (its only influence)."""
    positions, normals, faces, joint = [], [], [], []
    count = 0
    for k, joint_targets in enumerate(targets):
        for part in _bone_parts(joint_targets):
            positions.append(part.vertices @ world[k, :3, :3].T + world[k, :3, 3])
            normals.append(part.vertex_normals @ world[k, :3, :3].T)
            faces.append(part.faces + count)
            joint.append(np.full(len(part.vertices), k))
            count += len(part.vertices)
    return {"positions": np.concatenate(positions), "normals": np.concatenate(normals),
            "faces": np.concatenate(faces), "joint": np.concatenate(joint)}


def _hemisphere_continuous(quat: np.ndarray) -> np.ndarray:
    """Flip quaternions (T,K,4) so consecutive frames lie in the same hemisphere (short LINEAR paths)."""
    q = quat.copy()
    for t in range(1, len(q)):
        flip = np.einsum("ki,ki->k", q[t], q[t - 1]) < 0
        q[t, flip] *= -1
    return q


def unit_quats(quat: np.ndarray) -> np.ndarray:
    """Quaternions (T,K,4) as written: hemisphere-continuous, float32, renormalised."""
    q = _hemisphere_continuous(quat).astype(np.float32)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


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


def gltf_document(joints: np.ndarray, *, fps: float = 20.0, name: str = "motion") -> tuple[dict, bytes]:
    """The glTF JSON (dict) and its binary buffer for joint positions (T,22,3) in metres."""
    j = checked_motion(joints, fps)
    offsets = rest_offsets(j)
    rot = joint_rotations(j, offsets)
    quat = unit_quats(Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat().reshape(len(j), NUM_JOINTS, 4))
    rest = offsets.copy()
    rest[0] = j[0, 0]  # the bind pose is the first frame's
    extras = {"fps": float(fps), "frames": len(j), "units": "metres", "up": "+Y", "forward": "+Z"}
    return skeleton_document(JOINT_NAMES, PARENTS, rest, quat, {0: j[:, 0]}, bone_targets(PARENTS, offsets),
                             rest_quat=quat[0], fps=fps, name=name, extras=extras)


def skeleton_document(names, parents, rest: np.ndarray, quat: np.ndarray, moving: dict[int, np.ndarray],
                      targets: list[list[np.ndarray]], *, rest_quat: np.ndarray, fps: float, name: str,
                      extras: dict) -> tuple[dict, bytes]:
    """glTF JSON and buffer of an animated hierarchy (``parents`` listed first): a ROOT_NAME node holding one
    node per joint, at rest translations ``rest`` (J,3, metres; a root's is its position) and rotations
    ``rest_quat`` (J,4), the bind pose of a skinned mesh of ``targets``' bones; one LINEAR animation at ``fps``
    turns every joint by ``quat`` (T,J,4) and moves the joints ``moving`` names to their (T,3) translations."""
    frames, count = quat.shape[:2]
    builder = _Builder()
    material = {"name": "lsgan_skeleton", "doubleSided": False,
                "pbrMetallicRoughness": {"baseColorFactor": [0.85, 0.55, 0.2, 1.0],
                                         "metallicFactor": 0.0, "roughnessFactor": 0.7}}
    rest32 = np.asarray(rest).astype(np.float32)
    nodes = [{"name": ROOT_NAME, "children": [k + 1 for k in range(count) if parents[k] < 0]}]
    for k in range(count):
        node = {"name": names[k], "translation": [float(x) for x in rest32[k]],
                "rotation": [float(x) for x in rest_quat[k]]}
        children = [c + 1 for c in range(count) if parents[c] == k]
        if children:
            node["children"] = children
        nodes.append(node)
    world = _rest_world(parents, rest32.astype(np.float64), rest_quat)
    roots = nodes[0]["children"]
    mesh, skin = _skin(builder, targets, world, skeleton=roots[0] if len(roots) == 1 else 0)
    nodes.append({"name": "lsgan_skeleton", "mesh": 0, "skin": 0})  # a scene root: glTF ignores its parents

    times = (np.arange(frames, dtype=np.float64) / fps).astype(np.float32)
    time_acc = builder.add(times, "SCALAR", bounds=True)
    samplers, channels = [], []
    for k in range(count):
        samplers.append({"input": time_acc, "output": builder.add(quat[:, k], "VEC4"), "interpolation": "LINEAR"})
        channels.append({"sampler": k, "target": {"node": k + 1, "path": "rotation"}})
    for k, track in sorted(moving.items()):
        samplers.append({"input": time_acc, "output": builder.add(np.asarray(track).astype(np.float32), "VEC3"),
                         "interpolation": "LINEAR"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": k + 1, "path": "translation"}})
    return _finish(builder, name=name, scene_nodes=[0, count + 1], nodes=nodes, meshes=[mesh],
                   materials=[material], animation={"name": name, "samplers": samplers, "channels": channels},
                   extras=extras, skins=[skin])


def _skin(builder: _Builder, targets: list[list[np.ndarray]], world: np.ndarray, *, skeleton: int
          ) -> tuple[dict, dict]:
    """The skeleton mesh (one primitive, every vertex bound to one joint) and its skin over nodes 1..J."""
    m = skeleton_mesh(targets, world)
    joints = np.zeros((len(m["joint"]), 4), np.uint8 if len(world) < 256 else np.uint16)
    joints[:, 0] = m["joint"]
    weights = np.zeros((len(m["joint"]), 4), np.float32)
    weights[:, 0] = 1.0
    index_dtype = np.uint16 if len(m["positions"]) < 65535 else np.uint32
    attributes = {
        "POSITION": builder.add(m["positions"].astype(np.float32), "VEC3", target=ARRAY_BUFFER, bounds=True),
        "NORMAL": builder.add(m["normals"].astype(np.float32), "VEC3", target=ARRAY_BUFFER),
        "JOINTS_0": builder.add(joints, "VEC4", target=ARRAY_BUFFER),
        "WEIGHTS_0": builder.add(weights, "VEC4", target=ARRAY_BUFFER),
    }
    indices = builder.add(m["faces"].reshape(-1).astype(index_dtype), "SCALAR", target=ELEMENT_ARRAY_BUFFER,
                          bounds=True)
    mesh = {"name": "lsgan_skeleton", "primitives": [{"attributes": attributes, "indices": indices, "material": 0,
                                                      "mode": 4}]}
    inverse_bind = np.linalg.inv(world).astype(np.float32).transpose(0, 2, 1)  # glTF stores column-major
    skin = {"name": "lsgan_skeleton", "skeleton": skeleton, "joints": list(range(1, len(world) + 1)),
            "inverseBindMatrices": builder.add(inverse_bind.reshape(-1, 16), "MAT4")}
    return mesh, skin


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
    quat = unit_quats(Rotation.from_rotvec(poses.reshape(-1, 3)).as_quat().reshape(frames, model.num_joints, 4))
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
