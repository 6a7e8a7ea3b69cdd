"""AMASS (SMPL+H G release) ``.npz`` files -> 22 joints at 20 fps, as HumanML3D's raw_pose_processing does it.

The steps and their constants are the original's: stride ``int(mocap_framerate / 20)``, the SMPL-H body
model of the file's gender (male for 'male', female otherwise), the first 10 betas, joints 0..21, swap y
and z, then per ``index.csv`` row a dataset-specific head trim, ``[start_frame:end_frame]`` and x negated.
"""
from __future__ import annotations

import contextlib
import csv
import functools
import io
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from lsgan.data.clip import ClipError, RawClip
from lsgan.data.skeleton import FPS, NUM_JOINTS
from lsgan.pickles import PickleReadError, load_npy, load_npz, load_pickle, with_chumpy_advice

logger = logging.getLogger(__name__)

SWAP_Y_Z = np.array([[1, 0, 0], [0, 0, 1], [0, 1, 0]], dtype=np.float32)
"""HumanML3D's ``trans_matrix``: right-multiplying swaps y and z (AMASS is Z up, HumanML3D Y up)."""

HEAD_TRIMS: tuple[tuple[str, int], ...] = (
    ("Eyes_Japan_Dataset", 3 * FPS),
    ("MPI_HDM05", 3 * FPS),
    ("TotalCapture", 1 * FPS),
    ("MPI_Limits", 1 * FPS),
    ("Transitions_mocap", int(0.5 * FPS)),
)
"""Frames (at 20 fps) dropped from the start of clips whose source path contains the dataset name."""

SMPLH_NUM_JOINTS = 52
_MODEL_KEYS = ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f")
_HAND_KEYS = ("hands_componentsl", "hands_componentsr", "hands_meanl", "hands_meanr")
_INDEX_COLUMNS = ("source_path", "start_frame", "end_frame", "new_name")


def swap_y_z(joints: np.ndarray) -> np.ndarray:
    """``joints @ SWAP_Y_Z``: the axis change of HumanML3D's ``amass_to_pose`` (a reflection on its own)."""
    return np.asarray(joints) @ SWAP_Y_Z.astype(np.asarray(joints).dtype)


def negate_x(joints: np.ndarray) -> np.ndarray:
    """A copy with x negated (the index step of HumanML3D; after the y/z swap it makes a proper rotation)."""
    out = np.array(joints, copy=True)
    out[..., 0] *= -1
    return out


def z_up_to_y_up(joints: np.ndarray) -> np.ndarray:
    """AMASS Z-up world to HumanML3D Y-up: swap y and z, then negate x, i.e. (x,y,z) -> (-x,z,y).

    A rotation (determinant +1), so left stays left. It is its own inverse.
    """
    return negate_x(swap_y_z(joints))


# ----------------------------------------------------------------------------------------------------------
# Body models


def body_model_candidates(body_models: str, gender: str) -> list[str]:
    """Files tried, in order, for the SMPL-H model of ``gender`` under the folder ``body_models``.

    AMASS/HumanML3D layout: ``<dir>/<gender>/model.npz`` (also under ``<dir>/smplh/``); smplx layout:
    ``<dir>/smplh/SMPLH_<GENDER>.{npz,pkl}`` or ``<dir>/SMPLH_<GENDER>.{npz,pkl}``.
    """
    d = Path(body_models)
    g = gender.lower()
    upper = gender.upper()
    return [
        str(d / g / "model.npz"),
        str(d / "smplh" / g / "model.npz"),
        str(d / "smplh" / f"SMPLH_{upper}.npz"),
        str(d / "smplh" / f"SMPLH_{upper}.pkl"),
        str(d / f"SMPLH_{upper}.npz"),
        str(d / f"SMPLH_{upper}.pkl"),
    ]


def missing_model_message(body_models: str, genders: tuple[str, ...] = ("male", "female")) -> str:
    """What files are expected where, for an error about a missing body model."""
    expected = [c for g in genders for c in body_model_candidates(body_models, g)]
    return (f"{body_models}: no SMPL-H body model for gender(s) {', '.join(genders)} (expected one of "
            f"{', '.join(expected)}; AMASS/HumanML3D layout: the MANO 'Extended SMPL+H model' unpacked as "
            "<dir>/{male,female}/model.npz; smplx layout: <dir>/smplh/SMPLH_{MALE,FEMALE}.pkl made by smplx's "
            "tools/merge_smplh_mano.py)")


def find_body_model(body_models: str, gender: str) -> str:
    """The first existing file of :func:`body_model_candidates`; ClipError listing them all when none exists."""
    for candidate in body_model_candidates(body_models, gender):
        if os.path.isfile(candidate):
            return candidate
    raise ClipError(missing_model_message(body_models, (gender,)))


def model_gender(value: Any) -> str:
    """'male' or 'female': the body model HumanML3D uses for an AMASS ``gender`` entry.

    Bytes and 0-d arrays are decoded first. Everything but 'male' (also 'neutral') gets the female model,
    as in the original. Note: the original compares the raw entry with 'male', so a *bytes* b'male' took
    the female model there; here it is decoded and takes the male model.
    """
    v = value.item() if isinstance(value, np.ndarray) else value
    if isinstance(v, bytes):
        v = v.decode("utf-8", errors="replace")
    return "male" if str(v).strip().lower() == "male" else "female"


def _read_npz_model(path: str) -> dict[str, Any]:
    """The model arrays of an ``.npz`` body model (only the needed keys); 0-d object entries are unwrapped.

    Pickled (object) entries go through :func:`lsgan.pickles.load_npz`'s allowlist, never ``allow_pickle``.
    """
    return {k: v.item() if v.dtype == object and v.ndim == 0 else v
            for k, v in load_npz(path, _MODEL_KEYS + _HAND_KEYS).items()}


def read_body_model_file(path: str) -> dict[str, Any]:
    """The arrays of an SMPL-H model file (``.npz`` or smplx's chumpy-free ``.pkl``), checked for SMPL-H shape.

    Pickles are read by :mod:`lsgan.pickles`, which rebuilds arrays and sparse matrices only and refuses
    any other global, so a model file cannot run code. Hand PCA entries missing from AMASS's model.npz
    are filled with identity/zeros; they are unused because the hand pose is taken as raw axis-angle
    (``use_pca=False, flat_hand_mean=True``).
    """
    try:
        data = load_pickle(path) if path.endswith(".pkl") else _read_npz_model(path)
    except PickleReadError as exc:
        raise ClipError(with_chumpy_advice(exc, "original MANO pickles hold chumpy objects: convert them with "
                                                "smplx's tools/merge_smplh_mano.py or use AMASS's model.npz")) from exc
    if not isinstance(data, dict):
        raise ClipError(f"{path} is not an SMPL-H model file: it holds a {type(data).__name__}, not a dict")
    missing = [k for k in _MODEL_KEYS if k not in data]
    if missing:
        raise ClipError(f"{path} is not an SMPL-H model file: missing {', '.join(missing)}")
    n_joints = np.shape(data["kintree_table"])[-1]
    if n_joints != SMPLH_NUM_JOINTS:
        raise ClipError(f"{path} is not an SMPL-H model: it has {n_joints} joints, SMPL-H has {SMPLH_NUM_JOINTS}")
    data.setdefault("hands_componentsl", np.eye(45, dtype=np.float32))
    data.setdefault("hands_componentsr", np.eye(45, dtype=np.float32))
    data.setdefault("hands_meanl", np.zeros(45, dtype=np.float32))
    data.setdefault("hands_meanr", np.zeros(45, dtype=np.float32))
    return data


@functools.lru_cache(maxsize=8)
def load_body_model(path: str, device: str = "cpu") -> Any:
    """An ``smplx.SMPLH`` for the model file ``path`` (10 betas, raw axis-angle hands), cached per process."""
    import smplx
    from smplx.utils import Struct

    data = read_body_model_file(path)
    with contextlib.redirect_stdout(io.StringIO()):  # smplx prints a note about the 16-beta AMASS shapedirs
        model = smplx.SMPLH(
            model_path=path, data_struct=Struct(**data), num_betas=10, use_pca=False, flat_hand_mean=True,
            batch_size=1,
        )
    return model.to(device).eval()


def smplh_joints(model: Any, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray,
                 batch_frames: int = 4096) -> np.ndarray:
    """Joints 0..21, (N,22,3) float32, of an SMPL-H model for (N,156) axis-angle poses and (N,3) translations.

    The same smplx.lbs steps as ``SMPLH.forward`` for its ``joints`` output (shape blend, joint regressor,
    Rodrigues, rigid chain, + transl) without skinning the mesh, which would cost a (frames, 6890, 4, 4)
    tensor. Frames are processed ``batch_frames`` at a time.
    """
    import torch
    from smplx.lbs import batch_rigid_transform, batch_rodrigues, blend_shapes, vertices2joints

    dtype = model.shapedirs.dtype
    device = model.shapedirs.device
    poses = np.asarray(poses, dtype=np.float32)
    trans = np.asarray(trans, dtype=np.float32)
    shape = np.zeros(model.num_betas, dtype=np.float32)
    b = np.asarray(betas, dtype=np.float32).reshape(-1)[: model.num_betas]
    shape[: len(b)] = b
    out = np.empty((len(poses), NUM_JOINTS, 3), dtype=np.float32)
    with torch.no_grad():
        betas_t = torch.as_tensor(shape, dtype=dtype, device=device)[None]
        v_shaped = model.v_template[None] + blend_shapes(betas_t, model.shapedirs)
        rest = vertices2joints(model.J_regressor, v_shaped)
        for s in range(0, len(poses), max(1, batch_frames)):
            full_pose = torch.as_tensor(poses[s:s + batch_frames], dtype=dtype, device=device) + model.pose_mean
            n = full_pose.shape[0]
            rot_mats = batch_rodrigues(full_pose.reshape(-1, 3)).reshape(n, -1, 3, 3)
            posed, _ = batch_rigid_transform(rot_mats, rest.expand(n, -1, -1).contiguous(), model.parents, dtype=dtype)
            posed = posed + torch.as_tensor(trans[s:s + batch_frames], dtype=dtype, device=device)[:, None]
            out[s:s + n] = posed[:, :NUM_JOINTS].cpu().numpy()
    return out


_MOTION_KEYS = ("mocap_framerate", "trans", "poses", "betas", "gender", "mocap_frame_rate")


def _read_motion(path: str) -> dict[str, np.ndarray]:
    """The entries of an AMASS motion file that the import reads, each header checked before it is allocated."""
    try:
        data = load_npz(path, _MOTION_KEYS)
    except PickleReadError as exc:
        raise ClipError(str(exc)) from None
    for key, value in data.items():
        if value.dtype.hasobject:
            raise ClipError(f"{path}: entry {key!r} holds pickled objects, not numbers")
    return data


def amass_pose_data(path: str, body_models: str, device: str = "cpu", batch_frames: int = 4096) -> np.ndarray:
    """HumanML3D's ``pose_data`` for one AMASS file: (T,22,3) float32 at 20 fps, y/z swapped, x NOT negated.

    ClipError for files without ``mocap_framerate`` or ``trans`` (e.g. the shape-only ``shape.npz``).
    """
    npz = _read_motion(path)
    if "mocap_framerate" not in npz:
        hint = " (it has 'mocap_frame_rate': SMPL-X G release; HumanML3D uses SMPL+H G)" \
            if "mocap_frame_rate" in npz else " (a shape-only file?)"
        raise ClipError(f"{path}: no 'mocap_framerate'{hint}; skipped as in HumanML3D")
    if "trans" not in npz:
        raise ClipError(f"{path}: no 'trans' (a shape-only file?); skipped as in HumanML3D")
    for key in ("poses", "betas", "gender"):
        if key not in npz:
            raise ClipError(f"{path}: no {key!r}")
    fps, trans, poses, betas = float(npz["mocap_framerate"]), npz["trans"], npz["poses"], npz["betas"]
    gender = model_gender(npz["gender"])
    stride = int(fps / FPS)
    if stride < 1:
        raise ClipError(f"{path}: mocap_framerate {fps} is below {FPS} fps")
    n = trans.shape[0]
    if poses.ndim != 2 or poses.shape[1] != 156 or poses.shape[0] < n or trans.shape[1:] != (3,):
        raise ClipError(f"{path}: poses {poses.shape} / trans {trans.shape} are not SMPL+H (N,156) / (N,3)")
    model = load_body_model(find_body_model(body_models, gender), device)
    joints = smplh_joints(model, poses[:n:stride], trans[::stride], betas, batch_frames)
    return swap_y_z(joints)


def joints_file(path: str) -> np.ndarray:
    """A ready joint file of HumanML3D's ``pose_data`` (T,>=22,3) ``.npy`` (e.g. its humanact12.zip): joints 0..21."""
    try:
        data = load_npy(path)
    except PickleReadError as exc:
        raise ClipError(str(exc)) from None
    if data.ndim != 3 or data.shape[1] < NUM_JOINTS or data.shape[2] != 3:
        raise ClipError(f"{path}: shape {data.shape}, expected (T,>=22,3) joints")
    return np.ascontiguousarray(data[:, :NUM_JOINTS], dtype=np.float32)


# ----------------------------------------------------------------------------------------------------------
# HumanML3D's index.csv


@dataclass(frozen=True)
class IndexRow:
    """One row of HumanML3D's index.csv. ``source`` is the path after 'pose_data/' as written there."""

    source_path: str
    start_frame: int
    end_frame: int
    new_name: str

    @property
    def source(self) -> str:
        p = self.source_path.replace("\\", "/")
        marker = "pose_data/"
        if marker in p:
            return p.split(marker, 1)[1]
        return p[2:] if p.startswith("./") else p.lstrip("/")

    @property
    def item(self) -> str:
        """The AMASS file of this row, relative to the AMASS folder: ``source`` with '.npy' -> '.npz'."""
        s = self.source
        return s[:-4] + ".npz" if s.endswith(".npy") else s

    @property
    def name(self) -> str:
        return Path(self.new_name).stem

    @property
    def is_humanact12(self) -> bool:
        return "humanact12" in self.source_path


def read_index(path: str) -> list[IndexRow]:
    """The rows of an index.csv (columns source_path,start_frame,end_frame,new_name), in file order."""
    return list(_read_index_cached(path, os.stat(path).st_mtime_ns))


@functools.lru_cache(maxsize=4)
def _read_index_cached(path: str, mtime_ns: int) -> tuple[IndexRow, ...]:
    rows = []
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in _INDEX_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: missing column(s) {', '.join(missing)}; expected {','.join(_INDEX_COLUMNS)}")
        for line, rec in enumerate(reader, start=2):
            try:
                rows.append(IndexRow(rec["source_path"].strip(), int(rec["start_frame"]), int(rec["end_frame"]),
                                     rec["new_name"].strip()))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{path}:{line}: bad row {rec}: {exc}") from exc
    return tuple(rows)


def apply_index_row(pose_data: np.ndarray, row: IndexRow) -> np.ndarray:
    """HumanML3D's per-row step: head trim by dataset, ``[start_frame:end_frame]``, negate x; humanact12 rows whole."""
    data = np.array(pose_data, copy=True)
    if row.is_humanact12:
        return data
    for dataset, frames in HEAD_TRIMS:
        if dataset in row.source_path:
            data = data[frames:]
    data = data[row.start_frame:row.end_frame]
    data[..., 0] *= -1
    return data


# ----------------------------------------------------------------------------------------------------------
# The source


@dataclass
class AmassSource:
    """AMASS ``.npz`` files (SMPL+H G) with an SMPL-H body-model folder, optionally cut by HumanML3D's index.csv.

    Work items are the paths of the files to read (``root`` joined with their relative path), sorted.
    Without ``index_csv``: every ``*.npz`` under ``root``, one clip each named by its relative path
    ('/' -> '__', no extension), whole and in HumanML3D axes (swap y/z, negate x). With it: the files
    the index names, one clip per row named ``new_name`` without extension. A row's file may also be a
    ready ``pose_data`` joint ``.npy`` beside where the ``.npz`` would be (as HumanML3D ships for
    humanact12); it is used as is.
    """

    root: str
    body_models: str
    index_csv: str | None = None
    mirror: bool = True
    device: str = "cpu"
    batch_frames: int = 4096
    name: ClassVar[str] = "amass"

    def scan(self) -> list[str]:
        """Sorted paths of the AMASS files to read; ValueError for a missing folder, index or body model."""
        if not os.path.isdir(self.root):
            raise ValueError(f"AMASS folder {self.root!r} does not exist")
        if not any(os.path.isfile(c) for g in ("male", "female") for c in body_model_candidates(self.body_models, g)):
            raise ValueError(missing_model_message(self.body_models))
        if self.index_csv is not None:
            if not os.path.isfile(self.index_csv):
                raise ValueError(f"index file {self.index_csv!r} does not exist")
            return [self._resolve(rel) for rel in sorted({row.item for row in read_index(self.index_csv)})]
        found = []
        for dirpath, dirnames, filenames in os.walk(self.root):
            dirnames.sort()
            found += [os.path.relpath(os.path.join(dirpath, f), self.root) for f in filenames if f.endswith(".npz")]
        return [os.path.join(self.root, rel) for rel in sorted(Path(p).as_posix() for p in found)]

    def load(self, item: str) -> list[RawClip]:
        """The clips of one AMASS file (ClipError if it is missing, unreadable or has no motion)."""
        rel = Path(os.path.relpath(item, self.root)).as_posix()
        if self.index_csv is None:
            joints = negate_x(self._pose_data(item))
            name = rel[:-4] if rel.endswith(".npz") else rel
            return [RawClip(name=name.replace("/", "__"), source_file=item, joints=joints, mirror=self.mirror)]
        key = rel[:-4] + ".npz" if rel.endswith(".npy") else rel
        rows = [row for row in read_index(self.index_csv) if row.item == key]
        if not rows:
            raise ClipError(f"{item} is not referenced by {self.index_csv}")
        if not os.path.isfile(item):
            names = ", ".join(row.name for row in rows)
            raise ClipError(f"missing source file {item} (nor its .npy) for index row(s) {names} of {self.index_csv}")
        pose_data = joints_file(item) if item.endswith(".npy") else self._pose_data(item)
        clips, empty = [], []
        for row in rows:
            joints = apply_index_row(pose_data, row)
            if len(joints) == 0:
                empty.append(row.name)
                continue
            clips.append(RawClip(name=row.name, source_file=item, joints=np.ascontiguousarray(joints, np.float32),
                                 mirror=self.mirror))
        if not clips:
            raise ClipError(f"no index row keeps any frame of its {len(pose_data)} frames at 20 fps")
        if empty:
            logger.warning("%s: index row(s) %s keep no frame of its %d at 20 fps; skipped",
                           item, ", ".join(empty), len(pose_data))
        return clips

    def inputs(self) -> list[str]:
        """The index.csv, when given."""
        return [self.index_csv] if self.index_csv is not None else []

    def _pose_data(self, path: str) -> np.ndarray:
        if not os.path.isfile(path):
            raise ClipError(f"missing AMASS file {path}")
        return amass_pose_data(path, self.body_models, self.device, self.batch_frames)

    def _resolve(self, rel: str) -> str:
        """The file for an index entry: the AMASS ``.npz``, else a ready ``.npy``, else the (missing) ``.npz``."""
        npz = os.path.join(self.root, rel)
        npy = npz[:-4] + ".npy" if npz.endswith(".npz") else npz + ".npy"
        return npy if not os.path.isfile(npz) and os.path.isfile(npy) else npz
