"""The ``jump`` family: one to three two-footed jumps, in place or forward, with a ballistic flight."""
from __future__ import annotations

import numpy as np

from lsgan.data.skeleton import FPS
from lsgan.data.synthetic.captions import _NUMBER, _TIMES, Predicates
from lsgan.data.synthetic.feet import _reach_limit
from lsgan.data.synthetic.rig import (_FOOT, _HIP_DY, _HIP_W, _LEG, _P0, _REACH, _SIGN, _Pose, _arm, _both, _foot_dir,
                                      _pelvis_height)
from lsgan.data.synthetic.timing import _frames, _hermite, _keys, _mj, _repetitions

_G = 9.81


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
