"""Twist rules shared by every IK of lsgan's exports: which way each bone's twist faces, read off the body.

A bone's direction leaves its twist about itself open. Each bone (named by the SMPL joint it ends at) gets a
*reference direction* from the 22 joints, in the same frame as the joints (:func:`reference_directions`):

- thigh and shin (bones ending at a knee or ankle): the knee's forward, from the hip-ankle line to the knee;
  upper arm and forearm (ending at an elbow or wrist): where the elbow bends the hand to. A limb bent less than
  ``BENT_DEG`` blends towards the body's forward (the hips line for legs, the shoulders line for arms, crossed
  with pelvis->spine3) and, where the bone points along that forward, towards the previous frame's reference
  carried along with the bone. A slight bend the other way (a hyperextended knee or elbow) counts as the usual
  one. The lower bone's reference is the upper one's turned about the limb's hinge axis (normal to its plane).
- foot (ending at the toe): the sole's down, the toe direction crossed with the knee's hinge axis (the ankle
  bends about nearly the same axis), leaning to world down where the foot is level.
- spine bones and neck: the body's left, from the hips line at the pelvis to the shoulders line at the chest;
  hips and collars: the body's forward.

A skeleton's own convention is measured once (:func:`measure_axes`): the local axis of each bone that its
poses (a rig's own mocap, else its rest pose) turn towards the reference direction. Posing then aims each bone
along its target and that axis at the target's reference (:func:`aim_frames`), so the twist follows the body
and is the rig's own, whatever its rest frames are.
"""
from __future__ import annotations

import numpy as np

from lsgan.data.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS
from lsgan.motion.fit import shortest_arc

_I = JOINT_NAMES.index
BENT_DEG = (8.0, 25.0)  # a limb's bend plane counts fully from 25 degrees of bend, not at all below 8
_SIDES = ("left", "right")
LEG_TRUNK_DEG, LEGS_APART_DEG = 110.0, 90.0  # a standing layout (standing_frames): every frame of 300 Bandai clips


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def perpendicular(v: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The part of vectors ``v`` (...,3) perpendicular to unit vectors ``axis`` (...,3)."""
    return v - np.sum(v * axis, axis=-1, keepdims=True) * axis


def _ramp(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((x - lo) / (hi - lo), 0.0, 1.0)


def body_frame(j: np.ndarray) -> dict[str, np.ndarray]:
    """Per-frame unit lines (T,3) of a body (T,22,3): ``up`` (pelvis to spine3), ``hips`` and ``shoulders`` (right
    to left), and the ``forward`` of each line (line x up: +Z for a body facing +Z with its left at +X)."""
    up = unit(j[:, _I("spine3")] - j[:, _I("pelvis")])
    hips = unit(j[:, _I("left_hip")] - j[:, _I("right_hip")])
    shoulders = unit(j[:, _I("left_shoulder")] - j[:, _I("right_shoulder")])
    return {"up": up, "hips": hips, "shoulders": shoulders,
            "hips_forward": unit(np.cross(hips, up)), "shoulders_forward": unit(np.cross(shoulders, up))}


def _limb_forward(j: np.ndarray, a: int, b: int, c: int, sign: float, forward: np.ndarray) -> np.ndarray:
    """(T,3) forward of the limb a-b-c: its bend where it bends, else ``forward``, else the carried previous."""
    upper, whole = unit(j[:, b] - j[:, a]), unit(j[:, c] - j[:, a])
    bend = sign * unit(perpendicular(j[:, b] - j[:, a], whole))
    lower = unit(j[:, c] - j[:, b])
    w_bend = _ramp(np.degrees(np.arccos(np.clip(np.sum(upper * lower, -1), -1, 1))), *BENT_DEG)
    body = perpendicular(forward, upper)
    w_body = _ramp(np.linalg.norm(body, axis=-1), 0.3, 0.6)
    out = np.empty_like(upper)
    carried = unit(body[0])
    for t in range(len(j)):
        if t:
            carried = out[t - 1] - np.dot(out[t - 1], upper[t]) * upper[t]  # carried along with the bone
        guess = w_body[t] * unit(body[t]) + (1.0 - w_body[t]) * unit(carried)
        seen = bend[t] if w_bend[t] >= 1.0 or np.dot(bend[t], guess) >= 0 else -bend[t]  # slight hyperextension
        out[t] = unit(perpendicular(w_bend[t] * seen + (1.0 - w_bend[t]) * guess, upper[t]))
    return out


def _sole(toes: np.ndarray, hinge: np.ndarray) -> np.ndarray:
    """(T,3) the sole's down for toe directions (T,3): the toes crossed with the leg's hinge (knee axis), leaning
    to world down about the toes where the two agree (a level foot's sole faces the floor)."""
    bent = unit(np.cross(toes, hinge))
    level = perpendicular(np.broadcast_to([0.0, -1.0, 0.0], toes.shape), toes)
    agree = np.clip(np.sum(unit(level) * bent, axis=-1, keepdims=True), 0.0, 1.0)
    return unit(bent + 2.0 * agree * level)


def reference_directions(joints: np.ndarray) -> np.ndarray:
    """Reference directions (T,22,3) per bone, indexed by the joint it ends at (see the module docstring)."""
    j = np.asarray(joints, dtype=np.float64)
    body = body_frame(j)
    ref = np.zeros(j.shape)
    for k, blend in ((_I("spine1"), 0.0), (_I("spine2"), 1 / 3), (_I("spine3"), 2 / 3), (_I("neck"), 1.0),
                     (_I("head"), 1.0)):
        ref[:, k] = unit((1.0 - blend) * body["hips"] + blend * body["shoulders"])
    for side in _SIDES:
        hip, knee, ankle, toe = (_I(f"{side}_{n}") for n in ("hip", "knee", "ankle", "foot"))
        shoulder, elbow, wrist = (_I(f"{side}_{n}") for n in ("shoulder", "elbow", "wrist"))
        ref[:, hip] = body["hips_forward"]
        ref[:, _I(f"{side}_collar")] = ref[:, shoulder] = body["shoulders_forward"]
        hinges = []
        for a, b, c, sign, line in ((hip, knee, ankle, 1.0, "hips"), (shoulder, elbow, wrist, -1.0, "shoulders")):
            ref[:, b] = _limb_forward(j, a, b, c, sign, body[f"{line}_forward"])
            hinges.append(np.cross(unit(j[:, b] - j[:, a]), ref[:, b]))  # normal to the limb's plane
            ref[:, c] = unit(np.cross(hinges[-1], unit(j[:, c] - j[:, b])))
        ref[:, toe] = _sole(unit(j[:, toe] - j[:, ankle]), hinges[0])
    return ref


def standing_frames(joints: np.ndarray) -> np.ndarray:
    """(T,) which frames of joints (T,22,3) are laid out as a person standing (T-pose, A-pose, a walk), whatever
    way the figure faces or lies: both legs (hip to ankle) point away from the trunk (pelvis to spine3), over
    ``LEG_TRUNK_DEG`` from it, and within ``LEGS_APART_DEG`` of each other. Only such frames say where a rig's
    knees and elbows face: a zero pose with the legs spread along one line (Bandai's) says nothing of it."""
    j = np.asarray(joints, dtype=np.float64)
    up = unit(j[:, _I("spine3")] - j[:, _I("pelvis")])
    legs = [unit(j[:, _I(f"{side}_ankle")] - j[:, _I(f"{side}_hip")]) for side in _SIDES]
    cos_trunk = np.cos(np.radians(LEG_TRUNK_DEG))
    return ((np.sum(legs[0] * up, -1) < cos_trunk) & (np.sum(legs[1] * up, -1) < cos_trunk)
            & (np.sum(legs[0] * legs[1], -1) > np.cos(np.radians(LEGS_APART_DEG))))


def measure_axes(global_rot: np.ndarray, aims: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """Local axes (K,3), unit and perpendicular to each bone's local aim ``aims`` (K,3), that the poses
    ``global_rot`` (F,K,3,3) turn on average towards the reference directions ``refs`` (F,K,3), same frame."""
    local = np.einsum("fkji,fkj->fki", global_rot, refs)
    axis = unit(aims)
    mean = perpendicular(local.sum(axis=0), axis)
    fallback = perpendicular(np.eye(3)[np.argmin(np.abs(axis), axis=-1)], axis)  # degenerate: any perpendicular
    return unit(np.where(np.linalg.norm(mean, axis=-1, keepdims=True) > 1e-9, mean, fallback))


def aim_frames(aim: np.ndarray, axis: np.ndarray, goal: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Rotations (...,3,3) turning ``aim`` onto ``goal`` and ``axis`` (perpendicular to ``aim``) as close as
    possible to ``ref``; where ``ref`` lies along ``goal`` the twist is that of the shortest arc."""

    g = unit(goal)
    s = perpendicular(ref, g)
    arc = np.einsum("...ij,...j->...i", shortest_arc(aim, g), np.broadcast_to(axis, g.shape))
    s = unit(np.where(np.linalg.norm(s, axis=-1, keepdims=True) > 1e-6, s, arc))
    a, x = np.broadcast_arrays(unit(aim), unit(axis))
    target = np.stack([g, s, np.cross(g, s)], axis=-1)
    source = np.stack([a, x, np.cross(a, x)], axis=-1)
    return target @ np.swapaxes(source, -1, -2)


def smpl_axes(rest: np.ndarray) -> np.ndarray:
    """Local axes (22,3) of our own skeleton's single-child joints, measured on its rest joints (22,3): joint k's
    axis belongs to its bone towards its only child (rows of leaves and branching joints are unused)."""
    r = np.asarray(rest, dtype=np.float64)[:NUM_JOINTS]
    refs = reference_directions(r[None])[0]
    axes = np.zeros((NUM_JOINTS, 3))
    for k in range(NUM_JOINTS):
        kids = [c for c in range(NUM_JOINTS) if PARENTS[c] == k]
        if len(kids) == 1:
            axes[k] = measure_axes(np.eye(3)[None, None], (r[kids[0]] - r[k])[None], refs[None, kids])[0]
    return axes
