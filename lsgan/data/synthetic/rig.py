"""The procedural body: the target skeleton's proportions, a motion's drivers (:class:`_Pose`) and how they become
joint positions (bone directions, analytic two-bone IK for the legs).

Every bone is its BONE_LENGTHS entry long (forward kinematics of the target offsets). "Left" and "right" are the
character's own sides (+x is its left at rest, facing +z); side index 0 is the left, 1 the right.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from lsgan.data.skeleton import BONE_LENGTHS, NUM_JOINTS

_L = BONE_LENGTHS
_SIGN = np.array([1.0, -1.0])  # index 0 = the character's left (+x), 1 = its right (-x)
_SIDE_NAME = ("left", "right")
_HIP_W = _L[[1, 2]]
_THIGH = _L[[4, 5]]
_SHIN = _L[[7, 8]]
_FOOT = _L[[10, 11]]
_LEG = _THIGH + _SHIN
# The left leg is 1 cm longer than the right: the pelvis tilts slightly so that both knees bend alike.
_HIP_TILT = np.arcsin((_LEG[0] - _LEG[1]) / _HIP_W.sum())
_HIP_DY = _SIGN * _HIP_W * np.sin(_HIP_TILT)  # hip height above the pelvis, per side
_ANKLE_H = 0.075  # ankle height with the foot flat (the foot joint on the floor)
_P0 = np.arcsin(_ANKLE_H / _FOOT)  # flat-foot pitch of the ankle->foot bone, per side
_REACH = 0.999  # planted legs are kept below this fraction of full extension
_HIP, _KNEE, _ANKLE, _TOE = (1, 2), (4, 5), (7, 8), (10, 11)
_COLLAR, _SHOULDER, _ELBOW, _WRIST = (13, 14), (16, 17), (18, 19), (20, 21)
_NECK_DIR = np.array([0.0, 1.0, 0.08])
_HEAD_DIR = np.array([0.0, 1.0, 0.35])
_COLLAR_DIR = np.array([0.55, 0.83, -0.05])
_SHOULDER_DIR = np.array([1.0, -0.15, -0.05])


@dataclass
class _Pose:
    """A motion described by its drivers; :func:`_assemble` turns it into joint positions.

    Arm directions are in the torso frame (x = the character's left, y = up, z = forward).
    """

    pelvis: np.ndarray  # (T,3)
    yaw: np.ndarray  # (T,) facing angle about +y; positive turns the character to its left
    lean: np.ndarray  # (T,) torso pitch, positive forward
    roll: np.ndarray  # (T,) torso roll, positive towards the character's left
    foot: np.ndarray  # (T,2,3) foot-joint targets, left then right
    foot_dir: np.ndarray  # (T,2,3) ankle->foot directions
    upper: np.ndarray  # (T,2,3) upper-arm directions
    fore: np.ndarray  # (T,2,3) forearm directions
    knee_out: float = 0.1  # how far the knees point outwards


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rot_y(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rot_x(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _rot_z(a: np.ndarray) -> np.ndarray:
    c, s, z, o = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _arm(side: float, elev: np.ndarray | float, azim: np.ndarray | float, out: float = 0.0) -> np.ndarray:
    """Limb direction in the torso frame: ``elev`` from hanging down (0) to straight up (pi), raised in
    the plane at ``azim`` (0 = out to the side, pi/2 = forward); ``out`` adds a constant abduction."""
    elev, azim = np.broadcast_arrays(np.asarray(elev, dtype=np.float64), np.asarray(azim, dtype=np.float64))
    return np.stack([side * (np.sin(elev) * np.cos(azim) + out), -np.cos(elev), np.sin(elev) * np.sin(azim)], -1)


def _arm_angles(side: float, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`_arm` (without ``out``): (elev, azim) of directions (..., 3)."""
    elev = np.arccos(np.clip(-v[..., 1] / np.linalg.norm(v, axis=-1), -1.0, 1.0))
    return elev, np.arctan2(v[..., 2], side * v[..., 0])


def _both(fn: Callable[[int, float], np.ndarray]) -> np.ndarray:
    """Stack a per-side function (side index, sign) into (T,2,3), left first."""
    return np.stack([fn(k, s) for k, s in enumerate(_SIGN)], 1)


def _foot_dir(psi: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Ankle->foot unit direction from the foot's yaw and its downward pitch."""
    return np.stack([np.sin(psi) * np.cos(pitch), -np.sin(pitch), np.cos(psi) * np.cos(pitch)], -1)


def _two_bone(root: np.ndarray, target: np.ndarray, l1: float, l2: float, lateral: np.ndarray,
              out: float) -> tuple[np.ndarray, np.ndarray]:
    """Analytic two-bone IK: (middle, end) joints with |middle-root| = l1, |end-middle| = l2.

    The end reaches ``target`` when it can (else the nearest reachable point on the same ray); the middle
    joint bends towards cross(limb, lateral) (a knee bends forward) plus ``out`` x lateral.
    """
    d_vec = target - root
    d = np.linalg.norm(d_vec, axis=-1, keepdims=True)
    u = d_vec / np.maximum(d, 1e-9)
    d = np.clip(d, abs(l1 - l2) + 1e-4, (l1 + l2) * (1.0 - 1e-4))
    a = (l1 * l1 - l2 * l2 + d * d) / (2.0 * d)
    h = np.sqrt(np.maximum(l1 * l1 - a * a, 0.0))
    pole = np.cross(u, lateral) + out * lateral
    pole = _unit(pole - (pole * u).sum(-1, keepdims=True) * u)
    return root + a * u + h * pole, root + d * u


def _assemble(p: _Pose) -> np.ndarray:
    """Joint positions (T,22,3) float64: every bone is placed as parent + BONE_LENGTHS[j] * direction."""
    T = len(p.yaw)
    j = np.zeros((T, NUM_JOINTS, 3))
    ry = _rot_y(p.yaw)
    rt = ry @ _rot_x(p.lean) @ _rot_z(-p.roll)
    up = rt[..., :, 1]
    lateral = ry[..., :, 0]
    j[:, 0] = p.pelvis
    j[:, 3] = j[:, 0] + _L[3] * up
    j[:, 6] = j[:, 3] + _L[6] * up
    j[:, 9] = j[:, 6] + _L[9] * up
    j[:, 12] = j[:, 9] + _L[12] * (rt @ _unit(_NECK_DIR))
    j[:, 15] = j[:, 12] + _L[15] * (rt @ _unit(_HEAD_DIR))
    for k, s in enumerate(_SIGN):
        hip = j[:, 0] + s * _HIP_W[k] * np.cos(_HIP_TILT) * lateral + np.array([0.0, _HIP_DY[k], 0.0])
        fdir = _unit(p.foot_dir[:, k])
        knee, ankle = _two_bone(hip, p.foot[:, k] - _FOOT[k] * fdir, _THIGH[k], _SHIN[k], lateral, s * p.knee_out)
        j[:, _HIP[k]], j[:, _KNEE[k]], j[:, _ANKLE[k]] = hip, knee, ankle
        j[:, _TOE[k]] = ankle + _FOOT[k] * fdir
        side = np.array([s, 1.0, 1.0])
        j[:, _COLLAR[k]] = j[:, 9] + _L[_COLLAR[k]] * (rt @ _unit(_COLLAR_DIR * side))
        j[:, _SHOULDER[k]] = j[:, _COLLAR[k]] + _L[_SHOULDER[k]] * (rt @ _unit(_SHOULDER_DIR * side))
        upper = np.einsum("tij,tj->ti", rt, _unit(p.upper[:, k]))
        fore = np.einsum("tij,tj->ti", rt, _unit(p.fore[:, k]))
        j[:, _ELBOW[k]] = j[:, _SHOULDER[k]] + _L[_ELBOW[k]] * upper
        j[:, _WRIST[k]] = j[:, _ELBOW[k]] + _L[_WRIST[k]] * fore
    return j


def _pelvis_height(extension: float) -> float:
    """Pelvis height that puts flat feet straight under the hips at ``extension`` x leg length."""
    return float(_ANKLE_H + np.min(extension * _LEG - _HIP_DY))


def _finish(joints: np.ndarray) -> np.ndarray:
    """Put the lowest joint of the clip on the floor; float32."""
    out = joints.copy()
    out[..., 1] -= out[..., 1].min()
    return out.astype(np.float32)
