"""AMASS route: joints equal smplx's SMPL-H output after HumanML3D's stride, axis change and index trims.

The real body models are licensed and never shipped, so a small SMPL-H-shaped model (same keys and
shapes, ~300 vertices, a T-pose skeleton regressed from vertices placed at the joints) is written here.
"""
from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse
import smplx
import torch

from lsgan.data.clip import ClipError
from lsgan.data.skeleton import TARGET_OFFSETS
from lsgan.data.sources.amass import (
    AmassSource,
    apply_index_row,
    body_model_candidates,
    find_body_model,
    model_gender,
    read_index,
    z_up_to_y_up,
)
from lsgan.data.sources.humanact12 import detect_up_axis

# SMPL-H parents: the 22 body joints of SMPL, then 15 left-hand joints (from wrist 20), 15 right (from 21).
SMPLH_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]
for _wrist, _first in ((20, 22), (21, 37)):
    for _finger in range(5):
        _base = _first + 3 * _finger
        SMPLH_PARENTS += [_wrist, _base, _base + 1]
VERTS_PER_JOINT = 5
EXTRA_VERTS = 40
ATOL = 1e-4  # metres; float32 runs agree to ~1e-7, the margin covers other BLAS paths, not logic (>1e-2)
ORACLE_VERTEX_IDS = {"nose": 0, "reye": 1, "leye": 2, "rear": 3, "lear": 4}


def rest_joints() -> np.ndarray:
    """A T-pose of the 52 SMPL-H joints (SMPL model frame: Y up, +x the body's left), in metres."""
    offsets = np.zeros((52, 3))
    offsets[:22] = TARGET_OFFSETS
    for side, first in ((1.0, 22), (-1.0, 37)):
        for finger in range(5):
            for k in range(3):
                spread = 0.02 * (finger - 2) if k == 0 else 0.0
                offsets[first + 3 * finger + k] = (side * (0.08 if k == 0 else 0.03), 0.0, spread)
    joints = np.zeros((52, 3))
    joints[0] = (0.0, 0.9, 0.0)
    for j in range(1, 52):
        joints[j] = joints[SMPLH_PARENTS[j]] + offsets[j]
    return joints


def make_model(rng: np.random.Generator, scale: float) -> dict:
    """Arrays of a small SMPL-H model with the real file's keys and shapes (V vertices, 52 joints, 16 betas)."""
    joints = rest_joints() * scale
    n_v = 52 * VERTS_PER_JOINT + EXTRA_VERTS
    v = np.concatenate([
        np.repeat(joints, VERTS_PER_JOINT, axis=0) + rng.normal(0, 0.02, (52 * VERTS_PER_JOINT, 3)),
        rng.uniform(-0.5, 0.5, (EXTRA_VERTS, 3)) + (0, 1, 0),
    ])
    j_reg = np.zeros((52, n_v))
    for j in range(52):
        j_reg[j, j * VERTS_PER_JOINT:(j + 1) * VERTS_PER_JOINT] = 1.0 / VERTS_PER_JOINT
    weights = rng.dirichlet(np.ones(4), n_v)
    full_weights = np.zeros((n_v, 52))
    for i in range(n_v):
        owner = min(i // VERTS_PER_JOINT, 51)
        full_weights[i, [owner, SMPLH_PARENTS[owner] if owner else 0, 0, 3]] += weights[i]
    kintree = np.array([[4294967295] + SMPLH_PARENTS[1:], list(range(52))], dtype=np.int64)
    return {
        "v_template": v,
        "shapedirs": rng.normal(0, 0.01, (n_v, 3, 16)),
        "posedirs": rng.normal(0, 0.001, (n_v, 3, 51 * 9)),
        "J_regressor": j_reg,
        "weights": full_weights,
        "kintree_table": kintree,
        "f": rng.integers(0, n_v, (200, 3)).astype(np.uint32),
        "hands_componentsl": np.linalg.qr(rng.normal(size=(45, 45)))[0],
        "hands_componentsr": np.linalg.qr(rng.normal(size=(45, 45)))[0],
        "hands_meanl": rng.normal(0, 0.1, 45),
        "hands_meanr": rng.normal(0, 0.1, 45),
    }


@pytest.fixture(scope="session")
def models(tmp_path_factory) -> dict[str, Path]:
    """The same two models (male, female) in the AMASS layout (dense, no hand PCA) and the smplx layout (pkl)."""
    base = tmp_path_factory.mktemp("body_models")
    rng = np.random.default_rng(0)
    arrays = {"male": make_model(rng, 1.0), "female": make_model(rng, 0.9)}
    amass_dir, smplx_dir, flat_dir = base / "amass", base / "smplx", base / "flat"
    for gender, data in arrays.items():
        (amass_dir / gender).mkdir(parents=True)
        np.savez(amass_dir / gender / "model.npz", **{k: v for k, v in data.items() if not k.startswith("hands_")})
        (smplx_dir / "smplh").mkdir(parents=True, exist_ok=True)
        sparse = dict(data, J_regressor=scipy.sparse.csc_matrix(data["J_regressor"]))
        with open(smplx_dir / "smplh" / f"SMPLH_{gender.upper()}.pkl", "wb") as fh:
            pickle.dump(sparse, fh)
        flat_dir.mkdir(exist_ok=True)
        with open(flat_dir / f"SMPLH_{gender.upper()}.pkl", "wb") as fh:
            pickle.dump(sparse, fh)
    (amass_dir / "neutral").mkdir()
    np.savez(amass_dir / "neutral" / "model.npz", **make_model(rng, 0.95))
    return {"amass": amass_dir, "smplx": smplx_dir, "flat": flat_dir}


def oracle_joints(models: dict[str, Path], gender: str, poses: np.ndarray, trans: np.ndarray,
                  betas: np.ndarray) -> np.ndarray:
    """smplx itself, called the documented way: joints 0..21, then y and z swapped (no x negation)."""
    n = len(poses)
    bm = smplx.create(str(models["smplx"]), model_type="smplh", gender=gender, ext="pkl", use_pca=False,
                      flat_hand_mean=True, num_betas=10, batch_size=n, vertex_ids=ORACLE_VERTEX_IDS,
                      use_feet_keypoints=False, use_hands=False)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    with torch.no_grad():
        out = bm(global_orient=t(poses[:, :3]), body_pose=t(poses[:, 3:66]), left_hand_pose=t(poses[:, 66:111]),
                 right_hand_pose=t(poses[:, 111:156]), betas=t(np.repeat(betas[None, :10], n, 0)), transl=t(trans))
    j = out.joints[:, :22].numpy()
    return j @ np.array([[1, 0, 0], [0, 0, 1], [0, 1, 0]], dtype=np.float32)


def motion(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """AMASS-like (n,156) poses (Z-up root orientation plus noise) and a wandering (n,3) translation."""
    poses = rng.normal(0, 0.25, (n, 156))
    poses[:, :3] = np.array([np.pi / 2, 0, 0]) + rng.normal(0, 0.1, (n, 3))
    trans = np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0) + (0, 0, 0.9)
    return poses, trans


FILES = {  # relative path: (frames, fps, gender)
    "KIT/3/walk_poses.npz": (120, 60.0, b"male"),
    "MPI_HDM05/bk/run_poses.npz": (300, 60.0, "female"),
    "Transitions_mocap/mazen/t_poses.npz": (300, 120.0, "neutral"),
    "ACCAD/s1/fast_poses.npz": (100, 120.0, np.array("male")),
    "humanact12/humanact12/P01.npz": (60, 60.0, "male"),
}
INDEX = """source_path,start_frame,end_frame,new_name
./pose_data/KIT/3/walk_poses.npy,0,30,000001.npy
./pose_data/KIT/3/walk_poses.npy,10,40,000002.npy
./pose_data/MPI_HDM05/bk/run_poses.npy,5,30,000003.npy
./pose_data/Transitions_mocap/mazen/t_poses.npy,0,35,000004.npy
./pose_data/humanact12/humanact12/P01.npy,0,-1,000005.npy
./pose_data/humanact12/humanact12/P02.npy,0,-1,000006.npy
./pose_data/CMU/01/missing_poses.npy,0,20,000007.npy
./pose_data/ACCAD/s1/fast_poses.npy,100,120,000008.npy
"""


@pytest.fixture(scope="session")
def amass(tmp_path_factory) -> dict:
    """An AMASS-style folder (plus a shape-only file and a ready humanact12 joint .npy) and an index.csv."""
    root = tmp_path_factory.mktemp("amass")
    rng = np.random.default_rng(1)
    params = {}
    for rel, (n, fps, gender) in FILES.items():
        poses, trans = motion(rng, n)
        betas = rng.normal(0, 1, 16)
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        np.savez(root / rel, poses=poses, trans=trans, betas=betas, gender=gender, mocap_framerate=np.array(fps),
                 dmpls=np.zeros((n, 8)))
        params[rel] = (poses, trans, betas, fps, gender)
    np.savez(root / "KIT/3/shape.npz", betas=rng.normal(0, 1, 16), gender="male")
    ha12 = rng.normal(0, 1, (25, 24, 3)).astype(np.float32)
    np.save(root / "humanact12/humanact12/P02.npy", ha12)
    index = root.parent / "index.csv"
    index.write_text(INDEX)
    return {"root": root, "params": params, "index": index, "ha12": ha12}


def at(amass: dict, rel: str) -> str:
    """The work item (file path) of a file of the test AMASS folder."""
    return str(amass["root"] / rel)


def expected_pose_data(models: dict[str, Path], amass: dict, rel: str) -> np.ndarray:
    """HumanML3D's pose_data for one file, computed by hand: stride, smplx, swap y/z."""
    poses, trans, betas, fps, gender = amass["params"][rel]
    stride = int(fps / 20)
    g = "male" if np.asarray(gender).item() in (b"male", "male") else "female"
    return oracle_joints(models, g, poses[::stride], trans[::stride], betas)


def negx(a: np.ndarray) -> np.ndarray:
    out = a.copy()
    out[..., 0] *= -1
    return out


@pytest.mark.parametrize("layout", ["amass", "smplx"])
def test_whole_files_match_smplx(models, amass, layout):
    src = AmassSource(str(amass["root"]), str(models[layout]))
    items = src.scan()
    assert items == sorted(items)
    assert items == [str(amass["root"] / rel) for rel in [
        "ACCAD/s1/fast_poses.npz", "KIT/3/shape.npz", "KIT/3/walk_poses.npz", "MPI_HDM05/bk/run_poses.npz",
        "Transitions_mocap/mazen/t_poses.npz", "humanact12/humanact12/P01.npz",
    ]]
    for rel in FILES:
        (clip,) = src.load(str(amass["root"] / rel))
        assert clip.name == rel[:-4].replace("/", "__")
        assert clip.mirror is True and clip.captions == [] and clip.source_file == str(amass["root"] / rel)
        assert clip.joints.dtype == np.float32 and clip.joints.shape[1:] == (22, 3)
        np.testing.assert_allclose(clip.joints, negx(expected_pose_data(models, amass, rel)), atol=ATOL)
        assert detect_up_axis(clip.joints) == "y"


def test_stride_and_gender(models, amass):
    src = AmassSource(str(amass["root"]), str(models["amass"]))
    lengths = {rel: len(src.load(at(amass, rel))[0].joints) for rel in FILES}
    assert lengths["KIT/3/walk_poses.npz"] == 40  # 120 frames at 60 fps, stride 3
    assert lengths["ACCAD/s1/fast_poses.npz"] == 17  # 100 frames at 120 fps, stride 6
    assert lengths["Transitions_mocap/mazen/t_poses.npz"] == 50
    assert model_gender(b"male") == model_gender(np.array("male")) == model_gender(np.array(b"male")) == "male"
    assert model_gender("neutral") == model_gender("female") == model_gender(b"female") == "female"
    poses, trans, betas, _, _ = amass["params"]["KIT/3/walk_poses.npz"]
    female = oracle_joints(models, "female", poses[::3], trans[::3], betas)
    assert not np.allclose(src.load(at(amass, "KIT/3/walk_poses.npz"))[0].joints, negx(female), atol=1e-3)


def test_chunking_and_mirror_flag(models, amass):
    rel = "MPI_HDM05/bk/run_poses.npz"
    whole = AmassSource(str(amass["root"]), str(models["amass"])).load(at(amass, rel))[0]
    chunked_src = AmassSource(str(amass["root"]), str(models["amass"]), batch_frames=7, mirror=False)
    chunked = chunked_src.load(at(amass, rel))[0]
    np.testing.assert_allclose(chunked.joints, whole.joints, atol=1e-6)
    assert chunked.mirror is False


def test_shape_only_file_is_skipped_with_reason(models, amass):
    src = AmassSource(str(amass["root"]), str(models["amass"]))
    with pytest.raises(ClipError, match="mocap_framerate"):
        src.load(at(amass, "KIT/3/shape.npz"))


def test_index_trims(models, amass):
    src = AmassSource(str(amass["root"]), str(models["smplx"]), index_csv=str(amass["index"]))
    assert src.inputs() == [str(amass["index"])]
    assert src.scan() == [at(amass, rel) for rel in [
        "ACCAD/s1/fast_poses.npz", "CMU/01/missing_poses.npz", "KIT/3/walk_poses.npz", "MPI_HDM05/bk/run_poses.npz",
        "Transitions_mocap/mazen/t_poses.npz", "humanact12/humanact12/P01.npz", "humanact12/humanact12/P02.npy",
    ]]
    kit = expected_pose_data(models, amass, "KIT/3/walk_poses.npz")
    clips = src.load(at(amass, "KIT/3/walk_poses.npz"))
    assert [c.name for c in clips] == ["000001", "000002"]
    np.testing.assert_allclose(clips[0].joints, negx(kit[0:30]), atol=ATOL)
    np.testing.assert_allclose(clips[1].joints, negx(kit[10:40]), atol=ATOL)

    hdm = expected_pose_data(models, amass, "MPI_HDM05/bk/run_poses.npz")  # 100 frames; 3 s head = 60 frames
    (clip,) = src.load(at(amass, "MPI_HDM05/bk/run_poses.npz"))
    assert clip.name == "000003" and len(clip.joints) == 25
    np.testing.assert_allclose(clip.joints, negx(hdm[60:][5:30]), atol=ATOL)

    tr = expected_pose_data(models, amass, "Transitions_mocap/mazen/t_poses.npz")  # 0.5 s head = 10 frames
    (clip,) = src.load(at(amass, "Transitions_mocap/mazen/t_poses.npz"))
    assert len(clip.joints) == 35
    np.testing.assert_allclose(clip.joints, negx(tr[10:45]), atol=ATOL)


def test_index_humanact12_rows_are_whole_and_not_negated(models, amass):
    src = AmassSource(str(amass["root"]), str(models["amass"]), index_csv=str(amass["index"]))
    (clip,) = src.load(at(amass, "humanact12/humanact12/P01.npz"))
    assert clip.name == "000005"
    np.testing.assert_allclose(clip.joints, expected_pose_data(models, amass, "humanact12/humanact12/P01.npz"),
                               atol=ATOL)
    (clip,) = src.load(at(amass, "humanact12/humanact12/P02.npy"))  # a ready joint file, as in HumanML3D's zip
    assert clip.name == "000006" and clip.source_file.endswith("P02.npy")
    np.testing.assert_array_equal(clip.joints, amass["ha12"][:, :22])


def test_index_missing_source_and_empty_rows(models, amass):
    src = AmassSource(str(amass["root"]), str(models["amass"]), index_csv=str(amass["index"]))
    with pytest.raises(ClipError, match=r"missing_poses\.npz.*000007"):
        src.load(at(amass, "CMU/01/missing_poses.npz"))
    with pytest.raises(ClipError, match="no index row keeps any frame"):
        src.load(at(amass, "ACCAD/s1/fast_poses.npz"))  # 17 frames; [100:120] is empty


def test_apply_index_row_head_trims(tmp_path):
    data = np.arange(200, dtype=np.float32).reshape(200, 1, 1).repeat(3, axis=2)
    for dataset, head in [("Eyes_Japan_Dataset", 60), ("MPI_HDM05", 60), ("TotalCapture", 20), ("MPI_Limits", 20),
                          ("Transitions_mocap", 10), ("KIT", 0)]:
        path = tmp_path / f"{dataset}.csv"
        path.write_text(f"source_path,start_frame,end_frame,new_name\n./pose_data/{dataset}/a/b.npy,3,9,x.npy\n")
        (row,) = read_index(str(path))
        out = apply_index_row(data, row)
        np.testing.assert_array_equal(out[:, 0, 1], np.arange(head + 3, head + 9))
        np.testing.assert_array_equal(out[:, 0, 0], -out[:, 0, 1])


def test_missing_model_lists_expected_files(models, amass, tmp_path):
    wrong = tmp_path / "nowhere"
    src = AmassSource(str(amass["root"]), str(wrong))
    with pytest.raises(ValueError) as err:
        src.scan()
    for expected in [wrong / "male" / "model.npz", wrong / "smplh" / "SMPLH_FEMALE.pkl", wrong / "SMPLH_MALE.pkl"]:
        assert str(expected) in str(err.value)
    with pytest.raises(ClipError) as err:
        src.load(at(amass, "KIT/3/walk_poses.npz"))
    assert str(wrong / "male" / "model.npz") in str(err.value)
    assert str(wrong / "smplh" / "SMPLH_MALE.npz") in str(err.value)


def test_model_layouts_resolve(models):
    assert find_body_model(str(models["amass"]), "female") == str(models["amass"] / "female" / "model.npz")
    assert find_body_model(str(models["smplx"]), "male") == str(models["smplx"] / "smplh" / "SMPLH_MALE.pkl")
    assert find_body_model(str(models["flat"]), "male") == str(models["flat"] / "SMPLH_MALE.pkl")
    assert body_model_candidates("/m", "male")[0] == "/m/male/model.npz"


def test_z_up_to_y_up_is_a_rotation():
    m = z_up_to_y_up(np.eye(3, dtype=np.float32))
    assert np.isclose(np.linalg.det(m), 1.0)
    np.testing.assert_array_equal(z_up_to_y_up(np.array([1.0, 2.0, 3.0])), [-1.0, 3.0, 2.0])
