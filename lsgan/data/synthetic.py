"""Procedural, labelled motions on the HumanML3D 22-joint target skeleton: the project's built-in data.

The clips are synthetic (no motion capture): each is built from a few randomised parameters so that the
demo and the fast tests can train and evaluate without any download. Families (action labels):

- ``walk``, ``run``: forward, backward, sideways to the left or right; slow, normal or fast.
- ``turn-left``, ``turn-right``: stepping round in place (45-190 degrees) or walking in a curve (60-120).
- ``jump``: in place or forward, one to three times.
- ``wave-left-hand``, ``wave-right-hand``: the forearm swings side to side above the shoulder.
- ``raise-left-hand``, ``raise-right-hand``, ``raise-both-hands``: arms above the head, then down.
- ``squat``: one to three squats, arms forward for balance.
- ``kick-left``, ``kick-right``: front kicks, low or high.

How a clip is built: the feet are planned first (footholds on the floor, swing arcs between them, heel
lift before toe-off), the pelvis height is fitted so that every planted foot stays within reach, the
legs are solved with analytic two-bone IK and everything else is placed by bone directions. Every bone
is its BONE_LENGTHS entry long (forward kinematics of the target offsets), planted feet do not slide, and
the lowest joint of a clip touches y = 0. "Left" and "right" are the character's own sides (+x is its
left at rest, facing +z). Each clip gets three templated captions that name the same direction, side,
speed and repetitions as the motion. The output is joint positions only (rotations come from the
feature pipeline's IK) and is a pure function of (family, RNG state).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Callable, Sequence

import numpy as np
from scipy.ndimage import gaussian_filter1d, minimum_filter1d

from lsgan.data.skeleton import BONE_LENGTHS, FPS, NUM_JOINTS

FAMILIES: tuple[str, ...] = (
    "walk", "run", "turn-left", "turn-right", "jump", "wave-left-hand", "wave-right-hand",
    "raise-left-hand", "raise-right-hand", "raise-both-hands", "squat", "kick-left", "kick-right",
)
MIN_FRAMES = 40  # 2 s at 20 fps
MAX_FRAMES = 160  # 8 s

_G = 9.81
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
_SUBJECTS = (
    ("a person", "their"), ("someone", "their"), ("a man", "his"), ("the person", "their"),
    ("a woman", "her"), ("the man", "his"),
)
_TIMES = {1: "", 2: " twice", 3: " three times", 4: " four times"}
_NUMBER = {2: "two", 3: "three", 4: "four"}

Predicates = list[list[str]]  # groups of paraphrases; each caption comes from a different group


@dataclass(frozen=True)
class SyntheticClip:
    """One generated clip: joints (T,22,3) float32 metres at 20 fps, three captions, the family label."""

    name: str
    joints: np.ndarray
    captions: list[str]
    action: str


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


# ---------------------------------------------------------------------------------------------- maths

def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _mj(s: np.ndarray | float) -> np.ndarray:
    """Minimum-jerk blend 0 -> 1 on s in [0, 1] (clipped): zero velocity and acceleration at both ends."""
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def _keys(t: np.ndarray, times: Sequence[float], values: Sequence) -> np.ndarray:
    """Values (T, ...) at times t from keyframes, minimum-jerk between keys, held outside them."""
    k = np.asarray(times, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    flat = v.reshape(len(k), -1)
    i = np.clip(np.searchsorted(k, t, side="right") - 1, 0, len(k) - 2)
    w = _mj((t - k[i]) / np.maximum(k[i + 1] - k[i], 1e-9))[:, None]
    return (flat[i] + (flat[i + 1] - flat[i]) * w).reshape((len(t),) + v.shape[1:])


def _hermite(s: np.ndarray, y0: float, y1: float, m0: float, m1: float) -> np.ndarray:
    """Cubic Hermite on s in [0, 1]; m0, m1 are end slopes already scaled by the segment duration."""
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * y0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * y1 + (s3 - s2) * m1


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


# ------------------------------------------------------------------------------------------ assembly

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


# ------------------------------------------------------------------------------------- feet and pelvis

def _plan_feet(t: np.ndarray, root_xz: np.ndarray, yaw: np.ndarray, swings: Sequence[np.ndarray], width: float,
               lead: float, lift: float, heel_off: float, toe_out: float,
               land_from: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Foot-joint targets (N,2,3), ankle->foot directions (N,2,3) and support mask (N,2) from a step schedule.

    ``swings[k]`` (M,2) are the swing intervals (seconds) of foot k; between them the foot is planted at
    the root's position and facing at time min(stance middle, stance start + lead), ``width`` to its side.
    Before a swing the heel rises (the foot pitches down by ``heel_off`` about the planted foot joint);
    in the swing the foot travels to the next foothold on an arc ``lift`` high. The support mask marks
    the frames where the foot must stay within reach: planted, or landing (swing progress > ``land_from``).
    """
    N = len(t)
    foot = np.zeros((N, 2, 3))
    fdir = np.zeros((N, 2, 3))
    support = np.ones((N, 2), dtype=bool)
    for k, s in enumerate(_SIGN):
        sw = np.asarray(swings[k], dtype=np.float64).reshape(-1, 2)
        st_a = np.concatenate([[t[0]], sw[:, 1]])
        st_b = np.concatenate([sw[:, 0], [t[-1]]])
        t_ref = np.clip(np.minimum((st_a + st_b) / 2, st_a + lead), t[0], t[-1])
        yaw_ref = np.interp(t_ref, t, yaw)
        c, sn = np.cos(yaw_ref), np.sin(yaw_ref)
        off_x, off_z = s * width, _FOOT[k] * np.cos(_P0[k])  # the ankle under the hip line, the toe ahead
        plant = np.stack([np.interp(t_ref, t, root_xz[:, 0]) + c * off_x + sn * off_z,
                          np.interp(t_ref, t, root_xz[:, 1]) - sn * off_x + c * off_z], -1)
        psi = yaw_ref + s * toe_out
        if len(sw):
            j = np.searchsorted(sw[:, 0], t, side="right") - 1
            jj = np.clip(j, 0, len(sw) - 1)
            in_swing = (j >= 0) & (t < sw[jj, 1])
        else:
            j, jj = np.full(N, -1), np.zeros(N, dtype=np.int64)
            in_swing = np.zeros(N, dtype=bool)
        i = np.where(in_swing, 0, j + 1)
        dur = np.minimum(0.35 * (st_b[i] - st_a[i]), 0.25)
        rise = np.clip((t - (st_b[i] - dur)) / np.maximum(dur, 1e-9), 0.0, 1.0) * (i < len(sw))
        pitch = _P0[k] + heel_off * _mj(rise)
        xz, y, yaw_f, u = plant[i], np.zeros(N), psi[i], np.ones(N)
        if len(sw):
            u = np.clip((t - sw[jj, 0]) / (sw[jj, 1] - sw[jj, 0]), 0.0, 1.0)
            # Slow lift-off like _mj, smoothstep-like landing: the foot overshoots the next foothold less.
            w = (1.0 - u) * _mj(u) + u * u * u * (3.0 - 2.0 * u)
            xz = np.where(in_swing[:, None], plant[jj] + (plant[jj + 1] - plant[jj]) * w[:, None], xz)
            y = np.where(in_swing, lift * np.sin(np.pi * u) ** 0.75, y)
            pitch = np.where(in_swing, _P0[k] + heel_off * (1.0 - w), pitch)
            yaw_f = np.where(in_swing, psi[jj] + (psi[jj + 1] - psi[jj]) * w, yaw_f)
        foot[:, k] = np.stack([xz[:, 0], y, xz[:, 1]], -1)
        fdir[:, k] = _foot_dir(yaw_f, pitch)
        support[:, k] = ~in_swing | (u > land_from)
    return foot, fdir, support


def _reach_limit(pelvis_xz: np.ndarray, yaw: np.ndarray, foot: np.ndarray, fdir: np.ndarray,
                 support: np.ndarray, reach: float = _REACH) -> np.ndarray:
    """Highest pelvis per frame (T,) that keeps every supporting leg (mask (T,2)) below ``reach`` of full extension."""
    ankle = foot - _FOOT[None, :, None] * _unit(fdir)
    lateral = np.stack([np.cos(yaw), -np.sin(yaw)], -1)
    hip = pelvis_xz[:, None, :] + (_SIGN * _HIP_W * np.cos(_HIP_TILT))[None, :, None] * lateral[:, None, :]
    d2 = ((hip - ankle[..., [0, 2]]) ** 2).sum(-1)
    height = ankle[..., 1] + np.sqrt(np.maximum((reach * _LEG) ** 2 - d2, 0.0)) - _HIP_DY
    return np.where(support, height, np.inf).min(1)


def _follow_height(pelvis_xz: np.ndarray, yaw: np.ndarray, foot: np.ndarray, fdir: np.ndarray, support: np.ndarray,
                   h_max: float) -> np.ndarray:
    """Pelvis heights (T,) that ride just under the reach of the planted legs (an inverted-pendulum walk).

    The reach limit is eroded then smoothed, so the pelvis dips smoothly at double support and stays
    at most ``h_max`` (knees slightly bent) in mid-stance; a last clip keeps every planted foot reachable.
    """
    limit = np.minimum(_reach_limit(pelvis_xz, yaw, foot, fdir, support), h_max)
    y = gaussian_filter1d(minimum_filter1d(limit, 3, mode="nearest"), 0.8, mode="nearest")
    return np.minimum(y, _reach_limit(pelvis_xz, yaw, foot, fdir, support, 0.9995))


def _fit_height(pelvis_xz: np.ndarray, yaw: np.ndarray, foot: np.ndarray, fdir: np.ndarray, support: np.ndarray,
                bounce: np.ndarray, h_max: float) -> np.ndarray:
    """Pelvis heights (T,): the highest constant (at most h_max) plus ``bounce`` that every planted foot reaches."""
    limit = _reach_limit(pelvis_xz, yaw, foot, fdir, support) - bounce
    return min(h_max, float(limit.min())) + bounce


def _cyclic_swings(t0: float, t1: float, period: float, duty: float, phase: float,
                   rng: np.random.Generator) -> list[np.ndarray]:
    """Alternating swing intervals for a periodic gait, with a small random jitter on every step."""
    out = []
    for ph in (phase, phase + 0.5):
        n = np.arange(np.floor(t0 / period - ph) - 1, np.ceil(t1 / period - ph) + 2)
        centres = (n + ph + np.clip(rng.normal(0.0, 0.015, len(n)), -0.03, 0.03)) * period
        half = duty * period / 2
        out.append(np.stack([centres[:-1] + half, centres[1:] - half], -1))
    return out


def _rest_arms(t: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Hanging arms with a slow idle wobble: upper and forearm directions (T,2,3)."""
    e_u, e_f = rng.uniform(0.08, 0.16), rng.uniform(0.2, 0.45)
    a_u, a_f = rng.uniform(0.2, 0.6), np.pi / 2 - rng.uniform(0.2, 0.5)
    freq, ph = rng.uniform(0.15, 0.35), rng.uniform(0, 2 * np.pi, 2)
    wob = 0.03 * np.sin(2 * np.pi * freq * t[:, None] + ph)
    upper = _both(lambda k, s: _arm(s, e_u + wob[:, k], a_u))
    fore = _both(lambda k, s: _arm(s, e_f + 1.5 * wob[:, k], a_f))
    return upper, fore


def _stand(rng: np.random.Generator, T: int, width: tuple[float, float] = (0.1, 0.14),
           toe_out: tuple[float, float] = (0.05, 0.2)) -> tuple[np.ndarray, _Pose]:
    """Time axis and a standing pose with planted feet, a slight sway and hanging arms."""
    t = np.arange(T) / FPS
    yaw = np.zeros(T)
    empty = np.zeros((0, 2))
    foot, fdir, stance = _plan_feet(t, np.zeros((T, 2)), yaw, [empty, empty], rng.uniform(*width), 0.0, 0.0, 0.0,
                                    rng.uniform(*toe_out))
    amp, freq, ph = rng.uniform(0.004, 0.012, 2), rng.uniform(0.15, 0.4, 2), rng.uniform(0, 2 * np.pi, 2)
    sway = amp * np.sin(2 * np.pi * freq * t[:, None] + ph)
    y = _fit_height(sway, yaw, foot, fdir, stance, np.zeros(T), _pelvis_height(rng.uniform(0.997, 0.9995)))
    upper, fore = _rest_arms(t, rng)
    pose = _Pose(np.stack([sway[:, 0], y, sway[:, 1]], -1), yaw, np.full(T, rng.uniform(0.0, 0.05)), np.zeros(T),
                 foot, fdir, upper, fore)
    return t, pose


def _frames(seconds: float) -> int:
    return int(np.clip(round(seconds * FPS), MIN_FRAMES, MAX_FRAMES))


def _repetitions(u, reps: int, one: Callable, end: Callable[[float], float] = lambda time: time,
                 ) -> tuple[list, float, int]:
    """``reps`` repetitions after a lead-in, each ``one(time) -> (item, time it ends)``, dropping one repetition at
    a time until ``end(time)`` fits in MAX_FRAMES (one always stays): (items, end time, repetitions kept)."""
    while True:
        time, items = u(0.3, 1.0), []
        for _ in range(reps):
            item, time = one(time)
            items.append(item)
        total = end(time)
        if total <= MAX_FRAMES / FPS or reps == 1:
            return items, total, reps
        reps -= 1


def _excursion(u, go: tuple[float, float], hold: tuple[float, float], back: tuple[float, float],
               rest: tuple[float, float]) -> Callable:
    """``one`` for :func:`_repetitions`: 0 -> 1, held, -> 0, then a rest: its keys (time, value)."""
    def one(time: float) -> tuple[list, float]:
        g, h, b = u(*go), u(*hold), u(*back)
        keys = [(time, 0.0), (time + g, 1.0), (time + g + h, 1.0), (time + g + h + b, 0.0)]
        return keys, time + (g + h + b + u(*rest))
    return one


# ---------------------------------------------------------------------------------------- walk / run

_DIRS = {"forward": (0.0, 1.0), "backward": (0.0, -1.0), "left": (1.0, 0.0), "right": (-1.0, 0.0)}
_SPEEDS = {
    ("walk", "forward"): {"slow": (0.6, 0.85), "normal": (0.95, 1.3), "fast": (1.45, 1.8)},
    ("walk", "backward"): {"slow": (0.35, 0.5), "normal": (0.55, 0.75), "fast": (0.85, 1.05)},
    ("walk", "side"): {"slow": (0.3, 0.42), "normal": (0.45, 0.6), "fast": (0.65, 0.8)},
    ("run", "forward"): {"slow": (2.0, 2.5), "normal": (2.7, 3.2), "fast": (3.5, 4.2)},
    ("run", "backward"): {"slow": (1.3, 1.7), "normal": (1.8, 2.2), "fast": (2.3, 2.7)},
    ("run", "side"): {"slow": (1.2, 1.5), "normal": (1.6, 1.9), "fast": (2.0, 2.4)},
}


@dataclass(frozen=True)
class _Gait:
    v: float
    period: float  # one full cycle (two steps), seconds
    duty: float  # stance fraction of the cycle
    width: float
    lift: float
    heel_off: float
    toe_out: float
    bounce: float  # run: pelvis bob, < 0 = lowest at mid-stance (a walk follows its legs' reach instead)
    sway: float
    lean: float
    arm_amp: float
    elbow: float
    knee: float = 0.996  # walk: mid-stance hip-ankle distance as a fraction of the leg length


def _gait_params(rng: np.random.Generator, kind: str, direction: str, speed: str) -> _Gait:
    """Speed, cadence and style of a walk or run; stride and stance are sized so planted legs stay in reach."""
    axis = direction if direction in ("forward", "backward") else "side"
    v = rng.uniform(*_SPEEDS[(kind, axis)][speed])
    u = rng.uniform
    if kind == "walk":
        width = {"forward": u(0.09, 0.12), "backward": u(0.09, 0.12), "side": u(0.17, 0.19)}[axis]
        step = {"forward": 0.3 + 0.18 * v, "backward": 0.25 + 0.15 * v, "side": 0.2 + 0.15 * v}[axis] * u(0.95, 1.05)
        e_max = {"forward": 0.36, "backward": 0.3, "side": width - 0.02}[axis]
        duty = min(u(0.6, 0.65), e_max / step)
        return _Gait(v, 2 * step / v, duty, width, u(0.06, 0.1) if axis != "side" else u(0.05, 0.08),
                     {"forward": u(0.35, 0.55), "backward": u(0.05, 0.15), "side": u(0.1, 0.2)}[axis],
                     u(0.05, 0.15), 0.0, u(0.015, 0.03),
                     {"forward": u(0.03, 0.08), "backward": u(-0.02, 0.04), "side": u(0.0, 0.04)}[axis],
                     u(0.3, 0.5) if axis != "side" else u(0.05, 0.15), u(0.15, 0.35), u(0.993, 0.999))
    width = {"forward": u(0.07, 0.1), "backward": u(0.08, 0.11), "side": u(0.15, 0.17)}[axis]
    period = {"forward": 0.78 - 0.035 * v, "backward": 0.72 - 0.03 * v, "side": 0.68 - 0.04 * v}[axis] * u(0.95, 1.05)
    step = v * period / 2
    e_max = {"forward": 0.28, "backward": 0.26, "side": width - 0.03}[axis]
    return _Gait(v, period, float(np.clip(e_max / step, 0.22, 0.42)), width,
                 {"forward": u(0.12, 0.2), "backward": u(0.1, 0.15), "side": u(0.08, 0.12)}[axis],
                 {"forward": u(0.5, 0.8), "backward": u(0.05, 0.15), "side": u(0.1, 0.25)}[axis],
                 u(0.05, 0.15), -u(0.02, 0.035), u(0.005, 0.015),
                 {"forward": u(0.1, 0.2), "backward": u(0.0, 0.08), "side": u(0.02, 0.08)}[axis],
                 u(0.5, 0.8) if axis != "side" else u(0.1, 0.2), u(1.2, 1.6))


def _gait_pose(rng: np.random.Generator, T: int, kind: str, direction: str, speed: str,
               yaw_fn: Callable[[np.ndarray], np.ndarray] | None = None) -> _Pose:
    """A walk or run of T frames; ``yaw_fn`` (seconds -> facing angle) curves the path for walking turns."""
    g = _gait_params(rng, kind, direction, speed)
    pad = int(np.ceil(2 * g.period * FPS)) + 2
    t = (np.arange(T + 2 * pad) - pad) / FPS
    yaw = yaw_fn(t) if yaw_fn is not None else np.zeros(len(t))
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dz = _DIRS[direction]
    root = np.cumsum(g.v * np.stack([c * dx + s * dz, -s * dx + c * dz], -1), 0) / FPS
    root -= root[pad]
    phase = rng.uniform()
    swings = _cyclic_swings(t[0], t[-1], g.period, g.duty, phase, rng)
    foot, fdir, support = _plan_feet(t, root, yaw, swings, g.width, g.duty * g.period / 2, g.lift, g.heel_off,
                                     g.toe_out, 0.5 if kind == "walk" else 1.0)
    cycle = 2 * np.pi * (t / g.period - phase)  # 0 at a left mid-stance
    lateral, forward = np.stack([c, -s], -1), np.stack([s, c], -1)
    pelvis_xz = root + g.sway * np.cos(cycle)[:, None] * lateral
    bounce = g.bounce * np.cos(2 * cycle)
    crop = slice(pad, pad + T)
    if kind == "walk":
        y = _follow_height(pelvis_xz, yaw, foot, fdir, support, _pelvis_height(g.knee))[crop]
    else:
        y = _fit_height(pelvis_xz[crop], yaw[crop], foot[crop], fdir[crop], support[crop], bounce[crop],
                        _pelvis_height(_REACH))
    yaw, foot, fdir = yaw[crop], foot[crop], fdir[crop]
    pelvis_xz, forward, cycle = pelvis_xz[crop], forward[crop], cycle[crop]
    fwd = ((foot[..., [0, 2]] - pelvis_xz[:, None]) * forward[:, None]).sum(-1)
    fwd -= fwd.mean(0)
    elev = g.arm_amp * fwd[:, ::-1] / (np.abs(fwd).max() + 1e-6)  # each arm swings with the opposite foot
    upper = _both(lambda k, s: _arm(s, elev[:, k], np.pi / 2, 0.12))
    fore = _both(lambda k, s: _arm(s, elev[:, k] + g.elbow, np.pi / 2, 0.06))
    lean = g.lean + 0.015 * np.cos(2 * cycle)
    return _Pose(np.stack([pelvis_xz[:, 0], y, pelvis_xz[:, 1]], -1), yaw, lean, np.zeros(T), foot, fdir, upper, fore)


def _gait_predicates(kind: str, direction: str, speed: str) -> Predicates:
    d = direction
    adverbs = {"slow": ["slowly", "at a slow pace"], "normal": ["", "at a normal pace", "at a steady pace"],
               "fast": ["quickly", "fast", "at a fast pace"]}[speed]
    if kind == "walk":
        verbs = {
            "forward": ["walks forward", "walks straight ahead", "walks forwards", "takes several steps forward"],
            "backward": ["walks backward", "walks backwards", "steps backward", "moves backwards"],
        }.get(d, [f"walks to the {d}", f"sidesteps to the {d}", f"steps sideways to the {d}",
                  f"walks sideways to {{p}} {d}"])
        extra = {("forward", "slow"): ["strolls forward"], ("forward", "fast"): ["walks briskly forward"]}
        groups = [[f"{v} {a}".strip() for a in adverbs] for v in verbs]
        return groups + [[e] for e in extra.get((d, speed), [])]
    if d in ("forward", "backward"):
        table = {
            ("forward", "slow"): ["jogs forward", "jogs forward slowly", "runs slowly forward", "jogs ahead"],
            ("forward", "normal"): ["runs forward", "jogs forward", "is running forward", "runs straight ahead"],
            ("forward", "fast"): ["sprints forward", "runs forward fast", "dashes forward", "runs quickly forward"],
            ("backward", "slow"): ["jogs backward", "runs slowly backwards", "jogs backwards slowly"],
            ("backward", "normal"): ["runs backward", "jogs backwards", "backpedals", "runs backwards"],
            ("backward", "fast"): ["runs backward quickly", "backpedals fast", "sprints backwards"],
        }
        return [[v] for v in table[(d, speed)]]
    verbs = [f"jogs to the {d}", f"runs sideways to the {d}", f"shuffles sideways to the {d}",
             f"side-shuffles to {{p}} {d}"]
    adverbs = {"slow": ["slowly", ""], "normal": [""], "fast": ["quickly", "fast"]}[speed]
    return [[f"{v} {a}".strip() for a in adverbs] for v in verbs]


def _walk_or_run(rng: np.random.Generator, kind: str) -> tuple[_Pose, Predicates]:
    direction = str(rng.choice(["forward", "forward", "backward", "left", "right"]))
    speed = str(rng.choice(["slow", "normal", "fast"]))
    T = int(rng.integers(MIN_FRAMES, MAX_FRAMES + 1)) if kind == "walk" else int(rng.integers(MIN_FRAMES, 121))
    return _gait_pose(rng, T, kind, direction, speed), _gait_predicates(kind, direction, speed)


# ---------------------------------------------------------------------------------------------- turn

def _turn(rng: np.random.Generator, k: int) -> tuple[_Pose, Predicates]:
    """Turn to side k: stepping round in place, or a walk that curves that way."""
    s, d = _SIGN[k], _SIDE_NAME[k]
    if rng.random() < 0.35:
        angle = np.deg2rad(rng.uniform(60.0, 120.0))
        t_a, dur = rng.uniform(0.5, 1.5), rng.uniform(1.2, 2.5)
        T = _frames(t_a + dur + rng.uniform(0.5, 2.0))
        pose = _gait_pose(rng, T, "walk", "forward", str(rng.choice(["slow", "normal"])),
                          lambda t: s * angle * _mj((t - t_a) / dur))
        preds = [[f"walks forward and turns {d}"], [f"walks and turns to the {d}"], [f"walks in a curve to the {d}"],
                 [f"turns {d} while walking"], [f"walks forward, then veers to the {d}"]]
        return pose, preds
    pick = rng.random()  # a quarter turn, a half turn or anything in between
    deg = rng.uniform(*((80.0, 100.0) if pick < 0.4 else (165.0, 190.0) if pick < 0.7 else (45.0, 150.0)))
    angle = np.deg2rad(deg)
    cycle = rng.uniform(0.7, 1.0)
    n = max(2, int(np.ceil(angle / rng.uniform(0.8, 1.2))))
    pre, swing = rng.uniform(0.3, 1.0), rng.uniform(0.38, 0.45) * cycle
    T = _frames(pre + (n + 0.5) * cycle + rng.uniform(0.5, 1.5))
    t, pose = _stand(rng, T)
    lead_steps = np.array([[pre + i * cycle, pre + i * cycle + swing] for i in range(n)])
    swings = [lead_steps, lead_steps + 0.5 * cycle] if k == 0 else [lead_steps + 0.5 * cycle, lead_steps]
    yaw = s * angle * _mj((t - pre) / ((n - 0.5) * cycle + swing))
    foot, fdir, support = _plan_feet(t, np.zeros((T, 2)), yaw, swings, rng.uniform(0.1, 0.13), 0.5 * cycle,
                                    rng.uniform(0.05, 0.08), rng.uniform(0.1, 0.25), rng.uniform(0.05, 0.15))
    pelvis_xz = pose.pelvis[:, [0, 2]]
    y = _follow_height(pelvis_xz, yaw, foot, fdir, support, _pelvis_height(rng.uniform(0.993, 0.999)))
    pose = _Pose(np.stack([pelvis_xz[:, 0], y, pelvis_xz[:, 1]], -1), yaw, pose.lean, pose.roll, foot, fdir,
                 pose.upper, pose.fore)
    preds = [[f"turns {d}", f"turns {d} in place"], [f"turns to the {d}"], [f"turns to {{p}} {d}"],
             [f"pivots to the {d}"], [f"rotates {{p}} body to the {d}"]]
    if deg >= 150:
        preds = [[f"turns around to the {d}"], [f"turns around over {{p}} {d} shoulder"],
                 [f"does a half turn to the {d}"], [f"turns all the way around to the {d}"]] + preds[:2]
    elif 75 <= deg <= 105:
        preds += [[f"turns ninety degrees to the {d}"], [f"makes a quarter turn to the {d}"]]
    return pose, preds


# ---------------------------------------------------------------------------------------------- jump

def _jump(rng: np.random.Generator) -> tuple[_Pose, Predicates]:
    """One to three two-footed jumps: crouch, push onto the toes, ballistic flight, land and recover."""
    forward = rng.random() < 0.5
    reps = int(rng.integers(1, 4))
    u = rng.uniform
    width, toe_out, p_to = u(0.1, 0.14), u(0.05, 0.2), u(0.9, 1.1)
    lean0 = u(0.0, 0.05)
    jumps, total, reps = _jump_schedule(u, forward, reps)
    T = _frames(total)
    t = np.arange(T) / FPS
    fwd = 1.0 if forward else 0.0
    h_s = _pelvis_height(u(0.997, 0.9995))
    toe_z = [_FOOT[k] * np.cos(_P0[k]) for k in range(2)]
    # Pelvis and foot drivers, filled segment by segment; between jumps everything holds still.
    d = {"y": np.full(T, h_s), "z": np.zeros(T), "anchor": np.zeros(T), "pitch": np.tile(_P0, (T, 1)),
         "foot_y": np.zeros((T, 2)), "stance": np.ones((T, 2), dtype=bool)}
    lean_k, arm_k = [(0.0, lean0)], [(0.0, 0.12)]
    a = 0.0
    for j in jumps:
        ts, tc, tt, tl, tb, te = j["times"]
        a = _jump_drivers(d, t, j, a, fwd=fwd, width=width, p_to=p_to, h_s=h_s)
        lean_k += [(ts, lean0), (j["push"], j["lean"]), (tt, 0.1), (tl, 0.05), (tb, 0.3), (te, lean0)]
        arm_k += [(ts, 0.12), (j["push"], -0.6), (tt, j["arms"]), ((tt + tl) / 2, j["arms"] + 0.15), (tl, 1.0),
                  (tb, 0.6), (te, 0.12)]
    psi = _SIGN * toe_out
    foot = np.stack([
        np.stack([np.full(T, _SIGN[k] * width + toe_z[k] * np.sin(psi[k])), d["foot_y"][:, k],
                  d["anchor"] + toe_z[k] * np.cos(psi[k])], -1) for k in range(2)], 1)
    fdir = _foot_dir(np.broadcast_to(psi, (T, 2)), d["pitch"])
    pelvis_xz = np.stack([np.zeros(T), d["z"]], -1)
    y = np.minimum(d["y"], _reach_limit(pelvis_xz, np.zeros(T), foot, fdir, d["stance"]))
    lean = _keys(t, *zip(*lean_k))
    elev = _keys(t, *zip(*arm_k))
    upper = _both(lambda k, s: _arm(s, elev, np.pi / 2, 0.1))
    fore = _both(lambda k, s: _arm(s, elev + 0.3, np.pi / 2, 0.05))
    pose = _Pose(np.stack([pelvis_xz[:, 0], y, d["z"]], -1), np.zeros(T), lean, np.zeros(T), foot, fdir, upper, fore)
    return pose, _jump_captions(forward, reps, jumps)


def _jump_schedule(u, forward: bool, reps: int) -> tuple[list[dict], float, int]:
    """Each jump's sizes and phase times (start, crouch end, take-off, landing, bottom, end), the clip's length and
    how many jumps fit: one fewer until they fit MAX_FRAMES."""
    def one(time: float) -> tuple[dict, float]:
        j = {"dist": u(0.3, 0.9) if forward else 0.0, "rise": u(0.12, 0.3) if forward else u(0.15, 0.35),
             "crouch": u(0.12, 0.25), "land": u(0.1, 0.2), "tuck": u(0.1, 0.25), "arms": u(2.0, 2.6),
             "lean": u(0.3, 0.5)}
        j["flight"] = 2 * np.sqrt(2 * j["rise"] / _G)
        j["v0"] = _G * j["flight"] / 2
        spans = [u(0.35, 0.6), u(0.18, 0.28), j["flight"], u(0.2, 0.35), u(0.35, 0.6)]
        j["times"] = time + np.cumsum([0.0] + spans)
        return j, j["times"][-1] + u(0.1, 0.6)

    return _repetitions(u, reps, one, end=lambda time: time + u(0.2, 0.8))


def _jump_drivers(d: dict, t: np.ndarray, j: dict, a: float, *, fwd: float, width: float, p_to: float,
                  h_s: float) -> float:
    """Fill the drivers ``d`` (pelvis height y and forward z, foothold anchor, foot pitch, lift and stance) over one
    jump's phases, taking off from foothold ``a``; records the push's start in ``j["push"]``; returns where it
    lands."""
    y, z, anchor, pitch = d["y"], d["z"], d["anchor"], d["pitch"]
    ts, tc, tt, tl, tb, te = j["times"]
    # The legs are straight with the heels up at take-off and landing.
    ankle_to = min(_FOOT[k] * np.sin(p_to) for k in range(2))
    dz_to = 0.08 * fwd
    h_to = ankle_to - 0.01 + min(
        np.sqrt((_REACH * _LEG[k]) ** 2 - (width - _HIP_W[k]) ** 2
                - (dz_to + _FOOT[k] * (np.cos(p_to) - np.cos(_P0[k]))) ** 2) - _HIP_DY[k] for k in range(2))
    vz = j["dist"] / j["flight"]
    b = a + dz_to + j["dist"] + 0.1 * fwd  # landing foothold: the feet land ahead of the pelvis
    push_d = min(tt - tc, 2.8 * (h_to - h_s + j["crouch"]) / j["v0"])
    tc = j["push"] = tt - push_d
    m = (t >= ts) & (t < tc)
    s = (t[m] - ts) / (tc - ts)
    y[m] = h_s - j["crouch"] * _mj(s)
    z[m] = a - 0.06 * _mj(s)
    m = (t >= tc) & (t < tt)
    s = (t[m] - tc) / (tt - tc)
    y[m] = _hermite(s, h_s - j["crouch"], h_to, 0.0, j["v0"] * (tt - tc))
    z[m] = _hermite(s, a - 0.06, a + dz_to, 0.0, vz * (tt - tc))
    pitch[m] = _P0 + (p_to - _P0) * _mj(s)[:, None]
    m = (t >= tt) & (t < tl)
    tau = t[m] - tt
    s = tau / (tl - tt)
    y[m] = h_to + j["v0"] * tau - 0.5 * _G * tau**2
    z[m] = a + dz_to + vz * tau
    anchor[m] = a + (b - a) * _mj(s)
    d["foot_y"][m] = (y[m] - h_to + j["tuck"] * np.sin(np.pi * s))[:, None]
    pitch[m] = p_to - 0.2 * s[:, None]
    d["stance"][m] = False
    m = (t >= tl) & (t < tb)
    s = (t[m] - tl) / (tb - tl)
    y[m] = _hermite(s, h_to, h_s - j["land"], -j["v0"] * (tb - tl), 0.0)
    z[m] = _hermite(s, a + dz_to + j["dist"], b - 0.06 * fwd, vz * (tb - tl), 0.0)
    anchor[m] = b
    pitch[m] = p_to - 0.2 + (_P0 - p_to + 0.2) * _mj(2 * s)[:, None]
    m = (t >= tb) & (t < te)
    s = (t[m] - tb) / (te - tb)
    y[m] = h_s - j["land"] * (1 - _mj(s))
    z[m] = b - 0.06 * fwd * (1 - _mj(s))
    anchor[m] = b
    m = t >= te
    y[m], z[m], anchor[m] = h_s, b, b
    return b


def _jump_captions(forward: bool, reps: int, jumps: list[dict]) -> Predicates:
    times = _TIMES[reps]
    if forward:
        preds = [[f"jumps forward{times}"], [f"leaps forward{times}"], [f"jumps ahead{times}"],
                 [f"jumps forward with both feet{times}"]]
        preds += [["does a forward jump"]] if reps == 1 else [[f"does {_NUMBER[reps]} jumps forward"]]
        if max(j["dist"] for j in jumps) > 0.7:
            preds.append([f"jumps far forward{times}"])
        return preds
    preds = [[f"jumps up{times}"], [f"jumps in place{times}"], [f"jumps straight up{times}"],
             [f"jumps up and down{times}"]]
    preds += [["does a vertical jump"]] if reps == 1 else [[f"does {_NUMBER[reps]} jumps in place"]]
    return preds


# ----------------------------------------------------------------------------------------- squat

def _squat(rng: np.random.Generator) -> tuple[_Pose, Predicates]:
    """One to three squats: hips down and back, torso leaning forward, arms forward for balance."""
    u = rng.uniform
    reps = int(rng.integers(1, 4))
    depth, back, lean_max, arm = u(0.3, 0.48), u(0.15, 0.3), u(0.35, 0.6), u(1.1, 1.6)
    squats, time, reps = _repetitions(u, reps, _excursion(u, (0.7, 1.2), (0.1, 0.8), (0.7, 1.2), (0.2, 0.8)))
    T = _frames(time + u(0.0, 0.5))
    t, pose = _stand(rng, T, width=(0.14, 0.2), toe_out=(0.2, 0.4))
    prof = _keys(t, *zip(*[(0.0, 0.0)] + [k for keys in squats for k in keys]))
    pose.pelvis[:, 1] -= depth * prof
    pose.pelvis[:, 2] -= back * depth * prof
    pose.lean = pose.lean + lean_max * prof
    rest_u, rest_f = pose.upper, pose.fore
    fwd_u = _both(lambda k, s: _arm(s, np.full(T, arm), np.pi / 2, 0.1))
    fwd_f = _both(lambda k, s: _arm(s, np.full(T, arm + 0.1), np.pi / 2, 0.05))
    pose.upper = rest_u + (fwd_u - rest_u) * prof[:, None, None]
    pose.fore = rest_f + (fwd_f - rest_f) * prof[:, None, None]
    pose.knee_out = 0.35
    if reps == 1:
        preds = [["squats down and stands back up"], ["does a squat"], ["squats"],
                 ["bends {p} knees into a squat and stands up"], ["crouches down and stands up again"],
                 ["lowers {p} body into a squat"]]
        if depth > 0.42:
            preds.append(["does a deep squat"])
    else:
        n, times = _NUMBER[reps], _TIMES[reps]
        preds = [[f"does {n} squats"], [f"squats{times}"], [f"squats down and up{times}"], ["does squats"],
                 [f"performs {n} squats"]]
    return pose, preds


# ---------------------------------------------------------------------------------------------- arms

def _wave(rng: np.random.Generator, k: int) -> tuple[_Pose, Predicates]:
    """Raise the hand of side k and swing the forearm side to side above the shoulder."""
    u, s, d = rng.uniform, _SIGN[k], _SIDE_NAME[k]
    pre, up, down = u(0.3, 1.0), u(0.35, 0.6), u(0.4, 0.7)
    freq = u(1.5, 3.0)
    waves = int(rng.integers(2, 9))
    amp, centre, e_u, a_u = u(0.35, 0.6), u(-0.05, 0.25), u(1.4, 2.2), u(0.2, 0.8)
    t_w = pre + up
    t_end = t_w + waves / freq
    T = _frames(t_end + down + u(0.2, 1.0))
    t, pose = _stand(rng, T)
    keys = [0.0, pre, t_w, t_end, t_end + down]
    (eu0, au0), (ef0, af0) = _arm_angles(s, pose.upper[:, k]), _arm_angles(s, pose.fore[:, k])
    w = _keys(t, keys, [0.0, 0.0, 1.0, 1.0, 0.0])
    env = _keys(t, [t_w - 0.15, t_w + 0.1, t_end - 0.1, t_end + 0.1], [0.0, 1.0, 1.0, 0.0])
    osc = amp * env * np.sin(2 * np.pi * freq * (t - t_w))  # the forearm tilts out and in about the vertical
    pose.upper[:, k] = _arm(s, eu0 + (e_u - eu0) * w, au0 + (a_u - au0) * w)
    pose.fore[:, k] = _arm(s, ef0 + (np.pi - centre - ef0) * w - osc, af0 + (0.15 - af0) * w)
    adverb = " quickly" if freq > 2.5 else ""
    preds = [[f"waves {{p}} {d} hand{adverb}"], [f"waves with {{p}} {d} hand{adverb}"],
             [f"raises {{p}} {d} hand and waves"], [f"waves hello with {{p}} {d} hand"], [f"waves {{p}} {d} arm"],
             [f"gives a wave with {{p}} {d} hand"]]
    if waves >= 5:
        preds.append([f"waves {{p}} {d} hand repeatedly"])
    return pose, preds


def _raise(rng: np.random.Generator, sides: tuple[int, ...]) -> tuple[_Pose, Predicates]:
    """Raise one or both arms above the head, hold, lower; one to three times."""
    u = rng.uniform
    reps = int(rng.integers(1, 4))
    e_r, azim, bend = u(2.65, 3.0), u(0.0, 1.4), u(0.0, 0.2)
    raises, time, reps = _repetitions(u, reps, _excursion(u, (0.5, 1.0), (0.4, 1.8), (0.5, 1.0), (0.3, 0.8)))
    T = _frames(time + u(0.0, 0.5))
    t, pose = _stand(rng, T)
    times, vals = zip(*[(0.0, 0.0)] + [k for keys in raises for k in keys])
    for k in sides:
        s = _SIGN[k]
        delay = u(0.0, 0.08) if len(sides) > 1 else 0.0
        w = _keys(t, np.asarray(times) + delay, vals)
        (eu0, au0), (ef0, af0) = _arm_angles(s, pose.upper[:, k]), _arm_angles(s, pose.fore[:, k])
        a = azim + (u(-0.1, 0.1) if len(sides) > 1 else 0.0)
        pose.upper[:, k] = _arm(s, eu0 + (e_r - eu0) * w, au0 + (a - au0) * w)
        pose.fore[:, k] = _arm(s, ef0 + (min(e_r + bend, np.pi - 0.05) - ef0) * w, af0 + (a - af0) * w)
    times_word = _TIMES[reps]
    if len(sides) == 2:
        preds = [[f"raises both hands{times_word}"], [f"raises both arms above {{p}} head{times_word}"],
                 [f"lifts both arms up{times_word}"], [f"puts both hands up in the air{times_word}"],
                 [f"raises {{p}} arms overhead{times_word}"], [f"lifts both hands over {{p}} head{times_word}"]]
        return pose, preds
    d = _SIDE_NAME[sides[0]]
    preds = [[f"raises {{p}} {d} hand{times_word}"], [f"raises {{p}} {d} arm above {{p}} head{times_word}"],
             [f"lifts {{p}} {d} hand up{times_word}"], [f"puts {{p}} {d} hand up in the air{times_word}"],
             [f"raises {{p}} {d} arm up high{times_word}"], [f"lifts {{p}} {d} arm over {{p}} head{times_word}"]]
    if azim < 0.5:
        preds.append([f"raises {{p}} {d} arm out to the side and up{times_word}"])
    elif azim > 1.0:
        preds.append([f"raises {{p}} {d} arm forward and up over {{p}} head{times_word}"])
    return pose, preds


# ---------------------------------------------------------------------------------------------- kick

def _kick(rng: np.random.Generator, k: int) -> tuple[_Pose, Predicates]:
    """Front kicks with the leg of side k: shift the weight, wind up, kick, retract, replant."""
    u, s, d = rng.uniform, _SIGN[k], _SIDE_NAME[k]
    reps = int(rng.integers(1, 4))
    height, p_k, shift = u(0.3, 0.75), u(-0.2, 0.3), u(0.04, 0.07)
    def one(time: float) -> tuple[np.ndarray, float]:  # the phase times of a kick, from its weight shift
        times = time + np.cumsum([0.0, u(0.3, 0.5), u(0.2, 0.3), u(0.18, 0.28), u(0.2, 0.3), u(0.25, 0.4),
                                  u(0.3, 0.5)])
        return times, times[-1] + u(0.2, 0.6)

    kicks, time, reps = _repetitions(u, reps, one)
    T = _frames(time + u(0.0, 0.5))
    t, pose = _stand(rng, T)
    hip_y = pose.pelvis[0, 1] - 0.03
    ankle_y = height + _FOOT[k] * np.sin(p_k)
    ankle_fwd = np.sqrt((0.975 * _LEG[k]) ** 2 - (hip_y - ankle_y) ** 2)
    apex_fwd = ankle_fwd + _FOOT[k] * np.cos(p_k) - _FOOT[k] * np.cos(_P0[k])
    w_keys, f_keys, lean_keys, arm_keys = [(0.0, 0.0)], [(0.0, 0.0, 0.0, _P0[k])], [(0.0, 0.0)], [(0.0, 0.0, 0.0)]
    for tA, tS, tW, tK, tR, tD, tE in kicks:
        w_keys += [(tA, 0.0), (tS, 1.0), (tD, 1.0), (tE, 0.0)]
        f_keys += [(tS, 0.0, 0.0, _P0[k]), (tW, u(0.12, 0.22), -u(0.15, 0.25), _P0[k] + u(0.6, 0.9)),
                   (tK, height, apex_fwd, p_k), (tR, u(0.2, 0.3), u(0.1, 0.2), u(0.3, 0.6)), (tD, 0.0, 0.0, _P0[k])]
        lean_keys += [(tS, 0.0), (tK, -u(0.1, 0.25) * height / 0.75), (tD, 0.0)]
        arm_keys += [(tS, 0.0, 0.0), (tK, -u(0.2, 0.5), u(0.4, 0.8)), (tD, 0.0, 0.0)]
    w = _keys(t, *zip(*w_keys))
    f = _keys(t, [key[0] for key in f_keys], [key[1:] for key in f_keys])
    lean = _keys(t, *zip(*lean_keys))
    arms = _keys(t, [key[0] for key in arm_keys], [key[1:] for key in arm_keys])
    pose.pelvis[:, 0] -= s * shift * w
    pose.pelvis[:, 1] -= 0.03 * w
    pose.lean = pose.lean + lean
    pose.roll = -s * 0.06 * w
    base = pose.foot[0, k]
    psi = np.arctan2(pose.foot_dir[0, k, 0], pose.foot_dir[0, k, 2])
    pose.foot[:, k] = base + np.stack([np.zeros(T), f[:, 0], f[:, 1]], -1)
    pose.foot_dir[:, k] = _foot_dir(np.full(T, psi), f[:, 2])
    for side, swing in ((k, arms[:, 0]), (1 - k, arms[:, 1])):
        # Swing the arm in the sagittal plane and out to the side for balance, starting from its rest pose.
        delta = _arm(_SIGN[side], swing, np.pi / 2, 0.0) - _arm(_SIGN[side], 0.0, np.pi / 2)
        delta[:, 0] += _SIGN[side] * 0.4 * np.abs(swing)
        pose.upper[:, side] = _unit(pose.upper[:, side]) + delta
        pose.fore[:, side] = _unit(pose.fore[:, side]) + delta
    times = _TIMES[reps]
    preds = [[f"kicks with {{p}} {d} leg{times}"], [f"kicks forward with {{p}} {d} foot{times}"],
             [f"does a kick with the {d} leg{times}"], [f"kicks {{p}} {d} leg out in front{times}"],
             [f"performs a front kick with {{p}} {d} leg{times}"]]
    if height > 0.55:
        preds.append([f"kicks {{p}} {d} leg up high{times}"])
    elif height < 0.4:
        preds.append([f"does a low kick with {{p}} {d} foot{times}"])
    return pose, preds


# ------------------------------------------------------------------------------------------ captions

def _captions(rng: np.random.Generator, groups: Predicates, n: int = 3) -> list[str]:
    """n captions from distinct paraphrase groups, each with a subject; deterministic in ``rng``."""
    order = rng.permutation(len(groups))
    out = []
    for i in range(n):
        group = groups[order[i % len(groups)]]
        phrase = group[int(rng.integers(len(group)))]
        subject, pronoun = _SUBJECTS[int(rng.integers(len(_SUBJECTS)))]
        out.append(" ".join(f"{subject} {phrase.format(p=pronoun)}".split()))
    return out


_BUILDERS: dict[str, Callable[[np.random.Generator], tuple[_Pose, Predicates]]] = {
    "walk": partial(_walk_or_run, kind="walk"),
    "run": partial(_walk_or_run, kind="run"),
    "turn-left": partial(_turn, k=0),
    "turn-right": partial(_turn, k=1),
    "jump": _jump,
    "wave-left-hand": partial(_wave, k=0),
    "wave-right-hand": partial(_wave, k=1),
    "raise-left-hand": partial(_raise, sides=(0,)),
    "raise-right-hand": partial(_raise, sides=(1,)),
    "raise-both-hands": partial(_raise, sides=(0, 1)),
    "squat": _squat,
    "kick-left": partial(_kick, k=0),
    "kick-right": partial(_kick, k=1),
}


# ------------------------------------------------------------------------------------------ public API

def _check_families(families: Sequence[str] | None) -> tuple[str, ...]:
    fams = FAMILIES if families is None else tuple(families)
    unknown = [f for f in fams if f not in _BUILDERS]
    if unknown or not fams:
        raise ValueError(f"unknown or no synthetic families {unknown}; known: {', '.join(FAMILIES)}")
    return fams


def generate_clip(family: str, rng: np.random.Generator) -> tuple[np.ndarray, list[str], str]:
    """One clip of ``family``: joints (T,22,3) float32 (2-8 s at 20 fps), three captions, the action label."""
    (family,) = _check_families([family])
    pose, predicates = _BUILDERS[family](rng)
    joints = _finish(_assemble(pose))
    return joints, _captions(rng, predicates), family


def clip_family(index: int, families: Sequence[str] | None = None) -> str:
    """The family of clip ``index``: round-robin over ``families`` (all by default), so families are balanced."""
    fams = _check_families(families)
    return fams[index % len(fams)]


def synthetic_clip(index: int, seed: int = 0, families: Sequence[str] | None = None) -> SyntheticClip:
    """Clip ``index`` of the set defined by (seed, families); its RNG depends only on (seed, index)."""
    if index < 0 or seed < 0:
        raise ValueError(f"index and seed must be non-negative, got {index}, {seed}")
    family = clip_family(index, families)
    joints, captions, action = generate_clip(family, np.random.default_rng([seed, index]))
    return SyntheticClip(f"synth_{index:06d}", joints, captions, action)


def generate(num_clips: int, seed: int = 0, families: Sequence[str] | None = None) -> list[SyntheticClip]:
    """``num_clips`` clips, clip i being ``synthetic_clip(i, seed, families)``; the same seed gives the same data."""
    return [synthetic_clip(i, seed, families) for i in range(num_clips)]
