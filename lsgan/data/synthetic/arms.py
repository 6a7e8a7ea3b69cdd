"""The arm families: ``wave-left-hand`` and ``wave-right-hand`` (the forearm swings side to side above the
shoulder), ``raise-left-hand``, ``raise-right-hand`` and ``raise-both-hands`` (arms above the head, then down)."""
from __future__ import annotations

import numpy as np

from lsgan.data.synthetic.captions import _TIMES, Predicates
from lsgan.data.synthetic.rig import _SIDE_NAME, _SIGN, _Pose, _arm, _arm_angles
from lsgan.data.synthetic.stand import _stand
from lsgan.data.synthetic.timing import _excursion, _frames, _keys, _repetitions

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
