"""Bones of HumanML3D features, and features put on a skeleton: numpy or torch arrays alike (torch-free import).

The ``ric`` slice (features 4:67) holds joints 1..21 in the root's frame and feature 3 the root's height, so the
root sits at (0, height, 0) there: a rotation and a shift of the world's joints, with the same bones. One
implementation serves the VAE decoder's rigid step (:mod:`lsgan.models.decoder_head`, torch, trained through) and
the cross-faded seams of a timeline (:mod:`lsgan.timeline`, numpy, in both runtimes).
"""
from __future__ import annotations

import numpy as np

from lsgan.data.features import RIC
from lsgan.data.skeleton import NUM_JOINTS, PARENTS
from lsgan.data.skeleton import bones_below_root as bone_lengths  # (...,22,3) -> (...,21)


def _is_np(x) -> bool:
    return isinstance(x, np.ndarray)


def _ops(x):
    """(stack, concatenate, where) for ``x``'s kind of array."""
    if _is_np(x):
        return np.stack, np.concatenate, np.where
    import torch

    return torch.stack, torch.cat, torch.where


def _norm(x):
    """The norm over the last axis, kept as a size-1 axis."""
    return np.linalg.norm(x, axis=-1, keepdims=True) if _is_np(x) else x.norm(dim=-1, keepdim=True)


def root_frame_joints(features):
    """De-normalised features (...,263) -> the 22 joints (...,22,3) in the root's frame."""
    _, cat, _ = _ops(features)
    y = features[..., 3:4]
    root = cat([y * 0, y, y * 0], -1)[..., None, :]  # (...,1,3)
    return cat([root, features[..., RIC].reshape(tuple(features.shape[:-1]) + (NUM_JOINTS - 1, 3))], -2)


def skeleton_lengths(features):
    """The bone lengths (21,) of frames (N,263) of de-normalised features: their median over the frames."""
    lengths = bone_lengths(root_frame_joints(features))
    return np.median(lengths, axis=0) if _is_np(lengths) else lengths.double().quantile(0.5, dim=0).float()


def on_skeleton(features, lengths):
    """De-normalised features (...,263) with their ``ric`` joints on the bones ``lengths`` ((21,), or (...,21) per
    frame): from the root outwards, each joint at its parent plus the decoded bone's direction times the bone's
    length; a bone decoded with no length points up (+y). Every other feature is unchanged."""
    stack, cat, where = _ops(features)
    joints = root_frame_joints(features)
    zero = joints[..., 0, :1] * 0
    up = cat([zero, zero + 1, zero], -1)  # (...,3)
    out = [joints[..., 0, :]]
    for k in range(1, NUM_JOINTS):  # PARENTS lists every parent before its children
        bone = joints[..., k, :] - joints[..., PARENTS[k], :]
        norm = _norm(bone)
        short = norm <= 1e-8
        direction = where(short, up, bone / (norm + short))  # no 0/0, not even in the branch where() drops
        out.append(out[PARENTS[k]] + direction * lengths[..., k - 1 : k])
    ric = stack(out[1:], -2).reshape(tuple(features.shape[:-1]) + (3 * (NUM_JOINTS - 1),))
    return cat([features[..., : RIC.start], ric, features[..., RIC.stop :]], -1)
