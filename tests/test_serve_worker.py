"""The engine's own process (lsgan.serve.worker): the same motions as in the server's process, failures relayed as
one line, and no process left behind when the server stops or dies."""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from serve_client import Server

from lsgan.serve.engine import Item, load_engine
from lsgan.serve.worker import EngineProcess

pytestmark = pytest.mark.slow
ITEMS = [Item(text="a person walks forward", frames=40, seed=3), Item(text="a person jumps", frames=17, num=2, seed=9)]


def children(pid: int) -> list[int]:
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_child_gives_the_in_process_motions_and_relays_refusals(serve_models: Path, monkeypatch) -> None:
    """Joints, batch size and lengths equal the in-process engine's bit for bit (one thread in both: the count
    decides the order of float sums); a refused item is a ValueError with the engine's own message, and the child
    keeps serving after it; closing stops the child."""
    monkeypatch.setenv("LSGAN_THREADS", "1")  # the child inherits it
    args = dict(gan=str(serve_models / "gan"), vae=str(serve_models / "vae"))
    threads = torch.get_num_threads()
    local = load_engine(**args)
    child = EngineProcess(**args)
    try:
        assert (child.condition, child.max_frames, child.backend) == (local.condition, local.max_frames, "torch")
        got, want = child.run(ITEMS), local.run(ITEMS)
        assert [r.batch_size for r in got] == [3, 3]
        for g, w in zip(got, want):
            assert [j.shape for j in g.joints] == [j.shape for j in w.joints]
            for a, b in zip(g.joints, w.joints):
                np.testing.assert_array_equal(a, b)
        with pytest.raises(ValueError) as refused:
            child.run([Item(text="x", frames=5000)])
        with pytest.raises(ValueError) as alone:
            local.run([Item(text="x", frames=5000)])
        assert str(refused.value) == str(alone.value) and "\n" not in str(refused.value)
        np.testing.assert_array_equal(child.run(ITEMS[:1])[0].joints[0], local.run(ITEMS[:1])[0].joints[0])
    finally:
        child.close()
        torch.set_num_threads(threads)  # the in-process engine set this process's count
    assert child._proc.returncode == 0


def test_a_load_failure_is_the_same_one_line(serve_models: Path, tmp_path: Path) -> None:
    """A run that is not a GAN: the child's one-line reason, as loading in-process gives it, and the child exits."""
    args = dict(gan=str(serve_models / "vae"), vae=str(serve_models / "vae"))
    with pytest.raises(ValueError) as local:
        load_engine(**args)
    with pytest.raises(ValueError) as child:
        EngineProcess(**args)
    assert str(child.value) == str(local.value)


def test_the_engine_process_ends_with_the_server(serve_models: Path) -> None:
    """One engine child per server; SIGTERM (drain, exit 0) ends it, and so does the server's sudden death."""
    for death in ("SIGTERM", "SIGKILL"):
        s = Server("--gan", "gan", "--vae", "vae", cwd=serve_models)
        try:
            kids = children(s.proc.pid)
            assert len(kids) == 1 and b"lsgan.serve.worker" in Path(f"/proc/{kids[0]}/cmdline").read_bytes()
            status, out = s.json("POST", "/v1/generate", {"text": "a person waves", "frames": 20, "seed": 1})
            assert status == 200 and len(out["motions"][0]["joints"]) == 20
            os.kill(s.proc.pid, getattr(signal, death))
            code = s.proc.wait(30)
            assert code == (0 if death == "SIGTERM" else -signal.SIGKILL), s.stderr
            deadline = time.monotonic() + 10
            while alive(kids[0]) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert not alive(kids[0]), f"the engine process outlived the server ({death})"
        finally:
            s.stop()
