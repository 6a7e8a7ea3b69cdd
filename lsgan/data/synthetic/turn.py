"""The ``turn-left`` and ``turn-right`` families: stepping round in place (45-190 degrees) or walking in a curve
(60-120)."""
from __future__ import annotations

import numpy as np

from lsgan.data.synthetic.captions import Predicates
from lsgan.data.synthetic.feet import _follow_height, _plan_feet
from lsgan.data.synthetic.gait import _gait_pose
from lsgan.data.synthetic.rig import _SIDE_NAME, _SIGN, _Pose, _pelvis_height
from lsgan.data.synthetic.stand import _stand
from lsgan.data.synthetic.timing import _frames, _mj

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
