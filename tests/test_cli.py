"""The command line as a user runs it: a real subprocess, exit codes, stderr, help with examples."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np


def lsgan(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "lsgan.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_every_command_has_help_with_examples():
    for cmd in ("preprocess", "inspect"):
        out = lsgan(cmd, "--help")
        assert out.returncode == 0 and "Examples:" in out.stdout, cmd


def test_preprocess_and_inspect_a_joints_folder(tmp_path, hml_fixtures):
    ref = np.load(hml_fixtures / "reference_features.npz")
    (tmp_path / "j").mkdir()
    np.save(tmp_path / "j" / "a.npy", ref["noisy/joints_in"])
    np.save(tmp_path / "j" / "b.npy", ref["noisy/joints_in"][:5])
    out = lsgan("preprocess", "--source", "joints", str(tmp_path / "j"), "-o", str(tmp_path / "j.h5"), "--mirror")
    assert out.returncode == 0, out.stderr
    assert "2 clips (1 mirrored)" in out.stderr and "skipped 1" in out.stderr and "too short" in out.stderr
    info = lsgan("inspect", str(tmp_path / "j.h5"), "--json")
    assert json.loads(info.stdout)["clips"] == 2
    text = lsgan("inspect", str(tmp_path / "j.h5")).stdout
    assert "clips      2" in text and "splits" in text


def test_errors_go_to_stderr_with_a_nonzero_exit(tmp_path):
    out = lsgan("preprocess", "--source", "joints", str(tmp_path / "missing"), "-o", str(tmp_path / "x.h5"))
    assert out.returncode != 0 and "does not exist" in out.stderr
    (tmp_path / "empty").mkdir()
    out = lsgan("preprocess", "--source", "joints", str(tmp_path / "empty"), "-o", str(tmp_path / "x.h5"))
    assert out.returncode == 1 and "no input files" in out.stderr
    (tmp_path / "bad.h5").write_bytes(b"nope")
    out = lsgan("inspect", str(tmp_path / "bad.h5"))
    assert out.returncode == 1 and "bad.h5" in out.stderr and out.stdout == ""


def test_strict_flag_fails_on_a_bad_clip(tmp_path):
    (tmp_path / "j").mkdir()
    np.save(tmp_path / "j" / "nan.npy", np.full((30, 22, 3), np.nan, np.float32))
    out = lsgan("preprocess", "--source", "joints", str(tmp_path / "j"), "-o", str(tmp_path / "x.h5"), "--strict")
    assert out.returncode == 1 and "nan.npy" in out.stderr and "NaN" in out.stderr
    assert not (tmp_path / "x.h5").exists()


def test_a_prompts_file_reads_as_an_editor_shows_it(tmp_path):
    """A byte-order mark is dropped (its first line can be a comment), CRLF and blank lines are fine, a prompt may
    hold a '#' when it ends with its frames, and every line keeps its own frame count."""
    from lsgan.generation import read_prompts

    path = tmp_path / "p.txt"
    path.write_bytes("\ufeff// my prompts\r\nwalk forward#40\r\n\r\ndance to track #5 slowly#60\nwave\n".encode())
    got = [(r.text, r.frames) for r in read_prompts(path, 80)]
    assert got == [("walk forward", 40), ("dance to track #5 slowly", 60), ("wave", 80)]


def test_lsgan_alone_prints_its_help_and_usage_errors_point_at_the_right_help():
    """`lsgan` with nothing asks for the help (stdout, exit 0), not an error line holding it; a usage error's hint
    names the program as users type it, also when run as `python -m lsgan.cli`."""
    out = lsgan()
    assert out.returncode == 0 and out.stdout.startswith("Usage: lsgan") and out.stderr == "", out.stderr
    assert "train-vae" in out.stdout
    for args, hint in ((["--bogus"], "(see 'lsgan --help')"), (["nosuch"], "(see 'lsgan --help')"),
                       (["train-vae", "--bogus"], "(see 'lsgan train-vae --help')")):
        out = lsgan(*args)
        assert out.returncode == 2 and out.stderr.strip().endswith(hint), out.stderr
