"""`lsgan preprocess --source bvh` on real Bandai-Namco and CMU files, through the whole pipeline."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from lsgan.data.features import recover_from_ric
from lsgan.data.preprocess import preprocess
from lsgan.data.shards import Shard
from lsgan.data.sources.bvh import BvhSource

TAKES = ["raise-up-left-hand_normal_001", "raise-up-right-hand_active_002", "walk_normal_001",
         "walk-turn-left_elderly_001", "wave-left-hand_youthful_001", "run_masculine_001"]


@pytest.fixture(scope="module")
def bandai_subset(bandai_dir, tmp_path_factory) -> Path:
    """A few real clips with the dataset's cfg/ and labels, plus a file on another skeleton."""
    root = tmp_path_factory.mktemp("bandai")
    shutil.copytree(bandai_dir / "cfg", root / "cfg")
    (root / "data").mkdir()
    for take in TAKES:
        for ext in (".bvh.gz", ".json"):
            shutil.copy(bandai_dir / "data" / f"dataset-2_{take}{ext}", root / "data")
    return root


@pytest.fixture(scope="module")
def shard(bandai_subset, cmu_dir, tmp_path_factory):
    shutil.copy(cmu_dir / "131_01.bvh", bandai_subset / "data" / "cmu_131_01.bvh")  # unmapped for the bandai preset
    out = tmp_path_factory.mktemp("out") / "bandai.h5"
    result = preprocess(BvhSource(root=str(bandai_subset), preset="bandai"), out, workers=2, chunk_size=2)
    (bandai_subset / "data" / "cmu_131_01.bvh").unlink()
    with Shard(out) as s:
        yield s, result


def test_every_clip_and_its_mirror_arrive(shard):
    s, result = shard
    assert len(s) == 2 * len(TAKES)
    assert result.mirrored == len(TAKES)
    (skip,) = result.skipped
    assert "cmu_131_01.bvh" in skip.item and "unmapped skeleton" in skip.reason


def test_mirrors_swap_labels_captions_and_sides(shard):
    s, _ = shard
    i = s.names.index("dataset-2_raise-up-left-hand_normal_001")
    m = s.names.index("Mdataset-2_raise-up-left-hand_normal_001")
    assert s.action(i) == "raise-up-left-hand" and s.action(m) == "raise-up-right-hand"
    assert all("left" in c.text for c in s.captions(i)) and all("right" in c.text for c in s.captions(m))
    assert s.splits[i] == s.splits[m]
    for idx, up, down in ((i, 20, 21), (m, 21, 20)):
        j = recover_from_ric(s.features(idx))
        assert (j[:, up, 1] - j[:, 15, 1]).max() > 0.0  # that wrist goes above the head
        assert (j[:, down, 1] < j[:, down - 4, 1]).all()  # the other stays below its shoulder


def test_walking_moves_forward_and_feet_touch_the_floor(shard):
    s, _ = shard
    for name in ("dataset-2_walk_normal_001", "dataset-2_run_masculine_001"):
        x = s.features(s.names.index(name))
        assert x[:, 2].mean() > 0.02  # forward root velocity (metres per frame, body frame)
        j = recover_from_ric(x)
        feet = j[:, [7, 8, 10, 11], 1].min(axis=1)
        assert np.median(feet) < 0.08 and j[..., 1].min() > -0.02
        assert x[:, 259:263].mean() > 0.15  # foot contacts are detected


def test_labels_are_the_contents(shard):
    s, _ = shard
    assert set(s.action_names) >= {"raise-up-left-hand", "raise-up-right-hand", "walk", "run", "wave-right-hand"}
    assert s.source == "bvh" and s.fps == 20
