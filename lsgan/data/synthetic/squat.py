"""The ``squat`` family: one to three squats, arms forward for balance."""
from __future__ import annotations

import numpy as np

from lsgan.data.synthetic.captions import _NUMBER, _TIMES, Predicates
from lsgan.data.synthetic.rig import _Pose, _arm, _both
from lsgan.data.synthetic.stand import _stand
from lsgan.data.synthetic.timing import _excursion, _frames, _keys, _repetitions

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
