"""The preprocess pipeline end to end on real files: joints and HumanML3D folders, bad inputs, resume, formats."""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from lsgan.data.clip import Caption, mirror_caption, swap_left_right
from lsgan.data.features import joints_to_features, recover_from_ric
from lsgan.data.preprocess import PreprocessError, Skip, format_skips, hash_split, preprocess
from lsgan.data.shards import FORMAT, Shard, summarize
from lsgan.data.sources.humanml3d import HumanML3DSource
from lsgan.data.sources.joints import JointsSource

CASES = ("rigid_scaled", "noisy", "mirrored_reversed")


@pytest.fixture()
def joints_dir(tmp_path, hml_fixtures) -> Path:
    ref = np.load(hml_fixtures / "reference_features.npz")
    d = tmp_path / "joints"
    (d / "texts").mkdir(parents=True)
    for c in CASES:
        np.save(d / f"{c}.npy", ref[f"{c}/joints_in"])
    (d / "texts" / "noisy.txt").write_text(
        "a person walks and turns left#a/DET person/NOUN walk/VERB and/CCONJ turn/VERB left/ADV#0.0#0.0\n"
        "someone steps to the right#someone/PRON step/VERB to/ADP the/DET right/NOUN#1.0#6.5\n"
    )
    return d


def _add_bad_inputs(d: Path, good: np.ndarray) -> dict[str, str]:
    np.save(d / "nan_frames.npy", np.where(np.arange(len(good))[:, None, None] == 5, np.nan, good))
    np.save(d / "too_short.npy", good[:4])
    (d / "corrupt.npy").write_bytes(b"this is not an array")
    (d / "truncated.npy").write_bytes((d / "noisy.npy").read_bytes()[:3000])
    np.save(d / "wrong_skeleton.npy", np.zeros((50, 10, 3), np.float32))
    degenerate = np.repeat(good[:1], 40, axis=0).copy()
    degenerate[:, :] = good[0, 0]  # every joint at one point: zero-length bones
    np.save(d / "degenerate.npy", degenerate)
    return {"nan_frames": "NaN", "too_short": "too short", "corrupt": "not a .npy", "truncated": "truncated",
            "wrong_skeleton": "(T, 22, 3)", "degenerate": "not finite"}


def test_joints_folder_to_shard_matches_reference_features(joints_dir, hml_fixtures, tmp_path):
    ref = np.load(hml_fixtures / "reference_features.npz")
    result = preprocess(JointsSource(root=str(joints_dir)), tmp_path / "out.h5")
    assert result.clips == 3 and not result.skipped
    with Shard(tmp_path / "out.h5") as shard:
        assert shard.attrs["format"] == FORMAT
        for c in CASES:
            i = shard.names.index(c)
            assert np.abs(shard.features(i) - ref[f"{c}/features"]).max() <= 1e-4
        caps = shard.captions(shard.names.index("noisy"))
        assert [c.text for c in caps] == ["a person walks and turns left", "someone steps to the right"]
        assert (caps[1].start, caps[1].end) == (1.0, 6.5)
        prov = shard.provenance
        hashed = {Path(p["path"]).name: p["sha256"] for p in prov["inputs"]}
        assert len(hashed["noisy.npy"]) == 64
        assert prov["source"]["name"] == "joints" and prov["lsgan_version"]
        # Mean/Std of the train split with the group rule: std constant inside each group.
        assert np.allclose(shard.std[4:67], shard.std[4])
    assert not (tmp_path / "out.h5.parts").exists()
    assert not list(tmp_path.glob(".out.h5.*"))  # no temp file left behind


def test_each_bad_input_is_reported_and_skipped(joints_dir, hml_fixtures, tmp_path):
    good = np.load(joints_dir / "noisy.npy")
    expected = _add_bad_inputs(joints_dir, good)
    result = preprocess(JointsSource(root=str(joints_dir)), tmp_path / "out.h5", report=tmp_path / "report.json")
    assert result.clips == 3
    report = json.loads((tmp_path / "report.json").read_text())
    reasons = {Path(s["item"]).stem: s["reason"] for s in report["skipped"]}
    assert set(reasons) == set(expected)
    for name, needle in expected.items():
        assert needle in reasons[name], (name, reasons[name])
    for name in ("corrupt", "truncated"):
        assert f"{name}.npy" in reasons[name]  # the message names the file
    assert "skipped 6" in result.summary()


def test_strict_mode_makes_a_bad_clip_fatal_and_writes_nothing(joints_dir, tmp_path):
    np.save(joints_dir / "zz_short.npy", np.load(joints_dir / "noisy.npy")[:3])
    with pytest.raises(PreprocessError, match="zz_short.*too short"):
        preprocess(JointsSource(root=str(joints_dir)), tmp_path / "out.h5", strict=True, chunk_size=1)
    assert not (tmp_path / "out.h5").exists()


def _shard_content(path: Path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
        out["attrs"] = dict(f.attrs)
    return out


def _assert_same_shard(a: Path, b: Path) -> None:
    ca, cb = _shard_content(a), _shard_content(b)
    assert ca.keys() == cb.keys()
    for k in ca:
        if k == "attrs":
            assert {x: str(y) for x, y in ca[k].items()} == {x: str(y) for x, y in cb[k].items()}
        else:
            assert np.array_equal(np.asarray(ca[k]), np.asarray(cb[k])), k


def test_resume_after_interruption_gives_the_same_shard(joints_dir, tmp_path):
    for k in range(6):  # more inputs, so the run has several chunks
        np.save(joints_dir / f"extra{k}.npy", np.load(joints_dir / "noisy.npy")[k * 10 :])
    src = JointsSource(root=str(joints_dir), mirror=True)
    preprocess(src, tmp_path / "full.h5", chunk_size=2)

    def interrupt(done, total):
        if done >= 4:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        preprocess(src, tmp_path / "part.h5", chunk_size=2, on_progress=interrupt)
    assert not (tmp_path / "part.h5").exists()
    assert len(list((tmp_path / "part.h5.parts").glob("chunk_*.npz"))) == 2
    seen = []
    preprocess(src, tmp_path / "part.h5", chunk_size=2, resume=True, on_progress=lambda d, t: seen.append(d))
    assert seen[0] == 4  # the finished chunks were not redone
    _assert_same_shard(tmp_path / "full.h5", tmp_path / "part.h5")


def _interrupt_after(chunks: int):
    def hook(done, total):
        if done >= chunks:
            raise KeyboardInterrupt
    return hook


def test_resume_with_other_options_redoes_every_chunk(joints_dir, tmp_path):
    src = JointsSource(root=str(joints_dir))
    with pytest.raises(KeyboardInterrupt):
        preprocess(src, tmp_path / "o.h5", chunk_size=1, on_progress=_interrupt_after(1))
    seen = []
    preprocess(src, tmp_path / "o.h5", chunk_size=1, min_frames=20, resume=True, on_progress=lambda d, t: seen.append(d))
    assert seen[0] == 0  # no chunk made with min_frames=10 was reused
    preprocess(src, tmp_path / "fresh.h5", chunk_size=1, min_frames=20)
    _assert_same_shard(tmp_path / "fresh.h5", tmp_path / "o.h5")


def test_resume_rereads_edited_added_and_removed_inputs(joints_dir, tmp_path):
    src = JointsSource(root=str(joints_dir))
    with pytest.raises(KeyboardInterrupt):
        preprocess(src, tmp_path / "o.h5", chunk_size=1, on_progress=_interrupt_after(3))
    edited = np.load(joints_dir / "noisy.npy")[::-1].copy()
    np.save(joints_dir / "noisy.npy", edited)  # edited after its chunk was finished
    (joints_dir / "texts" / "rigid_scaled.txt").write_text("a new caption#a/DET new/ADJ caption/NOUN#0.0#0.0\n")
    np.save(joints_dir / "added.npy", edited[:40])
    (joints_dir / "mirrored_reversed.npy").unlink()
    preprocess(src, tmp_path / "o.h5", chunk_size=1, resume=True)
    preprocess(src, tmp_path / "fresh.h5", chunk_size=1)
    _assert_same_shard(tmp_path / "fresh.h5", tmp_path / "o.h5")
    with Shard(tmp_path / "o.h5") as shard:
        assert sorted(shard.names) == ["added", "noisy", "rigid_scaled"]
        assert shard.captions(shard.names.index("rigid_scaled"))[0].text == "a new caption"
        recorded = {e["path"]: e["sha256"] for e in shard.provenance["inputs"]}
    assert recorded[str(joints_dir / "noisy.npy")] == hashlib.sha256((joints_dir / "noisy.npy").read_bytes()).hexdigest()
    assert str(joints_dir / "mirrored_reversed.npy") not in recorded
    assert not (tmp_path / "o.h5.parts").exists()


def test_workers_give_the_same_shard(joints_dir, tmp_path):
    src = JointsSource(root=str(joints_dir), mirror=True)
    preprocess(src, tmp_path / "a.h5", chunk_size=1)
    preprocess(src, tmp_path / "b.h5", chunk_size=1, workers=2)
    _assert_same_shard(tmp_path / "a.h5", tmp_path / "b.h5")


def test_mirrored_copies_share_their_source_split_and_swap_sides(joints_dir, tmp_path):
    preprocess(JointsSource(root=str(joints_dir)), tmp_path / "m.h5", mirror=True)
    with Shard(tmp_path / "m.h5") as shard:
        assert len(shard) == 6
        i, m = shard.names.index("noisy"), shard.names.index("Mnoisy")
        assert shard.mirror_of[m] == "noisy" and shard.splits[i] == shard.splits[m]
        assert [c.text for c in shard.captions(m)][0] == "a person walks and turns right"
        assert "turn/VERB right/ADV" in shard.captions(m)[0].tokens
        ji, jm = recover_from_ric(shard.features(i)), recover_from_ric(shard.features(m))
        # The mirror's left wrist does what the original's right wrist did (heights are mirror-invariant).
        assert np.abs(jm[:, 20, 1] - ji[:, 21, 1]).max() < 0.03


def test_hash_split_is_deterministic_and_about_80_10_10():
    names = [f"clip{i}" for i in range(6000)]
    splits = [hash_split(n) for n in names]
    assert splits == [hash_split(n) for n in names]
    frac = {s: splits.count(s) / len(splits) for s in ("train", "val", "test")}
    assert abs(frac["train"] - 0.8) < 0.03 and abs(frac["val"] - 0.1) < 0.02 and abs(frac["test"] - 0.1) < 0.02


def test_swap_left_right_in_captions_and_labels():
    assert swap_left_right("wave-left-hand") == "wave-right-hand"
    assert swap_left_right("Left arm, then the right") == "Right arm, then the left"
    assert swap_left_right("leftover bright") == "leftover bright"
    cap = mirror_caption(Caption("turn left", "turn/VERB left/ADV", 1.0, 2.0))
    assert (cap.text, cap.tokens, cap.start, cap.end) == ("turn right", "turn/VERB right/ADV", 1.0, 2.0)


@pytest.fixture()
def hml_folder(tmp_path, hml_fixtures) -> Path:
    """A small processed-HumanML3D folder built from the fixture clip (+ its mirror and a shorter copy)."""
    d = tmp_path / "HumanML3D"
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (d / sub).mkdir(parents=True)
    vecs = np.load(hml_fixtures / "new_joint_vecs" / "012314.npy")
    np.save(d / "new_joint_vecs" / "012314.npy", vecs)
    np.save(d / "new_joint_vecs" / "M012314.npy", vecs[::-1].copy())
    np.save(d / "new_joint_vecs" / "000001.npy", vecs[:60])
    (d / "texts" / "012314.txt").write_text(
        "a person walks forward#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0\n"
        "the person turns around#the/DET person/NOUN turn/VERB around/ADP#2.0#5.0\n"
    )
    (d / "texts" / "M012314.txt").write_text("a person walks forward#a/DET person/NOUN walk/VERB forward/ADV#0.0#0.0\n")
    shutil.copy(hml_fixtures / "Mean.npy", d / "Mean.npy")
    shutil.copy(hml_fixtures / "Std.npy", d / "Std.npy")
    (d / "train.txt").write_text("012314\nM012314\n")
    (d / "val.txt").write_text("000001\n")
    (d / "test.txt").write_text("009999\n")  # listed but missing on disk
    return d


def test_humanml3d_folder_keeps_features_stats_splits_and_spans(hml_folder, hml_fixtures, tmp_path):
    result = preprocess(HumanML3DSource(root=str(hml_folder)), tmp_path / "h.h5")
    assert result.clips == 3
    assert [s.item for s in result.skipped] == ["009999"] and "missing on disk" in result.skipped[0].reason
    with Shard(tmp_path / "h.h5") as shard:
        i = shard.names.index("012314")
        np.testing.assert_array_equal(shard.features(i), np.load(hml_fixtures / "new_joint_vecs" / "012314.npy"))
        np.testing.assert_array_equal(shard.mean, np.load(hml_fixtures / "Mean.npy"))
        np.testing.assert_array_equal(shard.std, np.load(hml_fixtures / "Std.npy"))
        assert shard.splits[i] == "train" and shard.splits[shard.names.index("000001")] == "val"
        assert shard.mirror_of[shard.names.index("M012314")] == "012314"
        assert shard.captions(i)[1].start == 2.0 and shard.captions(i)[1].end == 5.0
    info = summarize(tmp_path / "h.h5")
    assert info["clips"] == 3 and info["captions"] == 3 and info["splits"] == {"train": 2, "val": 1}


def test_humanml3d_format_round_trip(joints_dir, hml_fixtures, tmp_path):
    ref = np.load(hml_fixtures / "reference_features.npz")
    out = tmp_path / "HML"
    preprocess(JointsSource(root=str(joints_dir)), out, format="humanml3d")
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        assert (out / sub).is_dir()
    for f in ("Mean.npy", "Std.npy", "train.txt", "val.txt", "test.txt", "train_val.txt", "all.txt"):
        assert (out / f).exists(), f
    vecs = np.load(out / "new_joint_vecs" / "noisy.npy")
    assert np.abs(vecs - ref["noisy/features"]).max() <= 1e-4
    assert np.abs(np.load(out / "new_joints" / "noisy.npy") - ref["noisy/recovered_joints"]).max() <= 1e-4
    lines = (out / "texts" / "noisy.txt").read_text().splitlines()
    assert lines[1].split("#") == ["someone steps to the right", "someone/PRON step/VERB to/ADP the/DET right/NOUN", "1.0", "6.5"]
    all_ids = (out / "all.txt").read_text().split()
    assert sorted(all_ids) == sorted(CASES)
    # Our own HumanML3D reader takes the folder back unchanged.
    preprocess(HumanML3DSource(root=str(out)), tmp_path / "back.h5")
    with Shard(tmp_path / "back.h5") as shard:
        np.testing.assert_array_equal(shard.features(shard.names.index("noisy")), vecs)
        np.testing.assert_array_equal(shard.mean, np.load(out / "Mean.npy"))


def test_rewriting_a_humanml3d_folder_replaces_it_whole(joints_dir, tmp_path):
    out = tmp_path / "HML"
    preprocess(JointsSource(root=str(joints_dir)), out, format="humanml3d")
    (joints_dir / "noisy.npy").unlink()
    with pytest.raises(ValueError, match="exists; pass --force"):
        preprocess(JointsSource(root=str(joints_dir)), out, format="humanml3d")
    preprocess(JointsSource(root=str(joints_dir)), out, format="humanml3d", force=True)
    assert sorted(p.stem for p in (out / "new_joint_vecs").glob("*.npy")) == ["mirrored_reversed", "rigid_scaled"]
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == [".lsgan-outputs.json"]


def test_featurising_our_recovered_joints_is_stable(hml_fixtures):
    joints = np.load(hml_fixtures / "new_joints" / "012314.npy")
    feats = joints_to_features(joints)
    assert feats.shape == (169, 263) and np.isfinite(feats).all()


def test_the_skip_summary_names_only_files_that_exist(tmp_path: Path) -> None:
    """A HumanML3D item is an id inside a path: the summary keeps the path whole (it named
    'new_joint_vecs/.npy' once); a BVH item is the path itself and leads its reason, which drops it."""
    vecs = tmp_path / "new_joint_vecs"
    hml = [Skip(i, f"{vecs / (i + '.npy')}: listed in the split files but missing on disk") for i in ("000001", "000002")]
    bvh = [Skip(str(tmp_path / f"{n}.bvh"), f"{tmp_path / (n + '.bvh')}: no HIERARCHY") for n in ("a", "b")]
    text = format_skips(hml + bvh)
    assert f"{vecs / '000001.npy'}: listed in the split files" in text and "/.npy" not in text, text
    assert "2 files: no HIERARCHY (e.g. a.bvh, b.bvh)" in text, text
