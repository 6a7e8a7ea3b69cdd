"""Joint maps: how a BVH skeleton becomes the 22 SMPL joints of :data:`lsgan.data.skeleton.JOINT_NAMES`.

A map names, for every SMPL joint, either one source joint or a point on the segment between two source
joints (for SMPL joints the source skeleton lacks, e.g. Bandai has two spine joints where SMPL has three).
It also says how to reach metres, Y up and the frame rate. Presets: ``bandai``, ``cmu`` and ``mixamo``.

User map file (JSON), the same fields as the presets::

    {
      "joints": {
        "pelvis": "Hips",
        "spine2": {"between": ["Spine", "Chest"], "t": 0.5},
        ...                                   (all 22 SMPL joint names)
      },
      "scale": 0.01,        metres per file unit (cm -> 0.01, inches -> 0.0254); default 1.0
      "up": "y",            the file's up axis: "y" (default) or "z" (Z-up, converted to Y-up, right-handed)
      "fps": null,          frames per second overriding the file's Frame Time; default null (use the file)
      "handedness": "right" "left" for files written in a left-handed frame: x is negated after FK
    }

``{"between": [a, b], "t": t}`` is ``(1 - t) * a + t * b``; ``t`` defaults to 0.5. Source names match
exactly, else case-insensitively. A file lacking a named joint raises :class:`ClipError` listing them.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lsgan.data.clip import ClipError
from lsgan.data.skeleton import JOINT_NAMES


@dataclass(frozen=True)
class Between:
    """The point ``(1 - t) * a + t * b`` on the segment between source joints ``a`` and ``b``."""

    a: str
    b: str
    t: float = 0.5


JointSpec = str | Between


@dataclass(frozen=True)
class JointMap:
    """Source joint (or interpolation) per SMPL joint, unit scale, up axis, handedness and optional frame rate."""

    joints: dict[str, JointSpec]
    scale: float = 1.0
    up: str = "y"
    fps: float | None = None
    handedness: str = "right"
    name: str = field(default="custom", compare=False)

    def __post_init__(self) -> None:
        missing = [j for j in JOINT_NAMES if j not in self.joints]
        unknown = sorted(set(self.joints) - set(JOINT_NAMES))
        if missing:
            raise ClipError(f"joint map {self.name!r} lacks SMPL joints {missing}")
        if unknown:
            raise ClipError(f"joint map {self.name!r} names unknown SMPL joints {unknown}; known: {list(JOINT_NAMES)}")
        if self.up not in ("y", "z"):
            raise ClipError(f"joint map {self.name!r}: up must be 'y' or 'z', got {self.up!r}")
        if self.handedness not in ("right", "left"):
            raise ClipError(f"joint map {self.name!r}: handedness must be 'right' or 'left', got {self.handedness!r}")
        if not self.scale > 0:
            raise ClipError(f"joint map {self.name!r}: scale must be positive, got {self.scale}")
        if self.fps is not None and not self.fps > 0:
            raise ClipError(f"joint map {self.name!r}: fps must be positive, got {self.fps}")

    def source_joints(self) -> list[str]:
        """Every source joint name the map reads, in first-use order."""
        out: list[str] = []
        for spec in self.joints.values():
            for n in (spec,) if isinstance(spec, str) else (spec.a, spec.b):
                if n not in out:
                    out.append(n)
        return out


BANDAI = JointMap(
    name="bandai",
    scale=0.01,
    joints={
        "pelvis": "Hips",
        "left_hip": "UpperLeg_L",
        "right_hip": "UpperLeg_R",
        "spine1": "Spine",
        "left_knee": "LowerLeg_L",
        "right_knee": "LowerLeg_R",
        "spine2": Between("Spine", "Chest", 0.5),
        "left_ankle": "Foot_L",
        "right_ankle": "Foot_R",
        "spine3": "Chest",
        "left_foot": "Toes_L",
        "right_foot": "Toes_R",
        "neck": "Neck",
        "left_collar": "Shoulder_L",
        "right_collar": "Shoulder_R",
        "head": "Head",
        "left_shoulder": "UpperArm_L",
        "right_shoulder": "UpperArm_R",
        "left_elbow": "LowerArm_L",
        "right_elbow": "LowerArm_R",
        "left_wrist": "Hand_L",
        "right_wrist": "Hand_R",
    },
)

# CMU (31 joints). LHipJoint, lowerback, lowerneck and the Collar joints sit on their parent (zero offset),
# so using them would give zero-length bones. Measured on 131_01 (metres above Hips): Chest 0.11, Chest2 0.22
# (where the arms branch, 0.09 below the shoulders, like SMPL's spine3), Neck 0.31 (shoulder height, the base
# of the neck), Head 0.40. Hence spine1 = Chest, spine2 = 70% of the way to Chest2 (SMPL's spine2->spine3
# bone is short), spine3 = Chest2, and each collar halfway between Neck and the shoulder: SMPL's collars
# sit near shoulder height about halfway out, so spine3 -> collar rises and collar -> shoulder runs sideways.
CMU = JointMap(
    name="cmu",
    scale=0.0254 / 0.45,
    joints={
        "pelvis": "Hips",
        "left_hip": "LeftHip",
        "right_hip": "RightHip",
        "spine1": "Chest",
        "left_knee": "LeftKnee",
        "right_knee": "RightKnee",
        "spine2": Between("Chest", "Chest2", 0.7),
        "left_ankle": "LeftAnkle",
        "right_ankle": "RightAnkle",
        "spine3": "Chest2",
        "left_foot": "LeftToe",
        "right_foot": "RightToe",
        "neck": "Neck",
        "left_collar": Between("Neck", "LeftShoulder", 0.5),
        "right_collar": Between("Neck", "RightShoulder", 0.5),
        "head": "Head",
        "left_shoulder": "LeftShoulder",
        "right_shoulder": "RightShoulder",
        "left_elbow": "LeftElbow",
        "right_elbow": "RightElbow",
        "left_wrist": "LeftWrist",
        "right_wrist": "RightWrist",
    },
)

# Mixamo's standard bone names (mixamorig:Hips, mixamorig:Spine, ...): three spine joints as SMPL has, so every
# SMPL joint has its own bone; fingers, eyes and *_End bones stay unmapped. Centimetres, Y up (a map file with
# the same joints and another scale or up axis covers other exports).
_MIXAMO_SIDES = {"left": "Left", "right": "Right"}
MIXAMO = JointMap(
    name="mixamo",
    scale=0.01,
    joints={
        "pelvis": "mixamorig:Hips",
        "spine1": "mixamorig:Spine",
        "spine2": "mixamorig:Spine1",
        "spine3": "mixamorig:Spine2",
        "neck": "mixamorig:Neck",
        "head": "mixamorig:Head",
        **{f"{side}_{smpl}": f"mixamorig:{name}{bone}" for side, name in _MIXAMO_SIDES.items()
           for smpl, bone in (("hip", "UpLeg"), ("knee", "Leg"), ("ankle", "Foot"), ("foot", "ToeBase"),
                              ("collar", "Shoulder"), ("shoulder", "Arm"), ("elbow", "ForeArm"),
                              ("wrist", "Hand"))},
    },
)

PRESETS: dict[str, JointMap] = {"bandai": BANDAI, "cmu": CMU, "mixamo": MIXAMO}



def _few(names: list[str], most: int = 30) -> str:
    """A list of names for a message, cut after ``most`` (a hostile file may declare a million joints)."""
    shown = ", ".join(repr(n[:64]) for n in names[:most])
    return f"[{shown}{f', ... {len(names) - most:,} more' if len(names) > most else ''}]"

def _parse_spec(smpl: str, spec: object, where: str) -> JointSpec:
    if isinstance(spec, str):
        return spec
    if isinstance(spec, dict) and set(spec) <= {"between", "t"} and "between" in spec:
        pair = spec["between"]
        t = spec.get("t", 0.5)
        if (
            isinstance(pair, list)
            and len(pair) == 2
            and all(isinstance(n, str) for n in pair)
            and isinstance(t, (int, float))
        ):
            return Between(pair[0], pair[1], float(t))
    raise ClipError(f"{where}: joint {smpl!r} must be a joint name or {{\"between\": [a, b], \"t\": t}}, got {spec!r}")


def joint_map_from_dict(data: dict, name: str = "custom") -> JointMap:
    """A :class:`JointMap` from the JSON structure documented in this module."""
    if not isinstance(data, dict) or not isinstance(data.get("joints"), dict):
        raise ClipError(f"{name}: a joint map is an object with a 'joints' object")
    unknown_keys = sorted(set(data) - {"joints", "scale", "up", "fps", "handedness"})
    if unknown_keys:
        raise ClipError(f"{name}: unknown joint map keys {unknown_keys}")
    joints = {smpl: _parse_spec(smpl, spec, name) for smpl, spec in data["joints"].items()}
    fps = data.get("fps")
    try:
        scale = float(data.get("scale", 1.0))
        fps = None if fps is None else float(fps)
    except (TypeError, ValueError) as exc:
        raise ClipError(f"{name}: scale and fps must be numbers: {exc}") from exc
    return JointMap(
        joints=joints,
        scale=scale,
        up=str(data.get("up", "y")).lower(),
        fps=fps,
        handedness=str(data.get("handedness", "right")).lower(),
        name=name,
    )


def load_joint_map(path: str | Path) -> JointMap:
    """Read a user joint map JSON file; a malformed file raises :class:`ClipError`."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ClipError(f"{path}: cannot read the joint map: {exc}") from exc
    return joint_map_from_dict(data, name=str(path))


def get_joint_map(preset: str = "bandai", path: str | Path | None = None) -> JointMap:
    """The map in ``path`` when given, else the named preset."""
    if path is not None:
        return load_joint_map(path)
    if preset not in PRESETS:
        raise ClipError(f"unknown joint map preset {preset!r}; known: {sorted(PRESETS)}")
    return PRESETS[preset]


def _resolve(names: tuple[str, ...], wanted: str) -> int | None:
    if wanted in names:
        return names.index(wanted)
    folded = [i for i, n in enumerate(names) if n.lower() == wanted.lower()]
    return folded[0] if len(folded) == 1 else None


def map_indices(jmap: JointMap, names: tuple[str, ...], source: str = "") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index arrays (a, b, t), each (22,): SMPL joint k = (1 - t[k]) * src[a[k]] + t[k] * src[b[k]].

    Raises :class:`ClipError` naming ``source`` and every source joint the map needs that ``names`` lacks.
    """
    lookup = {n: _resolve(names, n) for n in jmap.source_joints()}
    missing = [n for n, i in lookup.items() if i is None]
    if missing:
        raise ClipError(
            f"{source}: unmapped skeleton: joint map {jmap.name!r} needs joints {_few(missing)} that the file lacks "
            f"(it has {_few(list(names))})"
        )
    a = np.empty(len(JOINT_NAMES), dtype=np.int64)
    b = np.empty(len(JOINT_NAMES), dtype=np.int64)
    t = np.zeros(len(JOINT_NAMES), dtype=np.float64)
    for k, smpl in enumerate(JOINT_NAMES):
        spec = jmap.joints[smpl]
        if isinstance(spec, str):
            a[k] = b[k] = lookup[spec]
        else:
            a[k], b[k], t[k] = lookup[spec.a], lookup[spec.b], spec.t
    return a, b, t


def to_y_up(positions: np.ndarray, up: str) -> np.ndarray:
    """Positions (...,3) with ``up`` ('y' or 'z') as the vertical axis -> Y up, by a proper rotation.

    Z-up maps (x, y, z) -> (x, z, -y), a -90 degree turn about x, so a right-handed frame stays right-handed.
    """
    p = np.asarray(positions)
    if up == "y":
        return p
    if up == "z":
        return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)
    raise ValueError(f"up must be 'y' or 'z', got {up!r}")


def apply_joint_map(positions: np.ndarray, names: tuple[str, ...], jmap: JointMap, source: str = "") -> np.ndarray:
    """Source positions (F,J,3) in file units -> SMPL joints (F,22,3) in metres, Y up, right-handed."""
    a, b, t = map_indices(jmap, names, source)
    p = np.asarray(positions, dtype=np.float64)
    w = t[:, None]
    out = p[:, a] * (1.0 - w) + p[:, b] * w
    out = to_y_up(out * jmap.scale, jmap.up)
    if jmap.handedness == "left":
        out = out * np.array([-1.0, 1.0, 1.0])
    return out
