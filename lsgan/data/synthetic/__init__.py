"""Procedural, labelled motions on the HumanML3D 22-joint target skeleton: the project's built-in data.

The clips are synthetic (no motion capture): each is built from a few randomised parameters so that the
demo and the fast tests can train and evaluate without any download. Families (action labels):

- ``walk``, ``run``: forward, backward, sideways to the left or right; slow, normal or fast.
- ``turn-left``, ``turn-right``: stepping round in place (45-190 degrees) or walking in a curve (60-120).
- ``jump``: in place or forward, one to three times.
- ``wave-left-hand``, ``wave-right-hand``: the forearm swings side to side above the shoulder.
- ``raise-left-hand``, ``raise-right-hand``, ``raise-both-hands``: arms above the head, then down.
- ``squat``: one to three squats, arms forward for balance.
- ``kick-left``, ``kick-right``: front kicks, low or high.

How a clip is built: the feet are planned first (footholds on the floor, swing arcs between them, heel
lift before toe-off), the pelvis height is fitted so that every planted foot stays within reach, the
legs are solved with analytic two-bone IK and everything else is placed by bone directions. Every bone
is its BONE_LENGTHS entry long (forward kinematics of the target offsets), planted feet do not slide, and
the lowest joint of a clip touches y = 0. "Left" and "right" are the character's own sides (+x is its
left at rest, facing +z). Each clip gets three templated captions that name the same direction, side,
speed and repetitions as the motion. The output is joint positions only (rotations come from the
feature pipeline's IK) and is a pure function of (family, RNG state).

This package holds the public API (the families and how clips are drawn); beside it, one module per family or
family group (``gait``: walk and run, ``turn``, ``jump``, ``arms``: waves and raises, ``squat``, ``kick``), and what
they share: ``rig`` (proportions and assembly), ``feet`` (footholds and pelvis height), ``stand`` (the standing
start), ``timing`` (keyframe curves, clip lengths, repetitions) and ``captions`` (the caption templates).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Callable, Sequence

import numpy as np

from lsgan.data.synthetic.arms import _raise, _wave
from lsgan.data.synthetic.captions import Predicates, _captions
from lsgan.data.synthetic.gait import _walk_or_run
from lsgan.data.synthetic.jump import _jump
from lsgan.data.synthetic.kick import _kick
from lsgan.data.synthetic.rig import _Pose, _assemble, _finish
from lsgan.data.synthetic.squat import _squat
from lsgan.data.synthetic.turn import _turn

FAMILIES: tuple[str, ...] = (
    "walk", "run", "turn-left", "turn-right", "jump", "wave-left-hand", "wave-right-hand",
    "raise-left-hand", "raise-right-hand", "raise-both-hands", "squat", "kick-left", "kick-right",
)


@dataclass(frozen=True)
class SyntheticClip:
    """One generated clip: joints (T,22,3) float32 metres at 20 fps, three captions, the family label."""

    name: str
    joints: np.ndarray
    captions: list[str]
    action: str


_BUILDERS: dict[str, Callable[[np.random.Generator], tuple[_Pose, Predicates]]] = {
    "walk": partial(_walk_or_run, kind="walk"),
    "run": partial(_walk_or_run, kind="run"),
    "turn-left": partial(_turn, k=0),
    "turn-right": partial(_turn, k=1),
    "jump": _jump,
    "wave-left-hand": partial(_wave, k=0),
    "wave-right-hand": partial(_wave, k=1),
    "raise-left-hand": partial(_raise, sides=(0,)),
    "raise-right-hand": partial(_raise, sides=(1,)),
    "raise-both-hands": partial(_raise, sides=(0, 1)),
    "squat": _squat,
    "kick-left": partial(_kick, k=0),
    "kick-right": partial(_kick, k=1),
}


# ------------------------------------------------------------------------------------------ public API

def _check_families(families: Sequence[str] | None) -> tuple[str, ...]:
    fams = FAMILIES if families is None else tuple(families)
    unknown = [f for f in fams if f not in _BUILDERS]
    if unknown or not fams:
        raise ValueError(f"unknown or no synthetic families {unknown}; known: {', '.join(FAMILIES)}")
    return fams


def generate_clip(family: str, rng: np.random.Generator) -> tuple[np.ndarray, list[str], str]:
    """One clip of ``family``: joints (T,22,3) float32 (2-8 s at 20 fps), three captions, the action label."""
    (family,) = _check_families([family])
    pose, predicates = _BUILDERS[family](rng)
    joints = _finish(_assemble(pose))
    return joints, _captions(rng, predicates), family


def clip_family(index: int, families: Sequence[str] | None = None) -> str:
    """The family of clip ``index``: round-robin over ``families`` (all by default), so families are balanced."""
    fams = _check_families(families)
    return fams[index % len(fams)]


def synthetic_clip(index: int, seed: int = 0, families: Sequence[str] | None = None) -> SyntheticClip:
    """Clip ``index`` of the set defined by (seed, families); its RNG depends only on (seed, index)."""
    if index < 0 or seed < 0:
        raise ValueError(f"index and seed must be non-negative, got {index}, {seed}")
    family = clip_family(index, families)
    joints, captions, action = generate_clip(family, np.random.default_rng([seed, index]))
    return SyntheticClip(f"synth_{index:06d}", joints, captions, action)


def generate(num_clips: int, seed: int = 0, families: Sequence[str] | None = None) -> list[SyntheticClip]:
    """``num_clips`` clips, clip i being ``synthetic_clip(i, seed, families)``; the same seed gives the same data."""
    return [synthetic_clip(i, seed, families) for i in range(num_clips)]
