"""Batched quaternion and 6D-rotation maths, (w, x, y, z) order, numpy in and out.

Pure functions on arrays of any leading shape; they follow the conventions of the original HumanML3D
code so that features agree with it to float precision.
"""
from __future__ import annotations

import numpy as np


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the last axis (3 or 4 entries), keeping it: (..., n) -> (..., 1).

    Written out per component: much faster than a reduction over a short trailing axis.
    """
    out = a[..., 0:1] * b[..., 0:1]
    for i in range(1, a.shape[-1]):
        out = out + a[..., i : i + 1] * b[..., i : i + 1]
    return out


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors (or quaternions) along the last axis."""
    return v / np.sqrt(dot(v, v))


def qnormalize(q: np.ndarray) -> np.ndarray:
    return normalize(q)


def qinv(q: np.ndarray) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion)."""
    out = np.array(q, copy=True)
    out[..., 1:] *= -1
    return out


def qmul(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Hamilton product q*r, broadcasting over leading dimensions."""
    w0, x0, y0, z0 = np.moveaxis(q, -1, 0)
    w1, x1, y1, z1 = np.moveaxis(r, -1, 0)
    out = np.empty(np.broadcast_shapes(q.shape, r.shape), dtype=np.result_type(q, r))
    out[..., 0] = w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1
    out[..., 1] = w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1
    out[..., 2] = w0 * y1 - x0 * z1 + y0 * w1 + z0 * x1
    out[..., 3] = w0 * z1 + x0 * y1 - y0 * x1 + z0 * w1
    return out


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # np.cross is slow on small trailing axes; this is the same formula written out.
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), dtype=np.result_type(a, b))
    out[..., 0] = ay * bz - az * by
    out[..., 1] = az * bx - ax * bz
    out[..., 2] = ax * by - ay * bx
    return out


def qrot(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4), broadcasting."""
    qvec = q[..., 1:]
    uv = _cross(np.broadcast_to(qvec, np.broadcast_shapes(qvec.shape, v.shape)), v)
    uuv = _cross(np.broadcast_to(qvec, uv.shape), uv)
    return v + 2.0 * (q[..., :1] * uv + uuv)


def qbetween(v0: np.ndarray, v1: np.ndarray) -> np.ndarray:
    """The shortest-arc unit quaternion rotating v0 onto v1 (both (..., 3))."""
    out = np.empty(np.broadcast_shapes(v0.shape, v1.shape)[:-1] + (4,), dtype=np.result_type(v0, v1))
    out[..., 1:] = _cross(v0, v1)
    out[..., :1] = np.sqrt(dot(v0, v0) * dot(v1, v1)) + dot(v0, v1)
    return normalize(out)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions -> (..., 3, 3) rotation matrices."""
    r, i, j, k = np.moveaxis(q, -1, 0)
    two_s = 2.0 / (q * q).sum(-1)
    m = np.stack(
        (
            1 - two_s * (j * j + k * k), two_s * (i * j - k * r), two_s * (i * k + j * r),
            two_s * (i * j + k * r), 1 - two_s * (i * i + k * k), two_s * (j * k - i * r),
            two_s * (i * k - j * r), two_s * (j * k + i * r), 1 - two_s * (i * i + j * j),
        ),
        axis=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def quat_to_cont6d(q: np.ndarray) -> np.ndarray:
    """(..., 4) -> (..., 6): the first two columns of the rotation matrix, concatenated."""
    r, i, j, k = np.moveaxis(q, -1, 0)
    two_s = 2.0 / (q * q).sum(-1)
    out = np.empty(q.shape[:-1] + (6,), dtype=q.dtype)
    out[..., 0] = 1 - two_s * (j * j + k * k)
    out[..., 1] = two_s * (i * j + k * r)
    out[..., 2] = two_s * (i * k - j * r)
    out[..., 3] = two_s * (i * j - k * r)
    out[..., 4] = 1 - two_s * (i * i + k * k)
    out[..., 5] = two_s * (j * k + i * r)
    return out


def cont6d_to_matrix(d6: np.ndarray) -> np.ndarray:
    """(..., 6) continuous 6D rotations -> (..., 3, 3) by Gram-Schmidt; columns x, y, z."""
    x = d6[..., 0:3] / np.linalg.norm(d6[..., 0:3], axis=-1, keepdims=True)
    z = _cross(x, d6[..., 3:6])
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    y = _cross(z, x)
    return np.stack([x, y, z], axis=-1)


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions with w >= 0."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    q_abs = np.sqrt(np.maximum(0.0, np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                                              1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1)))
    # Four candidate quaternions, each well conditioned when its own |component| is largest.
    cands = np.stack(
        [
            np.stack([q_abs[..., 0] ** 2, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1),
            np.stack([m[..., 2, 1] - m[..., 1, 2], q_abs[..., 1] ** 2, m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0]], -1),
            np.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] + m[..., 0, 1], q_abs[..., 2] ** 2, m[..., 1, 2] + m[..., 2, 1]], -1),
            np.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 2, 0] + m[..., 0, 2], m[..., 2, 1] + m[..., 1, 2], q_abs[..., 3] ** 2], -1),
        ],
        axis=-2,
    ) / (2.0 * np.maximum(q_abs[..., None], 0.1))
    best = np.argmax(q_abs, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = qnormalize(q)
    return np.where(q[..., :1] < 0, -q, q)


def axis_angle_to_quat(aa: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle (rotation vectors) -> (..., 4) unit quaternions."""
    angle = np.linalg.norm(aa, axis=-1, keepdims=True)
    half = 0.5 * angle
    scale = np.where(angle > 1e-8, np.sin(half) / np.maximum(angle, 1e-12), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), aa * scale], axis=-1)
