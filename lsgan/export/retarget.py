"""Retarget (T,22,3) motions onto a user's BVH skeleton: ``lsgan export --bvh|--glb MOTION --rig CHARACTER.bvh``.

The rig is any BVH file (:func:`lsgan.data.bvh.read_bvh`); its hierarchy, rest pose (OFFSET lines with zero
rotations), channel orders, End Sites and units are kept and its motion is ignored. A joint map
(:mod:`lsgan.data.joint_maps`: the importer's format and presets) names the rig joint of each SMPL joint;
rig joints named directly are *mapped* (``between`` entries only place SMPL joints the rig lacks). The map's
``scale``, ``up`` and ``handedness`` say how our metres, Y up, become the rig's units and axes.

- Root: the pelvis joint follows our pelvis trajectory scaled by the ratio of the rig's leg length (hip to
  knee to ankle at rest) to ours, through the position channels of the pelvis joint or of its nearest
  ancestor with all three; the pelvis joint's ancestors keep their rest rotation. It is then raised or lowered
  so that the rig's lowest foot point (its foot joints and the End Sites below them: a toe's tip) is as high as
  our lowest foot joint in every frame where one of our feet is in contact
  (:func:`lsgan.motion.feet.estimate_contacts`), interpolated between them (:func:`floor_lift`): the rig stands
  on our floor whatever its proportions and wherever its root joint sits.
- Mapped joints, by IK on directions: the chain of rig joints from a mapped joint to the next mapped joint
  below it is turned so that it points along our bone between the two. A joint starting several chains (the
  pelvis, the chest) gets the Kabsch rotation of its rest chain vectors onto ours. The joint turning the last
  link of a chain aims it along our bone and takes its twist from our body (:mod:`lsgan.export.aim`: knees and
  elbows, and the hips and shoulders above them, from the limb's bend plane, or the body's forward when the limb
  is straight; feet from the toes and the knee's hinge; the spine and neck from the hips and shoulders lines),
  in the rig's own convention: the local axis that the rig's own mocap (its rest pose when the file has no
  frames) turns towards that reference direction is turned towards ours (:func:`rig_axes`). So the twist is
  the same whatever the rig's rest frames (pre-rotated bone frames of character-creator rigs included).
  Unmapped joints earlier in a chain share the bend: the k-th of n turns 1/(n-k) of the remaining arc.
- Everything else (fingers, end bones, mapped leaves such as the head or the hands) keeps its rest rotation.

A map that would write a lying, wrongly sized or mirrored character is reported by :func:`map_warnings`.

The BVH gets these rotations as Euler angles in each joint's channel order; the GLB (:func:`rig_gltf_document`)
gets the same rotations as quaternions on the rig's hierarchy in metres, Y up (the map's scale, up axis and
handedness undone), skinned to a mesh of its bones (:func:`lsgan.export.glb.skeleton_document`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lsgan.data.bvh import (POSITION_CHANNELS, ROTATION_CHANNELS, Bvh, forward_kinematics, local_transforms,
                            read_bvh)
from lsgan.data.clip import ClipError
from lsgan.data.joint_maps import JointMap, apply_joint_map, map_indices, to_y_up
from lsgan.data.skeleton import JOINT_NAMES
from lsgan.export.aim import aim_frames, measure_axes, reference_directions, standing_frames
from lsgan.export.bvh import bvh_text, channel_values, checked_motion, hierarchy_text
from lsgan.motion.fit import kabsch, shortest_arc
from lsgan.export.glb import bone_targets, pack_glb, skeleton_document, unit_quats
from lsgan.io import atomic_file

_LEGS = (("left_hip", "left_knee", "left_ankle"), ("right_hip", "right_knee", "right_ankle"))
MIRRORED_FRACTION = 0.8  # frames seen mirrored: a mirrored map 1.0; real rigs' clips (Bandai, CMU) 0.0
MOCAP_FRAMES = 10  # fewer frames are a bind pose, not mocap: a lying one may be the pose, not a wrong `up`
_FEET = [JOINT_NAMES.index(n) for n in ("left_ankle", "right_ankle", "left_foot", "right_foot")]


@dataclass(frozen=True)
class Plan:
    """What drives each rig joint: ``aims[j]`` = [(mapped joint m, rest vector j -> m, joints left in the chain)]."""

    pelvis: int
    carrier: int  # the joint whose position channels carry the root trajectory
    smpl_of: dict[int, int]  # mapped rig joint -> SMPL joint index
    start_of: dict[int, int]  # mapped rig joint -> the mapped joint its chain starts from
    length: dict[int, float]  # mapped rig joint -> rest length of its chain (file units)
    aims: dict[int, list[tuple[int, np.ndarray, int]]]
    axes: dict[int, np.ndarray]  # joint ending a one-chain aim -> its local axis facing the bone's reference


def rig_frame(positions: np.ndarray, jmap: JointMap) -> np.ndarray:
    """Our positions (...,3), metres, Y up, right-handed -> the rig's units, up axis and handedness."""
    p = np.asarray(positions, dtype=np.float64)
    if jmap.handedness == "left":
        p = p * np.array([-1.0, 1.0, 1.0])
    if jmap.up == "z":  # inverse of to_y_up's (x, y, z) -> (x, z, -y)
        p = np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)
    return p / jmap.scale


def metres_y_up(positions: np.ndarray, jmap: JointMap) -> np.ndarray:
    """The rig's positions (...,3) -> our metres, Y up, right-handed (the inverse of :func:`rig_frame`)."""
    p = to_y_up(np.asarray(positions, dtype=np.float64) * jmap.scale, jmap.up)
    return p * np.array([-1.0, 1.0, 1.0]) if jmap.handedness == "left" else p


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
    return Plan(pelvis, carrier, smpl_of, start_of, length, aims, rig_axes(rig, jmap, smpl_of, aims))


def global_rotations(parents: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Global rotations (F,J,3,3) of local ones (F,J,3,3), parents listed first."""
    out = np.empty_like(local)
    for k, parent in enumerate(parents):
        out[:, k] = local[:, k] if parent < 0 else out[:, parent] @ local[:, k]
    return out


def rig_poses(rig: Bvh, jmap: JointMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rig's own poses: global rotations (F,J,3,3), positions (F,J,3, file units) and our joints read from
    them (F,22,3): its mocap's frames, or its rest pose (F = 1) when the file has none."""
    if rig.num_frames:
        rot, pos = global_rotations(rig.parents, local_transforms(rig)[0]), forward_kinematics(rig)
    else:
        rot, pos = np.eye(3)[None, None].repeat(len(rig.names), 1), rest_positions(rig.parents, rig.offsets)[None]
    return rot, pos, apply_joint_map(pos, rig.names, jmap, rig.path)


def rig_axes(rig: Bvh, jmap: JointMap, smpl_of: dict, aims: dict) -> dict[int, np.ndarray]:
    """The rig's own twist convention: for each joint turning the last link of a chain (see :class:`Plan`), the
    local axis that the rig's poses (:func:`rig_poses`), those where it stands (:func:`standing_frames`; all when
    none does, which :func:`map_warnings` reports), turn towards the reference direction of the SMPL bone it
    drives (:func:`lsgan.export.aim.measure_axes`)."""
    twisted = [(c, smpl_of[a[0][0]], a[0][1]) for c, a in aims.items() if len(a) == 1 and a[0][2] == 1]
    if not twisted:
        return {}
    rot, _, j = rig_poses(rig, jmap)
    standing = standing_frames(j)
    if standing.any():
        rot, j = rot[standing], j[standing]
    refs = rig_frame(reference_directions(j), jmap)
    joints, ends, rest = zip(*twisted)
    axes = measure_axes(rot[:, list(joints)], np.array(rest), refs[:, list(ends)])
    return dict(zip(joints, axes))


def _local_rotation(aims, goals: list[np.ndarray], axis: np.ndarray | None, ref: np.ndarray) -> np.ndarray:
    """Local rotations (T,3,3) of one joint turning its rest chain vectors onto ``goals`` (parent frame): several
    at once by Kabsch; the last link of a chain with its ``axis`` towards ``ref``; an earlier one a share of the
    arc."""
    if len(aims) > 1:
        return kabsch(np.stack([r for _, r, _ in aims]), np.stack(goals, axis=1))
    _, rest, left = aims[0]
    if left == 1:
        return aim_frames(rest, axis, goals[0], ref)
    swing = shortest_arc(rest, goals[0])
    return Rotation.from_rotvec(Rotation.from_matrix(swing).as_rotvec() / left).as_matrix()


def solve(q: np.ndarray, refs: np.ndarray, root: np.ndarray, rig: Bvh,
          plan: Plan) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Local rotations (T,J,3,3), translations (T,J,3) and positions (T,J,3) posing ``rig`` like targets ``q``
    (T,22,3, rig frame; ``refs`` their bones' reference directions) with the pelvis joint at ``root`` (T,3)."""
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
        if aims:
            ref = np.einsum("tji,tj->ti", parent_rot, refs[:, plan.smpl_of[aims[0][0]]])
            local[:, k] = _local_rotation(aims, goals, plan.axes.get(k), ref)
        else:
            local[:, k] = eye
        global_rot[:, k] = parent_rot @ local[:, k]
    return local, trans, pos


def foot_joints(rig: Bvh, jmap: JointMap) -> list[int]:
    """The rig joints the map reads for our ankles and toes, and every joint below them."""
    a, b, _ = map_indices(jmap, rig.names, rig.path)
    feet = {int(x) for x in np.concatenate([a[_FEET], b[_FEET]])}
    for k, parent in enumerate(rig.parents):
        if parent in feet:
            feet.add(k)
    return sorted(feet)


def foot_points(rig: Bvh, jmap: JointMap, local: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Positions (T,P,3, file units) of the rig's foot joints (:func:`foot_joints`) and of the End Sites below
    them (a toe's tip), posed by local rotations ``local`` (T,J,3,3) at joint positions ``pos`` (T,J,3)."""
    feet = foot_joints(rig, jmap)
    ends = [(k, np.asarray(o, dtype=np.float64)) for k, o in rig.end_sites if k in feet]
    if not ends:
        return pos[:, feet]
    rot = global_rotations(rig.parents, local)
    tips = [pos[:, k] + rot[:, k] @ o for k, o in ends]
    return np.concatenate([pos[:, feet], np.stack(tips, axis=1)], axis=1)


def floor_lift(j: np.ndarray, feet: np.ndarray) -> np.ndarray:
    """Heights (T,) to raise the rig by so that its lowest foot point, ``feet`` (T,F,3: our frame, metres), is as
    high as our lowest foot joint in every frame where one of ours is in contact (estimated from ``j`` (T,22,3)),
    interpolated between those frames (the median difference throughout when ours never touches down)."""
    from lsgan.motion.feet import estimate_contacts

    gap = j[:, _FEET, 1].min(axis=1) - feet[..., 1].min(axis=1)
    contact = np.flatnonzero(estimate_contacts(j.astype(np.float32)).any(axis=1))
    if not len(contact):
        return np.full(len(j), float(np.median(gap)))
    return np.interp(np.arange(len(j)), contact, gap[contact])


def _solved(j: np.ndarray, rig: Bvh, jmap: JointMap) -> tuple[Plan, np.ndarray, np.ndarray]:
    """The plan and :func:`solve`'s local rotations and translations (rig frame) for a checked motion ``j``, the
    root raised or lowered to put the rig's feet on our floor (:func:`floor_lift`)."""
    plan = plan_rig(rig, jmap)
    rest = apply_joint_map(rest_positions(rig.parents, rig.offsets)[None], rig.names, jmap, rig.path)
    ours = leg_length(j)
    if not ours > 1e-6:
        raise ValueError("the motion's legs have zero length")
    scale = leg_length(rest) / ours
    refs = rig_frame(reference_directions(j), jmap)
    local, trans, pos = solve(rig_frame(j, jmap), refs, rig_frame(j[:, 0] * scale, jmap), rig, plan)
    lift = floor_lift(j, metres_y_up(foot_points(rig, jmap, local, pos), jmap))
    trans[:, plan.carrier] += rig_frame(lift[:, None] * np.array([0.0, 1.0, 0.0]), jmap)
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


def mirrored_fraction(j: np.ndarray) -> float:
    """Fraction of frames of joints (T,22,3) whose left hip lies on the body's right, the body facing where its
    toes point and its knees bend (level part): 0 for a person, 1 for a mirrored one (a wrong handedness)."""
    hip, knee, ankle = ([JOINT_NAMES.index(n) for n in leg] for leg in zip(*_LEGS))
    knees = j[:, knee] - (j[:, hip] + j[:, ankle]) / 2
    forward = (j[:, _FEET[2:]] - j[:, _FEET[:2]] + knees).sum(axis=1) * np.array([1.0, 0.0, 1.0])
    left = np.cross(np.array([0.0, 1.0, 0.0]), forward)
    hips = j[:, JOINT_NAMES.index("left_hip")] - j[:, JOINT_NAMES.index("right_hip")]
    return float(np.mean(np.einsum("ti,ti->t", hips, left) < 0))


def map_warnings(rig: Bvh, jmap: JointMap) -> list[str]:
    """Warnings (empty: plausible) for a rig and joint map that would write a lying, giant or tiny, mirrored or
    twisted character: the rig's own poses (:func:`rig_poses`) read through the map, checked as imports are
    (:mod:`lsgan.data.plausibility`: size, up axis) and for mirroring, each naming the map and the likely cause;
    poses that never stand (:func:`standing_frames`) cannot say which way is up, nor where the knees face."""
    from lsgan.data.plausibility import clip_checks, findings

    j = rig_poses(rig, jmap)[2]
    where = f"{rig.path}: joint map {jmap.name!r}"
    standing = standing_frames(j).any()
    found = [(kind, text) for kind, text in findings(clip_checks(j)) if kind in ("scale", "up")]
    out = [f"{where} would write a {'lying' if kind == 'up' else 'wrongly sized'} character: {text}"
           for kind, text in found if kind == "scale" or (standing and rig.num_frames >= MOCAP_FRAMES)]
    if standing and rig.num_frames < MOCAP_FRAMES and any(kind == "up" for kind, _ in found):
        pose = "frames" if rig.num_frames else "rest pose"
        out.append(f"{where}: the rig's {pose} lie down through this map: if the character stands in its own "
                   "software, the map's `up` axis is wrong and the export would lie down too; if only its bind pose "
                   "lies, the export is upright and this can be ignored")
    if not standing:
        poses = "none of the rig's frames shows" if rig.num_frames else "the rig's rest pose (no frames) is not"
        out.append(f"{rig.path}: {poses} a standing figure (legs below the trunk, side by side), so where its "
                   "knees and elbows face cannot be read and a skinned character may get twisted limbs: add a frame "
                   "of its bind pose (a T-pose) or some of its own mocap to the rig file")
    mirrored = mirrored_fraction(j)
    if standing and not found and mirrored >= MIRRORED_FRACTION:
        out.append(f"{where} would write a mirrored character: the left hip is on the body's right in "
                   f"{100 * mirrored:.0f}% of the rig's frames: wrong `handedness` in the joint map?")
    return out


def rig_bvh_text(bvh: Bvh) -> str:
    """BVH text of a :class:`Bvh` (hierarchy as read, offsets and End Sites in its units, its channel orders)."""
    hierarchy = hierarchy_text(bvh.names, bvh.parents, bvh.offsets, bvh.channels, bvh.end_sites)
    return bvh_text(hierarchy, bvh.motion, 1.0 / bvh.frame_time)


def load_rig(path: str | Path) -> Bvh:
    """Read a rig BVH; a missing or malformed file raises ClipError naming it."""
    if not Path(path).is_file():
        raise ClipError(f"{path}: no such rig file")
    return read_bvh(path, rest_only=True)


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
