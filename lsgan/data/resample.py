"""Change the frame rate of joint trajectories."""
from __future__ import annotations

import numpy as np

MAX_UPSAMPLING = 20.0
"""Most a clip is upsampled: 1 fps to 20 fps (the slowest frame rate the BVH reader accepts). A larger factor
is a wrong frame rate, and would allocate that many times the clip's frames (a 'Frame Time: 100000' read as
0.00001 fps and resampled to 20 fps: 2,000,000 frames for each one)."""


def resample(positions: np.ndarray, src_fps: float, dst_fps: float = 20.0) -> np.ndarray:
    """Resample (T, ...) positions from ``src_fps`` to ``dst_fps`` by linear interpolation in time.

    Integer ratios (60->20, 120->20) reduce to exact frame picking, as HumanML3D's stride does.
    The output covers the same time span: frames at t = k / dst_fps for t <= (T-1) / src_fps.
    """
    x = np.asarray(positions)
    if not (src_fps > 0 and dst_fps > 0):  # also NaN
        raise ValueError(f"frame rates must be positive, got {src_fps} -> {dst_fps}")
    if dst_fps / src_fps > MAX_UPSAMPLING:
        raise ValueError(f"resampling {src_fps:g} fps to {dst_fps:g} fps would multiply the frames by more than "
                         f"{MAX_UPSAMPLING:g}: a wrong frame rate?")
    if len(x) == 0:
        return x.copy()
    ratio = src_fps / dst_fps
    if abs(ratio - round(ratio)) < 1e-9:
        return x[:: int(round(ratio))].copy()
    duration = (len(x) - 1) / src_fps
    n_out = int(np.floor(duration * dst_fps + 1e-9)) + 1
    t = np.arange(n_out) * ratio  # fractional source frame index of each output frame
    i0 = np.minimum(np.floor(t).astype(np.int64), len(x) - 1)
    i1 = np.minimum(i0 + 1, len(x) - 1)
    w = (t - i0).reshape((-1,) + (1,) * (x.ndim - 1))
    return (x[i0] * (1.0 - w) + x[i1] * w).astype(x.dtype, copy=False)
