"""Small SMPL, SMPL-H and SMPL-X model files with smplx's keys, for tests (the real models are licensed).

The rest skeleton is a T-pose (arms along +-X, left = +X, Y up, facing +Z) a little larger than the
HumanML3D target skeleton, so fitting has to use the betas. The mesh is a tube around every bone, skinned
to the bone's two joints by position along it; each joint also owns four vertices placed symmetrically
about it, which the joint regressor averages, so rest joints are exact. Beta 0 scales the template about
the origin (a "size" direction), the others are small random directions. ``posedirs`` are zero, so
smplx's output equals plain linear blend skinning (what glTF does) and can be compared vertex for vertex.
"""
from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

from lsgan.data.body_model import MODEL_JOINTS
from lsgan.data.skeleton import PARENTS, TARGET_OFFSETS

TUBE_SIDES = 8
TUBE_RINGS = 6
SMPLX_MIN_VERTICES = 9930  # smplx's SMPL-X class reads fixed vertex ids up to 9929


def parents(model_type: str) -> list[int]:
    """Parent of each joint: SMPL's 22 body joints, then hands (SMPL 2; SMPL-H/X 15 per hand, after jaw/eyes)."""
    out = list(PARENTS)
    if model_type == "smpl":
        return out + [20, 21]
    if model_type == "smplx":
        out += [15, 15, 15]  # jaw, left eye, right eye
    for wrist in (20, 21):
        for _finger in range(5):
            base = len(out)
            out += [wrist, base, base + 1]
    return out


def _side(par: list[int], k: int) -> str:
    """'left' or 'right' for a joint below a wrist, 'head' for one below the head."""
    while k not in (15, 20, 21):
        k = par[k]
    return {15: "head", 20: "left", 21: "right"}[k]


def rest_skeleton(model_type: str, scale: float = 1.06) -> np.ndarray:
    """(J,3) T-pose joints in metres."""
    par = parents(model_type)
    offsets = np.zeros((len(par), 3))
    offsets[:22] = TARGET_OFFSETS
    for k, sign in ((13, 1.0), (14, -1.0)):  # collars go up and out from spine3, as in SMPL
        offsets[k] = np.linalg.norm(offsets[k]) * np.array([0.55 * sign, 0.83, 0.0])
    for left, right in ((16, 17), (18, 19), (20, 21)):  # arms out sideways: left +X, right -X
        offsets[left] = [np.linalg.norm(offsets[left]), 0.0, 0.0]
        offsets[right] = [-np.linalg.norm(offsets[right]), 0.0, 0.0]
    for k in range(22, len(par)):
        side = _side(par, k)
        offsets[k] = [0.0, 0.05, 0.08] if side == "head" else [0.03 if side == "left" else -0.03, 0.0, 0.0]
    joints = np.zeros_like(offsets)
    joints[0] = (0.0, 0.95, 0.0)
    for k in range(1, len(par)):
        joints[k] = joints[par[k]] + offsets[k]
    return joints * scale


def make_model(model_type: str, seed: int = 0, scale: float = 1.06, min_vertices: int = 0, min_faces: int = 0) -> dict:
    """Arrays of a small body model of ``model_type`` with smplx's keys and shapes.

    ``min_vertices`` / ``min_faces`` pad it to a real model's size (SMPL: 6890 / 13776) for timing."""
    rng = np.random.default_rng(seed)
    par = parents(model_type)
    n_joints = MODEL_JOINTS[model_type]
    joints = rest_skeleton(model_type, scale)
    verts, weights, faces = [], [], []
    for k in range(n_joints):  # four regressor vertices per joint
        for d in ([0.01, 0, 0], [-0.01, 0, 0], [0, 0, 0.01], [0, 0, -0.01]):
            verts.append(joints[k] + d)
            w = np.zeros(n_joints)
            w[k] = 1.0
            weights.append(w)
    for k in range(1, n_joints):  # a tube from parent to child
        a, b = joints[par[k]], joints[k]
        axis = b - a
        length = np.linalg.norm(axis)
        if length < 1e-6:
            continue
        unit = axis / length
        helper = np.array([0.0, 0.0, 1.0]) if abs(unit[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        u = np.cross(unit, helper)
        u /= np.linalg.norm(u)
        v = np.cross(unit, u)
        radius = min(0.06, 0.25 * length)
        base = len(verts)
        for r in range(TUBE_RINGS):
            s = r / (TUBE_RINGS - 1)
            for side in range(TUBE_SIDES):
                ang = 2 * np.pi * side / TUBE_SIDES
                verts.append(a + s * axis + radius * (np.cos(ang) * u + np.sin(ang) * v))
                w = np.zeros(n_joints)
                w[par[k]], w[k] = 1.0 - s, s
                weights.append(w)
        for r in range(TUBE_RINGS - 1):
            for side in range(TUBE_SIDES):
                i0 = base + r * TUBE_SIDES + side
                i1 = base + r * TUBE_SIDES + (side + 1) % TUBE_SIDES
                faces += [[i0, i1, i0 + TUBE_SIDES], [i1, i1 + TUBE_SIDES, i0 + TUBE_SIDES]]
    n_min = max(min_vertices, SMPLX_MIN_VERTICES if model_type == "smplx" else 0)
    while len(verts) < n_min:  # padding vertices (in no face) on the pelvis, so smplx's vertex ids exist
        verts.append(joints[0] + rng.normal(0, 0.01, 3))
        w = np.zeros(n_joints)
        w[0] = 1.0
        weights.append(w)
    v = np.array(verts)
    n_v = len(v)
    if len(faces) < min_faces:
        faces += rng.integers(0, n_v, (min_faces - len(faces), 3)).tolist()
    j_reg = np.zeros((n_joints, n_v))
    for k in range(n_joints):
        j_reg[k, 4 * k:4 * k + 4] = 0.25
    n_shape = {"smpl": 10, "smplh": 16, "smplx": 20}[model_type]
    shapedirs = rng.normal(0, 0.002, (n_v, 3, n_shape))
    shapedirs[..., 0] = 0.05 * v  # beta 0 = +5% size per unit
    data = {
        "v_template": v,
        "shapedirs": shapedirs,
        "posedirs": np.zeros((n_v, 3, (n_joints - 1) * 9)),
        "J_regressor": j_reg,
        "weights": np.array(weights),
        "kintree_table": np.array([[4294967295] + par[1:], list(range(n_joints))], dtype=np.int64),
        "f": np.array(faces, dtype=np.uint32),
    }
    if model_type in ("smplh", "smplx"):
        data.update(hands_componentsl=np.eye(45), hands_componentsr=np.eye(45), hands_meanl=np.zeros(45),
                    hands_meanr=np.zeros(45))
    if model_type == "smplx":
        data.update(lmk_faces_idx=np.arange(51, dtype=np.int64), lmk_bary_coords=np.full((51, 3), 1 / 3))
    return data


def write_models(folder: Path) -> Path:
    """SMPL (pkl), SMPL-H (npz) and SMPL-X (npz) neutral models in smplx's layout under ``folder``."""
    for model_type, ext in (("smpl", "pkl"), ("smplh", "npz"), ("smplx", "npz")):
        (folder / model_type).mkdir(parents=True, exist_ok=True)
        path = folder / model_type / f"{model_type.upper()}_NEUTRAL.{ext}"
        data = make_model(model_type)
        if ext == "pkl":
            with open(path, "wb") as fh:
                pickle.dump(data, fh)
        else:
            np.savez_compressed(path, **data)
    return folder
