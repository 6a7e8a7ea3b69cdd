"""Clean feet: hold each foot still while it is in contact, by IK on the leg only (what ``export --fix-feet`` runs).

Pure numpy on joint positions (T,22,3): HumanML3D joint order, Y up, metres, the floor at y = 0 (as
:mod:`lsgan.eval.quality` reads it). Contacts are (T,4) per frame for [left ankle 7, left foot 10, right
ankle 8, right foot 11], the order of HumanML3D's feature channels 259-262.

Contacts. A feature row t says whether the joint moved less than sqrt(0.002) = 4.5 cm between frames t and
t+1 (:func:`lsgan.data.features.foot_contacts`), so frames t and t+1 are both in contact
(:func:`frame_contacts`). :func:`contacts_from_features` reads a generated motion's own channels (> 0.5);
:func:`estimate_contacts` applies the same rule to the joints themselves, so a plain joints file gets the
contacts its features would carry. Both rules are speed only: a foot held still in the air (a kick at its
apex) counts too, so :func:`fix_feet` keeps a contact only where the joint is also within ``CONTACT_HEIGHT``
(5 cm, GMD's rule) of its lowest height in the clip.

Locking (causal, per side). When a contact starts, the joint's anchor is where the fixed motion has it at
that frame (so nothing jumps), lifted to the floor if it is below it; while the contact lasts the joint stays
on its anchor; when it ends the joint blends back to the original over ``BLEND_FRAMES`` frames (smoothstep).
The ankle goes to its anchor (or, with only the toe in contact, to where the original foot puts the locked
toe), the foot joint keeps its length and turns towards its anchor, or keeps the original direction when
free. The leg is solved by two-bone IK: the hip stays, thigh and shin keep their lengths of that frame, the
knee stays in the plane of the original bend (a 1 cm forward pull decides a straight leg's bend). When the
body moves further than the leg reaches (``REACH`` of the stretched leg; generated motions that glide do),
the side's locks are released and may start again after the blend: no joint is ever pulled off the hip.

Only knees, ankles and foot joints change (4, 5, 7, 8, 10, 11), and only on frames within a lock or its
blend; every other value is returned bit for bit.
"""
from __future__ import annotations

import numpy as np

from lsgan.data.features import FOOT_CONTACT, foot_contacts
from lsgan.data.kinematics import facing_across, forward_from_across
from lsgan.data.skeleton import FACE_JOINTS, NUM_JOINTS

CHANNEL_JOINTS = (7, 10, 8, 11)  # the contact channels' joints: left ankle, left foot, right ankle, right foot
SIDES = ((1, 4, 7, 10), (2, 5, 8, 11))  # hip, knee, ankle, foot joint of the left and right leg
LEG_JOINTS = (4, 5, 7, 8, 10, 11)  # the joints fix_feet may move
BLEND_FRAMES = 5  # frames to blend a released joint back to the original (0.25 s at 20 fps)
CONTACT_HEIGHT = 0.05  # m above the joint's lowest height in the clip: higher is not a ground contact
REACH = 0.995  # a lock holds while the ankle stays within this share of the stretched leg (or the original's)
MAX_OFFSET = 0.15  # m: a lock holds while its anchor stays within this horizontal distance of the original joint
CATCH_UP_SPEED = 0.02  # m/frame: the most a released joint moves faster than the original while blending back
KNEE_PULL = 0.01  # m: forward pull that decides which way a straight leg bends
_STRAIGHT = 0.02  # m: a knee closer than this to the hip-ankle line counts as (nearly) straight


def frame_contacts(pairs: np.ndarray, frames: int) -> np.ndarray:
    """Per-frame contacts (frames,4) from per-pair rows (P,4), row t for frames (t, t+1): both frames count."""
    pairs = np.asarray(pairs, dtype=bool)[: frames - 1]
    out = np.zeros((frames, pairs.shape[1]), dtype=bool)
    out[: len(pairs)] |= pairs
    out[1: len(pairs) + 1] |= pairs
    return out


def contacts_from_features(features: np.ndarray) -> np.ndarray:
    """Per-frame contacts (T,4) from de-normalised features (T,263): channels 259-262 over 0.5."""
    f = np.asarray(features)
    if f.ndim != 2 or f.shape[1] != FOOT_CONTACT.stop:
        raise ValueError(f"features must be (T, {FOOT_CONTACT.stop}), got shape {f.shape}")
    return frame_contacts(f[:, FOOT_CONTACT] > 0.5, len(f))


def estimate_contacts(joints: np.ndarray) -> np.ndarray:
    """Per-frame contacts (T,4) of joints (T,22,3) by the features' own rule (foot_contacts: speed only)."""
    j = _check(joints)
    return frame_contacts(foot_contacts(j.astype(np.float64)) > 0.5, len(j))


def ground_contacts(joints: np.ndarray, contacts: np.ndarray) -> np.ndarray:
    """``contacts`` (T,4) kept where the joint is within CONTACT_HEIGHT of its lowest height in the clip."""
    y = _check(joints)[:, list(CHANNEL_JOINTS), 1].astype(np.float64)
    return np.asarray(contacts, dtype=bool) & (y - y.min(axis=0) < CONTACT_HEIGHT)


def _check(joints: np.ndarray) -> np.ndarray:
    j = np.asarray(joints)
    if j.ndim != 3 or j.shape[1:] != (NUM_JOINTS, 3) or len(j) < 2:
        raise ValueError(f"joints must be (T, {NUM_JOINTS}, 3) with T >= 2, got shape {j.shape}")
    if not np.isfinite(j).all():
        raise ValueError("joints hold NaN or infinite values")
    return j


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _blend(k: int, n: int) -> float:
    """Weight of a released joint's anchor k frames after its lock ended (1 -> 0 over n frames, smoothstep)."""
    if k > n:
        return 0.0
    s = k / (n + 1)
    return 1.0 - s * s * (3.0 - 2.0 * s)


def catch_up_frames(offset: float) -> int:
    """Frames to blend a joint ``offset`` metres from the original back: BLEND_FRAMES, more when the smoothstep's
    peak speed (1.5 offset / (n + 1)) would be over CATCH_UP_SPEED."""
    return max(BLEND_FRAMES, int(np.ceil(1.5 * offset / CATCH_UP_SPEED)) - 1)


class _Lock:
    """One joint's lock: its anchor, how many frames since it was released, and the frames it held."""

    def __init__(self) -> None:
        self.anchor = np.zeros(3)
        self.held = False
        self.since = BLEND_FRAMES + 1  # frames since release (past the blend: free)
        self.frames = BLEND_FRAMES  # length of the current blend
        self.cooldown = 0  # frames before a reach-released lock may start again
        self.spans: list[tuple[int, int]] = []

    @property
    def weight(self) -> float:
        return 1.0 if self.held else _blend(self.since, self.frames)

    def release(self, t: int, frames: int = BLEND_FRAMES, cooldown: int = 0) -> None:
        """Let go at frame t (a blend of ``frames`` starts); ``cooldown`` frames pass before it may lock again."""
        self.cooldown = max(self.cooldown, cooldown)
        if self.held:
            self.held, self.since, self.frames = False, 1, frames
            first = self.spans.pop()[0]
            if first <= t - 1:
                self.spans.append((first, t - 1))

    def step(self, t: int, contact: bool, position: np.ndarray) -> None:
        """Advance to frame t (``position``: the original joint's): end a finished contact, count blend frames."""
        if self.held and not contact:
            self.release(t, catch_up_frames(np.linalg.norm((self.anchor - position)[[0, 2]])))
        elif not self.held:
            self.since += 1 if t else 0
            self.cooldown = max(self.cooldown - 1, 0)

    def start(self, t: int, position: np.ndarray, floor: float | None) -> None:
        self.anchor = position.copy()
        if floor is not None:
            self.anchor[1] = max(self.anchor[1], floor)
        self.held, self.since = True, 0
        self.spans.append((t, t))


def _targets(A, F, v, la: _Lock, lf: _Lock) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Desired ankle and toe of one frame from the locks (module docstring), with the locks' weights."""
    wa, wf = la.weight, lf.weight
    toe = F + wf * (lf.anchor - F)
    ankle = A + wa * (la.anchor - A) + (1.0 - wa) * (toe - F)
    on_sphere = toe + np.linalg.norm(v) * _unit(ankle - toe)  # the ankle a foot length from the toe
    return ankle + wf * (on_sphere - ankle), toe, wa, wf


def _place(H, A, A_des, reach) -> np.ndarray:
    """The ankle: ``A_des``, or where the segment from it to the original ankle ``A`` enters the leg's reach."""
    d, e = A_des - H, A - A_des
    if d @ d <= reach * reach:
        return A_des
    a, b, c = e @ e, 2.0 * (d @ e), d @ d - reach * reach  # |d + s e| = reach, the smallest s in [0, 1]
    s = (-b - np.sqrt(max(b * b - 4.0 * a * c, 0.0))) / (2.0 * a) if a > 1e-18 else 1.0
    return A_des + min(max(s, 0.0), 1.0) * e


def _toe(A_new, toe, v, wf) -> np.ndarray:
    n = np.linalg.norm(v)
    return A_new + n * _unit((1.0 - wf) * v / max(n, 1e-12) + wf * _unit(toe - A_new))


def _not_below(A, toe, lowest: float) -> np.ndarray:
    """``toe`` turned about the ankle ``A`` (the foot keeps its length) so it is not below ``lowest``."""
    if toe[1] >= lowest:
        return toe
    d = toe - A
    n = np.linalg.norm(d)
    dy = min(max(lowest - A[1], -n), n)
    h = d[[0, 2]]
    h = h / max(np.linalg.norm(h), 1e-12) * np.sqrt(max(n * n - dy * dy, 0.0))
    return A + np.array([h[0], dy, h[1]])


def _scan_side(j: np.ndarray, side: tuple[int, int, int, int], contacts: np.ndarray, floor: float | None):
    """Ankle and toe positions (T,3) of one leg, lock weights (T,) and the two locks (with their held spans)."""
    hip, knee, ankle, foot = side
    H, A, F = (j[:, k].astype(np.float64) for k in (hip, ankle, foot))
    thigh = np.linalg.norm(H - j[:, knee], axis=-1)
    reach = np.maximum(REACH * (thigh + np.linalg.norm(A - j[:, knee], axis=-1)), np.linalg.norm(A - H, axis=-1))
    locks = (_Lock(), _Lock())
    A_out, F_out, weight = A.copy(), F.copy(), np.zeros(len(j))

    def place(t: int):
        A_des, toe, wa, wf = _targets(A[t], F[t], F[t] - A[t], *locks)
        a_new = _place(H[t], A[t], A_des, reach[t]).copy()
        if floor is not None:  # never lower than the floor, or than the original where it already was below
            a_new[1] = max(a_new[1], min(floor, A[t, 1]))
        f_new = _toe(a_new, toe, F[t] - A[t], wf)
        if floor is not None:
            f_new = _not_below(a_new, f_new, min(floor, F[t, 1]))
        return A_des, a_new, f_new, max(wa, wf)

    for t in range(len(j)):
        for lock, c, X in zip(locks, contacts[t], (A, F)):
            lock.step(t, bool(c), X[t])
        A_des, a_new, f_new, w = place(t)
        starting = [not lk.held and bool(c) and lk.cooldown == 0 for lk, c in zip(locks, contacts[t])]
        if any(starting):  # anchor where the fixed motion is now, so nothing jumps
            for lock, go, pos in zip(locks, starting, (a_new, f_new)):
                if go:
                    lock.start(t, pos, floor)
            A_des, a_new, f_new, w = place(t)
        held = [lk for lk in locks if lk.held]
        offset = max([np.linalg.norm((lk.anchor - X[t])[[0, 2]]) for lk, X in zip(locks, (A, F)) if lk.held] or [0])
        if held and (np.linalg.norm(A_des - H[t]) > reach[t] or offset > MAX_OFFSET):
            n = catch_up_frames(offset)  # out of the leg's reach, or too far from the motion: let go, blend back
            for lock in locks:
                lock.release(t, n, cooldown=n)
            A_des, a_new, f_new, w = place(t)
        A_out[t], F_out[t], weight[t] = a_new, f_new, w
    for lock in locks:
        if lock.held:
            lock.spans[-1] = (lock.spans[-1][0], len(j) - 1)
    return A_out, F_out, weight, locks


def _knees(j: np.ndarray, side: tuple[int, int, int, int], A_new: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Knee positions (T,3) for the new ankles: thigh and shin lengths of each frame, the original bend plane."""
    hip, knee, ankle, _ = side
    H, K, A = (j[:, k].astype(np.float64) for k in (hip, knee, ankle))
    l1, l2 = np.linalg.norm(K - H, axis=-1), np.linalg.norm(A - K, axis=-1)
    axis0 = _unit(A - H)
    bend = (K - H) - np.einsum("ti,ti->t", K - H, axis0)[:, None] * axis0  # hip-ankle line -> knee, original
    forward = _unit(forward_from_across(facing_across(j.astype(np.float64), FACE_JOINTS)))
    straight = np.clip(1.0 - np.linalg.norm(bend, axis=-1) / _STRAIGHT, 0.0, 1.0)
    pole = bend + (KNEE_PULL * weight * straight)[:, None] * forward
    d_vec = A_new - H
    d = np.clip(np.linalg.norm(d_vec, axis=-1), np.abs(l1 - l2) + 1e-9, l1 + l2)
    u = _unit(d_vec)
    pole = pole - np.einsum("ti,ti->t", pole, u)[:, None] * u
    pole = np.where(np.linalg.norm(pole, axis=-1, keepdims=True) > 1e-9, pole, forward)
    a = (l1**2 - l2**2 + d**2) / (2.0 * d)
    h = np.sqrt(np.maximum(l1**2 - a**2, 0.0))
    return H + a[:, None] * u + h[:, None] * _unit(pole)


def _solve(joints: np.ndarray, contacts: np.ndarray, floor: float | None):
    j = _check(joints)
    c = np.asarray(contacts)
    c = c if c.dtype == bool else c > 0.5
    if c.shape != (len(j), 4):
        raise ValueError(f"contacts must be (T, 4) for {len(j)} frames, got shape {c.shape}")
    c = ground_contacts(j, c)
    out, spans = j.copy(), []
    for s, side in enumerate(SIDES):
        A_new, F_new, weight, locks = _scan_side(j, side, c[:, 2 * s: 2 * s + 2], floor)
        K_new = _knees(j, side, A_new, weight)
        moved = weight > 0
        for k, new in zip(side[1:], (K_new, A_new, F_new)):
            out[moved, k] = new[moved]
        spans += [lk.spans for lk in locks]
    return out, spans


def fix_feet(joints: np.ndarray, contacts: np.ndarray, *, floor: float | None = 0.0) -> np.ndarray:
    """Joints (T,22,3) with each foot held on its anchor while in contact (module docstring), same dtype.

    ``contacts`` (T,4) per frame, bool or in [0, 1] (over 0.5 is contact), for joints 7, 10, 8, 11.
    ``floor``: anchors below this height are lifted onto it (None: left where they are). Raises ValueError.
    """
    return _solve(joints, contacts, floor)[0]


def held_spans(joints: np.ndarray, contacts: np.ndarray, *, floor: float | None = 0.0) -> list[list[tuple[int, int]]]:
    """For joints 7, 10, 8, 11: the (first, last) frames of each span that :func:`fix_feet` holds on an anchor."""
    return _solve(joints, contacts, floor)[1]
