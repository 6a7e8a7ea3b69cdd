"""HumanAct12 route: clip count, action labels, the first 22 of 24 joints, and the up-axis option."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

from lsgan.data.clip import ClipError
from lsgan.data.skeleton import PARENTS, TARGET_OFFSETS
from lsgan.data.sources.amass import z_up_to_y_up
from lsgan.data.sources.humanact12 import ACTIONS, HumanAct12Source, detect_up_axis

LABELS = [0, 5, 11]


def y_up_clip(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n,24,3) joints of a standing Y-up body drifting around: SMPL's 22 joints plus two hand joints."""
    rest = np.zeros((22, 3))
    rest[0] = (0.0, 0.95, 0.0)
    for j in range(1, 22):
        rest[j] = rest[PARENTS[j]] + TARGET_OFFSETS[j]
    rest = np.concatenate([rest, rest[[20, 21]] + (0.0, -0.08, 0.0)])
    return (rest[None] + rng.normal(0, 0.02, (n, 24, 3)) + np.cumsum(rng.normal(0, 0.01, (n, 1, 3)), 0)).astype(
        np.float32)


@pytest.fixture()
def pkl_dir(tmp_path):
    rng = np.random.default_rng(0)
    lengths = [30, 45, 20]
    data = {
        "poses": [rng.normal(0, 0.2, (n, 72)).astype(np.float32) for n in lengths],
        "joints3D": [y_up_clip(rng, n) for n in lengths],
        "y": LABELS,
    }
    folder = tmp_path / "HumanAct12Poses"
    folder.mkdir()
    with open(folder / "humanact12poses.pkl", "wb") as fh:
        pickle.dump(data, fh)
    return folder, data


def test_clips_labels_and_joints(pkl_dir):
    folder, data = pkl_dir
    src = HumanAct12Source(str(folder))
    items = src.scan()
    assert len(items) == 3 and items == sorted(items)
    assert src.inputs() == [str(folder / "humanact12poses.pkl")]
    for i, item in enumerate(items):
        (clip,) = src.load(item)
        assert clip.name == f"humanact12_{i:04d}"
        assert clip.action == ACTIONS[LABELS[i]]
        assert clip.mirror is False and clip.captions == []
        assert clip.joints.dtype == np.float32 and clip.joints.shape == (len(data["joints3D"][i]), 22, 3)
        np.testing.assert_array_equal(clip.joints, data["joints3D"][i][:, :22])
        assert detect_up_axis(clip.joints) == "y"
    assert [src.load(it)[0].action for it in items] == ["warm_up", "lift_dumbbell", "throw"]
    assert len(ACTIONS) == 12


def test_file_path_and_mirror_option(pkl_dir):
    folder, _ = pkl_dir
    src = HumanAct12Source(str(folder / "humanact12poses.pkl"), mirror=True)
    (clip,) = src.load(src.scan()[1])
    assert clip.mirror is True and clip.name == "humanact12_0001"
    assert HumanAct12Source(str(folder.parent)).scan() == src.scan()


def test_up_axis_z(tmp_path):
    """A Z-up copy loaded with up_axis='z' comes back Y up and equal to the Y-up original."""
    rng = np.random.default_rng(1)
    y_up = y_up_clip(rng, 25)
    z_up = z_up_to_y_up(y_up)  # the change is its own inverse
    assert detect_up_axis(z_up) == "z"
    path = tmp_path / "humanact12poses.pkl"
    with open(path, "wb") as fh:
        pickle.dump({"poses": [np.zeros((25, 72))], "joints3D": [z_up], "y": [2]}, fh)
    (clip,) = HumanAct12Source(str(path), up_axis="z").load(f"{path}#0000")
    np.testing.assert_allclose(clip.joints, y_up[:, :22], atol=1e-6)
    assert detect_up_axis(clip.joints) == "y" and clip.action == "run"
    (as_stored,) = HumanAct12Source(str(path)).load(f"{path}#0000")
    assert detect_up_axis(as_stored.joints) == "z"


def test_detect_up_axis_sign():
    rng = np.random.default_rng(2)
    clip = y_up_clip(rng, 10)
    flipped = clip.copy()
    flipped[..., 1] *= -1
    assert detect_up_axis(clip) == "y" and detect_up_axis(flipped) == "-y"
    assert detect_up_axis(clip[0]) == "y"


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="humanact12poses.pkl"):
        HumanAct12Source(str(tmp_path)).scan()
    with pytest.raises(ValueError, match="up_axis"):
        HumanAct12Source(str(tmp_path), up_axis="x")
    path = tmp_path / "humanact12poses.pkl"
    with open(path, "wb") as fh:
        pickle.dump({"poses": [np.zeros((5, 72))] * 2, "joints3D": [np.zeros((5, 24, 3)), np.zeros((5, 10, 3))],
                     "y": [12, 1]}, fh)
    src = HumanAct12Source(str(path))
    first, second = src.scan()
    with pytest.raises(ClipError, match="action id 12"):
        src.load(first)
    with pytest.raises(ClipError, match="shape"):
        src.load(second)
