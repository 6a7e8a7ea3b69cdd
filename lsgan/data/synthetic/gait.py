"""The ``walk`` and ``run`` families: forward, backward or sideways; slow, normal or fast."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from lsgan.data.skeleton import FPS
from lsgan.data.synthetic.captions import Predicates
from lsgan.data.synthetic.feet import _cyclic_swings, _fit_height, _follow_height, _plan_feet
from lsgan.data.synthetic.rig import _REACH, _Pose, _arm, _both, _pelvis_height
from lsgan.data.synthetic.timing import MAX_FRAMES, MIN_FRAMES

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
