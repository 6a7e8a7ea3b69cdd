"""Constraints on a motion: a root path on the ground, keyframed joints and poses; read, checked, met and measured.

Torch-free (numpy), so that every runtime shares it: ``lsgan.control`` approaches constraints by optimisation (torch
only), then :func:`meet` meets them (the root closed onto the path and keyframes, keyframes of some joints completed
by inverse kinematics, poses retargeted, every pose warped in) and ``measure`` says how far the motion of record is
from each.

Coordinates are the motion's own: metres, Y up, the root at the origin on frame 0 facing +z (every decoded motion
starts there), 20 fps.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsgan.data.features import RIC, ROOT_Y, _qrot_yaw, _xp, recover_root
from lsgan.data.skeleton import FACE_JOINTS, FPS, JOINT_NAMES, NUM_JOINTS, PARENTS

START_TOLERANCE = 1e-3  # m: a path's or keyframe root's point on frame 0 is the origin within this
GROUND_SLACK = 0.25  # m: a keyframe joint lower than this under the ground (y = 0) is refused (a generated
# motion's feet, which continuations take as keyframes, can be centimetres below it)
MAX_COORD = 1e4  # m: coordinates beyond 10 km are refused (float32 keeps millimetres up to about there)


@dataclass
class Constraints:
    """What one motion of ``frames`` frames must do. ``path``: (frames, 2) ground positions (x, z) of the root, NaN
    rows free; ``keyframes``: {frame: (22, 3) joint positions, NaN entries free}; ``poses``: {frame: (22, 3) a
    whole pose to take wherever the motion is then: in its facing frame (root over the origin, facing +z, y up
    from the ground; :func:`facing_frame`), placed at the motion's root and facing on that frame}; ``origin``:
    where they came from, for messages (e.g. the file a continuation continues)."""

    frames: int
    path: np.ndarray | None = None
    keyframes: dict[int, np.ndarray] = field(default_factory=dict)
    fade: int = 0  # frames over which whole poses' remaining miss fades out (warp_poses); 0: WARP_FRAMES
    origin: str = ""
    facing: bool = False  # the root faces along the path where it moves (path_yaws)
    poses: dict[int, np.ndarray] = field(default_factory=dict)  # {frame: (22, 3) whole pose in its facing frame}

    def __post_init__(self) -> None:
        self.frames = _whole_number(self.frames, "frames")
        if self.frames < 2:
            raise ValueError(f"a constrained motion has at least 2 frames, not {self.frames}")
        if self.path is not None:
            self.path = np.asarray(self.path, np.float32)
            if self.path.shape != (self.frames, 2):
                raise ValueError(f"a path for {self.frames} frames is ({self.frames}, 2) ground points, "
                                 f"not {self.path.shape}")
            _check_coordinates(self.path, "a path")
            _check_start(self.path[0], "a path's point")
        keyframes = {}
        for f, pose in self.keyframes.items():
            f = _whole_number(f, "a keyframe's frame")
            pose = np.array(pose, np.float32)
            if not 0 <= f < self.frames:
                raise ValueError(f"keyframe {f} is not a frame of the motion: its {self.frames} frames are "
                                 f"0..{self.frames - 1}")
            if pose.shape != (NUM_JOINTS, 3):
                raise ValueError(f"keyframe {f}: a pose is {NUM_JOINTS} joints x 3 coordinates, not {pose.shape}")
            if np.isnan(pose).all():
                raise ValueError(f"keyframe {f} sets no joint")
            _check_coordinates(pose, f"keyframe {f}")
            low = np.nan_to_num(pose[:, 1], nan=0.0)
            if low.min() < -GROUND_SLACK:
                raise ValueError(f"keyframe {f}: {JOINT_NAMES[int(np.argmin(low))]} at y = {low.min():.2f} m is below "
                                 f"the ground (y = 0; {GROUND_SLACK * 100:.0f} cm of slack)")
            if f == 0:
                _check_start(pose[0, [0, 2]], "keyframe 0's root")
            keyframes[f] = pose
        self.keyframes = keyframes
        poses = {}
        for f, pose in self.poses.items():
            f = _whole_number(f, "a pose's frame")
            if not 0 <= f < self.frames:
                raise ValueError(f"pose {f} is not a frame of the motion: its {self.frames} frames are "
                                 f"0..{self.frames - 1}")
            if f in keyframes:
                raise ValueError(f"frame {f} has a keyframe and a pose: give one")
            poses[f] = whole_pose(pose)
        self.poses = poses
        if self.facing and self.path is None:
            raise ValueError("facing along the path needs a path")

    def root_points(self) -> np.ndarray | None:
        """(frames, 2) ground points the root must pass through: the path's, and the root's (x, z) of keyframes
        that set both; None when there are none."""
        out = np.full((self.frames, 2), np.nan, np.float32) if self.path is None else self.path.copy()
        for f, pose in self.keyframes.items():
            if not np.isnan(pose[0, [0, 2]]).any():
                out[f] = pose[0, [0, 2]]
        return None if np.isnan(out).all() else out

    def root_yaws(self) -> np.ndarray | None:
        """(frames,) facings (yaw, rad) the root must take: along the path where it moves, with ``facing``; those
        of keyframes that set the hips and shoulders apart (a pose with them on one vertical line faces nowhere),
        which win; None when there are none."""
        out = path_yaws(self.path) if self.facing else np.full(self.frames, np.nan)
        for f, pose in self.keyframes.items():
            if not np.isnan(pose[list(FACE_JOINTS)]).any() and has_facing(pose):
                out[f] = facing_yaw(pose)
        return None if np.isnan(out).all() else out

    def record(self) -> dict:
        """Everything, as JSON (NaN as null): what a server sends its engine process (:meth:`from_record`)."""
        def plain(a: np.ndarray) -> list:
            return np.where(np.isnan(a), None, a.astype(object)).tolist()

        return {"frames": self.frames, "path": None if self.path is None else plain(self.path),
                "keyframes": {str(f): plain(p) for f, p in self.keyframes.items()}, "fade": self.fade,
                "origin": self.origin, "facing": self.facing,
                "poses": {str(f): p.tolist() for f, p in self.poses.items()}}

    @classmethod
    def from_record(cls, record: dict) -> Constraints:
        def array(rows) -> np.ndarray:
            return np.array(rows, dtype=np.float64)  # None becomes NaN

        return cls(record["frames"], path=None if record["path"] is None else array(record["path"]),
                   keyframes={int(f): array(p) for f, p in record["keyframes"].items()}, fade=record["fade"],
                   origin=record["origin"], facing=record["facing"],
                   poses={int(f): np.array(p, np.float64) for f, p in record["poses"].items()})

    def describe(self, settings=None) -> dict:
        """What a manifest records: the path's set frames and points, the keyframes' set joints, the settings."""
        from dataclasses import asdict

        out: dict = {"frames": self.frames, **({"facing": True} if self.facing else {})}
        if self.path is not None:
            on = ~np.isnan(self.path).any(-1)
            out["path"] = [[int(f), *map(float, self.path[f])] for f in np.nonzero(on)[0]]
        out["keyframes"] = {str(f): {str(j): [None if np.isnan(v) else float(v) for v in pose[j]]
                                     for j in range(NUM_JOINTS) if not np.isnan(pose[j]).all()}
                            for f, pose in sorted(self.keyframes.items())}
        if self.poses:
            out["poses"] = {str(f): pose.tolist() for f, pose in sorted(self.poses.items())}
        if settings is not None:
            out["settings"] = asdict(settings)
        return out


def _whole_number(value, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{what} is a whole number, not {value!r}")
    return int(value)


def _check_coordinates(a: np.ndarray, what: str) -> None:
    """Set coordinates finite and within :data:`MAX_COORD` metres."""
    a = np.asarray(a, np.float64)
    set_ = a[~np.isnan(a)]
    if np.isinf(set_).any() or (np.abs(set_) > MAX_COORD).any():
        raise ValueError(f"{what} holds a coordinate that is infinite or beyond {MAX_COORD:.0f} m (metres are "
                         "expected)")


def _check_start(point: np.ndarray, what: str) -> None:
    """The root's ground point on frame 0, each coordinate that is set, is the origin: every motion starts there."""
    if (np.abs(np.nan_to_num(np.asarray(point, np.float64))) > START_TOLERANCE).any():  # any set coordinate
        shown = ", ".join("free" if np.isnan(v) else f"{v:.3f}" for v in point)
        raise ValueError(f"{what} on frame 0 is the motion's start, the origin (0, 0), not ({shown})")


def path_points(waypoints: np.ndarray, frames: int, fps: float = 20.0) -> np.ndarray:
    """(frames, 2) ground positions from waypoints (K, 3) of (time s, x, z), linearly between them; frames before
    the first and after the last waypoint are free (NaN)."""
    w = np.asarray(waypoints, np.float64)
    if w.ndim != 2 or w.shape[1] != 3 or len(w) == 0 or not np.isfinite(w).all():
        raise ValueError(f"waypoints are rows of finite (time, x, z), not an array of shape {w.shape}")
    if (np.diff(w[:, 0]) <= 0).any():
        raise ValueError("waypoint times must increase")
    t = np.arange(frames) / fps
    out = np.stack([np.interp(t, w[:, 0], w[:, 1]), np.interp(t, w[:, 0], w[:, 2])], -1)
    out[(t < w[0, 0] - 1e-9) | (t > w[-1, 0] + 1e-9)] = np.nan  # a waypoint on a frame keeps it (float rounding)
    return out.astype(np.float32)


FACING_SPEED = 0.2  # m/s: where a path moves slower than this it sets no facing (standing has no direction)
FACING_FROM = 10  # frames: every motion starts facing +z; the path's facing is set from here, turned into before


def path_yaws(path: np.ndarray, fps: float = FPS) -> np.ndarray:
    """(frames,) the yaw (rad, about +y from +z) of a path's (frames, 2) direction of travel, over two frames each
    side, from frame :data:`FACING_FROM` on (the root turns into it from its start, facing +z, over those frames);
    NaN before, and where the path is free nearby or slower than :data:`FACING_SPEED`."""
    p = np.asarray(path, np.float64)
    out = np.full(len(p), np.nan)
    for f in range(FACING_FROM, len(p)):
        a, b = max(f - 2, 0), min(f + 2, len(p) - 1)
        step = p[b] - p[a]
        if b > a and not np.isnan(step).any() and np.hypot(*step) / ((b - a) / fps) >= FACING_SPEED:
            out[f] = np.arctan2(step[0], step[1])
    return out


def _across(j):
    """The hips' and shoulders' across vector (..., 3) of poses (..., 22, 3), as HumanML3D takes it."""
    a, b, c, d = FACE_JOINTS
    return (j[..., a, :] - j[..., b, :]) + (j[..., c, :] - j[..., d, :])


def facing_yaw(joints):
    """The facing of poses (..., 22, 3), numpy arrays or torch tensors, as a yaw angle (rad) about +y from +z: the
    body's forward direction, up x the across (as HumanML3D turns each clip to face +z); 0 for a pose without one."""
    j = np.asarray(joints, np.float64) if isinstance(joints, np.ndarray) else joints
    across = _across(j)
    # forward = (0, 1, 0) x across = (across_z, 0, -across_x); + 0.0 turns -0.0 into 0.0 (atan2(0, -0.0) is pi)
    return _xp(j).atan2(across[..., 2] + 0.0, -across[..., 0] + 0.0)


def facing_frame(poses):
    """Poses (..., 22, 3), numpy or torch, with the root over the origin and the facing turned onto +z (heights
    kept): what a pose is wherever it stands."""
    shifted = poses - poses[..., :1, :] * (poses.new_tensor([1.0, 0.0, 1.0]) if not isinstance(poses, np.ndarray)
                                           else np.array([1.0, 0.0, 1.0]))
    return turn(shifted, -facing_yaw(poses)[..., None])


def has_facing(pose: np.ndarray) -> bool:
    """Whether a pose (22, 3) faces somewhere: its across has a horizontal part (1 mm)."""
    across = _across(np.asarray(pose, np.float64))
    return bool(np.hypot(across[0], across[2]) > 1e-3)


def turn(v, yaw):
    """Points (..., 3), numpy or torch, turned by ``yaw`` (rad, broadcast over the points) about +y: a pose facing
    yaw 0 then faces ``yaw``. The yaw quaternion of lsgan.data.features turns by twice its angle."""
    return _qrot_yaw(yaw / 2, v, inverse=False)


def _residual(on: np.ndarray, miss: np.ndarray, frames: int, fade: int) -> np.ndarray:
    """A miss (K, ...) known on the set frames ``on`` (K,) as a per-frame correction (frames, ...): zero on frame 0
    (where every motion starts, at the origin facing +z, whatever is asked of it); between set frames a cubic
    Hermite curve whose slope at a frame inside a run of set frames (a path, a continuation's shared frames) is the
    run's own rate and elsewhere the chord's, so the velocity it gives does not jump where a run ends; after the
    last set frame held, or, after a run, carried on at its rate and faded out over ``fade`` frames."""
    tail = np.shape(miss)[1:]
    miss = np.array(miss, np.float64).reshape(len(on), -1)
    on = np.asarray(on)
    if on[0] == 0:
        miss[0] = 0.0
    else:
        on, miss = np.concatenate([[0], on]), np.concatenate([np.zeros((1, miss.shape[1])), miss])
    out = np.zeros((frames, miss.shape[1]))
    slope = _slopes(on, miss)
    for k in range(len(on) - 1):
        a, b = on[k], on[k + 1]
        h = b - a
        u = (np.arange(a, b + 1) - a) / h  # (h + 1,)
        h00, h10, h01, h11 = 2 * u**3 - 3 * u**2 + 1, u**3 - 2 * u**2 + u, -2 * u**3 + 3 * u**2, u**3 - u**2
        out[a:b + 1] = (h00[:, None] * miss[k] + h10[:, None] * h * slope[k] + h01[:, None] * miss[k + 1]
                        + h11[:, None] * h * slope[k + 1])
    last = on[-1]
    out[last:] = miss[-1]
    if last + 1 < frames and len(on) > 1 and on[-2] == last - 1:  # after a run: its rate carried on, fading
        steps = np.arange(1, frames - last)
        carried = np.cumsum(np.where(steps < fade, 0.5 + 0.5 * np.cos(np.pi * steps / max(fade, 1)), 0.0))
        out[last + 1:] += carried[:, None] * (miss[-1] - miss[-2])
    return out.reshape((frames,) + tail)


def _slopes(on: np.ndarray, miss: np.ndarray) -> np.ndarray:
    """Per set frame, the miss's rate (per frame): a run's own difference where a neighbouring frame is set, else
    the chord between the neighbouring set frames (the ends: the one chord they have)."""
    out = np.zeros_like(miss)
    for k in range(len(on)):
        if k + 1 < len(on) and on[k + 1] == on[k] + 1 and k > 0 and on[k - 1] == on[k] - 1:
            out[k] = (miss[k + 1] - miss[k - 1]) / 2
        elif k > 0 and on[k - 1] == on[k] - 1:
            out[k] = miss[k] - miss[k - 1]
        elif k + 1 < len(on) and on[k + 1] == on[k] + 1:
            out[k] = miss[k + 1] - miss[k]
        else:
            lo, hi = max(k - 1, 0), min(k + 1, len(on) - 1)
            out[k] = (miss[hi] - miss[lo]) / max(on[hi] - on[lo], 1)
    return out


def close_root(features: np.ndarray, points: np.ndarray | None, yaws: np.ndarray | None = None,
               fade: int = 10) -> np.ndarray:
    """Features (T, 263) whose root faces every set yaw (T,) and passes through every set ground point (T, 2)
    exactly (NaN: free; None: nothing to meet). The root's turning channel (0) takes the facing's miss and its
    ground velocity channels (1, 2) the position's, each spread linearly between set frames and carried on, fading
    over ``fade`` frames, after the last (:func:`_residual`);
    height and pose are the decoded ones, so what the optimisation left shows as feet sliding or turning on the
    spot, which is measured."""
    f = np.array(features, dtype=np.float64)
    T = len(f)
    for name, a, width in (("points", points, (T, 2)), ("yaws", yaws, (T,))):
        if a is not None and np.shape(a) != width:
            raise ValueError(f"{name} for {T} frames are {width}, not {np.shape(a)}")
    if yaws is not None and not np.isnan(yaws).all():
        on = np.nonzero(~np.isnan(yaws))[0]
        angle, _ = recover_root(f)
        from lsgan.data.features import recover_from_ric

        miss = np.angle(np.exp(1j * (np.asarray(yaws, np.float64)[on] - facing_yaw(recover_from_ric(f)[on]))))
        angle = angle - _residual(on, miss, T, fade) / 2  # a half angle (the yaw quaternion's), turning the body back
        f[:-1, 0] = np.diff(angle)
    if points is not None and not np.isnan(points).all():
        on = np.nonzero(~np.isnan(points).any(-1))[0]
        angle, root = recover_root(f)
        ground = root[:, [0, 2]] + _residual(on, np.asarray(points, np.float64)[on] - root[on][:, [0, 2]], T, fade)
        step = np.zeros((T - 1, 3))
        step[:, [0, 2]] = np.diff(ground, axis=0)
        local = _qrot_yaw(angle[1:], step, inverse=False)  # pos[t+1] - pos[t] = R(angle[t+1])^-1 features[t, 1:3]
        f[:-1, 1], f[:-1, 2] = local[:, 0], local[:, 2]
    return f.astype(np.float32)


WARP_FRAMES = 5  # frames over which a keyframe's remaining pose miss fades out on each side (motion warping)


def warp_poses(features: np.ndarray, keyframes: dict[int, np.ndarray], fade: int = WARP_FRAMES) -> np.ndarray:
    """Features (T, 263) whose root-relative joints (and root height) reach every whole-pose keyframe exactly, by
    motion warping (Witkin and Popovic 1995) of the bones: at each keyframe, each bone's turn onto the keyframe's
    (a rotation vector, in the root's frame) and its length ratio, with the root height's miss, are spread to the
    frames around it (linear between keyframes up to 2 * ``fade`` frames apart, fading out over ``fade`` frames
    with a raised cosine beyond); the joints are then rebuilt from the root bone by bone. Turning bones rather than
    moving joints keeps limbs their length between keyframes: a raised arm swings up, it does not pass through
    the shoulder. Run after :func:`close_root`, which puts the root's ground position and facing there; keyframes
    that leave a joint free are completed first (:func:`meet`)."""
    whole = sorted(f for f, pose in keyframes.items() if not np.isnan(pose).any())
    f = np.array(features, dtype=np.float64)
    if not whole:
        return np.asarray(features, np.float32)
    angle, root = recover_root(f)
    local = np.concatenate([np.zeros((len(f), 1, 3)), f[:, RIC].reshape(len(f), NUM_JOINTS - 1, 3)], axis=1)
    local[:, 0, 1] = f[:, ROOT_Y.start]  # (T, 22, 3): the joints in the root's frame, the root over the origin
    parents = list(PARENTS[1:])
    bones = local[:, 1:] - local[:, parents]  # (T, 21, 3)
    miss = {}
    for k in whole:
        want = _qrot_yaw(np.full(NUM_JOINTS, angle[k]), np.asarray(keyframes[k], np.float64) - root[k] * [1.0, 0.0, 1.0],
                         inverse=False)
        goal = want[1:] - want[parents]
        ratio = np.log(np.maximum(np.linalg.norm(goal, axis=-1), 1e-9) / np.maximum(np.linalg.norm(bones[k], axis=-1),
                                                                                   1e-9))
        miss[k] = np.concatenate([[want[0, 1] - local[k, 0, 1]], _turn_between(bones[k], goal).ravel(), ratio])
    shift = _warp_field(miss, len(f), fade)  # (T, 1 + 63 + 21)
    turned = _rotate(bones, shift[:, 1:64].reshape(len(f), NUM_JOINTS - 1, 3)) * np.exp(shift[:, 64:])[..., None]
    out = local.copy()
    out[:, 0, 1] += shift[:, 0]
    for j in range(1, NUM_JOINTS):  # PARENTS lists every parent before its children
        out[:, j] = out[:, PARENTS[j]] + turned[:, j - 1]
    f[:, ROOT_Y.start] = out[:, 0, 1]
    f[:, RIC] = out[:, 1:].reshape(len(f), -1)
    return f.astype(np.float32)


def _turn_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of the shortest turns taking directions ``a`` (..., 3) onto ``b``; a half turn
    about an axis across ``a``."""
    ua = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    ub = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    axis = np.cross(ua, ub)
    sin, cos = np.linalg.norm(axis, axis=-1), np.sum(ua * ub, axis=-1)
    across = np.cross(ua, np.where(np.abs(ua[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]))
    axis = np.where((sin > 1e-9)[..., None], axis, across)
    axis /= np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-12)
    return axis * np.arctan2(sin, cos)[..., None]


def _rotate(v: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Vectors (..., 3) turned by rotation vectors (..., 3) (Rodrigues' formula)."""
    angle = np.linalg.norm(turn, axis=-1, keepdims=True)
    k = turn / np.maximum(angle, 1e-12)
    return v * np.cos(angle) + np.cross(k, v) * np.sin(angle) + k * np.sum(k * v, -1, keepdims=True) * (1 - np.cos(angle))


def _warp_field(miss: dict[int, np.ndarray], frames: int, fade: int) -> np.ndarray:
    """Per-frame displacement (frames, D) that equals ``miss[k]`` on each keyframe k: linear between keyframes at
    most 2 * fade apart, a raised-cosine fade to zero over ``fade`` frames outside each such run."""
    keys = sorted(miss)
    out = np.zeros((frames, len(miss[keys[0]])))
    runs, run = [], [keys[0]]
    for k in keys[1:]:
        if k - run[-1] <= 2 * fade:
            run.append(k)
        else:
            runs.append(run)
            run = [k]
    runs.append(run)
    t = np.arange(frames)
    for run in runs:
        values = np.stack([miss[k] for k in run])
        inside = (t >= run[0]) & (t <= run[-1])
        out[inside] += np.stack([np.interp(t[inside], run, values[:, d]) for d in range(values.shape[1])], -1)
        for edge, side in ((run[0], -1), (run[-1], 1)):
            dist = (t - edge) * side
            near = (dist > 0) & (dist < fade)
            out[near] += miss[edge] * (0.5 + 0.5 * np.cos(np.pi * dist[near] / fade))[:, None]
    return out


RIGID_PASSES = 2  # corrections of the warp for what making the motion rigid moves (measured in docs/control.md)


def meet(features: np.ndarray, c: Constraints) -> np.ndarray:
    """Features (T, 263) whose motion of record meets ``c``: the root closed onto its points and facings
    (:func:`close_root`); keyframes that set some joints completed into whole poses by inverse kinematics on the
    motion's own rigid pose there (:func:`lsgan.motion.ik.reach_pose`); every keyframe warped in
    (:func:`warp_poses`); then, :data:`RIGID_PASSES` times, the warp's targets moved by what the rigid fit every
    output goes through (:func:`lsgan.motion.rigid.make_rigid`) still misses of the set joints, so that the rigid
    joints, not only the decoded ones, reach them. The last stages of control, shared by every runtime."""
    from lsgan.data.features import recover_from_ric
    from lsgan.motion.rigid import make_rigid

    closed = close_root(features, c.root_points(), c.root_yaws())
    if not c.keyframes and not c.poses:
        return closed
    fade = c.fade or WARP_FRAMES

    def rigid(f: np.ndarray) -> np.ndarray:
        return make_rigid(recover_from_ric(f.astype(np.float64))).astype(np.float64)

    now = rigid(closed)
    want = _completed(c.keyframes, now)
    want.update(_placed(c.poses, now))
    if any(np.abs(w[0, [0, 2]] - now[f, 0, [0, 2]]).max() > 1e-4 for f, w in want.items()):
        # the inverse kinematics moved the body under a joint out of its reach: the root goes there too, and stays
        # where it is on the other keyframes
        points = c.root_points()
        points = np.full((c.frames, 2), np.nan) if points is None else points.astype(np.float64)
        for f, w in want.items():
            points[f] = w[0, [0, 2]]
        closed = close_root(features, points, c.root_yaws())
        now = rigid(closed)
        want = _completed(c.keyframes, now)
        want.update(_placed(c.poses, now))
    keys = dict(want)
    out = warp_poses(closed, keys, fade)
    for _ in range(RIGID_PASSES):
        now = rigid(out)
        keys = {f: keys[f] + (want[f] - now[f]) for f in keys}
        out = warp_poses(closed, keys, fade)
    return out


def on_skeleton(pose: np.ndarray, rigid: np.ndarray) -> np.ndarray:
    """A pose (22, 3) of any skeleton (a BVH rig's) retargeted onto a rigid motion's (T, 22, 3): its bone
    directions at the motion's bone lengths and branching layout (lsgan.motion.rigid.pose), the lowest foot as high
    above the ground as in the pose, in proportion to the legs (whatever the pose's units)."""
    from lsgan.data.skeleton import bone_lengths
    from lsgan.motion.rigid import pose as rigid_pose, rigid_offsets

    src = np.asarray(pose, np.float64)
    out = rigid_pose(src[None], rigid_offsets(np.asarray(rigid, np.float64)))[0]
    feet, legs = [7, 8, 10, 11], [1, 4, 7, 2, 5, 8]
    scale = bone_lengths(out)[legs].sum() / max(bone_lengths(src)[legs].sum(), 1e-9)  # the source's units and size
    return out + [0.0, scale * src[feet, 1].min() - out[feet, 1].min(), 0.0]


def _placed(poses: dict[int, np.ndarray], rigid: np.ndarray) -> dict[int, np.ndarray]:
    """Poses (facing frame, any skeleton) as whole keyframes: on the rigid motion's skeleton (:func:`on_skeleton`),
    where it stands and faces on their frames."""
    out = {}
    for f, pose in poses.items():
        here = rigid[f]
        out[f] = turn(on_skeleton(pose, rigid), np.full(NUM_JOINTS, float(facing_yaw(here)))) + here[0] * [1.0, 0.0, 1.0]
    return out


def _completed(keyframes: dict[int, np.ndarray], rigid: np.ndarray) -> dict[int, np.ndarray]:
    """Whole poses for keyframes: those given whole as they are, the others completed by inverse kinematics on the
    rigid motion's pose at their frame (:func:`lsgan.motion.ik.reach_pose`, fitted to its skeleton)."""
    from lsgan.motion.ik import reach_pose
    from lsgan.motion.rigid import rigid_offsets

    offsets = rigid_offsets(rigid)
    return {f: reach_pose(rigid[f], p, offsets) if np.isnan(p).any() else np.asarray(p, np.float64)
            for f, p in keyframes.items()}


def measure(joints: np.ndarray, c: Constraints) -> dict:
    """How far a motion's joints (T, 22, 3) are from ``c``, in metres: the root's ground distance to the path over
    its set frames, and each keyframed joint's distance over its set coordinates; for each pose, its joints' mean
    distance in the facing frame (wherever the motion stands) from the pose on the motion's skeleton; with
    ``facing``, the angle (deg)
    between the body's facing and the path's direction where it moves; mean and largest of each, absent when there
    is nothing of that kind to meet."""
    j = np.asarray(joints, np.float64)
    out = {}
    if c.path is not None and not np.isnan(c.path).all():
        on = ~np.isnan(c.path).any(-1)
        d = np.linalg.norm(j[: c.frames, 0][on][:, [0, 2]] - c.path[on], axis=-1)
        out["path_m"] = {"mean": float(d.mean()), "max": float(d.max())}
    if c.keyframes:
        d = []
        for f, pose in c.keyframes.items():
            set_ = ~np.isnan(pose)
            diff = np.where(set_, j[f] - np.nan_to_num(pose), 0.0)
            d += list(np.linalg.norm(diff, axis=-1)[set_.any(-1)])
        out["keyframes_m"] = {"mean": float(np.mean(d)), "max": float(np.max(d))}
    if c.poses:
        d = [np.linalg.norm(facing_frame(j[f]) - on_skeleton(pose, j), axis=-1).mean() for f, pose in c.poses.items()]
        out["poses_m"] = {"mean": float(np.mean(d)), "max": float(np.max(d))}
    if c.facing:
        want = path_yaws(c.path)
        on = ~np.isnan(want)
        if on.any():
            d = np.degrees(np.abs(np.angle(np.exp(1j * (facing_yaw(j[: c.frames][on]) - want[on])))))
            out["facing_deg"] = {"mean": float(d.mean()), "max": float(d.max())}
    seams = _seam_velocity(j, c)
    if seams:
        out["seam_velocity_m_s"] = {"mean": float(np.mean(seams)), "max": float(np.max(seams))}
    return out


def _seam_velocity(j: np.ndarray, c: Constraints) -> list[float]:
    """Where a run of whole-pose keyframes (two or more consecutive frames: a continuation's, an in-between's)
    meets the motion's own frames: how much the motion's step there differs from the run's own step, mean over
    joints, m/s. 0 when the motion carries on at the velocity the keyframes set."""
    whole = sorted(f for f, p in c.keyframes.items() if not np.isnan(p).any())
    out = []
    for f in whole:
        if f + 1 < len(j) and f - 1 in c.keyframes and f + 1 not in c.keyframes:  # a run ends: the next step
            want = c.keyframes[f] - c.keyframes[f - 1]
            out.append(float(np.linalg.norm((j[f + 1] - j[f]) - want, axis=-1).mean() * FPS))
        if f >= 1 and f + 1 in c.keyframes and f - 1 not in c.keyframes:  # a run starts: the step into it
            want = c.keyframes[f + 1] - c.keyframes[f]
            out.append(float(np.linalg.norm((j[f] - j[f - 1]) - want, axis=-1).mean() * FPS))
    return out


def read_path(path: str | os.PathLike, frames: int, fps: float = FPS) -> np.ndarray:
    """A root path (frames, 2) from a file: CSV (optionally a header line of names; '#' comments) or JSON (a list of
    rows, or {"points": rows}), read by :func:`path_from_rows`. Errors name the file."""
    from lsgan.errors import reading

    with reading(path, "a path: rows of (time s, x, z) waypoints or (x, z) per frame, as CSV or JSON"):
        return path_from_rows(_rows(Path(path)), frames, fps)


def path_from_rows(rows, frames: int, fps: float = FPS) -> np.ndarray:
    """A root path (frames, 2) from rows, shifted so that it starts at the origin where the motion starts (the file's
    and the server's rule). Rows of three numbers are waypoints (time s, x, z) from 0 s, at least a frame apart,
    within the motion, linear between them and free after the last; rows of two are one ground point (x, z) per
    frame from frame 0, free after the last."""
    rows = np.asarray(rows, np.float64)
    if rows.ndim != 2 or rows.shape[1] not in (2, 3) or not len(rows):
        raise ValueError(f"rows of 2 or 3 numbers, got an array of shape {rows.shape}")
    if len(rows) < 2:
        raise ValueError("a path needs at least two points (its first is where the motion starts)")
    if not np.isfinite(rows).all() or (np.abs(rows) > MAX_COORD).any():
        raise ValueError(f"a number is NaN, infinite or beyond {MAX_COORD:.0f} (metres and seconds)")
    if rows.shape[1] == 2:
        if len(rows) > frames:
            raise ValueError(f"{len(rows)} points for a motion of {frames} frames")
        out = np.full((frames, 2), np.nan, np.float32)
        out[: len(rows)] = rows - rows[0]
        return out
    t = rows[:, 0]
    if t[0] != 0:
        raise ValueError(f"the first waypoint is at {t[0]:g} s: a path starts with the motion, at 0 s")
    if (np.diff(t) < 1 / fps - 1e-9).any():
        k = int(np.argmax(np.diff(t) < 1 / fps - 1e-9))
        raise ValueError(f"waypoints at {t[k]:g} and {t[k + 1]:g} s are less than a frame ({1 / fps:g} s) "
                         "apart (times must increase)")
    if t[-1] > (frames - 1) / fps + 1e-9:
        raise ValueError(f"the path runs to {t[-1]:g} s; the motion ends at {(frames - 1) / fps:g} s "
                         f"(frame {frames - 1})")
    return path_points(rows - np.array([0.0, *rows[0, 1:]]), frames, fps)


_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(nan|inf|infinity)", re.IGNORECASE)


def _number(text: str) -> float:
    """A decimal number as written in a CSV (no '1_0', no words)."""
    if not _NUMBER.fullmatch(text.strip()):
        raise ValueError(f"{text.strip()!r} is not a number")
    return float(text)


def _numbers(value, where: str, free: bool = False) -> list[float]:
    """A JSON list of numbers (not booleans, strings or lists); with ``free``, null for a free coordinate (NaN)."""
    def number(v) -> bool:
        return (isinstance(v, (int, float)) and not isinstance(v, bool)) or (free and v is None)

    if not isinstance(value, list) or not all(number(v) for v in value):
        kind = "numbers (or null for a free coordinate)" if free else "numbers"
        raise ValueError(f"{where} is not a list of {kind}: {json.dumps(value)[:60]}")
    return [np.nan if v is None else float(v) for v in value]


MAX_FILE_BYTES = 16 * 2**20  # a path or keyframe file larger than this is refused unread


def _text(path: Path) -> str:
    """A constraint file's text, read up to :data:`MAX_FILE_BYTES` (a byte-order mark, as spreadsheets write it,
    is not data)."""
    with open(path, "rb") as fh:
        data = fh.read(MAX_FILE_BYTES + 1)
    if len(data) > MAX_FILE_BYTES:
        raise ValueError(f"larger than {MAX_FILE_BYTES // 2**20} MB: not a path or a pose")
    return data.decode("utf-8-sig")


def _json(text: str):
    """Parsed JSON of a constraint file (:func:`lsgan.jsonread.strict_json`): a free coordinate is null."""
    from lsgan.jsonread import strict_json

    return strict_json(text, " (leave a coordinate free with null)")


def _rows(path: Path) -> np.ndarray:
    text = _text(path)
    if path.suffix.lower() == ".json":
        data = _json(text)
        return json_rows(data["points"] if isinstance(data, dict) and "points" in data else data)
    lines = [ln.split("#")[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if lines and not any(ch.isdigit() for ch in lines[0].replace(",", "")):
        lines = lines[1:]  # a header of names
    return _table([[_number(v) for v in ln.replace(";", ",").split(",")] for ln in lines])


def json_rows(data) -> np.ndarray:
    """Rows of numbers from parsed JSON (a list of lists of numbers, no booleans or strings), as a (K, N) array."""
    if not isinstance(data, list):
        raise ValueError("a list of rows, or {\"points\": rows}")
    return _table([_numbers(r, f"row {i + 1}") for i, r in enumerate(data)])


def _table(rows: list[list[float]]) -> np.ndarray:
    if not rows:
        raise ValueError("no points")
    if len({len(r) for r in rows}) > 1:
        raise ValueError("rows of different lengths")
    return np.asarray(rows, dtype=np.float64).reshape(len(rows), -1)


def read_keyframe(spec: str, frames: int) -> tuple[int, np.ndarray]:
    """``FRAME:FILE`` -> (frame, pose (22, 3), NaN = free). FILE: ``.npy`` of the 22 joints (22, 3), every one set;
    or ``.json`` {"joint name or index": [x, y, z], ...} for some joints. Positions in the motion's own frame
    (module docstring). A frame beyond the motion, a missing file or a bad pose is an error naming it."""
    from lsgan.data.clip import load_npy
    from lsgan.errors import reading

    frame, sep, file = spec.partition(":")
    if not sep or not re.fullmatch(r"\s*[0-9]+\s*", frame) or not file.strip():
        raise ValueError(f"a keyframe is FRAME:FILE, a frame number and a file (e.g. 60:pose.npy), not {spec!r}")
    f, path = int(frame), Path(file)
    if not 0 <= f < frames:
        raise ValueError(f"keyframe {f} ({spec}) is beyond the motion's {frames} frames (0..{frames - 1})")
    if path.is_dir():
        raise ValueError(f"{path}: a folder, not a keyframe file")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such keyframe file")
    with reading(path, "a keyframe: a .npy of 22 joints x 3, or a .json of joint names to [x, y, z]"):
        if path.suffix.lower() == ".json":
            pose = pose_from_json(_json(_text(path)))
        else:
            pose = whole_pose(load_npy(path))
    return f, pose


BVH_FRAME = re.compile(r"(?P<file>.+\.bvh(?:\.gz)?)@(?P<frame>[0-9]+)", re.IGNORECASE)


def is_bvh_keyframe(spec: str) -> bool:
    """Whether ``FRAME:FILE`` names a BVH file (its frame then follows the file: ``60:clip.bvh@120``)."""
    file = spec.partition(":")[2].strip().lower()
    return ".bvh" in file and (file.endswith((".bvh", ".bvh.gz")) or "@" in file)


def read_bvh_pose(spec: str, frames: int, joint_map: str | None = None) -> tuple[int, np.ndarray]:
    """``FRAME:FILE.bvh@K`` -> (frame, the whole pose of the BVH's frame K (counted from 0 at the file's own rate)
    in its facing frame, :func:`facing_frame`): a pose the motion takes wherever it is on FRAME. The file's joints
    go through ``joint_map`` (a preset name, or a JSON joint map file; by default the first preset that finds every
    joint: lsgan.data.joint_maps), heights from the clip's floor (its lowest foot over all frames)."""
    from lsgan.data.bvh import forward_kinematics, read_bvh
    from lsgan.data.clip import ClipError
    from lsgan.data.skeleton import bone_lengths
    from lsgan.data.joint_maps import PRESETS, apply_joint_map, get_joint_map
    from lsgan.errors import reading

    frame, _, rest = spec.partition(":")
    m = BVH_FRAME.fullmatch(rest.strip())
    if not re.fullmatch(r"\s*[0-9]+\s*", frame) or m is None:
        raise ValueError(f"a BVH keyframe is FRAME:FILE.bvh@BVH_FRAME (e.g. 60:clip.bvh@120), not {spec!r}")
    f, path, k = int(frame), Path(m["file"]), int(m["frame"])
    if not 0 <= f < frames:
        raise ValueError(f"keyframe {f} ({spec}) is not a frame of the motion: its {frames} frames are 0..{frames - 1}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such BVH file")
    bvh = read_bvh(path)
    if not 0 <= k < len(bvh.motion):
        raise ValueError(f"{path}: has {len(bvh.motion)} frames (0..{len(bvh.motion) - 1}), not a frame {k}")
    if joint_map and joint_map not in PRESETS and not Path(joint_map).is_file():
        raise ValueError(f"--keyframe-map {joint_map!r}: neither a preset ({', '.join(PRESETS)}) nor a JSON file")
    maps = {joint_map: get_joint_map(joint_map, None) if joint_map in PRESETS else get_joint_map("bandai", joint_map)} \
        if joint_map else PRESETS
    tried = []
    for name, jmap in maps.items():
        try:
            joints = apply_joint_map(forward_kinematics(bvh), bvh.names, jmap, str(path))
            break
        except ClipError as e:
            missing = re.search(r"needs joints (\[[^]]*\])", str(e))
            names = re.findall(r"'([^']*)'", missing[1]) if missing else []
            tried.append(f"{name} lacks {', '.join(names[:3])}" + (f" and {len(names) - 3} more" if len(names) > 3
                                                                      else "") if names else
                         f"{name}: {str(e).split(': ', 1)[-1][:80]}")
    else:
        hint = "" if joint_map else "; give --keyframe-map"
        raise ValueError(f"{path}: no joint map fits its joints ({'; '.join(tried)}){hint}")
    with reading(path, "a BVH pose"):
        pose = whole_pose(joints[k] - [0.0, joints[:, [7, 8, 10, 11], 1].min(), 0.0]).astype(np.float64)
        short = np.nonzero(bone_lengths(pose)[1:] < 1e-3)[0]
        if len(short):
            raise ValueError(f"its bone to {JOINT_NAMES[short[0] + 1]} has no length through this joint map (two "
                             "joints mapped to one place)")
        return f, facing_frame(pose).astype(np.float32)


def whole_pose(pose) -> np.ndarray:
    """A pose (22, 3) that sets every joint, in HumanML3D's order, finite and within :data:`MAX_COORD`."""
    pose = np.asarray(pose, np.float64)
    if pose.shape != (NUM_JOINTS, 3):
        raise ValueError(f"a pose of this skeleton is ({NUM_JOINTS}, 3) joints (HumanML3D's order), not {pose.shape}")
    if np.isnan(pose).any():
        raise ValueError("a coordinate is NaN (a whole pose sets every joint; name joints to set some)")
    _check_coordinates(pose, "the pose")
    return pose.astype(np.float32)


def pose_from_json(data) -> np.ndarray:
    """A pose (22, 3), NaN = free, from parsed JSON: {"joint name or index": [x, y, z], ...} for some joints (a
    coordinate null is free: {"head": [null, 1.7, null]} sets the head's height only), or a list of the 22 joints'
    [x, y, z] (:func:`whole_pose`)."""
    if isinstance(data, list):
        return whole_pose(json_rows(data))
    if not isinstance(data, dict) or not data:
        raise ValueError("an object of joint names to [x, y, z], with at least one joint")
    pose = np.full((NUM_JOINTS, 3), np.nan)
    named: dict[int, str] = {}
    for name, xyz in data.items():
        values = _numbers(xyz, f"joint {name!r}", free=True)
        if len(values) != 3:
            raise ValueError(f"joint {name!r} has {len(values)} coordinates, not 3")
        j = _joint(name)
        if j in named:
            raise ValueError(f"joint {JOINT_NAMES[j]} is set twice (as {named[j]!r} and {name!r})")
        named[j] = name
        if np.isnan(values).all():
            raise ValueError(f"joint {name!r} sets no coordinate (null leaves one free; leave the joint out instead)")
        pose[j] = values
    _check_coordinates(pose, "the pose")
    return pose.astype(np.float32)


def _joint(name: str) -> int:
    if name.isascii() and name.isdigit() and int(name) < NUM_JOINTS:
        return int(name)
    if name not in JOINT_NAMES:
        raise ValueError(f"unknown joint {name!r}: give an index 0-{NUM_JOINTS - 1} or one of the {NUM_JOINTS} names "
                         "(pelvis, left_hip, ..., head, ..., left_wrist, right_wrist: docs/control.md lists them)")
    return JOINT_NAMES.index(name)


def reachable_speed(feat_mean: np.ndarray, feat_std: np.ndarray, fps: float = FPS) -> float:
    """The root's ground speed (m/s) beyond which no motion of a model goes: twice its training data's root velocity
    channels at their mean plus four standard deviations (the VAE's feature statistics). Twice, because the model's
    own motions go beyond the statistics' estimate (a Bandai GAN's by 12% within a frame), and a continuation of
    one must not be refused; a teleport (tens of m/s) still is."""
    m, sd = np.abs(np.asarray(feat_mean, np.float64)[1:3]), np.asarray(feat_std, np.float64)[1:3]
    return float(2.0 * np.linalg.norm(m + 4 * sd) * fps)


def model_reach(feat_mean: np.ndarray, feat_std: np.ndarray) -> tuple[float, np.ndarray]:
    """What :func:`check_reach` holds constraints to for a model whose VAE has these feature statistics: its
    :func:`reachable_speed` and its skeleton's 22 bone lengths (m, the mean pose's)."""
    from lsgan.data.features import recover_from_ric
    from lsgan.data.skeleton import bone_lengths

    mean = np.asarray(feat_mean, np.float32)
    return reachable_speed(mean, feat_std), bone_lengths(recover_from_ric(mean[None])[0].astype(np.float64))


def check_reach(c: Constraints, speed: float, skeleton: np.ndarray | None = None, fps: float = FPS) -> None:
    """Refuse what no motion of the model can do: a root that would move faster than ``speed`` (m/s) between two
    of its set ground points (the path's and keyframe roots', from the origin on frame 0), a whole keyframe pose
    whose bones are not the model's ``skeleton`` (22 bone lengths, m): in all within a factor 1.5, each bone within
    a factor 2 (3 cm of slack). Messages start with ``c.origin`` when it is set."""
    from lsgan.data.skeleton import JOINT_NAMES as NAMES, bone_lengths

    lead = f"{c.origin}: " if c.origin else ""
    for f, pose in sorted(c.keyframes.items()):  # poses (c.poses) are retargeted onto the motion's skeleton
        if skeleton is None or np.isnan(pose).any():
            continue
        mine, ref = bone_lengths(pose[None].astype(np.float64))[0, 1:], np.asarray(skeleton, np.float64)[1:]
        ratio = mine.sum() / ref.sum()
        each = (mine + 0.03) / (ref + 0.03)
        worst = int(np.argmax(np.abs(np.log(each))))
        if not 1 / 1.5 <= ratio <= 1.5 or not 0.5 <= each[worst] <= 2:
            raise ValueError(f"{lead}keyframe {f}: its bones are {ratio:.2f}x this model's skeleton in all, the bone "
                             f"to {NAMES[worst + 1]} {mine[worst] / max(ref[worst], 1e-9):.2f}x: a pose of another "
                             "skeleton or in other units (the joints are HumanML3D's 22, in metres)")
    points = c.root_points()
    if points is not None:
        points = points.copy()
        points[0] = 0.0  # every motion's root starts at the origin
        on = np.nonzero(~np.isnan(points).any(-1))[0]
        v = np.linalg.norm(np.diff(points[on], axis=0), axis=-1) / (np.diff(on) / fps)
        k = int(np.argmax(v)) if len(v) else 0
        if len(v) and v[k] > speed:
            a, b = (_root_source(c, int(f)) for f in on[k:k + 2])
            raise ValueError(f"{lead}the root would move at {v[k]:.1f} m/s from {a} at {on[k] / fps:.2f} s to {b} at "
                             f"{on[k + 1] / fps:.2f} s; this model's motions stay under {speed:.1f} m/s")


def _root_source(c: Constraints, frame: int) -> str:
    """What sets the root's ground point on ``frame``, for messages."""
    if frame in c.keyframes and not np.isnan(c.keyframes[frame][0, [0, 2]]).any():
        return f"keyframe {frame}'s root"
    if c.path is not None and not np.isnan(c.path[frame]).any():
        return "the path"
    return "the start (the origin)"


CONTINUE_FRAMES = 5  # frames a continuation shares with the motion it continues: position, heading, pose, velocity
CONTINUE_FADE = 10  # frames over which a continuation's remaining miss fades out after the shared frames


@dataclass(frozen=True)
class Placement:
    """Where a motion made in its own frame stands in another's: turned by ``yaw`` (rad) about +y, then moved by
    (``x``, 0, ``z``) metres."""

    yaw: float = 0.0
    x: float = 0.0
    z: float = 0.0

    def __post_init__(self) -> None:
        if not all(np.isfinite([self.yaw, self.x, self.z])) or max(abs(self.x), abs(self.z)) > MAX_COORD:
            raise ValueError(f"a placement is a finite turn and a shift within {MAX_COORD:.0f} m, not "
                             f"({self.yaw}, {self.x}, {self.z})")

    def apply(self, joints: np.ndarray) -> np.ndarray:
        """Joints (..., 3) of the motion's own frame in the other's."""
        j = np.asarray(joints, np.float64)
        return (turn(j, np.full(j.shape[:-1], self.yaw)) + [self.x, 0.0, self.z]).astype(np.float32)

    def undo(self, joints: np.ndarray) -> np.ndarray:
        """Joints (..., 3) of the other's frame in the motion's own."""
        j = np.asarray(joints, np.float64) - [self.x, 0.0, self.z]
        return turn(j, np.full(j.shape[:-1], -self.yaw)).astype(np.float32)

    def describe(self) -> dict:
        return {"yaw_rad": self.yaw, "x_m": self.x, "z_m": self.z}


def frame_at(joints: np.ndarray, frame: int) -> Placement:
    """The placement whose origin is ``joints[frame]``'s root on the ground, facing where that pose faces: a motion
    made in its own frame and placed by it starts there."""
    pose = np.asarray(joints[frame], np.float64)
    return Placement(float(facing_yaw(pose)), float(pose[0, 0]), float(pose[0, 2]))


def root_frame(features: np.ndarray, frame: int) -> Placement:
    """The placement whose origin is the root of ``features`` (T, 263) on ``frame``, turned as its heading: a motion
    made in its own frame and placed by it continues the features exactly as their concatenation would."""
    angle, root = recover_root(np.asarray(features, np.float64))
    return Placement(float(-2.0 * angle[frame]), float(root[frame, 0]), float(root[frame, 2]))


def continuing(previous: np.ndarray, frames: int, overlap: int = CONTINUE_FRAMES,
               frame: Placement | None = None, source: str = "") -> tuple[Constraints, Placement]:
    """Constraints for a motion of ``frames`` frames whose first ``overlap`` frames are the last ones of
    ``previous`` (T, 22, 3), and the placement that puts it where ``previous`` is (so it plays on from
    ``previous``'s frame T - overlap). ``frame``: that placement, when known (:func:`root_frame`); by default the
    pose's own (:func:`frame_at`). ``source``: what ``previous`` is, for messages."""
    return _bridging(previous, None, frames, overlap, frame, source)


def inbetween(a: np.ndarray, b: np.ndarray, frames: int, overlap: int = CONTINUE_FRAMES,
              source: str = "") -> tuple[Constraints, Placement]:
    """Constraints for a motion of ``frames`` frames that starts with the last ``overlap`` frames of ``a`` and
    ends with the first ``overlap`` frames of ``b`` (both (T, 22, 3) in one frame), and its placement there."""
    return _bridging(a, b, frames, overlap, None, source)


def _bridging(a: np.ndarray, b: np.ndarray | None, frames: int, overlap: int, place: Placement | None,
              source: str) -> tuple[Constraints, Placement]:
    lead = f"{source}: " if source else ""
    for name, m in (("the motion to continue", a), ("the motion to reach", b)):
        if m is None:
            continue
        if len(m) < overlap:
            raise ValueError(f"{lead}{name} has {len(m)} frames; it needs at least {overlap}")
        if not np.isfinite(m).all() or (np.abs(m) > MAX_COORD).any():
            raise ValueError(f"{lead}{name} holds a coordinate that is not finite or beyond {MAX_COORD:.0f} m")
        if not has_facing(m[len(m) - overlap if b is None or m is a else 0]):
            raise ValueError(f"{lead}{name} faces nowhere where it is joined (its hips and shoulders are on one "
                             "vertical line)")
    if frames < overlap * (1 if b is None else 2) + 1:
        shared = f"the {overlap} frames it shares with the motion it continues" if b is None else \
            f"the {overlap} frames it shares with each motion it joins"
        raise ValueError(f"a motion of {frames} frames cannot hold {shared} and one of its own")
    place = place or frame_at(a, len(a) - overlap)
    keys = {i: pose for i, pose in enumerate(place.undo(a[len(a) - overlap:]))}
    if b is not None:
        keys.update({frames - overlap + i: pose for i, pose in enumerate(place.undo(b[:overlap]))})
    return Constraints(frames, keyframes=keys, fade=CONTINUE_FADE, origin=source), place
