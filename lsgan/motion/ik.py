"""Inverse kinematics for a pose that must put some joints at given points: FABRIK along the skeleton's chains.

A keyframe that sets only some joints (a hand at a point, the head at a height) is completed into a whole pose
here, so that :func:`lsgan.constraints.warp_poses` can warp the motion onto it exactly as onto a whole pose. The
pose's own bone lengths are kept; the chains bend from where they are (FABRIK, Aristidou and Lasenby 2011), so a
reached arm keeps the plane its elbow bent in. Pure numpy: arrays in, arrays out.
"""
from __future__ import annotations

import numpy as np

from lsgan.data.skeleton import NUM_JOINTS, PARENTS

ITERATIONS = 256  # FABRIK passes at most; a reachable target is met to TOLERANCE within a few dozen
TOLERANCE = 1e-6  # metres
REACH = 0.99  # of a chain's length: how far a moved body lets it stretch (a straight chain has no bend left)
PROJECTIONS = 4  # rounds of solving and fitting the rigid skeleton's layout (reach_pose's ``offsets``)
# The chains solved, each from a joint held where it hangs: the children of the two branching joints (pelvis: hips
# and spine; spine3: neck and collars) keep the layout the rigid fit gives them (lsgan.motion.rigid), so a solved
# pose is one the motion of record can take. Spine first (it carries the arms), a collar from the spine, then arms
# and legs.
CHAINS = ((3, 6, 9, 12, 15), (3, 6, 9, 13), (3, 6, 9, 14), (13, 16, 18, 20), (14, 17, 19, 21), (1, 4, 7, 10),
          (2, 5, 8, 11))
LEGS = ((1, 4, 7, 10), (2, 5, 8, 11))
HELD = (1, 2, 3)  # the pelvis's children: set, they move the whole body (when the root is free)
LEG_FEET = (10, 11)
KNEE_FLOOR = 0.05  # metres: a solved knee lower than this is turned up (_highest_knee)
HIP_CLEARANCE = 0.15  # metres: the lowest the pelvis is lowered to above the feet when a spine target pulls it


def reach_pose(pose: np.ndarray, target: np.ndarray, offsets: np.ndarray | None = None) -> np.ndarray:
    """``pose`` (22, 3) moved so that every set coordinate of ``target`` (22, 3), NaN = free, is met
    (:func:`_solve`). ``offsets``: the rigid skeleton the pose will be fitted to (:func:`lsgan.motion.rigid.
    rigid_offsets`); then solving alternates with fitting it, so that the fit moves the solved joints little."""
    from lsgan.motion.rigid import pose as rigid_pose

    out = _solve(np.array(pose, np.float64), np.asarray(target, np.float64))
    for _ in range(PROJECTIONS if offsets is not None else 0):
        out = _solve(rigid_pose(out[None], offsets)[0], np.asarray(target, np.float64))
    return out


def _solve(out: np.ndarray, target: np.ndarray) -> np.ndarray:
    """A set root moves the whole pose, and so do set hips or spine (the mean of their misses, when the root is
    free); the feet go along sideways, and the legs are solved back onto the ground they stood on when the body
    rises or sinks. Along each chain of :data:`CHAINS` the joints up to each set one are solved by FABRIK with the
    chain's first joint held, and the joints hanging from a moved joint move with it. When the root is free and a
    spine joint is out of the spine's reach, the whole body goes under it (feet and all), then rises or sinks by
    what is still out of reach, as far as the legs still reach the feet (:func:`_lift`). A target still out of
    reach is approached in a straight line."""
    if target.shape != (NUM_JOINTS, 3) or out.shape != (NUM_JOINTS, 3):
        raise ValueError(f"a pose and its target are ({NUM_JOINTS}, 3), not {out.shape} and {target.shape}")
    free_root = bool(np.isnan(target[0]).all())
    move = np.zeros(3)
    if not free_root:
        move = np.where(np.isnan(target[0]), 0.0, target[0] - out[0])
    elif not np.isnan(target[list(HELD)]).all():
        miss = target[list(HELD)] - out[list(HELD)]
        on = ~np.isnan(miss)
        move = np.where(on, miss, 0.0).sum(0) / np.maximum(on.sum(0), 1)
    planted = out.copy()  # the feet's places: carried sideways with the body, kept when it rises or sinks
    planted[:, [0, 2]] += move[[0, 2]]
    out += move
    for chain in CHAINS:
        leg = chain in LEGS
        goals = {j: np.where(np.isnan(target[j]), out[j], target[j]) for j in chain[1:] if not np.isnan(target[j]).all()}
        if leg and chain[-1] not in goals and np.abs(out[chain[-1]] - planted[chain[-1]]).max() > 1e-9:
            for j in chain[2:]:  # the body rose or sank: the ankle and foot stay on their ground
                goals.setdefault(j, planted[j])
        base = 0
        for k in range(1, len(chain)):
            if chain[k] not in goals:
                continue
            segment = list(chain[base:k + 1])
            if free_root and chain[0] == 3 and base == 0 and _excess(out[segment], goals[chain[k]]).any():
                across = goals[chain[k]] - out[chain[k]]  # out of the spine's reach: the body goes there, upright
                across[1] = 0.0
                out += across
                planted += across
                out += _lift(out, planted, _excess(out[segment], goals[chain[k]]))
            before = out.copy()
            out[segment] = fabrik(out[segment], goals[chain[k]])
            if leg and len(segment) == 3 and out[segment[1], 1] < KNEE_FLOOR:
                out[segment[1]] = _highest_knee(out[segment])
            _carry(out, before, set(segment))
            base = k
    return out


def _highest_knee(points: np.ndarray) -> np.ndarray:
    """The middle joint of a hip-knee-ankle chain (3, 3) turned about the hip-ankle line to its highest place:
    a knee that FABRIK folded under the floor (a deep crouch) bends up instead, both bones kept."""
    hip, knee, ankle = points
    l1, l2 = np.linalg.norm(knee - hip), np.linalg.norm(ankle - knee)
    axis = ankle - hip
    d = np.linalg.norm(axis)
    if d < 1e-9:
        return knee
    axis /= d
    along = (d * d + l1 * l1 - l2 * l2) / (2 * d)
    radius = np.sqrt(max(l1 * l1 - along * along, 0.0))
    up = np.array([0.0, 1.0, 0.0]) - axis[1] * axis
    if np.linalg.norm(up) < 1e-9:
        return knee
    return hip + along * axis + radius * up / np.linalg.norm(up)


def _lift(pose: np.ndarray, planted: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The largest part of ``shift`` (3,) the body can move by with both legs still reaching their planted ankles
    (within :data:`REACH` of hip to ankle) and the hips at least :data:`HIP_CLEARANCE` above the feet."""
    lengths = [np.linalg.norm(np.diff(pose[list(leg[:3])], axis=0), axis=-1).sum() for leg in LEGS]  # hip to ankle
    for t in np.linspace(1.0, 0.0, 41):
        moved = pose + t * shift
        if all(np.linalg.norm(planted[leg[2]] - moved[leg[0]]) <= REACH * n for leg, n in zip(LEGS, lengths)) \
                and moved[0, 1] >= planted[list(LEG_FEET), 1].max() + HIP_CLEARANCE:
            return t * shift
    return np.zeros(3)


def _excess(points: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """How far a chain's base must move towards ``goal`` for its end to reach it, a little bent (nothing when it
    already can)."""
    reach = REACH * np.linalg.norm(np.diff(points, axis=0), axis=-1).sum()
    d = goal - points[0]
    n = np.linalg.norm(d)
    return d / n * (n - reach) if n > reach else np.zeros(3)


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
