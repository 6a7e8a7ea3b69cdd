"""One rigid skeleton for a generated motion: the joints every output of ``generate`` and ``serve`` carries.

A decoder's joints (``recover_from_ric`` of its features) are not rigid: a bone's length drifts within a motion.
The BVH and GLB exports pose a rigid skeleton, so without this step they would show another motion than the
joints .npy, the previews and the server. :func:`make_rigid` makes a motion rigid once, right after decoding.
A VAE with ``rigid_output`` (:mod:`lsgan.models.decoder_head`) already decodes every bone at the data's length;
this step then only fits the layout of the two branching joints' children, which that head leaves free.

Bone lengths are each motion's median (over its frames) by default: the skeleton the model made for that motion,
robust to the frames where a bone stretches most, so the rigid motion stays as close as it can to the decoded one.
The training skeleton (:data:`lsgan.data.skeleton.BONE_LENGTHS`, onto which ``preprocess`` retargets every source)
moved the joints of 60 motions of a small demo model (``lsgan demo --scale 0.05``) 5x further (36.6 mm on average
against 7.2, at most 175 against 31 mm) and sank their feet by 42 mm on average (0.4 mm with the median): its legs
are not the legs the model stood on the floor; pass it as ``lengths`` to give every motion one skeleton. The
layout of the two branching joints' children (pelvis: hips and spine; spine3: neck and collars) is the motion's
own mean layout (:func:`lsgan.motion.fit.rest_offsets`).

Joints are re-posed by forward kinematics from the root: a single child lies along the decoded bone's direction at
its length; the children of a branching joint are its rigid layout turned by the Kabsch fit onto the decoded
ones. That is exactly what the BVH and GLB exports' IK (:func:`lsgan.export.bvh.joint_rotations`) reproduces, so
they show these joints. The 6D rotation channels are not used: beyond the bone directions they only add the twist
about each bone, which moves no joint.
"""
from __future__ import annotations

import numpy as np

from lsgan.data.skeleton import NUM_JOINTS, PARENTS, bone_lengths
from lsgan.motion.fit import CHILDREN, kabsch, rest_offsets

_PARENTS = np.array(PARENTS)
_BRANCHING = tuple(k for k in range(NUM_JOINTS) if len(CHILDREN[k]) > 1)  # pelvis and spine3


def rigid_offsets(joints: np.ndarray, lengths: np.ndarray | None = None) -> np.ndarray:
    """Rest offsets (22,3) for a (T,22,3) motion: :func:`rest_offsets`'s directions at ``lengths`` (22,), by default
    the motion's median bone lengths."""
    offsets = rest_offsets(joints)
    if lengths is None:
        lengths = np.median(bone_lengths(np.asarray(joints, np.float64)), axis=0)
    norm = np.linalg.norm(offsets, axis=-1, keepdims=True)
    return offsets / np.maximum(norm, 1e-12) * np.asarray(lengths, np.float64)[:, None]


def pose(joints: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(T,22,3) joints of the rigid skeleton ``offsets`` posed like ``joints``: the root where it is, each bone
    turned onto the observed one (see the module docstring). Batched over frames."""
    j = np.asarray(joints, dtype=np.float64)
    lengths = np.linalg.norm(offsets[1:], axis=-1)  # (21,)
    bones = j[:, 1:] - j[:, _PARENTS[1:]]  # (T,21,3)
    norm = np.linalg.norm(bones, axis=-1, keepdims=True)
    rest = offsets[1:] / np.maximum(lengths, 1e-12)[:, None]
    bones = np.where(norm > 1e-9, bones / np.maximum(norm, 1e-12), rest) * lengths[:, None]  # length 0: at rest
    for k in _BRANCHING:  # a branching joint's children: its layout turned onto theirs, in one rotation
        kids = list(CHILDREN[k])
        turn = kabsch(offsets[kids], j[:, kids] - j[:, [k]])  # (T,3,3)
        bones[:, [c - 1 for c in kids]] = np.einsum("tij,kj->tki", turn, offsets[kids])
    out = np.empty_like(j)
    out[:, 0] = j[:, 0]
    for k in range(1, NUM_JOINTS):  # PARENTS lists every parent before its children
        out[:, k] = out[:, _PARENTS[k]] + bones[:, k - 1]
    return out


def make_rigid(joints: np.ndarray, lengths: np.ndarray | None = None) -> np.ndarray:
    """Rigid joints (..., T, 22, 3) float32 for decoded joints of the same shape: every bone at ``lengths`` (22,) in
    every frame (default: each motion's median), the layouts fitted per motion (each (T,22,3) of the leading axes).
    Frames holding NaN or infinite values stay as they are."""
    j = np.asarray(joints)
    if j.shape[-2:] != (NUM_JOINTS, 3) or j.ndim < 3:
        raise ValueError(f"joints must be (..., T, {NUM_JOINTS}, 3), got {j.shape}")
    flat = j.reshape((-1,) + j.shape[-3:])
    out = np.array(flat, dtype=np.float32)
    for b, motion in enumerate(flat):
        ok = np.isfinite(motion).all(axis=(-1, -2))
        if ok.any():
            out[b, ok] = pose(motion[ok], rigid_offsets(motion[ok], lengths))
    return out.reshape(j.shape)
