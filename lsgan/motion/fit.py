"""The geometry that posing a skeleton is built from, shared by the BVH and GLB writers, rigidifying and retargeting:
the rest skeleton fitted to a motion and the rotations between vector sets (arrays in, arrays out, batched)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from lsgan.data.skeleton import NUM_JOINTS, PARENTS, RAW_OFFSETS

_PARENTS = np.array(PARENTS)
CHILDREN: tuple[tuple[int, ...], ...] = tuple(
    tuple(int(c) for c in np.flatnonzero(_PARENTS == j)) for j in range(NUM_JOINTS)
)




def unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def kabsch(rest: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Rotations R (...,3,3) minimising sum_k |R rest_k - observed_k|^2, for (...,K,3) vector sets."""
    h = np.einsum("...ki,...kj->...ij", observed, rest)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, 2] *= np.where(d == 0, 1.0, d)[..., None]
    return u @ vt


def shortest_arc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotations (...,3,3) turning unit vectors a onto unit vectors b about a x b (180 degrees when opposite)."""
    a, b = np.broadcast_arrays(unit(a), unit(b))
    w = 1.0 + np.einsum("...i,...i->...", a, b)
    xyz = np.cross(a, b)
    opposite = w < 1e-9
    if opposite.any():
        alt = np.cross(a[opposite], np.array([1.0, 0.0, 0.0]))
        alt = np.where(np.linalg.norm(alt, axis=-1, keepdims=True) < 1e-6,
                       np.cross(a[opposite], np.array([0.0, 1.0, 0.0])), alt)
        xyz[opposite] = unit(alt)
        w[opposite] = 0.0
    quat = np.concatenate([xyz, w[..., None]], axis=-1)
    return Rotation.from_quat(quat.reshape(-1, 4)).as_matrix().reshape(a.shape[:-1] + (3, 3))


def rest_offsets(joints: np.ndarray) -> np.ndarray:
    """Rest offsets (22,3) in metres fitted to a (T,22,3) motion (see :mod:`lsgan.export.bvh`: the rest pose)."""
    j = np.asarray(joints, dtype=np.float64)
    bones = j[:, 1:] - j[:, _PARENTS[1:]]
    lengths = np.concatenate([[0.0], np.linalg.norm(bones, axis=-1).mean(axis=0)])
    offsets = RAW_OFFSETS * lengths[:, None]
    for parent, children in enumerate(CHILDREN):
        if len(children) < 2:
            continue
        kids = list(children)
        observed = j[:, kids] - j[:, [parent]]  # (T,K,3)
        local = np.einsum("tji,tkj->tki", kabsch(offsets[kids], observed), observed).mean(axis=0)
        local = unit(local) * lengths[kids, None]
        offsets[kids] = local @ kabsch(local, offsets[kids]).T
    return offsets
