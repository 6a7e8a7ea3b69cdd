"""Clean feet: plant each foot while it is in contact and step it on, by IK on the leg only (``export --fix-feet``).

Pure numpy on joint positions (T,22,3): HumanML3D joint order, Y up, metres, the floor at y = 0 (as
:mod:`lsgan.motion.quality` reads it). Contacts are (T,4) per frame for [left ankle 7, left foot 10, right
ankle 8, right foot 11], the order of HumanML3D's feature channels 259-262.

Contacts. A feature row t says whether the joint moved less than sqrt(0.002) = 4.5 cm between frames t and
t+1 (:func:`lsgan.data.features.foot_contacts`), so frames t and t+1 are both in contact
(:func:`frame_contacts`). :func:`contacts_from_features` reads a generated motion's own channels (> 0.5);
:func:`estimate_contacts` applies the same rule to the joints themselves. A side is in stance on a frame where
its ankle or toe channel says contact, that joint is within ``CONTACT_HEIGHT`` (5 cm, GMD's rule) of its lowest
height in the clip (a foot held still in the air is no contact) and the toe moves less than ``STANCE_SPEED``
or, in a run or sprint, less than ``STANCE_RATIO`` times the root (a foot gliding along with the body is in
contact, one swinging past it is not); gaps of up to ``GAP_FRAMES`` frames are bridged. Where the root moves
faster than ``GLIDE_SPEED`` (the channels' own contact speed), a foot within ``CONTACT_HEIGHT`` of its lowest
height that keeps pace with the body is in stance even unmarked: the channels' speed rule cannot mark a foot a
fast body carries along, and generated sprints come with none marked.

Plants and steps (per side, planned over the whole clip). A stance run whose toe stays within ``STILL_TOE`` of
where it rests (on the frames it is on the floor) is planted already and left as it is, and so is one whose toe
never skates by GMD's rule (:func:`lsgan.motion.quality.skating_pairs`: under 5 cm and faster than 2.5 cm a frame):
feet the field counts as clean stay clean, a glide slower than that included (steps under 5 cm would count as
skating, and steps higher than that to carry a slow glide would look like marching). Any other starts with a
plant where the toe comes down and to rest within ``ENTRY_FRAMES`` (the foot eases onto it), lifted onto the
floor. A plant holds the toe on its anchor and the ankle on its anchor at the frame's foot length; the heel turns
up about the toe (push-off) as far as the original's does where its ankle is off the ground, and as far as the leg
needs to stay within ``REACH`` of its stretched length. A generated body often glides on while its feet are marked
in contact; when the plant cannot hold any longer (the leg needs the heel up more than ``MAX_HEEL``, or the toe is
``MAX_OFFSET`` from the original's), the foot steps: it lands :func:`swing_frames` later (more where the toe would
move faster than its limit, below) on a new anchor, the original foot's place on the floor up to ``LEAD_FRAMES``
ahead, chosen so that the next plant holds longest, counting twice the frames the original toe is within ``NEAR``
of it. The right foot is planned after the left and ends each plant, where it can, so that its step does not
overlap the left foot's (a walk, not a hop). A plant also lets go where the original toe rises ``LIFT_OFF`` above
its anchor; at the end of a stance run the foot's offset from the original eases out, no faster than ``CATCH_UP``
beyond the original's own speed. Moves follow a minimum-jerk path (quintic, at rest at both ends; the ankle
carries its push-off speed and eases it out) and lift toe and ankle by ``TOE_LIFT`` times their horizontal length
at mid-swing, on a bump at rest at both ends. The figures are Bandai walks': their toe rises 8.5% of the step's
length, and moves for 6.3 + 3.3 d frame pairs on a step of d metres (5.3 + 3.3 d frames in the air).

No pops. No ankle or toe moves further in a frame than the fastest move of that foot's ankle or toe in the
original plus ``MAX_EXTRA`` (1.5 cm; the promise, tested over random walks, runs and sprints, is 2 cm): where the
plan would, the foot follows it at that speed (the ankle held within the leg's reach and above the floor, the toe
at the frame's foot length) until it catches up, and those frames hold nothing.

The knee is solved by two-bone IK: the hip stays, thigh and shin keep their lengths of that frame, the knee stays
in the plane of the original bend (a 1 cm forward pull decides a straight leg's bend). Only knees, ankles and foot
joints change (4, 5, 7, 8, 10, 11), and only on frames of a plant, step or catch-up; every other value is returned
bit for bit. No ankle or toe is put below the floor, or below where it already was. The result depends only on the
input (no randomness).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lsgan.data.features import FOOT_CONTACT, foot_contacts
from lsgan.data.kinematics import facing_across, forward_from_across
from lsgan.data.skeleton import FACE_JOINTS, NUM_JOINTS
from lsgan.motion.quality import skating_pairs

CHANNEL_JOINTS = (7, 10, 8, 11)  # the contact channels' joints: left ankle, left foot, right ankle, right foot
SIDES = ((1, 4, 7, 10), (2, 5, 8, 11))  # hip, knee, ankle, foot joint of the left and right leg
LEG_JOINTS = (4, 5, 7, 8, 10, 11)  # the joints fix_feet may move
CONTACT_HEIGHT = 0.05  # m above the joint's lowest height in the clip: higher is not a ground contact
STANCE_SPEED = 0.1  # m/frame: a toe moving faster is swinging, whatever its channel says (the rule is 4.5 cm)
STANCE_RATIO = 1.5  # ... unless it moves less than this times the root: a gliding foot keeps pace with the body
GLIDE_SPEED = 0.045  # m/frame: a root faster than the channels' contact speed; a low toe keeping pace is in stance
GAP_FRAMES = 2  # stance gaps this short are bridged
ENTRY_FRAMES, ENTRY_WAIT = 4, 0.005  # a run's first plant: where the toe rests this soon (waiting: m a frame)
REACH = 0.99  # share of the stretched leg a planted leg may use (Bandai walks in stance: 0.98-1.0 at most)
MAX_HEEL = np.radians(40.0)  # the most a planted heel turns up about the toe (Bandai push-offs: 40-55 degrees)
MAX_OFFSET = 0.3  # m: a plant holds while its toe stays within this horizontal distance of the original toe
LEAD_FRAMES = 12  # a step's landing is the original foot's place up to this many frames after it lands
SWING_FRAMES = (5, 11)  # the fewest and most frames a step is in the air
SWING_BASE, SWING_PER_M = 5.3, 3.3  # a step of d metres is in the air SWING_BASE + SWING_PER_M * d frames
LIFT_OFF = 0.015  # m: a plant lets go where the original toe rises this far above its anchor
CATCH_UP = 0.05  # m/frame: the most a foot moves faster than the original while rejoining it
EASE_FRAMES = 11  # the most frames a foot takes to rejoin the original
TOE_LIFT = 0.085  # lift of toe and ankle at mid-swing, as a share of the step's horizontal length
STILL_TOE = 0.003  # m: a stance run whose toe stays this close to where it rests is planted already ...
STILL_LOW = 0.02  # m: ... counting the frames where the toe is this close to its lowest height in the clip
NEAR = 0.02  # m: a landing scores the frames its plant holds, twice those where the original toe is this near
MAX_EXTRA = 0.015  # m/frame: the most a fixed ankle or toe moves in a frame beyond the original's largest move
PEAK = 2.0  # a move's fastest frame over its mean (minimum jerk: 1.875; the lift adds a little)
KNEE_PULL = 0.01  # m: forward pull that decides which way a straight leg bends
_STRAIGHT = 0.02  # m: a knee closer than this to the hip-ankle line counts as (nearly) straight
_UP = np.array([0.0, 1.0, 0.0])


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


def stance_frames(joints: np.ndarray, contacts: np.ndarray) -> np.ndarray:
    """Per-side stance (T,2) for the left and right foot (module docstring): what :func:`fix_feet` plants."""
    j = _check(joints)
    g = ground_contacts(j, contacts)
    step = np.linalg.norm(np.diff(j[:, [10, 11]][..., [0, 2]].astype(np.float64), axis=0), axis=-1)
    root = np.linalg.norm(np.diff(j[:, 0, [0, 2]].astype(np.float64), axis=0), axis=-1)
    fast = step >= np.maximum(STANCE_SPEED, STANCE_RATIO * root)[:, None]
    slow = np.ones((len(j), 2), dtype=bool)
    slow[1:] &= ~fast
    slow[:-1] &= ~fast
    marked = g[:, [0, 2]] | g[:, [1, 3]]
    y = j[:, [10, 11], 1].astype(np.float64)
    body = np.zeros(len(j), dtype=bool)
    body[1:] |= root > GLIDE_SPEED
    body[:-1] |= root > GLIDE_SPEED
    gliding = body[:, None] & (y - y.min(axis=0) < CONTACT_HEIGHT)  # the channels' speed rule cannot mark these
    stance = (marked | gliding) & slow
    for s in range(2):
        edges = np.flatnonzero(np.diff(np.r_[0, stance[:, s].astype(np.int8), 0]))
        for end, start in zip(edges[1:-1:2], edges[2::2]):  # a gap [end, start) between two runs
            if start - end <= GAP_FRAMES:
                stance[end:start, s] = True
    return stance


def _check(joints: np.ndarray) -> np.ndarray:
    j = np.asarray(joints)
    if j.ndim != 3 or j.shape[1:] != (NUM_JOINTS, 3) or len(j) < 2:
        raise ValueError(f"joints must be (T, {NUM_JOINTS}, 3) with T >= 2, got shape {j.shape}")
    if not np.isfinite(j).all():
        raise ValueError("joints hold NaN or infinite values")
    return j


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _flat(v: np.ndarray) -> np.ndarray:
    """Horizontal length of (...,3) vectors."""
    return np.linalg.norm(v[..., [0, 2]], axis=-1)


def swing_frames(distance: float) -> int:
    """Frames a step of ``distance`` metres spends in the air (Bandai walks' swing phases, SWING_FRAMES bounds)."""
    return int(np.clip(round(SWING_BASE + SWING_PER_M * distance), *SWING_FRAMES))


class _Leg:
    """One leg's original joints (float64) and lengths, and the geometry of a planted foot."""

    def __init__(self, j: np.ndarray, side: tuple[int, int, int, int], heel_up: np.ndarray, floor: float | None,
                 skates: np.ndarray):
        self.H, self.K, self.A, self.F = (j[:, k].astype(np.float64) for k in side)
        self.foot = np.linalg.norm(self.F - self.A, axis=-1)
        self.pitch = np.arcsin(np.clip((self.A - self.F)[:, 1] / np.maximum(self.foot, 1e-12), -1.0, 1.0))
        self.heel_up = heel_up  # (T,) frames whose ankle is off the ground: a plant follows the original's heel
        self.skates = skates  # (T-1,) frame pairs where the toe skates by GMD's rule (lsgan.motion.quality)
        legs = np.linalg.norm(self.K - self.H, axis=-1) + np.linalg.norm(self.A - self.K, axis=-1)
        self.reach = np.maximum(REACH * legs, np.linalg.norm(self.A - self.H, axis=-1))
        self.floor = floor
        fastest = max(np.linalg.norm(np.diff(x, axis=0), axis=-1).max() for x in (self.A, self.F))
        self.limit = float(fastest + MAX_EXTRA)  # m/frame: the most the fixed ankle or toe moves in a frame

    def still(self, first: int, last: int) -> bool:
        """Whether the original toe stays within STILL_TOE of where it is at ``first`` on the frames ``first..last``
        where it is on the floor (within STILL_LOW of its lowest): a foot planted already."""
        toe = self.F[first: last + 1]
        low = toe[:, 1] - self.F[:, 1].min() < STILL_LOW
        return bool((_flat(toe - self.F[first])[low] < STILL_TOE).all())

    def clean(self, first: int, last: int) -> bool:
        """Whether the toe skates by GMD's rule on no frame pair from ``first - 1`` to ``last``: a foot the field
        counts as clean (a glide slower than 0.5 m/s included), whose stance is left as it is."""
        return not self.skates[max(first - 1, 0): last + 1].any()

    def swing(self, distance: float) -> int:
        """Frames in the air of a step of ``distance`` m: Bandai's (:func:`swing_frames`), or more where the toe
        would otherwise move faster than its limit."""
        return max(swing_frames(distance), int(np.ceil(PEAK * distance / self.limit)) - 1)

    def anchor(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Ankle and toe of the original at ``frame``, lifted onto the floor: where a plant holds the foot."""
        a, t = self.A[frame].copy(), self.F[frame].copy()
        if self.floor is not None:
            a[1], t[1] = max(a[1], self.floor), max(t[1], self.floor)
        return a, t

    def heel(self, frames: np.ndarray, ankle: np.ndarray, toe: np.ndarray):
        """Ankles (N,3) of the foot planted on (ankle, toe) over ``frames`` (anchors (3,) or (N,3)), the angle (N,)
        the leg's reach needs the heel turned up (inf: no angle will do), and the angle it is turned.

        The ankle sits on the anchor's direction from the toe at the frame's foot length, turned up about the toe
        (in the foot's vertical plane) by the smallest angle that brings it within the leg's reach, or by as much
        as the original's heel is up where its ankle is off the ground, whichever is more.
        """
        n, r, g = self.foot[frames], self.reach[frames], toe - self.H[frames]
        e1 = _unit(ankle - toe)
        e2 = _unit(_UP - e1[..., 1:2] * e1)
        b, c = np.sum(g * e1, axis=-1), np.sum(g * e2, axis=-1)
        k = (r * r - np.sum(g * g, axis=-1) - n * n) / (2.0 * np.maximum(n, 1e-12))
        ratio = k / np.maximum(np.hypot(b, c), 1e-12)  # |ankle - hip| <= r  <=>  b cos + c sin <= k
        turn = np.mod(np.arctan2(c, b) + np.arccos(np.clip(ratio, -1.0, 1.0)), 2.0 * np.pi)
        need = np.where(b <= k, 0.0, np.where(ratio < -1.0, np.inf, turn))
        own = np.where(self.heel_up[frames], np.maximum(self.pitch[frames] - np.arcsin(e1[..., 1]), 0.0), 0.0)
        a = np.minimum(np.maximum(need, own), np.pi)
        return toe + n[:, None] * (np.cos(a)[:, None] * e1 + np.sin(a)[:, None] * e2), need, a

    def plant_ends(self, firsts: np.ndarray, stop: int, ankles: np.ndarray, toes: np.ndarray) -> np.ndarray:
        """For plants from ``firsts`` (P,) on anchors (P,3): the last frame each holds, at most ``stop`` (first - 1:
        none). A plant holds while the leg needs the heel up at most MAX_HEEL, its toe is within MAX_OFFSET of the
        original toe, and the original toe has not risen LIFT_OFF above it."""
        firsts = np.asarray(firsts)
        counts = stop - firsts + 1
        rows = np.repeat(np.arange(len(firsts)), counts)
        frames = np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts) + firsts[rows]
        _, need, _ = self.heel(frames, ankles[rows], toes[rows])
        bad = (need > MAX_HEEL) | (_flat(self.F[frames] - toes[rows]) > MAX_OFFSET)
        bad |= self.F[frames, 1] - toes[rows, 1] > LIFT_OFF
        return np.minimum.reduceat(np.where(bad, frames, stop + 1), np.cumsum(counts) - counts) - 1


@dataclass
class _Move:
    """A move of one foot on frames first..first+frames-1 (cut at the clip's end): from ``ankle`` and ``toe`` (where
    it was the frame before; None: from the original motion) onto ``target`` (anchors; None: the original)."""

    first: int
    frames: int
    ankle: np.ndarray | None
    toe: np.ndarray | None
    target: tuple[np.ndarray, np.ndarray] | None
    distance: float  # m: sets the lift
    velocity: np.ndarray  # the ankle's at push-off (a rising heel), m/frame; relative to the original's onto it


def _landing(leg: _Leg, end: int, stop: int, anchor: tuple[np.ndarray, np.ndarray]):
    """The step from a plant on ``anchor`` held to frame ``end``: (landing frame, new anchors, distance) onto the
    floor whose next plant holds longest within the stance run ending at ``stop``, counting twice the frames the
    original toe is within NEAR of it (the shortest such step), or None."""
    steps = []
    for lead in range(LEAD_FRAMES + 1):
        frames = SWING_FRAMES[0]
        for _ in range(2):  # the step's length sets its duration, which moves the landing
            new = leg.anchor(min(end + frames + 1 + lead, stop))
            frames = leg.swing(float(_flat(new[1] - anchor[1])))
        on = min(end + frames + 1 + lead, stop)
        if end + frames + 1 <= stop and leg.F[on, 1] - leg.F[:, 1].min() <= LIFT_OFF:  # not mid-air
            new = leg.anchor(on)
            steps.append((end + frames + 1, new, float(_flat(new[1] - anchor[1]))))
    if not steps:
        return None
    lands, toes = np.array([s[0] for s in steps]), np.array([s[1][1] for s in steps])
    ends = leg.plant_ends(lands, stop, np.array([s[1][0] for s in steps]), toes)
    if (ends < lands).all():
        return None
    near = [int((_flat(leg.F[a: b + 1] - toe) < NEAR).sum()) for a, b, toe in zip(lands, ends, toes)]
    return steps[int(np.argmax(np.where(ends < lands, -np.inf, ends - lands + 2.0 * np.array(near))))]


def _step(leg: _Leg, first: int, last: int, stop: int, anchor, busy: np.ndarray):
    """How a plant from ``first`` that cannot hold past ``last`` (< ``stop``, its run's end) steps on: (last frame
    held, landing frame, new anchors, distance), or None. Of the ends it may take, the one whose step overlaps the
    other foot's steps (``busy``) least, the latest of those."""
    step = _landing(leg, last, stop, anchor)
    if step is None or not busy.any():
        return None if step is None else (last, *step)
    frames = step[0] - last - 1
    overlap = [int(busy[end + 1: end + frames + 1].sum()) for end in range(last, first - 1, -1)]
    end = last - int(np.argmin(overlap))
    early = _landing(leg, end, stop, anchor) if end != last else None
    return (end, *early) if early is not None else (last, *step)


def _plan(leg: _Leg, stance: np.ndarray, busy: np.ndarray) -> tuple[list, list[_Move]]:
    """One foot's plants (first, last, ankle anchor, toe anchor) and steps over its stance frames (module
    docstring); ``busy``: frames where the other foot is in the air."""
    T = len(stance)
    plants: list = []
    moves: list[_Move] = []
    starts = np.flatnonzero(np.diff(np.r_[0, stance.astype(np.int8)]) == 1)
    run_end = np.zeros(T, dtype=int)
    for s in starts:
        e = s + int(np.argmin(stance[s:])) - 1 if not stance[s:].all() else T - 1
        run_end[s: e + 1] = e

    def next_stance(t: int) -> int | None:
        later = np.flatnonzero(stance[t:]) if t < T else []
        return t + int(later[0]) if len(later) else None

    def enter(t: int | None):
        """A run's first plant from the original motion at t: where the toe rests within ENTRY_FRAMES (the least
        height above the lowest there plus speed, in metres, plus ENTRY_WAIT a frame); the foot eases onto it."""
        if t is None:
            return None, None, None
        frames = np.arange(t, min(t + ENTRY_FRAMES, run_end[t]) + 1)
        speed = np.linalg.norm(leg.F[np.minimum(frames + 1, T - 1)] - leg.F[frames], axis=-1)
        score = leg.F[frames, 1] - leg.F[frames, 1].min() + speed + ENTRY_WAIT * (frames - t)
        rest = int(frames[np.argmin(score)])
        anchor = leg.anchor(rest)
        return rest, anchor, _Move(t, rest - t, None, None, anchor, 0.0, np.zeros(3)) if rest > t else None

    t, anchor, entry = enter(next_stance(0))
    while t is not None:
        stop = run_end[t]
        if leg.still(t, stop) or leg.clean(t, stop):  # planted already, or clean by the field's rule: as it is
            t, anchor, entry = enter(next_stance(stop + 1))
            continue
        last = int(leg.plant_ends(np.array([t]), stop, anchor[0][None], anchor[1][None])[0])
        if last < t:  # the leg cannot hold the foot here
            t, anchor, entry = enter(next_stance(t + 1))
            continue
        moves += [entry] if entry else []
        step = _step(leg, t, last, stop, anchor, busy) if last < stop else None
        end = step[0] if step else last
        plants.append((t, end, *anchor))
        heel = leg.heel(np.arange(max(end - 1, t), end + 1), *anchor)[0]
        start = heel[-1], anchor[1], heel[-1] - heel[0]
        if step:
            moves.append(_Move(end + 1, step[1] - end - 1, *start[:2], step[2], step[3], start[2]))
            t, anchor, entry = step[1], step[2], None
        elif end + 1 < T:  # the run is over: ease the foot's offset from the original out, with a step's lift
            distance = float(_flat(anchor[1] - leg.F[end]))
            offset = max(np.linalg.norm(start[0] - leg.A[end]), np.linalg.norm(anchor[1] - leg.F[end]))
            own = leg.A[end] - leg.A[max(end - 1, t)]  # the original's own speed goes on in the move
            rate = max(min(CATCH_UP, leg.limit - np.linalg.norm(own)), 0.01)
            frames = int(np.clip(np.ceil(PEAK * offset / rate), 2, EASE_FRAMES))
            moves.append(_Move(end + 1, frames, *start[:2], None, distance, start[2] - own))
            t, anchor, entry = enter(next_stance(end + frames + 1))
        else:
            t = None
    return plants, moves


def _place(H, A, A_des, reach) -> np.ndarray:
    """Ankles (N,3): ``A_des``, or where the segment from it to the original ankle ``A`` enters the leg's reach."""
    d, e = A_des - H, A - A_des
    dd = np.einsum("ij,ij->i", d, d)
    a, b, c = np.einsum("ij,ij->i", e, e), 2.0 * np.einsum("ij,ij->i", d, e), dd - reach * reach
    s = (-b - np.sqrt(np.maximum(b * b - 4.0 * a * c, 0.0))) / (2.0 * np.maximum(a, 1e-18))
    s = np.where(a > 1e-18, np.clip(s, 0.0, 1.0), 1.0)
    return np.where((dd <= reach * reach)[:, None], A_des, A_des + s[:, None] * e)


def _not_below(A, toe, lowest) -> np.ndarray:
    """Toes (N,3) turned about the ankles ``A`` (the foot keeps its length) so that none is below ``lowest``."""
    d = toe - A
    n = np.linalg.norm(d, axis=-1)
    dy = np.clip(lowest - A[:, 1], -n, n)
    h = _unit(d[:, [0, 2]]) * np.sqrt(np.maximum(n * n - dy * dy, 0.0))[:, None]
    turned = A + np.stack([h[:, 0], dy, h[:, 1]], axis=-1)
    return np.where((toe[:, 1] >= lowest)[:, None], toe, turned)


def _render(leg: _Leg, plants: list, moves: list[_Move]):
    """Ankle and toe positions (T,3) of one leg from its plan, the frames it changes (T,), and which frames hold
    the ankle and the toe on their anchors (T,2)."""
    T = len(leg.A)
    A_out, F_out = leg.A.copy(), leg.F.copy()
    moved, held = np.zeros(T, dtype=bool), np.zeros((T, 2), dtype=bool)
    for first, last, ankle, toe in plants:
        frames = np.arange(first, last + 1)
        A_out[frames], _, theta = leg.heel(frames, ankle, toe)
        F_out[frames] = toe
        moved[frames], held[frames, 0], held[frames, 1] = True, theta == 0.0, True
    for m in moves:
        frames = np.arange(m.first, min(m.first + m.frames, T))
        x = (frames - m.first + 1) / (m.frames + 1)
        s = (x ** 3 * (10.0 - 15.0 * x + 6.0 * x * x))[:, None]  # minimum jerk: rest to rest
        bump = (64.0 * (x * (1.0 - x)) ** 3 * m.distance)[:, None] * _UP  # d at mid-swing, at rest at both ends
        if m.target is None:  # back onto the original: its offset there eases out
            (QA, QF), first = (leg.A[frames], leg.F[frames]), m.first - 1
            PA, PF = m.ankle + QA - leg.A[first], m.toe + QF - leg.F[first]
        else:  # onto anchors: from still ones, or from the original
            (QA, QF), (PA, PF) = m.target, (m.ankle, m.toe) if m.toe is not None else (leg.A[frames], leg.F[frames])
        F_des = PF + s * (QF - PF) + TOE_LIFT * bump
        carry = (m.frames + 1) * x * (1.0 - x) ** 3 * (1.0 + 3.0 * x)  # the ankle's push-off speed, eased out
        A_des = PA + s * (QA - PA) + carry[:, None] * m.velocity + TOE_LIFT * bump
        A_new = _place(leg.H[frames], leg.A[frames], A_des, leg.reach[frames])
        A_out[frames], F_out[frames] = A_new, A_new + leg.foot[frames, None] * _unit(F_des - A_new)
        moved[frames] = True
    low = (np.minimum(leg.floor, leg.A[:, 1]), np.minimum(leg.floor, leg.F[:, 1])) if leg.floor is not None else None
    if low is not None:  # never lower than the floor, or than the original where it already was below
        A_out[:, 1] = np.maximum(A_out[:, 1], low[0])
        F_out = _not_below(A_out, F_out, low[1])
    A_out, F_out, late = _follow(leg, A_out, F_out, low)
    return A_out, F_out, moved | late, held & ~late[:, None]


def _toward(a: np.ndarray, n: float, prev: np.ndarray, want: np.ndarray, limit: float, low: float) -> np.ndarray:
    """The toe at ``n`` from the ankle ``a``, not below ``low``, nearest the direction of ``want`` within ``limit`` of
    ``prev``: from the sphere's point nearest ``prev``, turned toward ``want`` as far as the limit allows (on a
    grid of 65 turns; where none is within the limit, the nearest to ``prev``)."""
    share = np.linspace(0.0, 1.0, 65)[:, None]
    way = _unit((1.0 - share) * _unit(prev - a) + share * _unit(want - a))
    toes = _not_below(np.broadcast_to(a, way.shape), a + n * way, np.full(len(way), low))
    gap = np.linalg.norm(toes - prev, axis=-1)
    ok = np.flatnonzero(gap <= limit)
    return toes[ok[-1]] if len(ok) else toes[np.argmin(gap)]


def _within(x: np.ndarray, prev: np.ndarray, limit: float, hip: np.ndarray, reach: float, low: float) -> np.ndarray:
    """A point near ``x`` within ``limit`` of ``prev``, within ``reach`` of ``hip`` and not below ``low``
    (alternating projections onto the three convex sets; the last one, reach, holds exactly)."""
    for _ in range(20):
        if np.linalg.norm(x - prev) <= limit and x[1] >= low and np.linalg.norm(x - hip) <= reach:
            return x
        x = prev + (x - prev) * min(1.0, limit / max(np.linalg.norm(x - prev), 1e-12))
        x = np.array([x[0], max(x[1], low), x[2]])
        x = hip + (x - hip) * min(1.0, reach / max(np.linalg.norm(x - hip), 1e-12))
    return x


def _follow(leg: _Leg, A: np.ndarray, F: np.ndarray, low) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ankles and toes (T,3) that follow ``A`` and ``F`` no faster than the leg's limits (no pop, whatever the plan
    asks), and the frames where they lag it. Where the plan keeps to the limits they are the plan, bit for bit."""
    A, F = A.copy(), F.copy()
    late = np.zeros(len(A), dtype=bool)
    limit = leg.limit
    floor = None if low is None else low[0]
    for t in range(1, len(A)):
        goal, prev_a, prev_f = A[t].copy(), A[t - 1], F[t - 1]
        if np.linalg.norm(goal - prev_a) <= limit and np.linalg.norm(F[t] - prev_f) <= limit:
            continue
        n, way, toe_low = leg.foot[t], _unit(F[t] - goal), -np.inf if low is None else low[1][t]

        def foot(share: float) -> tuple[np.ndarray, np.ndarray]:
            a = _within(prev_a + share * (goal - prev_a), prev_a, limit, leg.H[t], leg.reach[t],
                        -np.inf if floor is None else floor[t])
            return a, _toward(a, n, prev_f, a + n * way, limit, toe_low)

        lo, hi, (a, f) = 0.0, 1.0, foot(1.0)
        if np.linalg.norm(f - prev_f) > limit:  # no toe within the limit: the ankle moves less
            for _ in range(12):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if np.linalg.norm(foot(mid)[1] - prev_f) <= limit else (lo, mid)
            a, f = foot(lo)
        A[t], F[t], late[t] = a, f, True
    return A, F, late


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


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) of each run of True in ``mask``."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return [(int(a), int(b) - 1) for a, b in zip(edges[::2], edges[1::2])]


def _solve(joints: np.ndarray, contacts: np.ndarray, floor: float | None):
    """Fixed joints and, per planted joint (7, 10, 8, 11), the spans it holds on an anchor; the right foot is
    planned after the left, timing its steps around the left's."""
    j = _check(joints)
    c = np.asarray(contacts)
    c = c if c.dtype == bool else c > 0.5
    if c.shape != (len(j), 4):
        raise ValueError(f"contacts must be (T, 4) for {len(j)} frames, got shape {c.shape}")
    stance = stance_frames(j, c)
    out, spans, busy = j.copy(), [], np.zeros(len(j), dtype=bool)
    heel_up = ~ground_contacts(j, c)[:, [0, 2]]
    skates = skating_pairs(j) if len(j) > 1 else np.zeros((0, 2), dtype=bool)
    for s, side in enumerate(SIDES):
        leg = _Leg(j, side, heel_up[:, s], floor, skates[:, s])
        plants, moves = _plan(leg, stance[:, s], busy)
        A_new, F_new, moved, held = _render(leg, plants, moves)
        for m in moves:
            busy[m.first: m.first + m.frames] = True
        K_new = _knees(j, side, A_new, moved.astype(np.float64))
        for k, new in zip(side[1:], (K_new, A_new, F_new)):
            out[moved, k] = new[moved]
        spans += [_runs(held[:, 0]), _runs(held[:, 1])]
    return out, spans


def fix_feet(joints: np.ndarray, contacts: np.ndarray, *, floor: float | None = 0.0) -> np.ndarray:
    """Joints (T,22,3) with each foot planted while in contact and stepping on (module docstring), same dtype.

    ``contacts`` (T,4) per frame, bool or in [0, 1] (over 0.5 is contact), for joints 7, 10, 8, 11.
    ``floor``: anchors below this height are lifted onto it (None: left where they are). Raises ValueError.
    """
    return _solve(joints, contacts, floor)[0]


def held_spans(joints: np.ndarray, contacts: np.ndarray, *, floor: float | None = 0.0) -> list[list[tuple[int, int]]]:
    """For joints 7, 10, 8, 11: the (first, last) frames of each span that :func:`fix_feet` holds on an anchor."""
    return _solve(joints, contacts, floor)[1]
