"""The test harness's forked runner (cli_runs.forked_lsgan) gives what a fresh ``lsgan`` process gives."""
from __future__ import annotations

import os
import subprocess

import pytest
from cli_runs import forked_lsgan, lsgan


def test_a_forked_command_gives_a_fresh_processs_code_streams_folder_and_environment(tmp_path):
    (tmp_path / "r.yaml").write_text("vae:\n  model: {num_heads: 0}\n")
    args = ("train-vae", "--data", "r.yaml", "--recipe", "r.yaml", "--out", "run")
    forked, fresh = forked_lsgan(*args, cwd=tmp_path), lsgan(*args, cwd=tmp_path)
    assert (forked.returncode, forked.stdout, forked.stderr) == (fresh.returncode, fresh.stdout, fresh.stderr)
    assert forked.returncode == 1 and "r.yaml: vae.model.num_heads: 0" in forked.stderr
    assert forked_lsgan("fly", cwd=tmp_path).returncode == 2
    debug = forked_lsgan(*args, cwd=tmp_path, env={"LSGAN_DEBUG": "1"})
    assert "Traceback" in debug.stderr and "Traceback" not in forked.stderr
    assert not (tmp_path / "run").exists() and os.getcwd() != str(tmp_path)


def test_a_forked_command_can_be_capped_and_killed(tmp_path):
    capped = forked_lsgan("preprocess", "--source", "synthetic", "--num-clips", 4, "-o", "s.h5", cwd=tmp_path,
                          headroom=16 << 20)
    assert capped.returncode != 0 and not (tmp_path / "s.h5").exists()
    with pytest.raises(subprocess.TimeoutExpired):
        forked_lsgan("preprocess", "--source", "synthetic", "--num-clips", 400, "-o", "s.h5", cwd=tmp_path,
                     timeout=0.5)
    fine = forked_lsgan("preprocess", "--source", "synthetic", "--num-clips", 4, "-o", "s.h5", cwd=tmp_path)
    assert fine.returncode == 0 and (tmp_path / "s.h5").is_file()


def test_a_command_whose_libraries_load_under_other_variables_gets_its_own_zygote(tmp_path, monkeypatch):
    from cli_runs import _zygote

    before = _zygote.cache_info().currsize
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")  # a variable torch reads when it loads, as a test may leave
    out = forked_lsgan("preprocess", "--source", "synthetic", "--num-clips", 4, "-o", "s.h5", cwd=tmp_path,
                       env={"OMP_NUM_THREADS": "2"}, headroom=2 << 30)
    assert out.returncode == 0, out.stderr
    assert _zygote.cache_info().currsize == before + 1
