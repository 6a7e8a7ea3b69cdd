"""The training Dataset: HumanML3D windows, length bounds as options, normalisation, bucketing."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from lsgan.data.clip import Caption
from lsgan.data.dataset import LengthBucketSampler, MotionDataset, collate
from lsgan.data.shards import ClipRecord, Shard, write_shard


@pytest.fixture()
def shard_path(tmp_path):
    rng = np.random.default_rng(0)
    clips = []
    for i, n in enumerate([20, 45, 120, 300, 80, 60]):
        caps = [Caption(f"clip {i} whole")]
        if n == 300:
            caps = [Caption("first part", start=0.0, end=3.0), Caption("second part", start=3.0, end=14.0)]
        clips.append(ClipRecord(name=f"c{i}", features=rng.normal(i, 1.0, (n, 263)).astype(np.float32),
                                split="train" if i < 5 else "test", captions=caps,
                                action="wave" if i % 2 else "walk"))
    path = tmp_path / "s.h5"
    write_shard(path, clips, source="test", action_names=["walk", "wave"], provenance={})
    return path


def test_windows_follow_the_protocol(shard_path):
    ds = MotionDataset(shard_path, "train")
    # c0 (20 frames) is too short; c3 is split into its two captioned spans (60 and 220 frames).
    spans = sorted((ds.names[0][w.clip], w.stop - w.start) for w in ds.windows)
    assert spans == [("c1", 45), ("c2", 120), ("c3", 60), ("c3", 220), ("c4", 80)]
    torch.manual_seed(0)
    for i in range(len(ds)):
        item = ds[i]
        assert item["length"] % 4 == 0 and 40 <= item["length"] <= 196
        assert item["motion"].shape == (item["length"], 263)
    long = [i for i, w in enumerate(ds.windows) if w.stop - w.start == 220][0]
    assert ds[long]["caption"] == "second part"


def test_length_bounds_are_options(shard_path):
    ds = MotionDataset(shard_path, "train", min_frames=16, max_frames=64)
    assert len(ds) == 6  # c0 now kept
    assert all(ds[i]["length"] <= 64 for i in range(len(ds)))
    assert len(MotionDataset(shard_path, "train", crop_long=False, max_frames=196)) == 4
    with pytest.raises(ValueError):
        MotionDataset(shard_path, "train", min_frames=100, max_frames=50)


def test_normalisation_uses_the_shard_stats(shard_path):
    ds = MotionDataset(shard_path, "train")
    raw = MotionDataset(shard_path, "train", normalize=False)
    torch.manual_seed(1)
    a = ds[2]
    torch.manual_seed(1)
    b = raw[2]
    with Shard(shard_path) as shard:
        np.testing.assert_allclose(a["motion"].numpy() * shard.std + shard.mean, b["motion"].numpy(), rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(ds.denormalize(a["motion"]).numpy(), b["motion"].numpy(), rtol=1e-5, atol=1e-4)


def test_crops_are_random_and_seeded(shard_path):
    ds = MotionDataset(shard_path, "train")
    long = [i for i, w in enumerate(ds.windows) if w.stop - w.start == 220][0]
    torch.manual_seed(0)
    first = [ds[long]["motion"][0, 0].item() for _ in range(5)]
    torch.manual_seed(0)
    again = [ds[long]["motion"][0, 0].item() for _ in range(5)]
    assert first == again and len(set(first)) > 1


def test_loader_with_bucketing_and_workers(shard_path):
    ds = MotionDataset(shard_path, "train", min_frames=16)
    sampler = LengthBucketSampler(ds.lengths(), batch_size=2, seed=3)
    seen = [i for b in sampler for i in b]
    assert sorted(seen) == list(range(len(ds)))
    loader = DataLoader(ds, batch_sampler=sampler, collate_fn=collate, num_workers=2)
    for batch in loader:
        assert batch["motion"].shape[0] == batch["mask"].shape[0] == len(batch["caption"])
        assert (batch["mask"].sum(1) == batch["length"]).all()
        assert batch["action"].dtype == torch.int64


def test_bucketing_reduces_padding():
    lengths = np.random.default_rng(0).integers(40, 197, 2000)
    def padding(sampler):
        return sum(lengths[b].max() * len(b) - lengths[b].sum() for b in sampler)
    bucketed = padding(LengthBucketSampler(lengths, 32))
    plain = padding(LengthBucketSampler(lengths, 32, pool_batches=1))
    assert bucketed < 0.2 * plain


def test_sampler_shards_across_ranks():
    lengths = np.arange(100)
    ranks = [list(LengthBucketSampler(lengths, 8, num_replicas=2, rank=r, seed=5)) for r in range(2)]
    a = {i for b in ranks[0] for i in b}
    b = {i for b in ranks[1] for i in b}
    assert not a & b and len(ranks[0]) == len(ranks[1])


def _same_batch(a: dict, b: dict) -> None:
    """Two batches hold the same windows bit for bit (padding as +0.0, not -0.0), captions and labels."""
    assert a["motion"].shape == b["motion"].shape
    assert torch.equal(a["motion"].view(torch.int32), b["motion"].view(torch.int32))
    for key in ("length", "mask", "action"):
        assert torch.equal(a[key].cpu(), b[key].cpu()), key
    for key in ("caption", "tokens", "name"):
        assert a[key] == b[key], key


@pytest.fixture()
def two_shards(shard_path, tmp_path):
    """The shard of ``shard_path`` and a second one, so that clips of the second start after the first's rows."""
    rng = np.random.default_rng(1)
    clips = [ClipRecord(name=f"d{i}", features=rng.normal(-i, 2.0, (n, 263)).astype(np.float32), split="train",
                        captions=[Caption(f"other {i} a"), Caption(f"other {i} b")], action="walk")
             for i, n in enumerate([50, 210, 64])]
    second = tmp_path / "t.h5"
    write_shard(second, clips, source="test", action_names=["walk", "wave"], provenance={})
    return [shard_path, second]


def test_gathered_batches_are_the_loader_batches_bit_for_bit(two_shards):
    """MotionDataset.gather from a FrameTable makes, under the same RNG state, the batch that collate makes of the
    items: the same crops, lengths, caption draws and normalisation, over two shards."""
    from lsgan.data.dataset import FrameTable

    ds = MotionDataset(two_shards, "train", min_frames=16, max_frames=100)
    table = FrameTable(ds)
    assert table.data.shape == (sum(Shard(p).num_frames for p in two_shards) + 1, 263)
    assert not table.data[-1].any()
    batches = list(LengthBucketSampler(ds.lengths(), 3, seed=4)) * 3
    torch.manual_seed(7)
    items = [collate([ds[i] for i in b]) for b in batches]
    torch.manual_seed(7)
    gathered = [ds.gather(b, table) for b in batches]
    for a, b in zip(items, gathered):
        _same_batch(a, b)
    assert len({tuple(b["caption"]) for b in gathered}) > 1 and any(b["mask"].logical_not().any() for b in gathered)
    raw = MotionDataset(two_shards, "train", min_frames=16, max_frames=100, normalize=False)
    with pytest.raises(ValueError, match="another normalisation"):
        raw.gather(batches[0], table)


def test_epoch_batches_from_a_frame_table_resume_where_the_loader_would(two_shards):
    """EpochBatches over a FrameTable gives the loader's batches across epoch boundaries, and a copy loaded with
    its state mid-epoch continues with the same batches."""
    from lsgan.data.dataset import FrameTable
    from lsgan.train.loop import EpochBatches

    ds = MotionDataset(two_shards, "train", min_frames=16, max_frames=100)
    sampler = LengthBucketSampler(ds.lengths(), 2, seed=1)
    per_epoch = len(sampler)
    loader, gathered = EpochBatches(ds, sampler, seed=1), EpochBatches(ds, sampler, seed=1, frames=FrameTable(ds))
    torch.manual_seed(3)
    want = [loader(s) for s in range(3 * per_epoch + 1)]
    torch.manual_seed(3)
    got = []
    for s in range(per_epoch + 1):
        got.append(gathered(s))
    state, rng = gathered.state(), torch.get_rng_state()
    assert state == {"epoch": 1, "batches_done": 1}
    resumed = EpochBatches(ds, sampler, seed=1, frames=FrameTable(ds))
    resumed.load(state)
    torch.set_rng_state(rng)
    got += [resumed(s) for s in range(per_epoch + 1, 3 * per_epoch + 1)]
    for a, b in zip(want, got, strict=True):
        _same_batch(a, b)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e38, -2e4])
def test_a_shard_with_non_finite_features_is_never_written(tmp_path, bad):
    """What write_shard accepts, Shard reads: a clip holding NaN, infinity or a value no motion has is refused by
    name and frame, and no file (not even a partial one) is left."""
    good = np.zeros((8, 263), np.float32)
    broken = good.copy()
    broken[3, 100] = bad
    with pytest.raises(ValueError, match="clip b: frame 3: features hold NaN, infinite or values beyond ±10000"):
        write_shard(tmp_path / "s.h5", [ClipRecord("a", good, "train"), ClipRecord("b", broken, "train")],
                    source="test", action_names=[], provenance={})
    assert list(tmp_path.iterdir()) == []
