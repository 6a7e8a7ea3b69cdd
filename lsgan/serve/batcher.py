"""Micro-batching: requests that arrive close together go through one engine pass; with several engines (each
its own process) passes run side by side.

A dispatcher thread takes the first waiting request, waits for an idle engine (the first one whenever it is
idle: passes alternating between processes ran 1.5x slower), gathers more requests for up to ``gather_ms`` (and
whatever is already waiting) until the pass holds ``max_batch`` motions, and hands the pass to that engine's
thread; a request that would overflow it opens the next pass. A request that is the only one admitted does not
wait: nothing could join it.
Threads per pass: a pass that runs alone (no other pass running, nobody waiting, and no pass started beside
another for ``settle_ms``) keeps its engine's own policy, the cores that other processes leave free; passes side
by side take ``cores // engines`` each. (On two cores, two one-thread passes made 1.3x the motions per second of
one two-thread pass, Bandai demo-size models, 16 new prompts a pass: the threads of a parallel region wait for
each other at every operation.) The settling time is for sustained load: between two passes there is often an
instant with nothing running or waiting, and a pass given every core then has another start beside it a
millisecond later (three threads on two cores). Waiting for ``settle_ms`` without overlap before a pass takes
every core made 32 clients 1-9% faster on two cores (four interleaved A/B pairs, Bandai demo-size models,
repeated prompts: +6.9, +9.2, +6.1 and +1.3%); one client at a time, whose passes never overlap, still gets every
core.
Admission is bounded (``max_in_flight``): past it :meth:`Batcher.submit` raises :class:`Busy` at once. A request
that waits past its timeout is cancelled and is not computed if its pass has not started.
"""
from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass, field

from lsgan.faults import fault_point
from lsgan.serve.engine import Engine, Item, Result
from lsgan.threads import usable_cpus

log = logging.getLogger("lsgan.serve")


class Busy(Exception):
    """The server holds as many requests as it may; try again after ``retry_after`` seconds."""

    def __init__(self, message: str, retry_after: int = 1) -> None:
        super().__init__(message)
        self.retry_after = retry_after


@dataclass(frozen=True)
class Pass:
    """What one pass was: its engine (index), its intra-op threads (None: the engine's own policy), its motions and
    the passes running beside it when it started."""

    engine: int
    threads: int | None
    motions: int
    beside: int


@dataclass
class Job:
    item: Item
    future: Future = field(default_factory=Future)
    queued_at: float = field(default_factory=time.perf_counter)
    started_at: float = 0.0  # when its pass began
    order: int | None = None  # its place in the queue among those of its rank (Batcher._put)


class Batcher:
    """A dispatcher thread that gathers queued jobs into passes, and a thread per engine that runs them."""

    def __init__(self, engines: list[Engine], *, gather_ms: float = 1.0, max_batch: int = 16,
                 max_in_flight: int = 64, cores: int | None = None, settle_ms: float = 250.0) -> None:
        self.engines = engines
        self.gather_s, self.max_batch, self.max_in_flight = gather_ms / 1e3, max_batch, max_in_flight
        self.settle_s = settle_ms / 1e3
        self._overlapped_at = -float("inf")  # when a pass last started beside another
        cores = cores or usable_cpus()
        self.share = max(1, cores // len(self.engines))  # threads of a pass beside others
        self._queue: queue.PriorityQueue = queue.PriorityQueue()  # (rank, order, job): see _put
        self._order = itertools.count()
        self._carry: Job | None = None  # a job that did not fit in the last pass: the next pass's first
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)  # an engine became idle
        self._idle = set(range(len(self.engines)))
        self._inboxes: list[queue.Queue] = [queue.Queue() for _ in self.engines]
        self.in_flight = 0
        self.running = 0  # passes in progress
        self.computing = 0  # requests in them
        self.recent: deque[Pass] = deque(maxlen=1024)  # the last passes started
        self._threads = [threading.Thread(target=self._work, args=(i,), name=f"lsgan-engine-{i}", daemon=True)
                         for i in range(len(self.engines))]
        self._threads.append(threading.Thread(target=self._dispatch, name="lsgan-batcher", daemon=True))
        for t in self._threads:
            t.start()

    def submit(self, item: Item) -> Job:
        """Queue ``item``; :class:`Busy` when ``max_in_flight`` requests are already admitted. Call :meth:`done`
        once the request is answered (or given up)."""
        with self._lock:
            if self.in_flight >= self.max_in_flight:
                raise Busy(f"server busy: {self.in_flight} requests in flight (the limit); retry shortly")
            self.in_flight += 1
        job = Job(item)
        self._put(job)
        return job

    def _put(self, job: Job | None) -> None:
        """Queue ``job`` behind the others of its rank: requests without constraints first, then constrained ones
        (each a pass of tenths of a second or more), then the closing mark (None) after everything."""
        rank = 2 if job is None else int(job.item.control is not None)
        order = next(self._order) if job is None or job.order is None else job.order
        if job is not None:
            job.order = order
        self._queue.put((rank, order, job))

    def _get(self, timeout: float | None = None) -> Job | None:
        return self._queue.get(timeout=timeout)[2]

    def done(self, job: Job) -> None:
        """The request of ``job`` is answered or abandoned: free its place, and skip it if not started."""
        job.future.cancel()
        with self._lock:
            self.in_flight -= 1

    def close(self, timeout: float = 30.0) -> None:
        """Finish the queued passes and stop the threads."""
        self._put(None)
        deadline = time.monotonic() + timeout
        for t in reversed(self._threads):  # the dispatcher first: it stops the engines' threads
            t.join(max(0.0, deadline - time.monotonic()))

    def _take_engine(self) -> int:
        """An idle engine, waiting for one; the first when it is idle, so that a lone request finds the same warm
        engine every time (another process's threads may still be spinning after its pass)."""
        with self._changed:
            self._changed.wait_for(lambda: self._idle)
            index = min(self._idle)
            self._idle.discard(index)
            return index

    def _gather(self, first: Job) -> list[Job]:
        """``first`` and the jobs that join it within the gathering window, up to ``max_batch`` motions. A job with
        constraints has its pass to itself, taken only when no request without constraints waits (:meth:`_put`):
        it is optimised for tenths of a second or more, which others should not wait for."""
        jobs, motions = [first], first.item.num
        if first.item.control is not None:
            return jobs
        deadline = time.perf_counter() + self.gather_s
        while motions < self.max_batch:
            alone = self.in_flight <= len(jobs) + self.computing  # no other request admitted could join
            try:
                job = self._get(timeout=0.0 if alone else max(0.0, deadline - time.perf_counter()))
            except queue.Empty:
                break
            if job is None:  # closing: finish this pass, stop after it
                self._put(None)
                break
            if job.item.control is not None:  # a pass of its own, after the requests without constraints
                self._put(job)
                break
            if motions + job.item.num > self.max_batch:
                self._carry = job
                break
            jobs.append(job)
            motions += job.item.num
        return jobs

    def _dispatch(self) -> None:
        """Passes to idle engines until closed; then the engines' threads finish their passes and stop."""
        while True:
            first, self._carry = self._carry or self._get(), None
            if first is None:
                break
            index = self._take_engine()  # after the first request: the first engine whenever it is idle by then
            jobs = [j for j in self._gather(first) if j.future.set_running_or_notify_cancel()]
            with self._changed:
                if not jobs:
                    self._idle.add(index)
                    continue
                threads = self._pass_threads()
                if self.running:
                    self._overlapped_at = time.perf_counter()
                self.recent.append(Pass(index, threads, sum(j.item.num for j in jobs), self.running))
                self.running += 1
                self.computing += len(jobs)
            self._inboxes[index].put((jobs, threads))
        for inbox in self._inboxes:
            inbox.put(None)

    def _pass_threads(self) -> int | None:
        """Intra-op threads for the pass about to start (under the lock): None (the engine's own policy, the cores
        other processes leave free) for a pass alone, after ``settle_ms`` without passes side by side; ``share``
        otherwise."""
        alone = self.running == 0 and self._carry is None and self._queue.empty()
        settled = time.perf_counter() - self._overlapped_at > self.settle_s
        return None if (alone and settled) or len(self.engines) == 1 else self.share

    def _work(self, index: int) -> None:
        """Engine ``index``'s thread: the passes the dispatcher hands it. The engine is marked idle before the
        answers go out, so that the request an answer brings finds it idle (the first engine, all its threads)."""
        while (task := self._inboxes[index].get()) is not None:
            jobs, threads = task
            try:
                outcomes = self._run(self.engines[index], jobs, threads)
            finally:
                with self._changed:
                    self.running -= 1
                    self.computing -= len(jobs)
                    self._idle.add(index)
                    self._changed.notify_all()
            for job, outcome in outcomes:
                if isinstance(outcome, Exception):
                    job.future.set_exception(outcome)
                else:
                    job.future.set_result(outcome)

    def _run(self, engine: Engine, jobs: list[Job], threads: int | None) -> list[tuple[Job, Result | Exception]]:
        """One engine pass for ``jobs``; when it fails, each job alone, so one bad job fails only itself."""
        now = time.perf_counter()
        for j in jobs:
            j.started_at = now
        fault_point("serve.pass")  # tests/test_serve.py: SIGTERM while this pass's requests are in flight
        try:
            return list(zip(jobs, engine.run([j.item for j in jobs], threads=threads)))
        except Exception as e:  # noqa: BLE001 - reported to the waiting request, the worker keeps running
            if len(jobs) == 1:
                log.exception("engine pass failed")
                return [(jobs[0], e)]
            return [outcome for j in jobs for outcome in self._run(engine, [j], threads)]
