"""Timing of the procedural motions: keyframe curves (minimum jerk, Hermite), clip lengths and repetitions."""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from lsgan.data.skeleton import FPS

MIN_FRAMES = 40  # 2 s at 20 fps
MAX_FRAMES = 160  # 8 s


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
