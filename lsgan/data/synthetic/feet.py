"""Feet first: footholds, swing arcs and heel lift from a step schedule, then the pelvis height that keeps every
planted foot within reach (so planted feet do not slide and no leg overstretches)."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.ndimage import gaussian_filter1d, minimum_filter1d

from lsgan.data.synthetic.rig import _FOOT, _HIP_DY, _HIP_TILT, _HIP_W, _LEG, _P0, _REACH, _SIGN, _foot_dir, _unit
from lsgan.data.synthetic.timing import _mj

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
