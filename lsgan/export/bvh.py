"""Export (T,22,3) joint positions as a BVH file that Blender, MotionBuilder and lsgan's reader load.

Units: the file is in centimetres (``UNITS_PER_METRE`` = 100, the common BVH unit; import into Blender
with scale 0.01). The hierarchy is the 22 SMPL joints (names from ``JOINT_NAMES``, parents from
``PARENTS``) written depth first; the pelvis carries ``Xposition Yposition Zposition Zrotation Yrotation
Xrotation``, every other joint ``Zrotation Yrotation Xrotation``, composed intrinsically (R = Rz @ Ry @ Rx,
as :func:`lsgan.data.bvh.local_transforms` reads them). The head, feet and wrists end in an End Site.

Rest pose: each bone points along its ``RAW_OFFSETS`` direction (legs and arms down, feet forward +z) with
the input's mean bone length. The children of the two branching joints (pelvis: hips + spine; spine3:
neck + collars) keep the input's mean relative layout instead, so that one rigid rotation of the branching
joint can place all of them; that layout is turned to lie as close as possible to the raw directions.

Rotations come from IK on the positions, so bones stay rigid: a branching joint's global orientation is
the Kabsch fit of its rest child offsets onto the observed ones; a joint with one child aims its rest bone
along the observed one with its twist taken from the body (:mod:`lsgan.export.aim`: knees and elbows from
their bend plane, feet from the toe and the floor, the spine from the hips and shoulders lines); leaves get
the identity.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lsgan.data.bvh import POSITION_CHANNELS, ROTATION_CHANNELS
from lsgan.data.skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS
from lsgan.motion.fit import CHILDREN, kabsch, rest_offsets
from lsgan.io import atomic_file

UNITS_PER_METRE = 100.0
ROOT_CHANNELS = ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
JOINT_CHANNELS = ("Zrotation", "Yrotation", "Xrotation")
END_SITE_FRACTION = 0.5  # an End Site continues the leaf's bone by this fraction of its length

_PARENTS = np.array(PARENTS)
MIN_BONE_M = 1e-6  # a bone shorter than this in every frame: joints collapsed, not a body
def _depth_first(joint: int = 0) -> list[int]:
    """Joint indices in the order the hierarchy is written (each joint before its children)."""
    order = [joint]
    for child in CHILDREN[joint]:
        order.extend(_depth_first(child))
    return order


FILE_ORDER: tuple[int, ...] = tuple(_depth_first())


def joint_rotations(joints: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Local rotations (T,22,3,3) that pose the rest skeleton ``offsets`` like ``joints`` (hierarchical FK).

    A joint with several children turns onto all of their bones at once (Kabsch); one with a single child aims
    its rest bone along the observed one and takes its twist from the body (:mod:`lsgan.export.aim`: the axis
    that faces the bone's reference direction at rest faces it in every frame); leaves keep the identity.
    """
    from lsgan.export.aim import aim_frames, reference_directions, smpl_axes

    j = np.asarray(joints, dtype=np.float64)
    t = j.shape[0]
    axes = smpl_axes(_rest_positions(offsets))
    refs = reference_directions(j)
    eye = np.broadcast_to(np.eye(3), (t, 3, 3))
    global_rot = np.empty((t, NUM_JOINTS, 3, 3))
    local_rot = np.empty((t, NUM_JOINTS, 3, 3))
    for k in range(NUM_JOINTS):
        parent_rot = eye if PARENTS[k] < 0 else global_rot[:, PARENTS[k]]
        kids = list(CHILDREN[k])
        if len(kids) > 1:
            world = kabsch(offsets[kids], j[:, kids] - j[:, [k]])
        elif kids:
            world = aim_frames(offsets[kids[0]], axes[k], j[:, kids[0]] - j[:, k], refs[:, kids[0]])
        else:
            world = parent_rot
        local_rot[:, k] = np.swapaxes(parent_rot, -1, -2) @ world
        global_rot[:, k] = world
    return local_rot


def _rest_positions(offsets: np.ndarray) -> np.ndarray:
    """Rest joint positions (22,3) of rest offsets (22,3): offsets summed down the chains."""
    pos = np.zeros((NUM_JOINTS, 3))
    for k in range(NUM_JOINTS):
        pos[k] = offsets[k] + (pos[PARENTS[k]] if PARENTS[k] >= 0 else 0.0)
    return pos


def channel_values(local: np.ndarray, translations: np.ndarray, channels) -> np.ndarray:
    """The MOTION block (T,C) for local rotations (T,J,3,3) and translations (T,J,3) in file units.

    Each joint's channels in its own order: positions from ``translations``, rotations as intrinsic Euler
    degrees in the joint's rotation order (R = R_c1 @ R_c2 @ R_c3, as the reader composes them). A joint with
    fewer than three rotation channels can only hold the identity; anything else raises ValueError.
    """
    t = local.shape[0]
    columns: list[np.ndarray] = []
    for k, chans in enumerate(channels):
        order = "".join(c[0] for c in chans if c in ROTATION_CHANNELS)
        if len(order) == 3:
            with warnings.catch_warnings():  # gimbal lock is harmless: the angles still compose to the same matrix
                warnings.simplefilter("ignore", UserWarning)
                angles = Rotation.from_matrix(local[:, k]).as_euler(order, degrees=True)
        elif np.allclose(local[:, k], np.eye(3), atol=1e-9):
            angles = np.zeros((t, 3))
        else:
            raise ValueError(f"joint {k} has rotation channels {order or 'none'}: it needs all three to turn")
        for c in chans:
            if c in POSITION_CHANNELS:
                columns.append(translations[:, k, POSITION_CHANNELS.index(c)])
            else:
                columns.append(angles[:, order.index(c[0])])
    return np.stack(columns, axis=1) if columns else np.zeros((t, 0))


def motion_channels(joints: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The MOTION block (T, 6 + 3*21) in file order: root position in file units, then ZYX Euler degrees."""
    j = np.asarray(joints, dtype=np.float64)
    local = joint_rotations(j, offsets)[:, list(FILE_ORDER)]
    translations = np.zeros((j.shape[0], NUM_JOINTS, 3))
    translations[:, 0] = j[:, 0] * UNITS_PER_METRE
    return channel_values(local, translations, [ROOT_CHANNELS] + [JOINT_CHANNELS] * (NUM_JOINTS - 1))


def hierarchy_text(names, parents, offsets: np.ndarray, channels, end_sites=()) -> str:
    """The HIERARCHY block of any skeleton whose joints are listed depth first (as a reader returns them).

    ``offsets`` (J,3) and the ``end_sites`` ((joint, offset) pairs) are in file units; ``channels[j]`` is
    joint j's channel list, written as given.
    """
    kids: list[list[int]] = [[] for _ in names]
    for k, parent in enumerate(parents):
        if parent >= 0:
            kids[int(parent)].append(k)
    ends: dict[int, list] = {}
    for joint, offset in end_sites:
        ends.setdefault(int(joint), []).append(offset)
    lines = ["HIERARCHY"]
    order: list[int] = []

    def fmt(v) -> str:
        return " ".join(f"{x:.6f}" for x in v)

    def write(k: int, depth: int) -> None:
        order.append(k)
        pad = "  " * depth
        lines.extend([f"{pad}{'ROOT' if parents[k] < 0 else 'JOINT'} {names[k]}", f"{pad}{{",
                      f"{pad}  OFFSET {fmt(offsets[k])}"])
        if channels[k]:
            lines.append(f"{pad}  CHANNELS {len(channels[k])} {' '.join(channels[k])}")
        for child in kids[k]:
            write(child, depth + 1)
        for end in ends.get(k, ()):
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {fmt(end)}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    for root in (k for k, parent in enumerate(parents) if parent < 0):
        write(root, 0)
    if order != list(range(len(names))):
        raise ValueError("the joints must be listed depth first, each parent before its children")
    return "\n".join(lines)


def bvh_text(hierarchy: str, motion: np.ndarray, fps: float) -> str:
    """A whole BVH file: ``hierarchy`` (from :func:`hierarchy_text`), then the MOTION block at ``fps``."""
    rows = np.char.mod("%.6f", np.asarray(motion, dtype=np.float64))
    body = "\n".join(" ".join(row) for row in rows)
    return f"{hierarchy}\nMOTION\nFrames: {len(rows)}\nFrame Time: {1.0 / fps:.8f}\n{body}\n"


def _hierarchy(offsets: np.ndarray) -> str:
    """The HIERARCHY block for rest offsets (22,3) in metres."""
    order = list(FILE_ORDER)
    position = {k: i for i, k in enumerate(order)}
    parents = [position[PARENTS[k]] if PARENTS[k] >= 0 else -1 for k in order]
    channels = [ROOT_CHANNELS if PARENTS[k] < 0 else JOINT_CHANNELS for k in order]
    ends = [(position[k], offsets[k] * END_SITE_FRACTION * UNITS_PER_METRE) for k in order if not CHILDREN[k]]
    return hierarchy_text([JOINT_NAMES[k] for k in order], parents, offsets[order] * UNITS_PER_METRE, channels, ends)


def checked_motion(joints: np.ndarray, fps: float) -> np.ndarray:
    """joints (T,22,3) as float64, or ValueError for a wrong shape, non-finite values or an fps that is not
    positive and finite (the BVH, GLB and retargeted exports check the same)."""
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 3 or j.shape[1:] != (NUM_JOINTS, 3) or j.shape[0] == 0:
        raise ValueError(f"joints must be (T,{NUM_JOINTS},3) with T > 0, got {j.shape}")
    if not np.isfinite(j).all():
        raise ValueError("joints hold NaN or infinite values")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive and finite, got {fps}")
    lengths = np.linalg.norm(j[:, 1:] - j[:, _PARENTS[1:]], axis=-1).max(axis=0)  # each bone's longest
    if (lengths < MIN_BONE_M).any():
        k = int(np.argmax(lengths < MIN_BONE_M)) + 1
        raise ValueError(f"not a body: the bone {JOINT_NAMES[PARENTS[k]]} -> {JOINT_NAMES[k]} has no length in any "
                         "frame (joints collapsed onto one point)")
    return j


def joints_to_bvh(joints: np.ndarray, *, fps: float = 20.0, offsets: np.ndarray | None = None) -> str:
    """BVH text for joint positions (T,22,3) in metres; ``offsets`` (22,3, metres) overrides the fitted rest pose.

    The positions are reproduced exactly when the input's bones are rigid (up to the 6 printed decimals);
    otherwise the rigid BVH skeleton follows every bone's direction with its mean length.
    """
    j = checked_motion(joints, fps)
    rest = rest_offsets(j) if offsets is None else np.asarray(offsets, dtype=np.float64)
    if rest.shape != (NUM_JOINTS, 3):
        raise ValueError(f"offsets must be ({NUM_JOINTS},3), got {rest.shape}")
    return bvh_text(_hierarchy(rest), motion_channels(j, rest), fps)


def write_bvh(path: str | Path, joints: np.ndarray, *, fps: float = 20.0,
              offsets: np.ndarray | None = None) -> Path:
    """Write :func:`joints_to_bvh` to ``path`` atomically (a temporary file beside it, then os.replace)."""
    path = Path(path)
    text = joints_to_bvh(joints, fps=fps, offsets=offsets)
    with atomic_file(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    return path


def load_motion_joints(path: str | os.PathLike) -> list[tuple[str, np.ndarray]]:
    """(name, joints (T,22,3)) pairs from a joints .npy, a features .npy (T,263), or a ``generate`` folder. The
    joints of features are recovered and made rigid as ``generate`` makes its motion of record."""
    from lsgan.data.clip import load_npy
    from lsgan.data.features import recover_from_ric
    from lsgan.data.skeleton import FEATURE_DIM
    from lsgan.motion.rigid import make_rigid

    path = Path(path)
    if path.is_dir():
        files = sorted(path.glob("*_joints.npy")) or sorted(path.glob("*.npy"))
        if not files:
            raise ValueError(f"{path}: no .npy motions in this folder")
        return [item for f in files for item in load_motion_joints(f)]
    array = load_npy(path)
    if array.ndim == 3 and array.shape[1:] == (NUM_JOINTS, 3):
        joints = array.astype(np.float32)
    elif array.ndim == 2 and array.shape[1] == FEATURE_DIM:
        joints = make_rigid(recover_from_ric(array.astype(np.float32))) if len(array) else \
            array.reshape(0, NUM_JOINTS, 3)
    else:
        raise ValueError(f"{path}: expected joints (T, 22, 3) or features (T, 263), got an array of shape "
                         f"{array.shape}")
    if not len(joints):
        raise ValueError(f"{path}: holds no frames")
    if not np.isfinite(joints).all():
        raise ValueError(f"{path}: holds NaN or infinite values")
    return [(path.stem, joints)]
