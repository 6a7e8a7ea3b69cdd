"""Forward and inverse kinematics on the 22-joint skeleton (arrays in, arrays out, batched over frames)."""
from __future__ import annotations

import numpy as np

from lsgan.data import quaternion as Q
from lsgan.data.skeleton import KINEMATIC_CHAIN, NUM_JOINTS, PARENTS, RAW_OFFSETS, TARGET_OFFSETS


def skeleton_offsets(joints: np.ndarray) -> np.ndarray:
    """Per-joint offsets of a pose: raw bone direction x measured bone length, (22,3) -> (22,3)."""
    j = np.asarray(joints, dtype=np.float64)
    lengths = np.linalg.norm(j[1:] - j[np.array(PARENTS[1:])], axis=-1)
    return np.concatenate([np.zeros((1, 3)), RAW_OFFSETS[1:] * lengths[:, None]], axis=0)


def facing_across(joints: np.ndarray, face_joints: tuple[int, int, int, int]) -> np.ndarray:
    """Unit across-body vector from (..., 22, 3) joints: (j[a]-j[b]) + (j[c]-j[d]) for face_joints (a,b,c,d)."""
    a, b, c, d = face_joints
    across = (joints[..., a, :] - joints[..., b, :]) + (joints[..., c, :] - joints[..., d, :])
    return Q.normalize(across)


def forward_from_across(across: np.ndarray) -> np.ndarray:
    """Forward direction = up x across (Y up)."""
    up = np.broadcast_to(np.array([0.0, 1.0, 0.0], dtype=across.dtype), across.shape)
    return Q._cross(up, across)


def inverse_kinematics(joints: np.ndarray, root_quat: np.ndarray) -> np.ndarray:
    """Local joint quaternions (T,22,4) that bend the raw rest pose onto (T,22,3) ``joints``.

    ``root_quat`` (T,4) is the root rotation; each bone's local rotation is the shortest arc from its
    raw offset direction to the observed bone, expressed in its parent's frame (as HumanML3D does).
    """
    T = joints.shape[0]
    quats = np.zeros((T, NUM_JOINTS, 4), dtype=joints.dtype)
    quats[:, 0] = root_quat
    for chain in KINEMATIC_CHAIN:
        R = root_quat
        for parent, child in zip(chain[:-1], chain[1:]):
            u = np.broadcast_to(RAW_OFFSETS[child].astype(joints.dtype), (T, 3))
            v = joints[:, child] - joints[:, parent]
            v = Q.normalize(v)
            rot_uv = Q.qbetween(u, v)
            quats[:, child] = Q.qmul(Q.qinv(R), rot_uv)
            R = rot_uv  # = R * local rotation
    return quats


def forward_kinematics(quats: np.ndarray, root_pos: np.ndarray, offsets: np.ndarray = TARGET_OFFSETS) -> np.ndarray:
    """Joint positions (T,22,3) from local quaternions (T,22,4), root positions (T,3) and offsets (22,3).

    As in HumanML3D, every kinematic chain starts from the root orientation: the arm chains, which
    begin at spine3, do not inherit the spine's rotations (the inverse above is built the same way).
    """
    offsets = np.asarray(offsets, dtype=quats.dtype)
    joints = np.zeros(quats.shape[:-1] + (3,), dtype=quats.dtype)
    joints[:, 0] = root_pos
    for chain in KINEMATIC_CHAIN:
        R = quats[:, 0]
        for parent, child in zip(chain[:-1], chain[1:]):
            R = Q.qmul(R, quats[:, child])
            joints[:, child] = Q.qrot(R, np.broadcast_to(offsets[child], R.shape[:-1] + (3,))) + joints[:, parent]
    return joints


def forward_kinematics_matrices(
    local_rotations: np.ndarray, root_pos: np.ndarray, offsets: np.ndarray = TARGET_OFFSETS
) -> np.ndarray:
    """Joint positions (...,22,3) from local rotation matrices (...,22,3,3) (entry 0 = root orientation).

    Same chain convention as :func:`forward_kinematics`: each chain starts from the root orientation.
    """
    offsets = np.asarray(offsets, dtype=np.float64)
    joints = np.zeros(local_rotations.shape[:-2] + (3,))
    joints[..., 0, :] = root_pos
    for chain in KINEMATIC_CHAIN:
        R = local_rotations[..., 0, :, :]
        for parent, child in zip(chain[:-1], chain[1:]):
            R = R @ local_rotations[..., child, :, :]
            joints[..., child, :] = R @ offsets[child] + joints[..., parent, :]
    return joints
