"""Inverse kinematics for a pose that must put some joints at given points: FABRIK along the skeleton's chains.

A keyframe that sets only some joints (a hand at a point, the head at a height) is completed into a whole pose
here, so that :func:`lsgan.constraints.warp_poses` can warp the motion onto it exactly as onto a whole pose. The
pose's own bone lengths are kept; the chains bend from where they are (FABRIK, Aristidou and Lasenby 2011), so a
reached arm keeps the plane its elbow bent in. Pure numpy: arrays in, arrays out.
"""
from __future__ import annotations

import numpy as np

from lsgan.data.skeleton import KINEMATIC_CHAIN, NUM_JOINTS, PARENTS

ITERATIONS = 64  # FABRIK passes at most; a reachable target is met to TOLERANCE within a few dozen
TOLERANCE = 1e-6  # metres


def reach_pose(pose: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``pose`` (22, 3) moved so that every set coordinate of ``target`` (22, 3), NaN = free, is met: a set root
    moves the whole pose; along each chain (legs, spine, arms, base first) the joints up to each set one are
    solved by FABRIK with the chain's base held, and the joints hanging from a moved joint move with it. A target
    out of reach is approached in a straight line (the miss is what :func:`lsgan.constraints.measure` reports)."""
    out = np.array(pose, np.float64)
    target = np.asarray(target, np.float64)
    if target.shape != (NUM_JOINTS, 3) or out.shape != (NUM_JOINTS, 3):
        raise ValueError(f"a pose and its target are ({NUM_JOINTS}, 3), not {out.shape} and {target.shape}")
    if not np.isnan(target[0]).all():
        out += np.where(np.isnan(target[0]), 0.0, target[0] - out[0])
    for chain in KINEMATIC_CHAIN:
        base = 0
        for k in range(1, len(chain)):
            j = chain[k]
            if np.isnan(target[j]).all():
                continue
            goal = np.where(np.isnan(target[j]), out[j], target[j])
            segment = list(chain[base:k + 1])
            before = out.copy()
            out[segment] = fabrik(out[segment], goal)
            _carry(out, before, set(segment))
            base = k
    return out


def fabrik(points: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """A chain's joints (n, 3), its first held, moved so that its last is at ``goal`` with every link's length kept
    (FABRIK); straight towards ``goal`` when it is beyond the chain's reach."""
    p = np.array(points, np.float64)
    lengths = np.linalg.norm(np.diff(p, axis=0), axis=-1)
    base = p[0].copy()
    if np.linalg.norm(goal - base) >= lengths.sum():
        direction = _unit(goal - base)
        return base + np.concatenate([[0.0], np.cumsum(lengths)])[:, None] * direction
    for _ in range(ITERATIONS):
        if np.linalg.norm(p[-1] - goal) < TOLERANCE:
            break
        p[-1] = goal
        for i in range(len(p) - 2, -1, -1):
            p[i] = p[i + 1] + lengths[i] * _unit(p[i] - p[i + 1])
        p[0] = base
        for i in range(len(p) - 1):
            p[i + 1] = p[i] + lengths[i] * _unit(p[i + 1] - p[i])
    return p


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 else np.array([0.0, 1.0, 0.0])


def _carry(out: np.ndarray, before: np.ndarray, solved: set[int]) -> None:
    """Joints outside ``solved`` move as their parent moved (in place; parents precede children in the order)."""
    for j in range(1, NUM_JOINTS):
        if j not in solved:
            out[j] = before[j] + (out[PARENTS[j]] - before[PARENTS[j]])
