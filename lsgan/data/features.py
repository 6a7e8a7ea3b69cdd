"""The HumanML3D 263-d motion representation: joints (T,22,3) -> features (T-1,263) and back.

Follows the original HumanML3D code step by step (uniform skeleton, floor, origin, facing +z, foot
contacts, IK with a smoothed facing, root-invariant positions, velocities) so that features of data
made with the original scripts agree to float precision. Layout per frame::

    [0]        root angular velocity about y        [1:3]      root linear velocity (x, z)
    [3]        root height                          [4:67]     ric positions of joints 1..21
    [67:193]   6D rotations of joints 1..21         [193:259]  velocities of the 22 joints
    [259:263]  foot contacts: left (7,10), right (8,11)
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.ndimage import gaussian_filter1d

from lsgan.data import quaternion as Q
from lsgan.data.kinematics import (
    facing_across,
    forward_from_across,
    forward_kinematics,
    inverse_kinematics,
    skeleton_offsets,
)
from lsgan.data.skeleton import (
    FACE_JOINTS,
    FEATURE_DIM,
    FOOT_CONTACT_THRESHOLD,
    KINEMATIC_CHAIN,
    LEFT_FOOT,
    LEG_JOINTS,
    NUM_JOINTS,
    RIGHT_FOOT,
    TARGET_OFFSETS,
)

# The original IK unpacks the face joints in another order than the rest of the code, so its
# across vector is (left hip - right hip) + (right shoulder - left shoulder). Kept for fidelity.
_IK_FACE_JOINTS = (FACE_JOINTS[1], FACE_JOINTS[0], FACE_JOINTS[2], FACE_JOINTS[3])
_Z = np.array([0.0, 0.0, 1.0])

_BATCH_FRAMES = 2048

# Feature slices.
ROOT_ROT_VEL = slice(0, 1)
ROOT_LIN_VEL = slice(1, 3)
ROOT_Y = slice(3, 4)
RIC = slice(4, 67)
ROT6D = slice(67, 193)
LOCAL_VEL = slice(193, 259)
FOOT_CONTACT = slice(259, 263)
GROUPS = (ROOT_ROT_VEL, ROOT_LIN_VEL, ROOT_Y, RIC, ROT6D, LOCAL_VEL, FOOT_CONTACT)


def _segment_starts(lengths: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)


def _root_quats(joints: np.ndarray, lengths: np.ndarray, smooth: bool) -> np.ndarray:
    """Root rotations (N,4) of concatenated clips (N,22,3): facing turned onto +z, per frame."""
    forward = forward_from_across(facing_across(joints, _IK_FACE_JOINTS))
    starts = _segment_starts(lengths)
    if smooth:
        forward = np.concatenate(
            [gaussian_filter1d(forward[s : s + n], 20, axis=0, mode="nearest") for s, n in zip(starts, lengths)]
        )
    forward = Q.normalize(forward)
    quats = Q.qbetween(forward, np.broadcast_to(_Z.astype(forward.dtype), forward.shape))
    # The reference code pins the first frame's root rotation to the identity (the clip was already
    # turned to face +z there); the features of frame 0 depend on it.
    quats[starts] = (1.0, 0.0, 0.0, 0.0)
    return quats


def uniform_skeleton(joints: np.ndarray, target_offsets: np.ndarray = TARGET_OFFSETS) -> np.ndarray:
    """Retarget (T,22,3) joints onto the target bone lengths, keeping the pose; root scaled by leg ratio."""
    return _uniform_skeleton(np.asarray(joints, dtype=np.float64), np.array([len(joints)]), target_offsets)


def _uniform_skeleton(joints: np.ndarray, lengths: np.ndarray, target_offsets: np.ndarray = TARGET_OFFSETS) -> np.ndarray:
    tgt = np.asarray(target_offsets, dtype=joints.dtype)
    a, b = LEG_JOINTS
    tgt_leg = np.abs(tgt[a]).max() + np.abs(tgt[b]).max()
    scales = []
    for s in _segment_starts(lengths):
        src = skeleton_offsets(joints[s])
        scales.append(tgt_leg / (np.abs(src[a]).max() + np.abs(src[b]).max()))
    scale = np.repeat(np.array(scales, dtype=joints.dtype), lengths)[:, None]
    quats = inverse_kinematics(joints, _root_quats(joints, lengths, smooth=False))
    return forward_kinematics(quats, joints[:, 0] * scale, tgt)


def _canonicalise(joints: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Per clip: floor at y=0, root x,z at the origin at frame 0, facing +z at frame 0."""
    starts = _segment_starts(lengths)
    floor = np.minimum.reduceat(joints[..., 1].min(-1), starts)
    first = joints[starts]  # (B,22,3)
    shift = first[:, 0] * np.array([1.0, 0.0, 1.0]) + floor[:, None] * np.array([0.0, 1.0, 0.0])
    forward = forward_from_across(facing_across(first, FACE_JOINTS))
    forward = Q.normalize(forward)
    q = Q.qbetween(forward, np.broadcast_to(_Z, forward.shape))  # (B,4)
    moved = joints - np.repeat(shift, lengths, axis=0)[:, None]
    return Q.qrot(np.repeat(q, lengths, axis=0)[:, None], moved)


def foot_contacts(joints: np.ndarray, threshold: float = FOOT_CONTACT_THRESHOLD) -> np.ndarray:
    """(T,22,3) -> (T-1,4) float32 contacts: squared per-frame displacement of joints 7,10,8,11 below threshold."""
    feet = list(LEFT_FOOT) + list(RIGHT_FOOT)
    disp = ((joints[1:, feet] - joints[:-1, feet]) ** 2).sum(-1)
    return (disp < threshold).astype(np.float32)


def _features_batch(clips: Sequence[np.ndarray], feet_threshold: float) -> list[np.ndarray]:
    """Features of many clips at once: the per-frame work runs on all frames concatenated."""
    for j in clips:
        if j.ndim != 3 or j.shape[1:] != (NUM_JOINTS, 3):
            raise ValueError(f"expected joints of shape (T, 22, 3), got {j.shape}")
        if len(j) < 2:
            raise ValueError(f"need at least 2 frames to compute features, got {len(j)}")
    lengths = np.array([len(j) for j in clips], dtype=np.int64)
    starts = _segment_starts(lengths)
    positions = np.concatenate([np.asarray(j, dtype=np.float32) for j in clips])
    positions = _canonicalise(_uniform_skeleton(positions, lengths), lengths)

    root_quat = _root_quats(positions, lengths, smooth=True)
    quats = inverse_kinematics(positions, root_quat)
    cont6d = Q.quat_to_cont6d(quats[:, 1:])  # (N,21,6)
    # Pairs (t, t+1) inside each clip: every frame but the last of its clip.
    keep = np.ones(len(positions), dtype=bool)
    keep[starts + lengths - 1] = False
    cur = np.flatnonzero(keep)
    nxt = cur + 1
    delta = positions[nxt] - positions[cur]  # (M,22,3)
    root_vel = Q.qrot(root_quat[nxt], delta[:, 0])
    r_vel = Q.qmul(root_quat[nxt], Q.qinv(root_quat[cur]))

    ric = positions[cur].copy()
    ric[..., 0] -= ric[:, 0:1, 0]
    ric[..., 2] -= ric[:, 0:1, 2]
    ric = Q.qrot(root_quat[cur][:, None], ric)
    local_vel = Q.qrot(root_quat[cur][:, None], delta)
    feet = list(LEFT_FOOT) + list(RIGHT_FOOT)

    M = len(cur)
    out = np.empty((M, FEATURE_DIM), dtype=np.float32)
    out[:, ROOT_ROT_VEL] = np.arcsin(np.clip(r_vel[:, 2:3], -1.0, 1.0))
    out[:, ROOT_LIN_VEL] = root_vel[:, [0, 2]]
    out[:, ROOT_Y] = ric[:, 0, 1:2]
    out[:, RIC] = ric[:, 1:].reshape(M, -1)
    out[:, ROT6D] = cont6d[cur].reshape(M, -1)
    out[:, LOCAL_VEL] = local_vel.reshape(M, -1)
    out[:, FOOT_CONTACT] = ((delta[:, feet] ** 2).sum(-1) < feet_threshold)
    return np.split(out, np.cumsum(lengths - 1)[:-1])


def joints_to_features(
    joints: np.ndarray | Sequence[np.ndarray], feet_threshold: float = FOOT_CONTACT_THRESHOLD
) -> np.ndarray | list[np.ndarray]:
    """HumanML3D features of one clip (T,22,3) -> (T-1,263), or of a list of clips -> list of arrays.

    A list is processed in one batch (all frames together), which is several times faster than a loop.
    """
    if isinstance(joints, np.ndarray):
        return _features_batch([joints], feet_threshold)[0]
    out: list[np.ndarray] = []
    group: list[np.ndarray] = []
    for clip in joints:  # groups of about _BATCH_FRAMES frames keep the working set in cache
        group.append(clip)
        if sum(len(c) for c in group) >= _BATCH_FRAMES:
            out += _features_batch(group, feet_threshold)
            group = []
    return out + (_features_batch(group, feet_threshold) if group else [])


def _xp(x):
    """numpy or torch, whichever ``x`` belongs to (the recover functions take both)."""
    if isinstance(x, np.ndarray):
        return np
    import torch

    return torch


def _cumsum(x, axis: int):
    return np.cumsum(x, axis=axis) if isinstance(x, np.ndarray) else x.cumsum(dim=axis)


def _qrot_yaw(angle, v, inverse: bool):
    """Rotate v (..., 3) about +y by the yaw quaternion (cos a, 0, sin a, 0) (or its inverse)."""
    c, s = _xp(angle).cos(angle), _xp(angle).sin(angle)
    if inverse:
        s = -s
    # For q = (c, 0, s, 0): qrot gives x' = x(1-2s^2) + 2cs z, z' = z(1-2s^2) - 2cs x.
    c2, s2 = 1 - 2 * s * s, 2 * c * s
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return _xp(v).stack([x * c2 + z * s2, y, z * c2 - x * s2], -1)


def recover_root(features):
    """Root yaw angle (...,T) and root position (...,T,3) integrated from features (...,T,263)."""
    rot_vel = features[..., 0]
    angle = _xp(features).zeros_like(rot_vel)
    angle[..., 1:] = rot_vel[..., :-1]
    angle = _cumsum(angle, -1)
    vel = _xp(features).zeros_like(features[..., :3])
    vel[..., 1:, 0] = features[..., :-1, 1]
    vel[..., 1:, 2] = features[..., :-1, 2]
    pos = _cumsum(_qrot_yaw(angle, vel, inverse=True), -2)
    pos[..., 1] = features[..., 3]
    return angle, pos


def recover_from_ric(features):
    """Joint positions (...,T,22,3) from features (...,T,263) via the root-invariant positions.

    Accepts numpy arrays or torch tensors (batched) and returns the same kind.
    """
    angle, root = recover_root(features)
    ric = features[..., RIC].reshape(features.shape[:-1] + (NUM_JOINTS - 1, 3))
    joints = _qrot_yaw(angle[..., None], ric, inverse=True)
    joints[..., 0] = joints[..., 0] + root[..., None, 0]
    joints[..., 2] = joints[..., 2] + root[..., None, 2]
    xp = _xp(features)
    cat = np.concatenate if xp is np else xp.cat
    return cat([root[..., None, :], joints], -2)


def recover_from_rot(features: np.ndarray, offsets: np.ndarray = TARGET_OFFSETS) -> np.ndarray:
    """Joint positions (...,T,22,3) by forward kinematics of the 6D rotations on the target skeleton (numpy)."""
    features = np.asarray(features, dtype=np.float64)
    angle, root = recover_root(features)
    yaw = np.zeros(angle.shape + (4,))
    yaw[..., 0], yaw[..., 2] = np.cos(angle), np.sin(angle)
    mats = np.empty(features.shape[:-1] + (NUM_JOINTS, 3, 3))
    mats[..., 0, :, :] = Q.quat_to_matrix(yaw)
    mats[..., 1:, :, :] = Q.cont6d_to_matrix(features[..., ROT6D].reshape(features.shape[:-1] + (NUM_JOINTS - 1, 6)))
    offsets = np.asarray(offsets, dtype=np.float64)
    joints = np.zeros(features.shape[:-1] + (NUM_JOINTS, 3))
    joints[..., 0, :] = root
    for chain in KINEMATIC_CHAIN:
        R = mats[..., 0, :, :]
        for parent, child in zip(chain[:-1], chain[1:]):
            R = R @ mats[..., child, :, :]
            joints[..., child, :] = R @ offsets[child] + joints[..., parent, :]
    return joints.astype(np.float32)


def mirror_features(features: np.ndarray) -> np.ndarray:
    """Features of the mirrored motion, computed through the joints (recover, mirror, re-featurise)."""
    from lsgan.data.skeleton import mirror_joints

    joints = recover_from_ric(np.asarray(features, dtype=np.float64))
    return joints_to_features(mirror_joints(joints))


def group_std(std: np.ndarray) -> np.ndarray:
    """Replace a (263,) per-feature std by the mean std of each of the 7 feature groups (HumanML3D's rule)."""
    out = np.array(std, dtype=np.float64, copy=True)
    for g in GROUPS:
        out[g] = out[g].mean()
    return out.astype(np.float32)
