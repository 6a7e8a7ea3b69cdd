"""Standing still: planted feet, a slight sway and hanging arms; the start of every in-place family."""
from __future__ import annotations

import numpy as np

from lsgan.data.skeleton import FPS
from lsgan.data.synthetic.feet import _fit_height, _plan_feet
from lsgan.data.synthetic.rig import _Pose, _arm, _both, _pelvis_height

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
