"""A command whose stdout fails says so in one line naming stdout, with exit 1: a full disk, a closed descriptor, a
pipe whose reader has gone. Real processes, real descriptors; ``inspect`` prints its report to stdout."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from cli_runs import lsgan

from lsgan.cli.streams import Stream


@pytest.fixture(scope="module")
def shard(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("streams")
    out = lsgan("preprocess", "--source", "synthetic", "--num-clips", 8, "-o", d / "s.h5", cwd=d)
    assert out.returncode == 0, out.stderr
    return d / "s.h5"


def _full():
    return open("/dev/full", "w"), None


def _closed():
    return None, lambda: os.close(1)


def _no_reader():
    read, write = os.pipe()
    os.close(read)  # before the command starts: its first write meets a pipe nobody reads
    return os.fdopen(write, "w"), None


ROWS = [  # (how stdout fails, phrase)
    pytest.param(_full, "error: stdout: disk full", id="full-disk", marks=pytest.mark.skipif(
        not os.path.exists("/dev/full"), reason="this system has no /dev/full")),
    pytest.param(_closed, "error: stdout: it is closed; the output is lost", id="closed"),
    pytest.param(_no_reader, "error: stdout: its reader closed the pipe", id="broken-pipe"),
]


@pytest.mark.parametrize("stdout, phrase", ROWS)
@pytest.mark.parametrize("args", [["inspect", "SHARD"], ["--help"]], ids=["inspect", "help"])
def test_a_failing_stdout_is_one_line_naming_it(shard: Path, stdout, phrase: str, args: list[str]) -> None:
    before = shard.read_bytes()
    target, preexec = stdout()
    argv = [str(shard) if a == "SHARD" else a for a in args]
    try:
        out = subprocess.run([sys.executable, "-m", "lsgan.cli", *argv], stdout=target, stderr=subprocess.PIPE,
                             text=True, timeout=120, preexec_fn=preexec, cwd=shard.parent)
    finally:
        if target is not None:
            target.close()
    assert out.returncode == 1, out.stderr
    assert out.stderr.splitlines() == [out.stderr.strip()] and out.stderr.startswith(phrase), out.stderr
    assert shard.read_bytes() == before


def test_the_stream_wrapper_names_itself_and_passes_text_through(tmp_path: Path) -> None:
    """The wrapper as click sees it: text goes through, bytes are refused as a text stream refuses them, and a
    write error names the stream."""
    with open(tmp_path / "f.txt", "w") as f:
        s = Stream(f, "stdout")
        assert s.write("a\n") == 2 and s.at_line_start
        s.write("b")
        assert not s.at_line_start
        with pytest.raises(TypeError):
            s.write(b"x")
        s.flush()
    assert (tmp_path / "f.txt").read_text() == "a\nb"
    with pytest.raises(OSError) as e:
        Stream(None, "stdout").write("x")
    assert e.value.filename == "stdout"
