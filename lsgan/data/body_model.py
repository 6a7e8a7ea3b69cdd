"""SMPL-family body models (SMPL, SMPL-H, SMPL-X) read from the files users bring, never shipped.

Only what skinning and the skeleton need is read: the template mesh, the shape blend shapes, the joint
regressor, the skinning weights, the kinematic tree and the faces. Files are found in smplx's layout
(``DIR/smpl/SMPL_NEUTRAL.pkl``, ``DIR/smplx/SMPLX_NEUTRAL.npz``...), flat (``DIR/SMPLH_MALE.pkl``) or
AMASS's (``DIR/neutral/model.npz``). ``.pkl`` files, and pickled entries of ``.npz`` files, are read
by :mod:`lsgan.pickles`, which only rebuilds numpy arrays and scipy sparse matrices from an exact
allowlist, so a model file cannot run code.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lsgan.data.skeleton import JOINT_NAMES
from lsgan.pickles import PickleReadError, load_npz, load_pickle, with_chumpy_advice

MODEL_JOINTS = {"smpl": 24, "smplh": 52, "smplx": 55}
MODEL_TYPES = tuple(MODEL_JOINTS)
GENDERS = ("neutral", "male", "female")
REQUIRED_KEYS = ("v_template", "shapedirs", "J_regressor", "weights", "kintree_table", "f")
NUM_BETAS = 10

_FINGERS = [f"{f}{k}" for f in ("index", "middle", "pinky", "ring", "thumb") for k in (1, 2, 3)]
_HANDS = [f"left_{f}" for f in _FINGERS] + [f"right_{f}" for f in _FINGERS]
JOINT_NAMES_BY_TYPE: dict[str, tuple[str, ...]] = {
    "smpl": tuple(JOINT_NAMES) + ("left_hand", "right_hand"),
    "smplh": tuple(JOINT_NAMES) + tuple(_HANDS),
    "smplx": tuple(JOINT_NAMES) + ("jaw", "left_eye", "right_eye") + tuple(_HANDS),
}


class BodyModelError(ValueError):
    """A body model that is missing or unreadable; the message names the file and what was expected."""


@dataclass(frozen=True)
class BodyModel:
    """The arrays of one body model (float32 unless noted); J joints, V vertices."""

    path: str
    model_type: str  # "smpl" | "smplh" | "smplx"
    gender: str
    v_template: np.ndarray  # (V,3) rest mesh, metres, Y up, facing +Z
    shapedirs: np.ndarray  # (V,3,B) identity blend shapes, B <= NUM_BETAS
    j_regressor: np.ndarray  # (J,V) dense
    weights: np.ndarray  # (V,J) skinning weights, rows sum to 1
    parents: np.ndarray  # (J,) int64, -1 for the pelvis
    faces: np.ndarray  # (F,3) int64

    @property
    def num_joints(self) -> int:
        return len(self.parents)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return JOINT_NAMES_BY_TYPE[self.model_type]

    def rest_vertices(self, betas: np.ndarray | None = None) -> np.ndarray:
        """(V,3) template with the identity blend shapes of ``betas`` (zeros when None) applied."""
        if betas is None:
            return self.v_template.copy()
        b = np.asarray(betas, dtype=np.float32).reshape(-1)[: self.shapedirs.shape[-1]]
        return self.v_template + self.shapedirs[..., : len(b)] @ b

    def rest_joints(self, betas: np.ndarray | None = None) -> np.ndarray:
        """(J,3) joint locations of the rest mesh for ``betas``."""
        return self.j_regressor @ self.rest_vertices(betas)


def model_candidates(folder: str | Path, model_type: str, gender: str) -> list[Path]:
    """Files tried, in order, for one model type and gender under ``folder``."""
    d = Path(folder)
    upper = f"{model_type.upper()}_{gender.upper()}"
    out = []
    for ext in ("npz", "pkl"):
        out += [d / model_type / f"{upper}.{ext}", d / f"{upper}.{ext}"]
    if model_type == "smplh":
        out += [d / gender / "model.npz", d / "smplh" / gender / "model.npz"]
    return out


def find_body_model(path: str | Path, *, model_type: str = "auto", gender: str = "neutral") -> tuple[Path, str]:
    """The model file and its type for ``path`` (a file, or a folder in one of the known layouts).

    ``model_type="auto"`` takes the first of SMPL, SMPL-H, SMPL-X found. BodyModelError lists the files
    that were expected when nothing is found.
    """
    gender = gender.lower()
    if gender not in GENDERS:
        raise BodyModelError(f"gender must be one of {', '.join(GENDERS)}, got {gender!r}")
    types = MODEL_TYPES if model_type == "auto" else (model_type,)
    if model_type != "auto" and model_type not in MODEL_JOINTS:
        raise BodyModelError(f"model type must be auto or one of {', '.join(MODEL_TYPES)}, got {model_type!r}")
    p = Path(path)
    if p.is_file():
        return p, model_type
    tried: list[Path] = []
    if p.is_dir():
        for t in types:
            for candidate in model_candidates(p, t, gender):
                if candidate.is_file():
                    return candidate, t
                tried.append(candidate)
    where = "does not exist" if not p.exists() else "holds none of the expected files"
    lines = [f"body model {str(p)!r} {where}; expected a model file or a folder with one of:"]
    lines += [f"  {c}" for c in (tried or [c for t in types for c in model_candidates(p, t, gender)])]
    lines.append("(SMPL, SMPL-H or SMPL-X from their websites, laid out as smplx expects: "
                 "https://github.com/vchoutas/smplx#model-loading; lsgan never downloads them)")
    raise BodyModelError("\n".join(lines))


def _read_arrays(path: Path) -> dict:
    """The model's entries; 0-d object entries of an ``.npz`` (a pickled sparse matrix) are unwrapped."""
    try:
        if path.suffix == ".pkl":
            data = load_pickle(path)
        else:
            data = {k: v.item() if v.dtype == object and v.ndim == 0 else v
                    for k, v in load_npz(path, REQUIRED_KEYS).items()}
    except PickleReadError as exc:
        raise BodyModelError(with_chumpy_advice(exc, "original SMPL pickles hold chumpy objects: remove them with "
                                                     "smplx's tools/clean_ch.py (or use the .npz release)")) from exc
    if not isinstance(data, dict):
        raise BodyModelError(f"{path} is not a body model file: it holds a {type(data).__name__}, not a dict")
    return data


def _dense(a) -> np.ndarray:
    return np.asarray(a.toarray() if hasattr(a, "toarray") else a)


def read_body_model(path: str | Path, *, model_type: str = "auto", gender: str = "neutral") -> BodyModel:
    """Load the body model at ``path`` (file or folder, see :func:`find_body_model`), checked for shape."""
    file, found_type = find_body_model(path, model_type=model_type, gender=gender)
    data = _read_arrays(file)
    missing = [k for k in REQUIRED_KEYS if k not in data]
    if missing:
        raise BodyModelError(f"{file} is not an SMPL-family model file: missing {', '.join(missing)} "
                             f"(expected keys {', '.join(REQUIRED_KEYS)})")
    kintree = _dense(data["kintree_table"]).astype(np.int64)
    n_joints = kintree.shape[-1]
    by_count = {v: k for k, v in MODEL_JOINTS.items()}
    if n_joints not in by_count:
        raise BodyModelError(f"{file}: {n_joints} joints is none of SMPL (24), SMPL-H (52) or SMPL-X (55)")
    if found_type not in ("auto", by_count[n_joints]):
        raise BodyModelError(f"{file} has {n_joints} joints: it is {by_count[n_joints]}, not {found_type}")
    v_template = _dense(data["v_template"]).astype(np.float32)
    n_verts = v_template.shape[0]
    shapedirs = _dense(data["shapedirs"]).astype(np.float32)
    if shapedirs.ndim == 2:
        shapedirs = shapedirs[..., None]
    j_regressor = _dense(data["J_regressor"]).astype(np.float32)
    weights = _dense(data["weights"]).astype(np.float32)
    faces = _dense(data["f"]).astype(np.int64)
    checks = [
        (v_template.ndim == 2 and v_template.shape[1] == 3, f"v_template {v_template.shape} is not (V,3)"),
        (shapedirs.shape[:2] == (n_verts, 3), f"shapedirs {shapedirs.shape} is not ({n_verts},3,B)"),
        (j_regressor.shape == (n_joints, n_verts), f"J_regressor {j_regressor.shape} is not ({n_joints},{n_verts})"),
        (weights.shape == (n_verts, n_joints), f"weights {weights.shape} is not ({n_verts},{n_joints})"),
        (faces.ndim == 2 and faces.shape[1] == 3 and faces.min() >= 0 and faces.max() < n_verts,
         f"faces {faces.shape} are not (F,3) indices below {n_verts}"),
    ]
    for ok, problem in checks:
        if not ok:
            raise BodyModelError(f"{file}: {problem}")
    parents = kintree[0].copy()
    parents[0] = -1
    if not all(0 <= parents[j] < j for j in range(1, n_joints)):
        raise BodyModelError(f"{file}: kintree_table is not a tree with parents before children")
    return BodyModel(
        path=str(file), model_type=by_count[n_joints], gender=gender.lower(), v_template=v_template,
        shapedirs=shapedirs[..., :NUM_BETAS], j_regressor=j_regressor, weights=weights, parents=parents,
        faces=faces,
    )
