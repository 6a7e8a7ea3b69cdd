"""HumanAct12 (``humanact12poses.pkl``): 1,191 action-labelled clips of SMPL joints at 20 fps.

The file is a pickle (a dict of lists of numpy arrays and ints). It is read by :mod:`lsgan.pickles`,
which rebuilds only arrays from an exact allowlist of globals and refuses anything else, so the file
cannot run code; it is only read from the path the user names, never searched for or downloaded.
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from lsgan.data.clip import ClipError, RawClip
from lsgan.data.skeleton import LEFT_FOOT, NUM_JOINTS, RIGHT_FOOT
from lsgan.data.sources.amass import z_up_to_y_up
from lsgan.pickles import load_pickle

ACTIONS: tuple[str, ...] = (
    "warm_up", "walk", "run", "jump", "drink", "lift_dumbbell", "sit", "eat", "turn_steering_wheel",
    "phone", "boxing", "throw",
)
"""Action names in the order of the pickle's ``y`` ids 0..11."""

PICKLE_NAME = "humanact12poses.pkl"
_HEAD = 15
_AXES = "xyz"


def detect_up_axis(joints: np.ndarray) -> str:
    """Which axis points up in (..., 22+, 3) joints: the one along which head minus feet is largest.

    Returns 'x', 'y' or 'z', with a leading '-' when the head lies towards the negative side
    (e.g. '-y' for Y-down data). Averaged over all frames.
    """
    j = np.asarray(joints, dtype=np.float64)
    feet = j[..., list(LEFT_FOOT + RIGHT_FOOT), :].mean(axis=-2)
    d = (j[..., _HEAD, :] - feet).reshape(-1, 3).mean(axis=0)
    axis = int(np.argmax(np.abs(d)))
    return ("-" if d[axis] < 0 else "") + _AXES[axis]


def resolve_pickle(path: str) -> str:
    """``path`` itself if it is a file, else ``humanact12poses.pkl`` inside it (or in its HumanAct12Poses/)."""
    if os.path.isfile(path):
        return path
    candidates = [os.path.join(path, PICKLE_NAME), os.path.join(path, "HumanAct12Poses", PICKLE_NAME)]
    for candidate in candidates:
        if os.path.isfile(candidate):
            return candidate
    raise ValueError(f"no HumanAct12 pickle at {path!r}; expected the file itself or one of: {', '.join(candidates)}")


@functools.lru_cache(maxsize=2)
def _read_pickle(path: str, mtime_ns: int) -> dict[str, Any]:
    """The checked HumanAct12 dict; PickleReadError (a ValueError naming the file) for a refused or damaged one."""
    data = load_pickle(path)
    if not isinstance(data, dict) or any(k not in data for k in ("joints3D", "y")):
        raise ValueError(f"{path}: expected a dict with 'joints3D' and 'y' (the HumanAct12 layout)")
    if len(data["joints3D"]) != len(data["y"]):
        raise ValueError(f"{path}: {len(data['joints3D'])} joints3D entries but {len(data['y'])} labels")
    return data


def read_humanact12(path: str) -> dict[str, Any]:
    """The HumanAct12 dict (``poses``, ``joints3D``, ``y``), read once per process (cached by path and mtime)."""
    return _read_pickle(path, os.stat(path).st_mtime_ns)


@dataclass
class HumanAct12Source:
    """HumanAct12's ``humanact12poses.pkl``: one work item per clip, joints 0..21 of ``joints3D``.

    ``up_axis='y'`` takes the joints as stored (as HumanML3D does); ``'z'`` applies the AMASS change
    (x,y,z) -> (-x,z,y) for Z-up copies. Items are ``'<pickle path>#<clip index>'``.
    """

    path: str
    up_axis: str = "y"
    mirror: bool = False
    name: ClassVar[str] = "humanact12"

    def __post_init__(self) -> None:
        if self.up_axis not in ("y", "z"):
            raise ValueError(f"up_axis must be 'y' or 'z', got {self.up_axis!r}")

    def scan(self) -> list[str]:
        """One item per clip, in pickle order."""
        pkl = resolve_pickle(self.path)
        return [f"{pkl}#{i:04d}" for i in range(len(read_humanact12(pkl)["joints3D"]))]

    def load(self, item: str) -> list[RawClip]:
        """The clip ``humanact12_{i:04d}`` with its action name."""
        pkl, _, index = item.rpartition("#")
        i = int(index)
        data = read_humanact12(pkl)
        joints = np.asarray(data["joints3D"][i], dtype=np.float32)
        if joints.ndim != 3 or joints.shape[1] < NUM_JOINTS or joints.shape[2] != 3:
            raise ClipError(f"{item}: joints3D has shape {joints.shape}, expected (T,24,3)")
        label = int(data["y"][i])
        if not 0 <= label < len(ACTIONS):
            raise ClipError(f"{item}: action id {label} is outside 0..{len(ACTIONS) - 1}")
        joints = np.ascontiguousarray(joints[:, :NUM_JOINTS])
        if self.up_axis == "z":
            joints = z_up_to_y_up(joints)
        return [RawClip(name=f"humanact12_{i:04d}", source_file=pkl, joints=joints, action=ACTIONS[label],
                        mirror=self.mirror)]

    def inputs(self) -> list[str]:
        """The pickle (the items name clips inside it)."""
        return [resolve_pickle(self.path)]
