"""How many intra-op threads torch uses: per workload, and re-decided as the machine gets busy or idle.

Two facts measured on a 2-core machine set the policy (``benchmarks/contention.py``):

- Small matrix work (the latent GAN's MLP steps, a batch of a few latents) gains nothing from a second thread:
  the work per operation is below what pays for waking it. Such workloads are ``light``: one thread.
- Heavy work (VAE steps, encoding, decoding motions, the text encoder) runs ~1.8x faster on two threads when the
  machine is idle, but threads that wait on each other collapse when another process takes a core: every
  parallel region ends when its slowest thread does, and that thread waits for the scheduler. Beside one
  busy-loop process, two threads ran a VAE step 3.2x slower than idle; one thread, 1.8x. Such workloads are
  ``heavy``: as many threads as there are cores that other processes leave free, re-decided every ``interval``
  seconds from what the other processes actually used (``/proc/stat`` minus this process's own CPU time).

An explicit count always wins: ``LSGAN_THREADS`` (what ``lsgan --threads N`` sets) or ``OMP_NUM_THREADS``.
Elsewhere than Linux (no ``/proc``), work keeps torch's own count. The module imports torch only where it sets
torch's count, so that the torch-free ONNX runtime (lsgan.deploy.runtime) shares the rest.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

ENV = "LSGAN_THREADS"
LARGE_BATCH = 64  # motions decoded at once from which every operation is large (benchmarks/contention.py)
_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def fixed_threads() -> int | None:
    """The count the user fixed (``LSGAN_THREADS``, else ``OMP_NUM_THREADS``), or None."""
    for name in (ENV, "OMP_NUM_THREADS"):
        value = os.environ.get(name, "").strip()
        if value:
            try:
                n = int(value)
            except ValueError:
                raise ValueError(f"{name}={value!r}: expected a whole number of threads >= 1") from None
            if n < 1:
                raise ValueError(f"{name}={value!r}: expected a whole number of threads >= 1")
            return n
    return None


def usable_cpus() -> int:
    """Cores this process may run on: its affinity, bounded by a cgroup (v2) CPU quota."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        if quota != "max":
            cpus = min(cpus, max(1, int(int(quota) / int(period))))
    except (OSError, ValueError):
        pass
    return max(1, cpus)


@dataclass
class _Sample:
    wall: float
    busy_ticks: int  # every process's CPU time on our cores
    own_ticks: int  # this process's CPU time (all its threads)


def _sample() -> _Sample | None:
    """CPU time used on the cores this process may use, and by this process; None without /proc."""
    try:
        cores = os.sched_getaffinity(0)
        busy = 0
        with open("/proc/stat") as f:
            for line in f:
                if not line.startswith("cpu") or line[3] == " " or int(line.split()[0][3:]) not in cores:
                    continue
                v = [int(x) for x in line.split()[1:]]
                busy += sum(v[:8]) - v[3] - v[4]  # user nice system idle iowait irq softirq steal: not idle/iowait
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        own = int(fields[11]) + int(fields[12])  # utime, stime
    except (OSError, ValueError, IndexError, AttributeError):
        return None
    return _Sample(time.monotonic(), busy, own)


def others_load(before: _Sample, after: _Sample) -> float:
    """Cores' worth of CPU the other processes used between two samples."""
    seconds = after.wall - before.wall
    if seconds <= 0:
        return 0.0
    others = (after.busy_ticks - before.busy_ticks) - (after.own_ticks - before.own_ticks)
    return max(0.0, others / _TICKS / seconds)


def _running_others() -> float | None:
    """Runnable tasks right now that are not this process's threads (``/proc/loadavg``), or None."""
    try:
        running = int(Path("/proc/loadavg").read_text().split()[3].split("/")[0])
        own = 0
        for task in Path("/proc/self/task").iterdir():
            if (task / "stat").read_text().rsplit(")", 1)[1].split()[0] == "R":
                own += 1
    except (OSError, ValueError, IndexError):
        return None
    return float(max(0, running - own))


def start_threads(window: float = 0.25) -> int:
    """Threads for the cores other processes leave free, measured over ``window`` seconds now (every usable core
    without /proc)."""
    cpus = usable_cpus()
    before = _sample()
    if cpus == 1:
        return 1
    if before is None:
        return cpus
    time.sleep(window)
    after = _sample()
    return threads_for(cpus - others_load(before, after), cpus) if after else cpus


def run_threads(recorded: int = 0) -> int:
    """A training run's count, kept for the whole run so that its numbers do not depend on the machine's load
    (a step's sums come out in another order on another count): fixed by the user, else the count the run
    recorded when it started (a resume), else the free cores now."""
    return fixed_threads() or recorded or start_threads()


def threads_said() -> str:
    """The policy in force, in words: a fixed count, or adaptive up to the usable cores."""
    fixed = fixed_threads()
    return f"{fixed} (fixed)" if fixed else f"adaptive, up to {usable_cpus()}"


def _torch():
    import torch

    return torch


def _median(values: list[float]) -> float:
    return sorted(values)[len(values) // 2]


def threads_for(free_cores: float, cpus: int) -> int:
    """Threads for heavy work with ``free_cores`` left by other processes: rounded, at least 1, at most ``cpus``."""
    return max(1, min(cpus, int(free_cores + 0.5)))


class FreeCores:
    """Threads for the cores other processes leave free, re-measured at most every ``interval`` seconds from what
    they used (``/proc/stat``); between two measurements, the last one; before the first window has passed, the
    tasks runnable right now. Torch-free: the ONNX runtime follows the load with it too."""

    def __init__(self, interval: float = 0.5) -> None:
        self.interval, self.cpus = interval, usable_cpus()
        self._last = _sample()
        self._free = 0

    def threads(self) -> int | None:
        """The count now, or None where the load cannot be read (no /proc)."""
        if self._last is None:
            return None
        if time.monotonic() - self._last.wall >= self.interval and (now := _sample()) is not None:
            others, self._last = others_load(self._last, now), now
        elif self._free:
            return self._free
        else:  # too short a window to measure: count what is runnable right now
            others = _running_others() or 0.0
        self._free = threads_for(self.cpus - others, self.cpus)
        return self._free


class ThreadPolicy:
    """Sets torch's intra-op threads for a piece of work and keeps them right while it runs.

    ``with ThreadPolicy(tune=True) as policy:`` then ``policy.update()`` before each step. Every ``interval``
    seconds it measures how many cores other processes leave free (the *level*). The count for a level is:

    - fixed (``threads=``, ``LSGAN_THREADS``, ``OMP_NUM_THREADS``): always that;
    - ``tune`` (a loop of similar steps: training, encoding): the faster of two counts, the free cores and the
      other choice (one thread when all cores are free, all of them when some are taken), timed alternately over
      a few steps the first time the level is met and remembered for it. Small steps keep one thread even on an
      idle machine; a step of large operations keeps all threads beside a busy process, where it gets more of
      the machine than one thread would;
    - ``large`` (one-off work made of large operations: decoding a batch of many motions): all cores;
    - otherwise: the free cores.

    The count torch had before is restored on exit.
    """

    def __init__(self, *, tune: bool = False, large: bool = False, interval: float = 0.5,
                 threads: int | None = None, warmup: int = 2, trials: int = 3) -> None:
        self.tune, self.large, self.interval = tune, large, interval
        self.fixed = threads if threads is not None else fixed_threads()
        self.cpus = usable_cpus()
        self.threads = 0
        self.chosen: dict[int, int] = {}  # level (free cores) -> the count its trial chose
        self._warmup, self._trials = warmup, trials
        self._free = FreeCores(interval)
        self._before = _torch().get_num_threads()
        self._trial: list[int | None] = []  # the counts of the next steps of a running trial (None: not timed)
        self._level = 0  # the level the running trial is for
        self._tick: tuple[float, int | None] | None = None
        self._laps: dict[int, list[float]] = {}

    @property
    def tuning(self) -> bool:
        """Whether a trial is running."""
        return bool(self._trial) or self._tick is not None

    def free_threads(self) -> int:
        """The level: :class:`FreeCores` (torch's own count without /proc)."""
        n = self._free.threads()
        return self._before if n is None else n

    def _next_trial_count(self) -> int | None:
        """Time the step that just ended; the count of the next step while a trial runs, else None (then the
        trial's choice is remembered for its level)."""
        now = time.perf_counter()
        if self._tick is not None and self._tick[1] is not None:
            self._laps.setdefault(self._tick[1], []).append(now - self._tick[0])
        if not self._trial:
            self._tick = None
            if len(self._laps) == 2:
                self.chosen[self._level] = min(self._laps, key=lambda n: _median(self._laps[n]))
            self._laps = {}
            return None
        n = self._trial.pop(0)
        self._tick = (now, n)
        return n

    def _start_trial(self, level: int) -> None:
        other = 1 if level == self.cpus else self.cpus
        self._level = level
        self._trial = [None] * self._warmup + [level, other] * self._trials

    def decide(self) -> int:
        """The count for the next step (see the class)."""
        if self.fixed is not None:
            return self.fixed
        if self.cpus == 1:
            return 1
        if self.tuning:
            n = self._next_trial_count()
            if n is not None or self.tuning:
                return n if n is not None else self.threads or self.cpus
        if self.large:
            return self.cpus
        level = self.free_threads()
        if not self.tune:
            return level
        if level not in self.chosen:
            self._start_trial(level)
            return self._next_trial_count() or level
        return self.chosen[level]

    def update(self) -> int:
        """Set torch's count for the next step (only when it changes); returns it."""
        n = self.decide()
        if n != _torch().get_num_threads():  # not self.threads: another policy may have set torch's count since
            _torch().set_num_threads(n)
        self.threads = n
        return n

    def __enter__(self) -> ThreadPolicy:
        self.update()
        return self

    def __exit__(self, *exc) -> None:
        _torch().set_num_threads(self._before)
