"""The engine processes (lsgan.serve.worker): the same motions as in the server's process, failures relayed as
one line, passes side by side on two engines, and no process left behind when the server stops or dies."""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from serve_client import Server

from lsgan.serve.batcher import Batcher, Pass
from lsgan.serve.engine import Item, load_engine
from lsgan.serve.server import MAX_WORKERS
from lsgan.serve.worker import EngineProcess
from lsgan.threads import usable_cpus

pytestmark = pytest.mark.slow
SAME = 1e-5  # metres: "the same motion" (as tests/test_serve.py)
ITEMS = [Item(text="a person walks forward", frames=40, seed=3), Item(text="a person jumps", frames=17, num=2, seed=9)]


def children(pid: int) -> list[int]:
    """The child processes of ``pid`` (of any of its threads)."""
    tasks = Path(f"/proc/{pid}/task").iterdir()
    return sorted({int(c) for task in tasks for c in (task / "children").read_text().split()})


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


def test_the_engine_processes_end_with_the_server(serve_models: Path) -> None:
    """One engine child per usable core (at most MAX_WORKERS) by default, or --workers of them; SIGTERM (drain,
    exit 0) ends them all, and so does the server's sudden death."""
    for death, extra, count in (("SIGTERM", [], min(usable_cpus(), MAX_WORKERS)), ("SIGKILL", ["--workers", 3], 3)):
        s = Server("--gan", "gan", "--vae", "vae", *extra, cwd=serve_models)
        try:
            kids = children(s.proc.pid)
            assert len(kids) == count, s.stderr
            assert all(b"lsgan.serve.worker" in Path(f"/proc/{k}/cmdline").read_bytes() for k in kids)
            assert (f"{count} engine processes" if count > 1 else "one engine process") in s.stderr
            status, out = s.json("POST", "/v1/generate", {"text": "a person waves", "frames": 20, "seed": 1})
            assert status == 200 and len(out["motions"][0]["joints"]) == 20
            os.kill(s.proc.pid, getattr(signal, death))
            code = s.proc.wait(30)
            assert code == (0 if death == "SIGTERM" else -signal.SIGKILL), s.stderr
            deadline = time.monotonic() + 10
            while any(map(alive, kids)) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert not any(map(alive, kids)), f"an engine process outlived the server ({death})"
        finally:
            s.stop()


def test_passes_run_side_by_side_on_two_engines(serve_models: Path) -> None:
    """Two engine processes behind one batcher: a lone request goes to the first engine, on the free cores; a
    burst fills passes of max_batch motions on both engines at once, one thread each on two cores; right after
    it a lone pass still shares, until settle_ms pass without passes side by side; every motion equals the lone
    engine's for its seed (SAME, 1e-5 m: thread counts only reorder float sums)."""
    args = dict(gan=str(serve_models / "gan"), vae=str(serve_models / "vae"))
    engines = [EngineProcess(**args), EngineProcess(**args)]
    batcher = Batcher(engines, gather_ms=20, max_batch=2, cores=2, settle_ms=1000)

    def lone_pass() -> Pass:
        job = batcher.submit(items[0])
        job.future.result(60)
        batcher.done(job)
        return batcher.recent[-1]

    items = [Item(text=f"a person walks {k} steps", frames=24 + k, seed=k) for k in range(12)]
    try:
        lone = lone_pass()
        assert (lone.engine, lone.beside, lone.motions, lone.threads) == (0, 0, 1, None)  # its engine's own policy
        jobs = [batcher.submit(it) for it in items]
        results = [j.future.result(120) for j in jobs]
        for j in jobs:
            batcher.done(j)
        burst = list(batcher.recent)[1:]
        assert lone_pass().threads == 1  # alone for an instant under load: it still shares the cores
        time.sleep(1.05)
        assert lone_pass().threads is None  # the load has settled: every free core again
        assert sum(p.motions for p in burst) == len(items) and max(p.motions for p in burst) == 2
        assert {p.engine for p in burst} == {0, 1} and any(p.beside == 1 for p in burst)
        assert all(p.threads == 1 for p in burst if p.beside)  # two cores shared by two passes
        for it, got in zip(items, results):
            want = engines[0].run([it], threads=2)[0].joints[0]
            assert got.joints[0].shape == (it.frames, 22, 3)
            np.testing.assert_allclose(got.joints[0], want, rtol=0, atol=SAME)
    finally:
        batcher.close()
        for e in engines:
            e.close()


def test_requests_without_constraints_go_before_constrained_ones(serve_models: Path) -> None:
    """While a constrained pass runs, a constrained request and then a plain one arrive: the plain one's pass
    starts first (constrained passes are taken only when no plain request waits), and each constrained request
    has a pass of its own."""
    from lsgan.constraints import Constraints, path_points

    engine = EngineProcess(gan=str(serve_models / "gan"), vae=str(serve_models / "vae"))
    batcher = Batcher([engine], gather_ms=1, max_batch=8, cores=2)
    path = path_points(np.array([[0, 0, 0], [2.0, 0.5, 1.5], [9.5, 1.0, 6.0]]), 196)
    control = Constraints(196, path=path).record()
    try:
        first = batcher.submit(Item(text="a person walks", frames=196, num=2, seed=1, control=control))
        time.sleep(0.05)  # the first pass has started
        late = batcher.submit(Item(text="a person walks", frames=196, num=2, seed=2, control=control))
        plain = batcher.submit(Item(text="a person waves", frames=40, seed=3))
        for job in (first, late, plain):
            job.future.result(120)
            batcher.done(job)
        assert first.started_at < plain.started_at < late.started_at
        assert [p.motions for p in batcher.recent] == [2, 1, 2]
        assert late.future.result().control[0]["path_m"]["max"] < 1e-4
    finally:
        batcher.close()
        engine.close()


@pytest.mark.parametrize("signals, code", [((signal.SIGINT,), 130), ((signal.SIGTERM, signal.SIGINT), 130),
                                           ((signal.SIGINT, signal.SIGTERM), 130)],
                         ids=["ctrl-c", "term-then-int", "int-then-term"])
def test_ctrl_c_stops_the_server_in_one_line(serve_models: Path, signals, code: int) -> None:
    """Ctrl-C, alone or 50 ms from a SIGTERM, drains the server like SIGTERM and exits 130 with one 'interrupted'
    line: the signals uvicorn raises again after draining are recorded, never raised inside it (a traceback)."""
    s = Server("--gan", "gan", "--vae", "vae", "--workers", 1, cwd=serve_models)
    try:
        for i, sig in enumerate(signals):
            time.sleep(0.05 * i)
            os.kill(s.proc.pid, sig)
        assert s.proc.wait(30) == code, s.stderr
        s._reader.join(5)
        assert "Traceback" not in s.stderr and "ERROR" not in s.stderr, s.stderr
        tail = s.stderr.strip().splitlines()
        assert tail[-2:] == ["lsgan serve: stopped", "interrupted"], s.stderr
    finally:
        s.stop()
