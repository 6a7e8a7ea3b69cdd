"""Plausibility checks on imported clips: is this (T,22,3) array a person, upright, metre-sized, on a floor?

A wrong joint map imports without an error but yields nonsense: with the wrong ``up`` axis the figure
lies on its side or back (or stands on its head), with the wrong ``scale`` it is 150 m or 1.5 cm tall,
with a joint mapped to the wrong source joint its bones stretch from frame to frame, and with left and right
knees (or elbows) swapped they sit on the wrong sides of the body in every frame. The checks here
measure each clip in lsgan's convention (Y up, metres, 20 fps, :data:`lsgan.data.skeleton.JOINT_NAMES`),
compare the figures with human ranges held in :class:`Thresholds` and name the likely cause.

Every check is a fraction of frames or a median, never a single frame, so a performer who lies down
for a moment or does a short handstand does not trigger a warning. Only the size check is in metres;
the others are relative to the clip's own skeleton, so a wrong scale and a wrong up axis are told apart.
``docs/plausibility.md`` documents each threshold and its measured false-positive rate.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Mapping

import numpy as np

from lsgan.data.skeleton import BONE_LENGTHS, JOINT_NAMES, PARENTS, bone_lengths

PELVIS, NECK, HEAD = 0, 12, 15
FEET = (7, 8, 10, 11)  # ankles and toes
ACROSS = ((2, 1), (17, 16))  # (right, left) hips and shoulders: right - left points to the body's right
LEGS = ((4, 7), (5, 8))  # thigh and shin bones (indexed by child joint), left and right
SIDES = {"knees": ((5, 4), (2, 1)), "elbows": ((19, 18), (17, 16))}  # (right, left) pair, and the (right, left)
# pair whose line says where the body's right is: the hips for the knees, the shoulders for the elbows
TRUNK = (3, 6, 9, 12, 15)  # pelvis -> spine1 -> spine2 -> spine3 -> neck -> head
KINDS = ("scale", "up", "bones", "floor")
CAUSES = {
    "scale": "wrong `scale` (file units to metres)?",
    "up": "wrong `up` axis in the joint map or source?",
    "bones": "a joint mapped to the wrong source joint?",
    "floor": "figure floats above its floor: wrong `up` axis, or motion on stairs/ramps?",
}


@dataclass(frozen=True)
class Thresholds:
    """Every limit of the checks, in one place; why each value: docs/plausibility.md. Lengths marked ``_m``
    are metres, ``_rel`` are fractions of the clip's skeleton height, ``_fraction`` are fractions of frames."""

    min_height_m: float = 0.75  # skeleton height (ankle to head along the bones) of a ~0.9 m tall child
    max_height_m: float = 2.4  # ... of a ~2.8 m tall person, taller than anyone on record
    upright_cos: float = 0.5  # a frame is upright when the pelvis->neck direction is within 60 deg of +Y
    min_upright_fraction: float = 0.2  # lying in more than 80% of the frames: the up axis is suspect
    max_inverted_fraction: float = 0.5  # spine within 60 deg of -Y in half the frames: up axis points down
    vertical_facing_cos: float = 0.866  # the chest faces within 30 deg of straight up or down (reported only)
    max_bone_variation: float = 0.1  # std / mean of a bone's length over the frames; rigid mocap: < 0.03
    bone_floor_rel: float = 0.1  # ... the mean floored at this, so jitter on 5 cm bones does not count
    contact_height_rel: float = 0.05  # a foot joint this close to the floor (7 cm on HumanML3D's skeleton)
    floor_quantile: float = 0.05  # floor = this quantile of the per-frame lowest joint (ignores glitches)
    min_contact_fraction: float = 0.2  # a foot near the floor in fewer frames: the figure floats
    max_head_height_rel: float = 1.5  # median head height above the floor; standing: 0.93-1.07
    max_crossed_fraction: float = 0.5  # knees (elbows) on the wrong side of the hips (shoulders); real: 0


DEFAULT_THRESHOLDS = Thresholds()


def _unit(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis; zero vectors stay zero."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 1e-12)


def skeleton_height(lengths: np.ndarray) -> np.ndarray:
    """Ankle-to-head length along the bones from bone lengths (..., 22) (see ``bone_lengths``) -> (...):
    mean leg (thigh + shin) plus the trunk (pelvis to head). Pose-independent, so it measures the unit
    scale whatever the performer does."""
    b = np.asarray(lengths)
    leg = 0.5 * (b[..., LEGS[0]].sum(-1) + b[..., LEGS[1]].sum(-1))
    return leg + b[..., TRUNK].sum(-1)


HUMAN_HEIGHT_M = float(skeleton_height(BONE_LENGTHS))  # 1.4755 m: the HumanML3D target skeleton


def spine_cos(joints: np.ndarray) -> np.ndarray:
    """Cosine between the pelvis->neck direction and +Y, (..., 22, 3) -> (...): 1 upright, -1 upside down."""
    j = np.asarray(joints, dtype=np.float64)
    return _unit(j[..., NECK, :] - j[..., PELVIS, :])[..., 1]


def facing(joints: np.ndarray) -> np.ndarray:
    """The chest's forward direction, (..., 22, 3) -> (..., 3) unit: spine x (right hips + right shoulders).

    Unlike HumanML3D's facing (+Y x across, horizontal by construction) it follows the body, so it points
    straight up or down when the figure lies on its back or front, as a wrong up axis makes it.
    """
    j = np.asarray(joints, dtype=np.float64)
    across = sum(j[..., r, :] - j[..., l, :] for r, l in ACROSS)
    return _unit(np.cross(j[..., NECK, :] - j[..., PELVIS, :], across))


def bone_variation(lengths: np.ndarray, floor_rel: float = 0.1) -> tuple[float, int]:
    """(largest std over the frames of a bone's length relative to its mean length, that bone's child
    joint) from one clip's bone lengths (T,22). The mean is floored at ``floor_rel`` skeleton heights, so
    millimetre jitter on a 5 cm spine bone does not read as 10 % and zero-length bones do not divide by 0."""
    b = np.asarray(lengths, dtype=np.float64)
    mean = np.maximum(b.mean(axis=0), floor_rel * float(np.median(skeleton_height(b))))
    cv = np.divide(b.std(axis=0), mean, out=np.zeros(b.shape[-1]), where=mean > 0)
    cv[0] = 0.0
    k = int(np.argmax(cv))
    return float(cv[k]), max(k, 1)


def crossed_fraction(joints: np.ndarray, pair: str) -> float:
    """Fraction of frames whose right knee (``pair='knees'``) or elbow (``'elbows'``) lies to the body's left of
    its left twin, the body's right taken from the hips (shoulders). Real mocap: 0; that pair's left and right
    swapped in the joint map: 1. Legs crossed at the ankles do not count; knees pass each other only briefly."""
    j = np.asarray(joints, dtype=np.float64)
    (r, l), (ar, al) = SIDES[pair]
    return float(np.mean(np.einsum("...i,...i->...", j[..., r, :] - j[..., l, :], j[..., ar, :] - j[..., al, :]) < 0))


def clip_checks(joints: np.ndarray, thresholds: Thresholds = DEFAULT_THRESHOLDS) -> dict:
    """The plausibility figures of one clip, joints (T,22,3) in metres, Y up (T >= 1, finite).

    Returns floats (metres, or fractions of frames in [0, 1]) and two ints: ``frames``,
    ``skeleton_height_m`` (median), ``bone_variation`` (max relative std over bones), ``worst_bone``
    (its child joint), ``foot_height_m`` (median height of the lowest foot joint above the clip's floor),
    ``contact_fraction`` (frames with a foot within ``contact_height_rel`` skeleton heights of the floor),
    ``head_height_m`` (median head height above the floor), ``head_above_pelvis_fraction``,
    ``upright_fraction`` / ``inverted_fraction`` (spine within 60 degrees of +Y / -Y),
    ``vertical_facing_fraction`` (chest facing up or down), ``pelvis_rise_m`` (range of the pelvis height),
    ``knees_crossed_fraction`` / ``elbows_crossed_fraction`` (see :func:`crossed_fraction`).
    """
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 3 or j.shape[1:] != (len(JOINT_NAMES), 3) or len(j) == 0:
        raise ValueError(f"expected joints of shape (T, {len(JOINT_NAMES)}, 3) with T >= 1, got {j.shape}")
    lengths = bone_lengths(j)
    height = float(np.median(skeleton_height(lengths)))
    variation, worst = bone_variation(lengths, thresholds.bone_floor_rel)
    y = j[..., 1] - np.quantile(j[..., 1].min(axis=1), thresholds.floor_quantile)
    foot = y[:, FEET].min(axis=1)
    cos = spine_cos(j)
    return {
        "frames": int(len(j)),
        "skeleton_height_m": height,
        "bone_variation": variation,
        "worst_bone": worst,
        "foot_height_m": float(np.median(foot)),
        "contact_fraction": float(np.mean(foot <= thresholds.contact_height_rel * height)),
        "head_height_m": float(np.median(y[:, HEAD])),
        "head_above_pelvis_fraction": float(np.mean(y[:, HEAD] > y[:, PELVIS])),
        "upright_fraction": float(np.mean(cos > thresholds.upright_cos)),
        "inverted_fraction": float(np.mean(cos < -thresholds.upright_cos)),
        "vertical_facing_fraction": float(np.mean(np.abs(facing(j)[:, 1]) > thresholds.vertical_facing_cos)),
        "pelvis_rise_m": float(np.ptp(y[:, PELVIS])),
        "knees_crossed_fraction": crossed_fraction(j, "knees"),
        "elbows_crossed_fraction": crossed_fraction(j, "elbows"),
    }


def _pct(x: float) -> str:
    return f"{100 * x:.0f}%"


def _scale_finding(c: Mapping, t: Thresholds) -> str | None:
    h = c["skeleton_height_m"]
    if t.min_height_m <= h <= t.max_height_m:
        return None
    factor = h / HUMAN_HEIGHT_M
    return (f"figure {h:.3g} m tall ankle to head (humans {t.min_height_m}-{t.max_height_m} m), {factor:.3g}x "
            f"the HumanML3D skeleton: wrong `scale` (file units to metres: cm 0.01, mm 0.001, inch 0.0254)? "
            f"try about {1 / factor:.3g}x the scale used")


def _up_finding(c: Mapping, t: Thresholds) -> str | None:
    head_below = _pct(1.0 - c["head_above_pelvis_fraction"])
    if c["inverted_fraction"] >= t.max_inverted_fraction:
        return (f"figure upside down in {_pct(c['inverted_fraction'])} of frames (head below the pelvis in "
                f"{head_below}): the up axis points down: wrong `up` axis or sign in the joint map or source?")
    if c["upright_fraction"] >= t.min_upright_fraction:
        return None
    return (f"figure upright in only {_pct(c['upright_fraction'])} of frames (spine near horizontal, head below "
            f"the pelvis in {head_below}, chest facing up or down in {_pct(c['vertical_facing_fraction'])}): "
            f"lying figure: wrong `up` axis in the joint map or source (or a performer lying or crawling "
            f"throughout)?")


def _bones_finding(c: Mapping, t: Thresholds) -> str | None:
    for pair, joint in (("knees", "knee"), ("elbows", "elbow")):
        crossed = c.get(f"{pair}_crossed_fraction", 0.0)  # absent from the checks of older lsgan runs
        if crossed >= t.max_crossed_fraction:
            return (f"right {joint} on the body's left of the left {joint} in {_pct(crossed)} of frames: left and "
                    f"right {pair} (or their parents) swapped in the joint map?")
    if c["bone_variation"] <= t.max_bone_variation:
        return None
    k = int(c["worst_bone"])
    return (f"bone {JOINT_NAMES[PARENTS[k]]}->{JOINT_NAMES[k]} changes length by {_pct(c['bone_variation'])} "
            f"(std over frames / mean length): a joint mapped to the wrong source joint, or joints from "
            f"another skeleton or from markers?")


def _floor_finding(c: Mapping, t: Thresholds) -> str | None:
    h = max(c["skeleton_height_m"], 1e-12)
    if c["contact_fraction"] >= t.min_contact_fraction and c["head_height_m"] <= t.max_head_height_rel * h:
        return None
    return (f"a foot near the floor in only {_pct(c['contact_fraction'])} of frames, head median "
            f"{c['head_height_m']:.3g} m above the floor ({c['head_height_m'] / h:.2g}x the skeleton height), "
            f"pelvis height ranging over {c['pelvis_rise_m']:.3g} m: figure floating above its floor: wrong `up` "
            f"axis (travel along the vertical), or motion on stairs or mostly in the air?")


_FINDERS = {"scale": _scale_finding, "up": _up_finding, "bones": _bones_finding, "floor": _floor_finding}


def findings(checks: Mapping, thresholds: Thresholds = DEFAULT_THRESHOLDS) -> list[tuple[str, str]]:
    """(kind, description with the likely cause) for every limit a clip's checks break, kinds in KINDS order.

    A clip flagged ``up`` is not also flagged ``floor``: a wrong up axis is the likelier cause of both.
    """
    out: list[tuple[str, str]] = []
    for kind, finder in _FINDERS.items():
        text = finder(checks, thresholds)
        if text is not None and not (kind == "floor" and out and out[-1][0] == "up"):
            out.append((kind, text))
    return out


def clip_warnings(name: str, checks: Mapping, thresholds: Thresholds = DEFAULT_THRESHOLDS) -> list[str]:
    """One-line warnings naming the clip, the figure out of range and the likely cause (empty: plausible)."""
    return [f"{name}: {text}" for _, text in findings(checks, thresholds)]


def summarise(checks_by_clip: Mapping[str, Mapping], thresholds: Thresholds = DEFAULT_THRESHOLDS) -> dict:
    """The JSON report's section: clips checked and flagged, counts and clip names per warning kind, the
    warnings themselves, (min, median, max) of every figure over the clips, and the thresholds used."""
    flagged: dict[str, list[str]] = {k: [] for k in KINDS}
    warnings: dict[str, list[str]] = {}
    for name, checks in checks_by_clip.items():
        found = findings(checks, thresholds)
        for kind, text in found:
            flagged[kind].append(name)
        if found:
            warnings[name] = [text for _, text in found]
    keys = [k for k in next(iter(checks_by_clip.values()), {})
            if k != "worst_bone" and all(k in c for c in checks_by_clip.values())]
    ranges = {}
    for key in keys:
        v = np.array([float(c[key]) for c in checks_by_clip.values()])
        ranges[key] = {"min": float(v.min()), "median": float(np.median(v)), "max": float(v.max())}
    return {
        "clips": len(checks_by_clip),
        "flagged": len(warnings),
        "counts": {k: len(v) for k, v in flagged.items()},
        "flagged_clips": flagged,
        "warnings": warnings,
        "ranges": ranges,
        "thresholds": asdict(thresholds),
    }


def _span(ranges: Mapping, key: str, fmt) -> str:
    return f"{fmt(ranges[key]['min'])}-{fmt(ranges[key]['max'])}"


def format_summary(summary: Mapping, limit: int = 3) -> str:
    """A few terminal lines: clips flagged, per kind the count, the cause and the first ``limit`` clip names,
    and the ranges of the main figures over the clips."""
    lines = [f"plausibility: {summary['clips']} clips checked, {summary['flagged']} flagged"]
    for kind in KINDS:
        names = summary["flagged_clips"].get(kind, [])
        if names:
            more = f" and {len(names) - limit} more" if len(names) > limit else ""
            lines.append(f"  {kind}: {len(names)} clips ({', '.join(names[:limit])}{more}): {CAUSES[kind]}")
    r = summary["ranges"]
    if r:
        lines.append(
            f"  skeleton height {_span(r, 'skeleton_height_m', lambda v: f'{v:.3g}')} m, head "
            f"{_span(r, 'head_height_m', lambda v: f'{v:.3g}')} m above the floor, upright "
            f"{_span(r, 'upright_fraction', _pct)} of frames, foot contact {_span(r, 'contact_fraction', _pct)}, "
            f"bone variation up to {_pct(r['bone_variation']['max'])}")
    return "\n".join(lines)
