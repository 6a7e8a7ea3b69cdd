"""Retarget (T,22,3) motions onto a user's BVH skeleton: ``lsgan export --bvh|--glb MOTION --rig CHARACTER.bvh``.

The rig is any BVH file (:func:`lsgan.data.bvh.read_bvh`); its hierarchy, rest pose (OFFSET lines with zero
rotations), channel orders, End Sites and units are kept and its motion is ignored. A joint map
(:mod:`lsgan.data.joint_maps`: the importer's format and presets) names the rig joint of each SMPL joint;
rig joints named directly are *mapped* (``between`` entries only place SMPL joints the rig lacks). The map's
``scale``, ``up`` and ``handedness`` say how our metres, Y up, become the rig's units and axes.

- Root: the pelvis joint follows our pelvis trajectory scaled by the ratio of the rig's leg length (hip to
  knee to ankle at rest) to ours, through the position channels of the pelvis joint or of its nearest
  ancestor with all three; the pelvis joint's ancestors keep their rest rotation.
- Mapped joints, by IK on directions: the chain of rig joints from a mapped joint to the next mapped joint
  below it is turned so that it points along our bone between the two. A joint starting several chains (the
  pelvis, the chest) gets the Kabsch rotation of its rest chain vectors onto ours; a joint starting one gets
  the shortest arc, with the twist carried from frame to frame (:func:`lsgan.export.body._continue_twist`).
  Unmapped joints inside a chain share the bend: the k-th of n turns 1/(n-k) of the remaining arc, so the
  last one aims exactly.
- Everything else (fingers, end bones, mapped leaves such as the head or the hands) keeps its rest rotation.

The BVH gets these rotations as Euler angles in each joint's channel order; the GLB (:func:`rig_gltf_document`)
gets the same rotations as quaternions on the rig's hierarchy in metres, Y up (the map's scale, up axis and
handedness undone), skinned to a mesh of its bones (:func:`lsgan.export.glb.skeleton_document`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lsgan.data.bvh import POSITION_CHANNELS, ROTATION_CHANNELS, Bvh, read_bvh
from lsgan.data.clip import ClipError
from lsgan.data.joint_maps import JointMap, apply_joint_map, map_indices
from lsgan.data.skeleton import JOINT_NAMES
from lsgan.export.body import _continue_twist as continue_twist
from lsgan.export.bvh import bvh_text, channel_values, checked_motion, hierarchy_text, kabsch, shortest_arc
from lsgan.export.glb import bone_targets, pack_glb, skeleton_document, unit_quats
from lsgan.io import atomic_file

_LEGS = (("left_hip", "left_knee", "left_ankle"), ("right_hip", "right_knee", "right_ankle"))


@dataclass(frozen=True)
class Plan:
    """What drives each rig joint: ``aims[j]`` = [(mapped joint m, rest vector j -> m, joints left in the chain)]."""

    pelvis: int
    carrier: int  # the joint whose position channels carry the root trajectory
    smpl_of: dict[int, int]  # mapped rig joint -> SMPL joint index
    start_of: dict[int, int]  # mapped rig joint -> the mapped joint its chain starts from
    length: dict[int, float]  # mapped rig joint -> rest length of its chain (file units)
    aims: dict[int, list[tuple[int, np.ndarray, int]]]


def rig_frame(positions: np.ndarray, jmap: JointMap) -> np.ndarray:
    """Our positions (...,3), metres, Y up, right-handed -> the rig's units, up axis and handedness."""
    p = np.asarray(positions, dtype=np.float64)
    if jmap.handedness == "left":
        p = p * np.array([-1.0, 1.0, 1.0])
    if jmap.up == "z":  # inverse of to_y_up's (x, y, z) -> (x, z, -y)
        p = np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)
    return p / jmap.scale


def rest_positions(parents: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Global rest positions (J,3) of a hierarchy: offsets summed down the chains, no rotation."""
    pos = np.zeros_like(np.asarray(offsets, dtype=np.float64))
    for k, parent in enumerate(parents):
        pos[k] = offsets[k] + (pos[parent] if parent >= 0 else 0.0)
    return pos


def leg_length(joints: np.ndarray) -> float:
    """Mean over both legs (and frames) of hip-knee plus knee-ankle length, for SMPL joints (...,22,3)."""
    idx = [[JOINT_NAMES.index(n) for n in leg] for leg in _LEGS]
    j = np.asarray(joints, dtype=np.float64)
    return float(np.mean([np.linalg.norm(j[..., b, :] - j[..., a, :], axis=-1)
                          + np.linalg.norm(j[..., c, :] - j[..., b, :], axis=-1) for a, b, c in idx]))


def _ancestors(parents: np.ndarray, j: int) -> list[int]:
    out = []
    while parents[j] >= 0:
        j = int(parents[j])
        out.append(j)
    return out


def plan_rig(rig: Bvh, jmap: JointMap) -> Plan:
    """The chains that drive ``rig`` under ``jmap``; a map that does not fit the rig raises ClipError naming it."""
    a, _, _ = map_indices(jmap, rig.names, rig.path)
    where = f"{rig.path}: joint map {jmap.name!r}"
    if not isinstance(jmap.joints["pelvis"], str):
        raise ClipError(f"{where}: retargeting needs the pelvis mapped to one rig joint, not a 'between' point")
    smpl_of: dict[int, int] = {}
    for k, smpl in enumerate(JOINT_NAMES):
        if isinstance(jmap.joints[smpl], str):
            smpl_of.setdefault(int(a[k]), k)
    pelvis = int(a[0])
    parents = rig.parents
    start_of, length, aims = {}, {}, {}
    for m in smpl_of:
        if m == pelvis:
            continue
        up = _ancestors(parents, m)
        if pelvis not in up:
            raise ClipError(f"{where}: {rig.names[m]!r} ({JOINT_NAMES[smpl_of[m]]}) is not below the pelvis joint "
                            f"{rig.names[pelvis]!r}")
        chain = list(reversed(up[: next(i for i, c in enumerate(up) if c in smpl_of) + 1]))
        vectors = np.cumsum([rig.offsets[c] for c in chain[1:] + [m]][::-1], axis=0)[::-1]
        if np.linalg.norm(vectors[0]) < 1e-9:
            raise ClipError(f"{where}: {rig.names[m]!r} sits on {rig.names[chain[0]]!r} (a zero-length bone)")
        start_of[m], length[m] = chain[0], float(np.linalg.norm(vectors[0]))
        for i, c in enumerate(chain):
            aims.setdefault(c, []).append((m, vectors[i], len(chain) - i))
    carrier = next((c for c in [pelvis] + _ancestors(parents, pelvis)
                    if set(POSITION_CHANNELS) <= set(rig.channels[c])), None)
    if carrier is None:
        raise ClipError(f"{rig.path}: no Xposition/Yposition/Zposition channels on {rig.names[pelvis]!r} or above it")
    for c in aims:
        if sum(ch in ROTATION_CHANNELS for ch in rig.channels[c]) != 3:
            raise ClipError(f"{rig.path}: joint {rig.names[c]!r} needs three rotation channels to follow the motion, "
                            f"has {' '.join(rig.channels[c]) or 'none'}")
    return Plan(pelvis, carrier, smpl_of, start_of, length, aims)


def _local_rotation(aims, goals: list[np.ndarray]) -> np.ndarray:
    """Local rotations (T,3,3) of one joint turning its rest chain vectors onto ``goals`` (parent frame)."""
    if len(aims) > 1:
        return kabsch(np.stack([r for _, r, _ in aims]), np.stack(goals, axis=1))
    _, rest, left = aims[0]
    swing = shortest_arc(rest, goals[0])
    if left == 1:
        return continue_twist(swing, goals[0])
    return Rotation.from_rotvec(Rotation.from_matrix(swing).as_rotvec() / left).as_matrix()


def solve(q: np.ndarray, root: np.ndarray, rig: Bvh, plan: Plan) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations (T,J,3,3) and translations (T,J,3) posing ``rig`` like targets ``q`` (T,22,3, rig frame)
    with the pelvis joint at ``root`` (T,3)."""
    t, n = len(q), len(rig.names)
    eye = np.broadcast_to(np.eye(3), (t, 3, 3))
    trans = np.broadcast_to(rig.offsets, (t, n, 3)).copy()
    trans[:, plan.carrier] += root - rest_positions(rig.parents, rig.offsets)[plan.pelvis]
    global_rot, pos, local = np.empty((t, n, 3, 3)), np.empty((t, n, 3)), np.empty((t, n, 3, 3))
    for k, parent in enumerate(rig.parents):
        parent_rot = eye if parent < 0 else global_rot[:, parent]
        pos[:, k] = (0.0 if parent < 0 else pos[:, parent]) + np.einsum("tij,tj->ti", parent_rot, trans[:, k])
        aims = plan.aims.get(k, [])
        goals = []
        for m, _, _ in aims:
            start = plan.start_of[m]
            bone = q[:, plan.smpl_of[m]] - q[:, plan.smpl_of[start]]
            bone = bone / np.maximum(np.linalg.norm(bone, axis=-1, keepdims=True), 1e-12)
            goal = pos[:, start] + bone * plan.length[m] - pos[:, k]
            goals.append(np.einsum("tji,tj->ti", parent_rot, goal))
        local[:, k] = _local_rotation(aims, goals) if aims else eye
        global_rot[:, k] = parent_rot @ local[:, k]
    return local, trans


def _solved(j: np.ndarray, rig: Bvh, jmap: JointMap) -> tuple[Plan, np.ndarray, np.ndarray]:
    """The plan and :func:`solve`'s local rotations and translations (rig frame) for a checked motion ``j``."""
    plan = plan_rig(rig, jmap)
    rest = apply_joint_map(rest_positions(rig.parents, rig.offsets)[None], rig.names, jmap, rig.path)
    ours = leg_length(j)
    if not ours > 1e-6:
        raise ValueError("the motion's legs have zero length")
    scale = leg_length(rest) / ours
    local, trans = solve(rig_frame(j, jmap), rig_frame(j[:, 0] * scale, jmap), rig, plan)
    return plan, local, trans


def retarget(joints: np.ndarray, rig: Bvh, jmap: JointMap, *, fps: float = 20.0) -> Bvh:
    """Our motion (T,22,3: metres, Y up) on ``rig``'s skeleton: a :class:`Bvh` with the rig's hierarchy and a
    new MOTION block at ``fps``. Raises ValueError for a bad motion, ClipError for a map that does not fit."""
    _, local, trans = _solved(checked_motion(joints, fps), rig, jmap)
    motion = channel_values(local, trans, rig.channels)
    return Bvh(path=rig.path, names=rig.names, parents=rig.parents, offsets=rig.offsets, channels=rig.channels,
               frame_time=1.0 / fps, motion=motion, end_sites=rig.end_sites)


def rig_gltf_document(joints: np.ndarray, rig: Bvh, jmap: JointMap, *, fps: float = 20.0,
                      name: str = "motion") -> tuple[dict, bytes]:
    """glTF JSON and buffer of our motion on ``rig``: its hierarchy as nodes at its rest pose (metres, Y up,
    right-handed, through the map's scale, up axis and handedness), skinned, and animated with the rotations
    and root translation that :func:`retarget` writes to the BVH."""
    plan, local, trans = _solved(checked_motion(joints, fps), rig, jmap)
    axes = rig_frame(np.eye(3), jmap) * jmap.scale  # C, with ours = scale * C @ rig (rig_frame is C.T / scale)

    def metres(v) -> np.ndarray:
        return np.asarray(v, dtype=np.float64) @ axes.T * jmap.scale

    rot = np.einsum("ij,tkjl,ml->tkim", axes, local, axes)  # the same turns seen in our frame
    quat = unit_quats(Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_quat().reshape(*rot.shape[:2], 4))
    rest, root = metres(rig.offsets), metres(trans[:, plan.carrier])
    ends = [(k, metres(o)) for k, o in rig.end_sites]
    extras = {"fps": float(fps), "frames": len(local), "units": "metres", "up": "+Y", "forward": "+Z",
              "rig": Path(rig.path).name, "joint_map": jmap.name}
    identity = np.tile(np.array([0.0, 0.0, 0.0, 1.0], np.float32), (len(rig.names), 1))
    return skeleton_document(rig.names, rig.parents, rest, quat, {plan.carrier: root},
                             bone_targets(rig.parents, rest, ends, moving={plan.carrier}), rest_quat=identity,
                             fps=fps, name=name, extras=extras)


def rig_bvh_text(bvh: Bvh) -> str:
    """BVH text of a :class:`Bvh` (hierarchy as read, offsets and End Sites in its units, its channel orders)."""
    hierarchy = hierarchy_text(bvh.names, bvh.parents, bvh.offsets, bvh.channels, bvh.end_sites)
    return bvh_text(hierarchy, bvh.motion, 1.0 / bvh.frame_time)


def load_rig(path: str | Path) -> Bvh:
    """Read a rig BVH; a missing or malformed file raises ClipError naming it."""
    if not Path(path).is_file():
        raise ClipError(f"{path}: no such rig file")
    return read_bvh(path)


def write_rig_glb(path: str | Path, joints: np.ndarray, rig: Bvh, jmap: JointMap, *, fps: float = 20.0) -> Path:
    """Write :func:`rig_gltf_document` of ``joints`` as a GLB file on ``rig``, atomically."""
    path = Path(path)
    data = pack_glb(*rig_gltf_document(joints, rig, jmap, fps=fps, name=path.stem))
    with atomic_file(path) as fh:
        fh.write(data)
    return path


def write_rig_bvh(path: str | Path, joints: np.ndarray, rig: Bvh, jmap: JointMap, *, fps: float = 20.0) -> Path:
    """Write :func:`retarget` of ``joints`` as a BVH file on ``rig``, atomically."""
    path = Path(path)
    text = rig_bvh_text(retarget(joints, rig, jmap, fps=fps))
    with atomic_file(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    return path
