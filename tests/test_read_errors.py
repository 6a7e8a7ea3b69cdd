"""Unreadable inputs and unwritable outputs (issue 10): one line naming the file, a non-zero exit, nothing changed.

Real HDF5 files (a synthetic shard, damaged in place), real tiny training runs through the CLI.
"""
from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from torch.utils.data import DataLoader

from lsgan.data.dataset import MotionDataset, collate
from lsgan.data.shards import DataFileError, Shard, summarize, write_shard
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
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "lsgan.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env)


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


def _cache_as_shard(p: Path, run: Path) -> None:
    shutil.copy(run / "cache.h5", p)


BAD_SHARDS = {
    "not-hdf5": (_not_hdf5, "not an HDF5 file"),
    "empty": (_empty, "not an HDF5 file"),
    "truncated": (_truncated, "truncated or corrupt HDF5 (truncated file"),
    "other-hdf5": (_other_hdf5, "not an lsgan motion shard (no format attribute)"),
    "missing-dataset": (_missing_dataset, "not an lsgan motion shard (missing clips/length)"),
    "a-cache": (_cache_as_shard, "not an lsgan motion shard (format attribute is 'lsgan-latent-cache')"),
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
