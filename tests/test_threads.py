"""lsgan's thread policy (lsgan/threads.py) with real busy processes and real step timings."""
from __future__ import annotations

import subprocess
import sys
import time

import pytest
import torch

from lsgan import threads as T

LINUX = sys.platform.startswith("linux")


@pytest.fixture()
def adaptive(monkeypatch):
    """No fixed count in the environment: the policy decides."""
    monkeypatch.delenv("LSGAN_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def busy(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
        p.wait()


@pytest.mark.parametrize("env, value, expect", [
    ("LSGAN_THREADS", "3", 3), ("OMP_NUM_THREADS", "2", 2), ("LSGAN_THREADS", "", None),
])
def test_fixed_count_comes_from_the_environment(adaptive, monkeypatch, env, value, expect):
    monkeypatch.setenv(env, value)
    assert T.fixed_threads() == expect


@pytest.mark.parametrize("value", ["0", "two", "-1"])
def test_a_bad_fixed_count_is_refused_by_name(adaptive, monkeypatch, value):
    monkeypatch.setenv("LSGAN_THREADS", value)
    with pytest.raises(ValueError, match="LSGAN_THREADS"):
        T.fixed_threads()


def test_lsgan_threads_wins_over_omp(adaptive, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "4")
    monkeypatch.setenv("LSGAN_THREADS", "1")
    assert T.fixed_threads() == 1


@pytest.mark.parametrize("free, cpus, expect", [(2.0, 2, 2), (1.6, 2, 2), (1.3, 2, 1), (0.2, 2, 1), (9.0, 4, 4)])
def test_threads_for_rounds_the_free_cores_within_one_and_the_cpus(free, cpus, expect):
    assert T.threads_for(free, cpus) == expect


def test_a_fixed_count_is_applied_and_the_old_one_restored(adaptive):
    torch.set_num_threads(2)
    with T.ThreadPolicy(tune=True, threads=1) as policy:
        assert torch.get_num_threads() == 1 and not policy.tuning
    assert torch.get_num_threads() == 2


@pytest.mark.skipif(not LINUX, reason="the load is read from /proc")
def test_others_load_sees_a_busy_process():
    before = T._sample()
    procs = busy(1)
    try:
        time.sleep(0.6)
        after = T._sample()
    finally:
        stop(procs)
    assert T.others_load(before, after) > 0.5


@pytest.mark.skipif(not LINUX, reason="the load is read from /proc")
def test_the_count_drops_to_one_while_every_core_is_busy(adaptive):
    cpus = T.usable_cpus()
    if cpus < 2:
        pytest.skip("one usable core: the policy always runs one thread")
    procs = busy(cpus)
    try:
        with T.ThreadPolicy(interval=0.3) as policy:
            time.sleep(0.8)
            assert policy.update() == 1
            assert torch.get_num_threads() == 1
    finally:
        stop(procs)


def _step_costing(policy: T.ThreadPolicy, seconds_by_count: dict[int, float], steps: int) -> list[int]:
    """Run ``steps`` steps whose duration depends on torch's thread count; the counts used, step by step."""
    used = []
    for _ in range(steps):
        used.append(policy.update())
        time.sleep(seconds_by_count[1 if torch.get_num_threads() == 1 else 2])
    return used


@pytest.mark.skipif(not LINUX, reason="the load is read from /proc")
@pytest.mark.parametrize("one_is_faster", [True, False])
def test_a_trial_keeps_the_faster_count_for_its_level(adaptive, one_is_faster):
    cpus = T.usable_cpus()
    if cpus < 2:
        pytest.skip("one usable core: nothing to try")
    costs = {1: 0.01, 2: 0.05} if one_is_faster else {1: 0.05, 2: 0.01}
    with T.ThreadPolicy(tune=True, interval=60.0, warmup=1, trials=2) as policy:
        level = policy._level
        arms = {level, 1 if level == cpus else cpus}
        if 1 not in arms:
            pytest.skip(f"the machine is busy: the trial compares {sorted(arms)}, not one thread")
        used = _step_costing(policy, costs, 8)
        assert not policy.tuning
        assert policy.chosen[level] == (1 if one_is_faster else max(arms))
        assert set(used[1:5]) == arms  # the trial alternated between the two counts
        assert used[-1] == policy.chosen[level]


def test_a_single_core_or_large_work_needs_no_trial(adaptive):
    policy = T.ThreadPolicy(large=True)
    assert policy.update() == policy.cpus and not policy.tuning


@pytest.mark.skipif(T.usable_cpus() < 2, reason="one usable core: nothing to compare")
def test_inference_does_not_depend_on_the_thread_count(adaptive):
    """Why generation and encoding may follow the load while training may not: their results are bitwise the
    same on one thread and on two (a VAE decode and encode, MiniLM), whereas a training step's are not."""
    from lsgan.models.text import load_text_encoder
    from lsgan.models.vae import MotionVAE, VAEConfig

    torch.manual_seed(0)
    vae = MotionVAE(VAEConfig(d_model=128, num_layers=3, ff_size=512)).eval()
    enc = load_text_encoder("minilm")
    z, x = torch.randn(8, 256), torch.randn(8, 120, 263)
    mask = torch.arange(120)[None] < torch.tensor([120, 96, 80, 64, 120, 40, 100, 120])[:, None]
    out = {}
    for n in (1, 2):
        torch.set_num_threads(n)
        with torch.no_grad():
            out[n] = (vae.decode(z, mask), *vae.encode(x, mask),
                      enc.encode(["a person walks forward", "someone jumps twice and then sits down"] * 4))
    assert all(torch.equal(a, b) for a, b in zip(out[1], out[2]))
