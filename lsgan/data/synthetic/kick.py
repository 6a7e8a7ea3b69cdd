"""The ``kick-left`` and ``kick-right`` families: front kicks, low or high."""
from __future__ import annotations

import numpy as np

from lsgan.data.synthetic.captions import _TIMES, Predicates
from lsgan.data.synthetic.rig import _FOOT, _LEG, _P0, _SIDE_NAME, _SIGN, _Pose, _arm, _foot_dir, _unit
from lsgan.data.synthetic.stand import _stand
from lsgan.data.synthetic.timing import _frames, _keys, _repetitions

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
