"""Unreadable inputs and unwritable outputs (issue 10): one line naming the file, a non-zero exit, nothing changed.

Real HDF5 files (a synthetic shard, damaged in place), real tiny training runs through the CLI. Hostile inputs
(issue 28: pickles past the bounds, HDF5 data from outside the file or larger than it, bad clip tables, BVH
headers that claim too much; then small files that decode to gigabytes: HDF5 chunks never written, strings that
share one stored copy, pickled arrays that share one memoised buffer, a gzip BVH padded with 3 GB of spaces) are
one table, HOSTILE, run through the CLI in a child Python whose address space is capped at what it maps after its
imports plus 2 GiB (as tests/test_fuzz_readers.py caps its examples): a bomb that slips through fails the row with
a MemoryError instead of taking the machine's memory.
"""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import re
import shutil
import struct
import subprocess
import zlib
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.sparse as sp
from body_models import make_model
from cli_runs import forked_lsgan
from test_fuzz_readers import ALLOC_HEADROOM
from torch.utils.data import DataLoader

from lsgan.data.dataset import MotionDataset, collate
from lsgan.data.shards import DataFileError, Shard, summarize, write_shard
from lsgan.data.skeleton import JOINT_NAMES
from lsgan.models.cache import (
    StaleCache,
    check_cache_vae,
    encode_latents,
    read_cache_attrs,
    read_latent_cache,
    write_latent_cache,
)
from lsgan.models.checkpoint import weights_hash

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = """
vae:
  model: {latent_dim: 32, d_model: 32, num_layers: 1, num_heads: 2, ff_size: 64, dropout: 0.0, max_len: 200}
  train: {batch_size: 16, max_steps: 2, val_every: 2, ckpt_every: 2, log_every: 1, lr: 1.0e-3, val_batches: 1,
          num_workers: WORKERS}
"""


def lsgan(*args, cwd) -> subprocess.CompletedProcess:
    """The command in a fresh process (forked after the heavy imports; cli_runs.forked_lsgan)."""
    return forked_lsgan(*args, cwd=cwd, env={k: v for k, v in os.environ.items() if k.startswith("LSGAN_")})


def capped_lsgan(*args, cwd) -> subprocess.CompletedProcess:
    """lsgan in a child Python whose address space is capped after its imports (see the module's docstring)."""
    return forked_lsgan(*args, cwd=cwd, preload=("lsgan.cli", "lsgan.data.dataset", "lsgan.data.preprocess"),
                        headroom=ALLOC_HEADROOM)


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` with the SHA-256 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def one_error_line(out: subprocess.CompletedProcess) -> str:
    """The command failed with exactly one `error:` line and no traceback; returns that line."""
    assert out.returncode != 0, out.stderr
    assert "Traceback" not in out.stderr, out.stderr
    errors = [line for line in out.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, out.stderr
    return errors[0]


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A synthetic shard, a tiny VAE trained on it and its latent cache, all made with the CLI."""
    d = tmp_path_factory.mktemp("read-errors")
    for workers in (0, 1):
        (d / f"tiny{workers}.yaml").write_text(TINY.replace("WORKERS", str(workers)))
    steps = [
        ("preprocess", "--source", "synthetic", "--num-clips", 20, "-o", "synth.h5"),
        ("train-vae", "--data", "synth.h5", "--recipe", "tiny0.yaml", "--out", "vae"),
        ("encode-latents", "--data", "synth.h5", "--vae", "vae", "--text-encoder", "none", "-o", "cache.h5"),
    ]
    for step in steps:
        out = lsgan(*step, cwd=d)
        assert out.returncode == 0, f"{step[0]} failed:\n{out.stderr[-3000:]}"
    return d


def damaged_shard(run: Path, folder: Path) -> tuple[Path, set[str]]:
    """A copy of the shard with bytes in the middle of its last compressed features chunk overwritten;
    returns it and the names of the clips with frames in that chunk."""
    path = folder / "damaged.h5"
    shutil.copy(run / "synth.h5", path)
    with h5py.File(path, "r") as f:
        ds = f["features"]
        info = ds.id.get_chunk_info(ds.id.get_num_chunks() - 1)
        first, last = info.chunk_offset[0], info.chunk_offset[0] + ds.chunks[0]
        names = f["clips/name"].asstr()[()]
        offsets, lengths = f["clips/offset"][()], f["clips/length"][()]
    hit = {str(n) for n, o, k in zip(names, offsets, lengths) if o < last and o + k > first}
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(bytes(range(256)) * 4)
    return path, hit


# -- files that are not (whole) shards or caches ------------------------------------------------------------


def _not_hdf5(p: Path, run: Path) -> None:
    p.write_text("name,frames\nwalk,120\n")


def _empty(p: Path, run: Path) -> None:
    p.write_bytes(b"")


def _truncated(p: Path, run: Path) -> None:
    p.write_bytes((run / "synth.h5").read_bytes()[:6000])


def _other_hdf5(p: Path, run: Path) -> None:
    with h5py.File(p, "w") as f:
        f["x"] = np.arange(3)


def _missing_dataset(p: Path, run: Path) -> None:
    shutil.copy(run / "synth.h5", p)
    with h5py.File(p, "r+") as f:
        del f["clips/length"]


def _stats(values: dict[str, float]) -> Callable[[Path, Path], None]:
    def make(p: Path, run: Path) -> None:
        shutil.copy(run / "synth.h5", p)
        with h5py.File(p, "r+") as f:
            for name, value in values.items():
                f[name][5] = value
    return make


def _cache_as_shard(p: Path, run: Path) -> None:
    shutil.copy(run / "cache.h5", p)


BAD_SHARDS = {
    "not-hdf5": (_not_hdf5, "not an HDF5 file"),
    "empty": (_empty, "not an HDF5 file"),
    "truncated": (_truncated, "truncated or corrupt HDF5 (truncated file"),
    "other-hdf5": (_other_hdf5, "not an lsgan motion shard (no format attribute)"),
    "missing-dataset": (_missing_dataset, "not an lsgan motion shard (missing clips/length)"),
    "a-cache": (_cache_as_shard, "not an lsgan motion shard (format attribute is 'lsgan-latent-cache')"),
    **{f"stats-{name}": (_stats(values), "stats/mean and stats/std hold 1 value that cannot normalise features")
       for name, values in (("std-zero", {"stats/std": 0.0}), ("std-negative", {"stats/std": -1.0}),
                            ("std-nan", {"stats/std": float("nan")}), ("mean-inf", {"stats/mean": float("inf")}))},
}


@pytest.mark.parametrize("case", sorted(BAD_SHARDS))
def test_a_bad_shard_is_one_line_naming_it(run: Path, tmp_path: Path, case: str) -> None:
    make, phrase = BAD_SHARDS[case]
    path = tmp_path / "bad.h5"
    make(path, run)
    before = snapshot(tmp_path)
    for read in (Shard, summarize, lambda p: MotionDataset([run / "synth.h5", p])):
        with pytest.raises(DataFileError) as e:
            read(path)
        assert str(e.value).startswith(f"{path}: ") and phrase in str(e.value) and "\n" not in str(e.value)
    line = one_error_line(lsgan("inspect", path.name, cwd=tmp_path))
    assert line == f"error: bad.h5: {str(e.value).split(': ', 1)[1]}"
    line = one_error_line(lsgan("train-vae", "--data", "bad.h5", "--recipe", run / "tiny0.yaml", "--out", "vae",
                                cwd=tmp_path))
    assert line.startswith("error: bad.h5: ") and phrase in line
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("damage", ["all-nan", "one-inf", "one-huge"])
def test_features_changed_to_non_finite_values_are_named(run: Path, tmp_path: Path, damage: str) -> None:
    """Features overwritten in place: every value NaN (a dataset that now compresses 1000x, which must not read as
    a decompression bomb) or one infinity in clip 3. Opening works; reading the frames names the clip and frame."""
    path = tmp_path / "bad.h5"
    shutil.copy(run / "synth.h5", path)
    with h5py.File(path, "r+") as f:
        offset = int(f["clips/offset"][3])
        if damage == "all-nan":
            f["features"][...] = np.nan
        else:
            f["features"][offset + 2, 7] = np.inf if damage == "one-inf" else 1e38
    clip, frame = (0, 0) if damage == "all-nan" else (3, 2)
    phrase = f"(index {clip}), frame {frame}: features hold NaN, infinite or values beyond ±10000"
    before = snapshot(tmp_path)
    with Shard(path) as shard:
        for read in (shard.all_features, lambda: shard.features(clip)):
            with pytest.raises(DataFileError, match=re.escape(phrase)):
                read()
        if damage != "all-nan":
            assert np.isfinite(shard.features(clip + 1)).all() and np.isfinite(shard.features(clip, 3)).all()
    line = one_error_line(lsgan("train-vae", "--data", "bad.h5", "--recipe", run / "tiny0.yaml", "--out", "vae",
                                cwd=tmp_path))
    assert line.startswith("error: bad.h5: clip ") and phrase in line
    assert snapshot(tmp_path) == before


def test_a_directory_or_missing_file_as_shard(tmp_path: Path) -> None:
    with pytest.raises(DataFileError, match="is a directory, not an HDF5 file$"):
        Shard(tmp_path)
    with pytest.raises(DataFileError, match="nope.h5: no such file$"):
        Shard(tmp_path / "nope.h5")
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("case", ["not-hdf5", "truncated", "other-hdf5", "a-shard", "missing-dataset"])
def test_a_bad_cache_is_one_line_naming_it(run: Path, tmp_path: Path, case: str) -> None:
    path = tmp_path / "bad.h5"
    if case == "a-shard":
        shutil.copy(run / "synth.h5", path)
        phrase = "not an lsgan latent cache (format attribute is 'lsgan-motion-shard'"
    elif case == "missing-dataset":
        shutil.copy(run / "cache.h5", path)
        with h5py.File(path, "r+") as f:
            del f["latents/logvar"]
        phrase = "not an lsgan latent cache (missing latents/logvar)"
    else:
        make, phrase = BAD_SHARDS[case]
        make(path, run)
        phrase = phrase.replace("motion shard", "latent cache").replace(")", "")
    before = snapshot(tmp_path)
    for read in (read_cache_attrs, read_latent_cache, check_cache_vae):
        with pytest.raises(DataFileError) as e:
            read(path)
        assert str(e.value).startswith(f"{path}: ") and phrase in str(e.value) and "\n" not in str(e.value)
    assert snapshot(tmp_path) == before


# -- a damaged compressed chunk ------------------------------------------------------------------------------


def test_a_damaged_chunk_names_the_shard_and_the_clip(run: Path, tmp_path: Path) -> None:
    path, hit = damaged_shard(run, tmp_path)
    with Shard(path) as shard:
        bad = [i for i in range(len(shard)) if shard.names[i] in hit]
        assert shard.features(0).shape[1] == 263  # the clips in the intact chunk still read
        with pytest.raises(DataFileError) as e:
            shard.features(bad[0])
    name = shard.names[bad[0]]
    assert str(e.value) == (f"{path}: clip {name} (index {bad[0]}): unreadable features (corrupt compressed data: "
                            "filter returned failure during read)")
    with pytest.raises(DataFileError, match=f"^{re.escape(str(path))}: clip {name} \\(index {bad[0]}\\): unreadable"):
        Shard(path, in_memory=True)  # reads every frame at once: the first clip of the damaged chunk is named
    ds = MotionDataset(path, split=None, min_frames=1)
    for workers in (0, 1):
        with pytest.raises(DataFileError) as e:
            list(DataLoader(ds, batch_size=64, collate_fn=collate, num_workers=workers))
        message = str(e.value)
        assert message.startswith(f"{path}: clip ") and message.split()[2] in hit and "\n" not in message


@pytest.mark.parametrize("workers", [0, 1])
def test_train_vae_stops_on_a_damaged_chunk(run: Path, tmp_path: Path, workers: int) -> None:
    path, hit = damaged_shard(run, tmp_path)
    before = snapshot(tmp_path)
    out = lsgan("train-vae", "--data", path.name, "--recipe", run / f"tiny{workers}.yaml", "--out", "vae",
                "--max-steps", 2, cwd=tmp_path)
    line = one_error_line(out)
    assert line.startswith(f"error: {path.name}: clip ") and line.split()[3] in hit, line
    assert "unreadable features (corrupt compressed data: " in line
    assert not (tmp_path / "vae" / "last").exists()
    assert {k: v for k, v in snapshot(tmp_path).items() if not k.startswith("vae/")} == before


def test_encode_latents_names_the_damaged_clip(run: Path, tmp_path: Path) -> None:
    path, hit = damaged_shard(run, tmp_path)
    before = snapshot(tmp_path)
    with pytest.raises(DataFileError) as e:
        encode_latents(path, run / "vae", tmp_path / "cache.h5", text_encoder=None, progress=False)
    assert str(e.value).startswith(f"{path}: clip ") and str(e.value).split()[2] in hit
    assert snapshot(tmp_path) == before


# -- outputs that cannot be written --------------------------------------------------------------------------


def _write_both(target: Path) -> list[str]:
    """The errors of write_shard and write_latent_cache to ``target``."""
    errors = []
    with pytest.raises(DataFileError) as e:
        write_shard(target, [], source="test", action_names=[], provenance={})
    errors.append(str(e.value))
    with pytest.raises(DataFileError) as e:
        write_latent_cache(target, names=["a"], splits=["train"], actions=np.array([-1]), lengths=np.array([40]),
                           mu=np.zeros((1, 4)), logvar=np.zeros((1, 4)), caption_clip=np.zeros(0, int),
                           caption_text=[], caption_embedding=np.zeros((0, 0)), action_names=[], vae_hash="x")
    errors.append(str(e.value))
    return errors


def test_writing_to_a_directory_or_under_a_file(tmp_path: Path) -> None:
    (tmp_path / "out.h5").mkdir()
    (tmp_path / "out.h5" / "keep.txt").write_text("keep")
    (tmp_path / "notes.txt").write_text("a file, not a folder")
    before = snapshot(tmp_path)
    assert _write_both(tmp_path / "out.h5") == [f"{tmp_path / 'out.h5'}: cannot write (is a directory)"] * 2
    under = tmp_path / "notes.txt" / "sub" / "out.h5"
    assert _write_both(under) == [f"{under}: cannot write ({tmp_path / 'notes.txt'} is a file, not a folder)"] * 2
    assert snapshot(tmp_path) == before and sorted(os.listdir(tmp_path)) == ["notes.txt", "out.h5"]


@pytest.fixture()
def public_tmp():
    """A temporary folder that any user can enter (pytest's own are private to their owner)."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="lsgan-read-errors-") as d:
        os.chmod(d, 0o755)
        yield Path(d)


@pytest.mark.parametrize("mode", [0o555, 0o700])
def test_writing_into_a_read_only_folder(public_tmp: Path, mode: int) -> None:
    """Permission denied for real: as root (which ignores the mode bits) the writes run in a forked child that
    has dropped to user 'nobody', after it has checked that it cannot create a file there. The folder is
    read-only (0o555), or not even enterable (0o700)."""
    folder = public_tmp / "read-only"
    folder.mkdir()
    (folder / "old.h5").write_bytes(b"old")
    os.chmod(folder, mode)
    before = snapshot(public_tmp)
    try:
        result = _without_write_access(folder, lambda: _write_both(folder / "out.h5"))
    finally:
        os.chmod(folder, 0o755)
    assert result == [f"{folder / 'out.h5'}: cannot write (permission denied)"] * 2
    assert snapshot(public_tmp) == before and os.listdir(folder) == ["old.h5"]


def _without_write_access(folder: Path, body):
    """``body()`` in a forked child that is not root; its result (JSON), or what went wrong, as text."""
    import json

    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        try:
            os.close(r)
            try:
                if os.geteuid() == 0:
                    os.setgroups([])
                    os.setgid(65534)
                    os.setuid(65534)
                (folder / "probe").touch()
                result = {"skip": f"{folder} is writable to this process"}
            except PermissionError:
                result = body() if os.geteuid() != 0 else {"skip": "cannot stop being root here"}
        except BaseException as e:  # noqa: BLE001 - reported to the parent
            result = f"{type(e).__name__}: {e}"
        finally:
            os.write(w, json.dumps(result).encode())
            os._exit(0)
    os.close(w)
    with os.fdopen(r) as f:
        text = f.read()
    os.waitpid(pid, 0)
    result = json.loads(text)
    if isinstance(result, dict):
        pytest.skip(result["skip"])
    return result


# -- a latent cache checked against its VAE ------------------------------------------------------------------


def test_check_cache_vae_finds_the_recorded_vae_from_any_directory(run: Path, tmp_path: Path, monkeypatch) -> None:
    attrs = read_cache_attrs(run / "cache.h5")
    assert Path(attrs["vae_path"]).is_absolute() and Path(attrs["vae_path"]) == (run / "vae" / "best").resolve()
    expected = weights_hash(run / "vae")
    assert check_cache_vae(run / "cache.h5") == expected == attrs["vae_hash"]
    monkeypatch.chdir(tmp_path)
    assert check_cache_vae(run / "cache.h5") == expected
    assert check_cache_vae(run / "cache.h5", allow_stale=True) is None
    assert read_latent_cache(run / "cache.h5", expect_vae_hash=check_cache_vae(run / "cache.h5")).vae_hash == expected


def test_a_moved_vae_is_refused_unless_given(run: Path, tmp_path: Path, monkeypatch) -> None:
    shutil.copy(run / "cache.h5", tmp_path / "cache.h5")
    shutil.copytree(run / "vae", tmp_path / "vae")
    with h5py.File(tmp_path / "cache.h5", "r+") as f:  # as if encoded from tmp_path/vae, which then moved
        f.attrs["vae_path"] = str(tmp_path / "vae" / "best")
    (tmp_path / "vae").rename(tmp_path / "moved")
    before = snapshot(tmp_path)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(DataFileError) as e:
        check_cache_vae("cache.h5")
    assert str(e.value) == (f"cache.h5: cannot check that the cache matches its VAE: {tmp_path / 'vae' / 'best'} "
                            "not found (moved?); pass --vae RUN (or --allow-stale)")
    assert check_cache_vae("cache.h5", vae="moved") == weights_hash(run / "vae")
    assert check_cache_vae("cache.h5", vae=tmp_path / "moved" / "best") == weights_hash(run / "vae")
    assert check_cache_vae("cache.h5", allow_stale=True) is None
    assert snapshot(tmp_path) == before


def test_a_cache_of_an_older_lsgan_with_a_relative_vae_path(run: Path, tmp_path: Path, monkeypatch) -> None:
    shutil.copy(run / "cache.h5", tmp_path / "cache.h5")
    shutil.copytree(run / "vae", tmp_path / "vae")
    with h5py.File(tmp_path / "cache.h5", "r+") as f:
        f.attrs["vae_path"] = "vae/best"  # relative to where encode-latents ran: the cache's folder
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert check_cache_vae(tmp_path / "cache.h5") == weights_hash(run / "vae")
    shutil.rmtree(tmp_path / "vae")
    with pytest.raises(DataFileError, match="vae/best not found \\(moved\\?\\); pass --vae RUN"):
        check_cache_vae(tmp_path / "cache.h5")


def test_a_retrained_vae_is_refused_with_both_hashes(run: Path, tmp_path: Path, monkeypatch) -> None:
    shutil.copytree(run / "vae", tmp_path / "vae")
    out = lsgan("encode-latents", "--data", run / "synth.h5", "--vae", "vae", "--text-encoder", "none",
                "-o", "cache.h5", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    old = read_cache_attrs(tmp_path / "cache.h5")["vae_hash"]
    shutil.rmtree(tmp_path / "vae")
    out = lsgan("train-vae", "--data", run / "synth.h5", "--recipe", run / "tiny0.yaml", "--out", "vae", "--seed", 1,
                cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    new = weights_hash(tmp_path / "vae")
    assert new != old
    cache = tmp_path / "cache.h5"
    before = snapshot(tmp_path)
    for where in (tmp_path, run):  # the working directory makes no difference
        monkeypatch.chdir(where)
        for vae in (None, tmp_path / "vae"):
            with pytest.raises(StaleCache) as e:
                check_cache_vae(cache, vae=vae)
            message = str(e.value)
            assert message.startswith(f"{cache} was encoded with another VAE than {tmp_path / 'vae' / 'best'}")
            assert old in message and new in message and "\n" not in message
    assert check_cache_vae(cache, vae=run / "vae") == old  # the VAE it was encoded with, wherever it is now
    with pytest.raises(StaleCache, match="another VAE checkpoint"):
        read_latent_cache(cache, expect_vae_hash=new)
    assert snapshot(tmp_path) == before


# -- hostile inputs (issue 28): one row each, through the command line -------------------------------------------
#
# Each row writes its files in a fresh folder and returns the command; the command must exit with the row's code,
# print one `error:` line (and no traceback) with the phrase somewhere on stderr, and change no file that existed.

MAP = {"joints": {n: n for n in JOINT_NAMES}, "scale": 0.01, "up": "y"}


def _body_model_export(w: Path, payload: bytes) -> list:
    (w / "model.pkl").write_bytes(payload)
    np.save(w / "walk_joints.npy", np.zeros((8, 22, 3), np.float32))
    return ["export", "--glb", "walk_joints.npy", "--body-model", "model.pkl", "-o", "walk.glb"]


def _nested_key(w: Path, run: Path) -> list:
    return _body_model_export(w, b"\x80\x02})" + b"\x85" * 1_000_000 + b"Ns.")


def _s0_dtype(w: Path, run: Path) -> list:
    s0 = (b"\x80\x02cnumpy._core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R(K\x01\x8a\x05"
          + (1 << 32).to_bytes(5, "little") + b"\x85cnumpy\ndtype\nX\x02\x00\x00\x00S0\x89\x88\x87R"
          b"(K\x03X\x01\x00\x00\x00|NNNK\x00K\x01K\x00tb\x89C\x00tb.")
    return _body_model_export(w, b"\x80\x02}X\x0a\x00\x00\x00v_template" + s0[2:-1] + b"s.")  # {"v_template": s0}


def _huge_sparse(w: Path, run: Path) -> list:
    model = make_model("smpl")
    model["J_regressor"] = sp.csc_matrix((3_000_000, 8_000))
    return _body_model_export(w, pickle.dumps(model, protocol=4))


def _shard_copy(w: Path, run: Path, change) -> list:
    """A copy of the synthetic shard, changed by ``change(f, w)``; the command inspects it."""
    shutil.copy(run / "synth.h5", w / "bad.h5")
    with h5py.File(w / "bad.h5", "r+") as f:
        change(f, w)
    return ["inspect", "bad.h5"]


def _replace(f: h5py.File, name: str, **create) -> None:
    del f[name]
    f.create_dataset(name, **create)


def _huge_features(f: h5py.File, w: Path) -> None:  # 3.8 TiB, compressed, no chunk written
    _replace(f, "features", shape=(3_600_000_000, 263), dtype=np.float32, chunks=(1024, 263), compression="gzip")


def _huge_table(f: h5py.File, w: Path) -> None:  # 8 GB of offsets in a file of a few hundred KB
    _replace(f, "clips/offset", shape=(10**9,), dtype=np.int64)


def _external_storage(f: h5py.File, w: Path) -> None:
    n = f["clips/offset"].shape[0]
    (w / "elsewhere.bin").write_bytes(np.arange(n, dtype=np.int64).tobytes())
    _replace(f, "clips/offset", shape=(n,), dtype=np.int64, external=[(str(w / "elsewhere.bin"), 0, 8 * n)])


def _external_link(f: h5py.File, w: Path) -> None:
    with h5py.File(w / "other.h5", "w") as other:
        other["mean"], other["std"] = np.zeros(263, np.float32), np.ones(263, np.float32)
    del f["stats"]
    f["stats"] = h5py.ExternalLink(str(w / "other.h5"), "/")


def _virtual(f: h5py.File, w: Path) -> None:
    n = f["clips/length"].shape[0]
    with h5py.File(w / "other.h5", "w") as other:
        other["length"] = np.full(n, 40, np.int32)
    layout = h5py.VirtualLayout(shape=(n,), dtype=np.int32)
    layout[:] = h5py.VirtualSource(str(w / "other.h5"), "length", shape=(n,))
    del f["clips/length"]
    f.create_virtual_dataset("clips/length", layout)


def _offsets(value):
    def change(f: h5py.File, w: Path) -> None:
        offsets = f["clips/offset"][()]
        offsets[1] = value if value < 0 else f["features"].shape[0] - 3
        f["clips/offset"][...] = offsets
    return change


def _encode(w: Path, run: Path, change) -> list:
    _shard_copy(w, run, change)
    return ["encode-latents", "--data", "bad.h5", "--vae", run / "vae", "--text-encoder", "none", "-o", "cache.h5"]


def _bvh(w: Path, text_of) -> list:
    from lsgan.data.synthetic import generate
    from lsgan.export.bvh import write_bvh

    (w / "bvh").mkdir()
    write_bvh(w / "bvh" / "walk.bvh", generate(1, seed=0)[0].joints)
    (w / "bvh" / "walk.bvh").write_bytes(text_of((w / "bvh" / "walk.bvh").read_text()))
    (w / "map.json").write_text(json.dumps(MAP))
    return ["preprocess", "--source", "bvh", "--joint-map", "map.json", "bvh", "-o", "out.h5"]


def _unwritten_chunks(w: Path, run: Path) -> list:
    """/features resized to 32,000,000 rows (31 GiB declared), only the real rows' chunks written: a 3 MB file."""
    shutil.copy(run / "synth.h5", w / "bad.h5")
    with h5py.File(w / "bad.h5", "r+") as f:
        x = f["features"][()]
        _replace(f, "features", shape=(32_000_000, 263), maxshape=(None, 263), dtype=np.float32, chunks=(1024, 263),
                 compression="gzip", shuffle=True)
        f["features"][: len(x)] = x
    return ["train-vae", "--data", "bad.h5", "--recipe", run / "tiny0.yaml", "--out", "vae"]


def _zero_chunks(f: h5py.File, w: Path) -> None:  # 300,000 rows of stored zeros: 316 MB from a few hundred KB
    rows = f["features"].shape[0]
    f["features"].resize(300_000, axis=0)
    for start in range(rows, 300_000, 50_000):
        f["features"][start:start + 50_000] = 0


def _rows_beyond_clips(f: h5py.File, w: Path) -> None:  # every chunk written (zeros), 100,000 rows no clip uses
    rows = f["features"].shape[0]
    f["features"].resize(100_000, axis=0)
    f["features"][rows:] = 0


def _shared_strings(w: Path, run: Path, chunked: bool, n: int = 20_000, size: int = 1 << 20) -> list:
    """captions/text of ``n`` entries whose stored references all point at the first one's string of ``size``
    bytes (20 GB decoded from a 5 MB file): patched in the file (contiguous) or as raw chunks (chunked)."""
    shutil.copy(run / "synth.h5", w / "bad.h5")
    with h5py.File(w / "bad.h5", "r+") as f:
        for key in ("clip", "text", "tokens", "start", "end"):
            del f[f"captions/{key}"]
        f["captions/clip"], f["captions/start"], f["captions/end"] = np.zeros(n, np.int32), np.zeros(n), np.zeros(n)
        f.create_dataset("captions/tokens", data=np.array([""] * n, dtype=object), dtype=h5py.string_dtype())
        text = f.create_dataset("captions/text", data=np.array(["x" * size] + [""] * (n - 1), dtype=object),
                                dtype=h5py.string_dtype(), chunks=(1000,) if chunked else None)
        if chunked:
            first = text.id.read_direct_chunk((0,))[1][:16]
            for c in range(0, n, 1000):
                text.id.write_direct_chunk((c,), first * 1000)
        offset = text.id.get_offset()
    if not chunked:
        with open(w / "bad.h5", "r+b") as fh:
            fh.seek(offset)
            first = fh.read(16)
            fh.seek(offset)
            fh.write(first * n)
    return ["inspect", "bad.h5"]


def _string_attribute_array(f: h5py.File, w: Path) -> None:
    f.attrs["lsgan_version"] = np.array(["0.1"] * 10, dtype=h5py.string_dtype())


def _strings_as_numbers(f: h5py.File, w: Path) -> None:
    n = f["clips/offset"].shape[0]
    _replace(f, "clips/offset", data=np.array(["0"] * n, dtype=object), dtype=h5py.string_dtype())


class _SharedData:
    """Pickles as a numpy array whose data is ``data``: the pickler memoises it, so every array made of the same
    bytes object refers to one copy in the file."""

    def __init__(self, data: bytes, shape: tuple[int, ...]) -> None:
        self.data, self.shape = data, shape

    def __reduce__(self):
        from numpy._core.multiarray import _reconstruct

        return _reconstruct, (np.ndarray, (0,), b"b"), (1, self.shape, np.dtype("f4"), False, self.data)


def _memo_shared_arrays(w: Path, run: Path) -> list:
    """A HumanAct12 pickle of 500 joints3D arrays whose data is one memoised 20 MB buffer (10 GB built, 21 MB file)."""
    frames = (20 << 20) // (24 * 3 * 4)
    data = bytes(frames * 24 * 3 * 4)
    joints = [_SharedData(data, (frames, 24, 3)) for _ in range(500)]
    (w / "amp.pkl").write_bytes(pickle.dumps({"joints3D": joints, "y": [0] * 500}, protocol=2))
    return ["preprocess", "--source", "humanact12", "amp.pkl", "-o", "ha.h5"]


def _padded_gzip(text: bytes, mib: int) -> bytes:
    """``text`` then ``mib`` MiB of spaces as one valid gzip member, built without compressing them all: after a
    full flush a deflate block refers to nothing before it, so one compressed MiB repeats; the CRC is true."""
    block = b" " * (1 << 20)
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    head, body = c.compress(text) + c.flush(zlib.Z_FULL_FLUSH), c.compress(block) + c.flush(zlib.Z_FULL_FLUSH)
    crc = zlib.crc32(text)
    for _ in range(mib):
        crc = zlib.crc32(block, crc)
    size = (len(text) + mib * len(block)) & 0xFFFFFFFF
    return b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\xff" + head + body * mib + c.flush() + struct.pack("<II", crc, size)


def _bvh_gzip_bomb(w: Path, run: Path) -> list:
    """A valid BVH then 3 GB of spaces, gzipped to 3 MB."""
    args = _bvh(w, lambda t: t.encode())
    (w / "bvh" / "walk.bvh.gz").write_bytes(_padded_gzip((w / "bvh" / "walk.bvh").read_bytes(), 3000))
    (w / "bvh" / "walk.bvh").unlink()
    return args


HOSTILE = {
    "nested-tuple-pickle": (_nested_key, 1, "refused: containers nested more than 100 deep"),
    "s0-dtype": (_s0_dtype, 1, "has zero-size items"),
    "huge-sparse-matrix": (_huge_sparse, 1, "bytes dense, more than MEMORY_BUDGET"),
    "shard-declares-3.8-TiB": (lambda w, r: _shard_copy(w, r, _huge_features), 1,
                               "refused: dataset features declares (3600000000, 263) items"),
    "table-larger-than-file": (lambda w, r: _shard_copy(w, r, _huge_table), 1,
                               "refused: dataset clips/offset declares (1000000000,) items"),
    "hdf5-external-storage": (lambda w, r: _shard_copy(w, r, _external_storage), 1,
                              "refused: dataset clips/offset keeps its data in other files"),
    "hdf5-external-link": (lambda w, r: _shard_copy(w, r, _external_link), 1, "refused: stats is an external link"),
    "hdf5-virtual-dataset": (lambda w, r: _shard_copy(w, r, _virtual), 1, "refused: dataset clips/length is virtual"),
    "negative-offset": (lambda w, r: _encode(w, r, _offsets(-5)), 1, "(index 1): offset -5 is negative"),
    "offset-out-of-range": (lambda w, r: _encode(w, r, _offsets(1)), 1, "lie outside the"),
    "bvh-huge-frames": (lambda w, r: _bvh(w, lambda t: re.sub(r"Frames: \d+", "Frames: 100000000", t).encode()), 1,
                        "wrong 'Frames:' line"),
    "bvh-frame-time-100000": (lambda w, r: _bvh(w, lambda t: re.sub(r"Frame Time: \S+", "Frame Time: 100000",
                                                                     t).encode()), 1, "frame time 100000 s is outside"),
    "bvh-bom-cr-reads": (lambda w, r: _bvh(w, lambda t: b"\xef\xbb\xbf" + t.replace("\n", "\r").encode()), 0, ""),
    "hdf5-unwritten-chunks": (_unwritten_chunks, 1, "refused: dataset features declares (32000000, 263) items, "
                              "33,664,000,000 bytes, but stores only 2 of its 31,250 chunks"),
    "hdf5-stored-zero-chunks": (lambda w, r: _shard_copy(w, r, _zero_chunks), 1, "stored bytes inflate to at most"),
    "features-beyond-clips": (lambda w, r: _shard_copy(w, r, _rows_beyond_clips), 1,
                              "features declares 100,000 rows but its clips use"),
    "hdf5-shared-strings": (lambda w, r: _shared_strings(w, r, chunked=False), 1,
                            "refused: its strings would decode to more than"),
    "hdf5-shared-strings-chunked": (lambda w, r: _shared_strings(w, r, chunked=True), 1,
                                    "refused: its strings would decode to more than"),
    "hdf5-string-array-attribute": (lambda w, r: _shard_copy(w, r, _string_attribute_array), 1,
                                    "refused: attribute lsgan_version of / holds variable-length data of shape (10,)"),
    "hdf5-strings-as-numbers": (lambda w, r: _shard_copy(w, r, _strings_as_numbers), 1,
                                "clips/offset holds object, not numbers"),
    "pickle-memo-shared-data": (_memo_shared_arrays, 1, "refused: the arrays it builds would take more than "
                                                        "MEMORY_BUDGET"),
    "bvh-gzip-bomb": (_bvh_gzip_bomb, 1, "refused: inflates to more than"),
}


@pytest.mark.parametrize("case", list(HOSTILE))
def test_hostile_input_is_one_line_or_reads(run: Path, tmp_path: Path, case: str) -> None:
    make, code, phrase = HOSTILE[case]
    args = make(tmp_path, run)
    before = snapshot(tmp_path)
    out = capped_lsgan(*args, cwd=tmp_path)
    assert out.returncode == code, out.stderr[-3000:]
    if code:
        one_error_line(out)
        assert phrase in out.stderr, out.stderr[-3000:]
    after = snapshot(tmp_path)
    assert {k: after.get(k) for k in before} == before


def test_a_cache_with_bad_tables_is_one_line(run: Path, tmp_path: Path) -> None:
    cases = {"clips/action": (lambda a: a + 99, r"window 0 has action \d+, not an index into the \d+ action names"),
             "clips/length": (lambda a: a * 0, "window 0 has length 0, not a positive frame count"),
             "captions/clip": (lambda a: a - 7, r"caption 0 belongs to window -\d+, outside the \d+ windows")}
    for name, (change, phrase) in cases.items():
        path = tmp_path / f"{name.replace('/', '-')}.h5"
        shutil.copy(run / "cache.h5", path)
        with h5py.File(path, "r+") as f:
            if not f[name].shape[0]:
                _replace(f, name, data=np.array([-7], np.int32))
                _replace(f, "captions/text", data=np.array(["x"], dtype=object), dtype=h5py.string_dtype())
                _replace(f, "captions/embedding", data=np.zeros((1, 0), np.float32))
            else:
                f[name][...] = change(f[name][()])
        with pytest.raises(DataFileError, match=phrase) as e:
            read_latent_cache(path)
        assert str(e.value).startswith(f"{path}: ") and "\n" not in str(e.value)
    path = tmp_path / "narrow.h5"
    shutil.copy(run / "cache.h5", path)
    with h5py.File(path, "r+") as f:
        _replace(f, "latents/mu", data=f["latents/mu"][:, :-1])
    with pytest.raises(DataFileError, match=r"latents/mu has shape \(\d+, 31\), expected \(\d+, 32\)"):
        read_latent_cache(path)
