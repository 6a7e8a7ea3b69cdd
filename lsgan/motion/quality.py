"""Motion-quality figures animators read: foot skating, ground penetration, floating, jitter, stretching bones.

Pure numpy on joint positions (..., T, 22, 3): HumanML3D joint order (lsgan.data.skeleton), 20 fps, Y up, metres.
Leading axes are a batch of equal-length motions; each function returns one value per motion (...,).
``quality_metrics`` takes motions of any lengths and averages each figure over motions.

The floor is the plane y = 0: HumanML3D puts each clip's lowest joint over the whole clip on it (its
motion_process.py; lsgan.data.features does the same), and a generated motion keeps the root height the VAE
decodes, so its floor is the same plane. Nothing here re-floors a motion: that would hide penetration and floating.

Foot skating is GMD's figure, to the line (korrawe/guided-motion-diffusion,
data_loaders/humanml/utils/metrics.py, ``calculate_skating_ratio``): the foot joints are 10 and 11 (left_foot,
right_foot: the toes); a foot is in contact between frames t and t+1 when its height is under 5 cm in both; it
skates when, in contact, its horizontal (XZ) speed is over 0.5 m/s (2.5 cm per frame at 20 fps) both between the
two frames and averaged over a 5-frame window (scipy's uniform_filter1d, zeros beyond the ends); a frame pair
counts when either foot skates, and the ratio is over the T - 1 pairs. Evaluation code built on GMD's function
sums the per-motion ratios and divides by the number of motions, as ``quality_metrics`` does. One difference:
GMD runs it on motions padded to 196 frames, so padding counts as pairs that do not skate; here only real frames do.

Penetration and floating follow PhysDiff's definitions (Yuan et al., ICCV 2023): "the distance between the ground
and the lowest body mesh vertex below the ground", and above it, per frame, averaged over the frames with the zeros
(as a public reimplementation built on UHC's smpl_eval.py does; we found no evaluation code of PhysDiff's own).
PhysDiff works on SMPL mesh vertices; here the lowest joint stands in for the lowest vertex. PhysDiff's Float
counts every frame, jumps too; ``floating`` counts only frames where the feet should be on the ground (see there).
PhysDiff's Skate is a mean displacement of contacting feet in mm, not a ratio; the ratio is GMD's.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.ndimage import uniform_filter1d

from lsgan.data.skeleton import FPS, bone_lengths

FEET = [10, 11]  # left_foot, right_foot (toe joints): GMD's foot joints
CONTACT_HEIGHT = 0.05  # m: a foot under this height is on the ground (GMD)
SKATE_SPEED = 0.5  # m/s: 2.5 cm per frame at 20 fps (GMD)
SKATE_WINDOW = 5  # frames: GMD's moving average of the foot speed
POP_JOINTS = [7, 10, 8, 11]  # left ankle, left foot, right ankle, right foot: a foot's joints, side by side
POP_SLACK = 0.02  # m: a foot joint moving this much faster than the foot's fastest move in the original pops


def _check(joints: np.ndarray, min_frames: int) -> np.ndarray:
    x = np.asarray(joints, dtype=np.float64)
    if x.ndim < 3 or x.shape[-1] != 3 or x.shape[-2] <= max(FEET):
        raise ValueError(f"joints must be (..., T, 22, 3) in HumanML3D order, got shape {x.shape}")
    if x.shape[-3] < min_frames:
        raise ValueError(f"this figure needs at least {min_frames} frames, got {x.shape[-3]}")
    return x


def _feet(x: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Foot heights (..., T, 2), horizontal speeds (..., T-1, 2) in m/s, and GMD's contact (..., T-1, 2)."""
    feet = x[..., FEET, :]  # (..., T, 2, 3)
    height = feet[..., 1]  # (..., T, 2)
    speed = np.linalg.norm(np.diff(feet[..., [0, 2]], axis=-3), axis=-1) * fps  # (..., T-1, 2)
    contact = (height[..., :-1, :] < CONTACT_HEIGHT) & (height[..., 1:, :] < CONTACT_HEIGHT)  # (..., T-1, 2)
    return height, speed, contact


def skating_pairs(joints: np.ndarray, fps: float = FPS) -> np.ndarray:
    """Which foot (toes 10, 11) skates between frames t and t+1 by GMD's rule (module docstring). (..., T-1, 2)"""
    _, speed, contact = _feet(_check(joints, 2), fps)
    window = uniform_filter1d(speed, size=SKATE_WINDOW, axis=-2, mode="constant", origin=0)  # (..., T-1, 2)
    return contact & (speed > SKATE_SPEED) & (window > SKATE_SPEED)


def foot_skating_ratio(joints: np.ndarray, fps: float = FPS) -> np.ndarray:
    """Share of frame pairs in which a foot on the ground slides (GMD's skating ratio; module docstring). (...,)"""
    return skating_pairs(joints, fps).any(axis=-1).mean(axis=-1)


def ground_penetration(joints: np.ndarray) -> np.ndarray:
    """Mean over frames of how far the lowest joint is below the floor (0 when above), metres. (...,)"""
    lowest = _check(joints, 1)[..., 1].min(axis=-1)  # (..., T)
    return np.maximum(-lowest, 0.0).mean(axis=-1)


def floating(joints: np.ndarray, fps: float = FPS) -> np.ndarray:
    """Mean over frame pairs of the lowest foot's height where the feet should be on the ground but are not, metres.

    The feet should be on the ground when the body rests on them: both feet still (each moving less than 2.5 cm
    per frame, GMD's skating speed, in 3D) between frames t and t+1. They are not on it when neither foot is in
    contact (GMD's 5 cm rule). Such a pair counts the lower foot's height over the two frames; every other pair
    counts 0 (a stride lifts a foot, a jump moves both, a one-legged stand keeps one down). Sitting with the feet
    lifted and still would count too. (...,)
    """
    x = _check(joints, 2)
    height, _, contact = _feet(x, fps)
    moves = np.linalg.norm(np.diff(x[..., FEET, :], axis=-3), axis=-1) * fps  # (..., T-1, 2)
    resting = (moves < SKATE_SPEED).all(axis=-1) & ~contact.any(axis=-1)  # (..., T-1)
    lowest = np.minimum(height[..., :-1, :], height[..., 1:, :]).min(axis=-1)  # (..., T-1)
    return np.where(resting, lowest, 0.0).mean(axis=-1)


def jerk(joints: np.ndarray, fps: float = FPS) -> np.ndarray:
    """Mean jerk: the norm of the third time derivative of every joint's position, averaged over joints and
    frames, in m/s^3 (third finite difference times fps^3). Jitter shows up as high jerk. (...,)"""
    d3 = np.diff(_check(joints, 4), n=3, axis=-3) * float(fps) ** 3  # (..., T-3, J, 3)
    return np.linalg.norm(d3, axis=-1).mean(axis=(-2, -1))


def bone_variation(joints: np.ndarray) -> np.ndarray:
    """How far a motion's skeleton is from rigid: each bone's standard deviation of length over the frames, averaged
    over the 21 bones, in millimetres (mocap's is 0). (...,)"""
    lengths = bone_lengths(_check(joints, 1).astype(np.float64))[..., 1:]  # (..., T, 21)
    return lengths.std(axis=-2).mean(axis=-1) * 1000.0


def foot_pops(before: np.ndarray, after: np.ndarray, slack: float = POP_SLACK) -> np.ndarray:
    """Frame-to-frame moves of the ankles and toes (7, 10, 8, 11) in ``after`` longer than the fastest move of the
    same foot (its ankle or toe) in ``before`` plus ``slack`` metres: the snaps an edit (a foot clean-up) adds,
    counted per motion. (...,)"""
    moves = [np.linalg.norm(np.diff(_check(x, 2)[..., POP_JOINTS, :], axis=-3), axis=-1) for x in (before, after)]
    if moves[0].shape != moves[1].shape:
        raise ValueError(f"before and after must have the same shape, got {before.shape} and {after.shape}")
    feet = [moves[0][..., 2 * s: 2 * s + 2].max(axis=(-2, -1), keepdims=True) for s in range(2)]
    limit = np.repeat(np.concatenate(feet, axis=-1), 2, axis=-1) + slack  # (..., 1, 4)
    return (moves[1] > limit).sum(axis=(-2, -1))


def toe_above(joints: np.ndarray, height: float = CONTACT_HEIGHT) -> np.ndarray:
    """Share of toe-frames (each of the toes 10 and 11 on each frame) higher than ``height`` above the floor:
    how much of the time the feet are lifted. (...,)"""
    return (_check(joints, 1)[..., FEET, 1] > height).mean(axis=(-2, -1))


FIGURES = {  # key: (function of (joints, fps), the fewest frames it is defined on)
    "foot_skating_ratio": (foot_skating_ratio, 2),
    "penetration_m": (lambda j, fps: ground_penetration(j), 1),
    "floating_m": (floating, 2),
    "jerk_m_s3": (jerk, 4),
    "bone_std_mm": (lambda j, fps: bone_variation(j), 1),
}


def quality_metrics(joints_list: Sequence[np.ndarray], fps: float = FPS) -> dict[str, float]:
    """Each figure per motion (T_i, 22, 3), then averaged over the motions long enough for it (each weighs the
    same; NaN when none is: jerk needs 4 frames, skating and floating 2).

    Keys: foot_skating_ratio, penetration_m, floating_m, jerk_m_s3, bone_std_mm, num_motions.
    """
    if len(joints_list) == 0:
        raise ValueError("quality_metrics needs at least one motion")
    out: dict[str, float] = {}
    for key, (figure, fewest) in FIGURES.items():
        values = []
        for i, joints in enumerate(joints_list):
            if np.shape(joints)[0] < fewest:
                continue
            try:
                values.append(float(figure(joints, fps)))
            except ValueError as e:
                raise ValueError(f"motion {i}: {e}") from e
        out[key] = float(np.mean(values)) if values else float("nan")
    return {**out, "num_motions": len(joints_list)}
