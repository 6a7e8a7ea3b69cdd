"""The 22-joint HumanML3D skeleton (SMPL joint order, Y up, metres) and its pure geometry helpers."""
from __future__ import annotations

import numpy as np

JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist",
)
NUM_JOINTS = 22
FEATURE_DIM = 263
FPS = 20

PARENTS: tuple[int, ...] = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)

KINEMATIC_CHAIN: tuple[tuple[int, ...], ...] = (
    (0, 2, 5, 8, 11),
    (0, 1, 4, 7, 10),
    (0, 3, 6, 9, 12, 15),
    (9, 14, 17, 19, 21),
    (9, 13, 16, 18, 20),
)

# Unit direction of each bone in the rest pose (the T2M "raw offsets").
RAW_OFFSETS = np.array(
    [[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0],
     [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0],
     [-1, 0, 0], [0, 0, 1], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0],
     [0, -1, 0]],
    dtype=np.float64,
)

# Bone lengths of the HumanML3D target skeleton (clip 000021, frame 0), in metres, per joint
# (the length of the bone from its parent). Target offsets = RAW_OFFSETS * BONE_LENGTHS.
BONE_LENGTHS = np.array(
    [0.0, 0.10307394713163376, 0.10988335311412811, 0.13156825304031372, 0.39362314343452454,
     0.3901881277561188, 0.14319026470184326, 0.43243297934532166, 0.42564332485198975,
     0.057364705950021744, 0.1433817446231842, 0.1494186669588089, 0.21935999393463135,
     0.13748683035373688, 0.14338283240795135, 0.10303927212953568, 0.13161398470401764,
     0.12298430502414703, 0.2568398416042328, 0.2630918622016907, 0.2660118639469147,
     0.26987630128860474],
    dtype=np.float64,
)
TARGET_OFFSETS = (RAW_OFFSETS * BONE_LENGTHS[:, None]).astype(np.float32)

FACE_JOINTS = (2, 1, 17, 16)  # right hip, left hip, right shoulder, left shoulder
LEG_JOINTS = (5, 8)  # lower legs: their bone lengths give the scale ratio
LEFT_FOOT = (7, 10)
RIGHT_FOOT = (8, 11)
FOOT_CONTACT_THRESHOLD = 0.002

MIRROR_PAIRS: tuple[tuple[int, int], ...] = (
    (1, 2), (4, 5), (7, 8), (10, 11), (13, 14), (16, 17), (18, 19), (20, 21),
)


def _mirror_permutation() -> np.ndarray:
    perm = np.arange(NUM_JOINTS)
    for a, b in MIRROR_PAIRS:
        perm[a], perm[b] = b, a
    return perm


MIRROR_PERMUTATION = _mirror_permutation()


def mirror_joints(joints: np.ndarray) -> np.ndarray:
    """Mirror (..., 22, 3) joint positions across the YZ plane: negate x, swap left and right joints."""
    out = np.array(joints, copy=True)[..., MIRROR_PERMUTATION, :]
    out[..., 0] *= -1
    return out


def bones_below_root(joints):
    """The length of every bone below the root, (..., 22, 3) -> (..., 21): numpy arrays or torch tensors."""
    d = joints[..., 1:, :] - joints[..., list(PARENTS[1:]), :]
    return np.linalg.norm(d, axis=-1) if isinstance(d, np.ndarray) else d.norm(dim=-1)


def bone_lengths(joints: np.ndarray) -> np.ndarray:
    """Length of every bone, (..., 22, 3) -> (..., 22); entry 0 (the root) is 0."""
    lengths = bones_below_root(np.asarray(joints))
    return np.concatenate([np.zeros(lengths.shape[:-1] + (1,), dtype=lengths.dtype), lengths], axis=-1)
