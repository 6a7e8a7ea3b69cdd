"""Ctrl-C is never lost: a real ``lsgan`` process interrupted at any moment exits 130 with one line.

The terminal sends SIGINT to the whole process group (the main process and its workers), so the tests do the
same, at moments spread from start-up to the end of the run. A run may exit 0 only when it had finished (its
output written and its summary printed) before the signal came. The first moment is after Python's own
start-up (the interpreter and its site packages, measured here), which no program can guard; the runs use the
installed ``lsgan`` script, as a user does.
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

TRIES = 12
PREPROCESS = ["preprocess", "--source", "synthetic", "--num-clips", "80"]
SCRIPT = str(Path(sys.executable).with_name("lsgan"))


def python_start_up() -> float:
    """Seconds until a Python process has imported lsgan (the longest of three), before any of its code runs."""
    times = []
    for _ in range(3):
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-c", "import lsgan"], check=True)
        times.append(time.monotonic() - t0)
    return max(times)


def start(args: list, cwd: Path) -> subprocess.Popen:
    """``lsgan ARGS`` in a process group of its own, with SIGINT at its default (pytest may run in the
    background, where it is ignored)."""
    env = {k: v for k, v in os.environ.items() if k not in ("LSGAN_DEBUG", "LSGAN_FAULT")}
    env["OMP_NUM_THREADS"] = "1"
    return subprocess.Popen([SCRIPT, *map(str, args)], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def interrupted_at(args: list, cwd: Path, delay: float) -> tuple[int, str]:
    """(exit code, stderr) of a run whose process group is sent SIGINT after ``delay`` s (unless it has exited)."""
    proc = start(args, cwd)
    time.sleep(delay)
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    return proc.returncode, stderr


def problems(code: int, stderr: str, *, finished: bool) -> list[str]:
    """What breaks the promise in one interrupted run (``finished``: its output and summary are there)."""
    found = [f"{word} on stderr" for word in ("Traceback", "Exception ignored") if word in stderr]
    stopped = [line for line in stderr.splitlines() if line.startswith("interrupted")]
    if code == 130:
        found += [] if len(stopped) == 1 else [f"{len(stopped)} 'interrupted' lines"]
    elif code == 0:
        found += [] if finished and not stopped else ["exit 0 without a finished run"]
    else:
        found.append(f"exit code {code}")
    return found


@pytest.mark.parametrize("workers", [1, 2])
def test_ctrl_c_at_any_moment_exits_130(tmp_path: Path, workers: int) -> None:
    args = [*PREPROCESS, "--workers", workers]
    t0 = time.monotonic()
    ref = start([*args, "-o", tmp_path / "ref.h5"], tmp_path)
    _, err = ref.communicate(timeout=120)
    duration = time.monotonic() - t0
    assert ref.returncode == 0, err
    first = max(0.05, 2 * python_start_up())
    rng = random.Random(workers)
    seen: dict[int, int] = {}
    failures = []
    for i in range(TRIES):
        delay = first + (duration - first) * (i + rng.random()) / TRIES  # one moment in each twelfth of the run
        out = tmp_path / f"s{i}.h5"
        code, stderr = interrupted_at([*args, "-o", out], tmp_path, delay)
        seen[code] = seen.get(code, 0) + 1
        if found := problems(code, stderr, finished=out.is_file() and "plausibility:" in stderr):
            failures.append(f"signal at {delay:.2f} s of {duration:.2f} s: {', '.join(found)}\n{stderr[-2000:]}")
    print(f"workers {workers}: {TRIES} signals from {first:.2f} s to {duration:.2f} s, exit codes {seen}")
    assert not failures, "\n\n".join(failures)
    assert seen.get(130, 0) >= TRIES // 2, seen  # most moments fall inside the run


GUARDED = textwrap.dedent("""
    import os, signal, sys
    from lsgan.interrupts import InterruptGuard

    class Finaliser:
        def __del__(self):  # the Ctrl-C lands here, where Python can only print and ignore the exception
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(10_000):
                pass

    def work():
        Finaliser()
        for _ in range(10 ** 9):
            pass
        return "finished"

    guard = InterruptGuard()
    try:
        print(guard.call(work))
    except KeyboardInterrupt:
        print("interrupted")
    print("received", guard.stop())
""")


def test_an_interrupt_swallowed_by_a_finaliser_is_raised_again(tmp_path: Path) -> None:
    """The case behind lost Ctrl-Cs: SIGINT handled inside a ``__del__`` (Python ignores the exception there)."""
    out = subprocess.run([sys.executable, "-c", GUARDED], capture_output=True, text=True, cwd=tmp_path, timeout=120,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["interrupted", "received True"], out.stdout
    assert "Exception ignored" not in out.stderr and "Traceback" not in out.stderr


def test_without_the_guard_python_loses_it(tmp_path: Path) -> None:
    """The control: the same script with Python's own handler prints 'Exception ignored' and runs to the end."""
    script = GUARDED.replace("guard = InterruptGuard()", "").replace("guard.call(work)", "work()")
    script = script.replace("10 ** 9", "10 ** 6").replace('print("received", guard.stop())', "")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=120,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert out.stdout.startswith("finished"), out.stdout
    assert "Exception ignored" in out.stderr and "KeyboardInterrupt" in out.stderr


HELD = textwrap.dedent("""
    import os, signal
    from lsgan.interrupts import InterruptGuard, signals_held

    guard = InterruptGuard()
    steps = []

    def work():
        with signals_held(signal.SIGINT, signal.SIGTERM):
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(100_000):
                pass
            steps.append("the held step finished")
        steps.append("never")

    try:
        guard.call(work)
    except KeyboardInterrupt as e:
        steps.append(f"then {type(e).__name__} {int(e.signum)}")
    guard.stop()
    print("; ".join(steps))
""")


def test_signals_held_wait_for_the_step_and_then_interrupt_it(tmp_path: Path) -> None:
    """A step run under signals_held (a temporary made and recorded) finishes whole; SIGTERM and SIGINT that came
    meanwhile are raised right after it, and SIGTERM is what the interrupt reports."""
    out = subprocess.run([sys.executable, "-c", HELD], capture_output=True, text=True, cwd=tmp_path, timeout=120,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"the held step finished; then Interrupted {int(signal.SIGTERM)}", out.stdout
