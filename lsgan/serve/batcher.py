"""Micro-batching: requests that arrive close together go through one engine pass, in one worker thread.

The worker takes the first waiting request, then gathers more for up to ``gather_ms`` (and whatever is already
waiting) until the pass holds ``max_batch`` motions; a request that would overflow it opens the next pass. A
request that is the only one admitted does not wait: nothing could join it.
Admission is bounded (``max_in_flight``): past it :meth:`Batcher.submit` raises :class:`Busy` at once. A request
that waits past its timeout is cancelled and is not computed if its pass has not started.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field

from lsgan.faults import fault_point
from lsgan.serve.engine import Engine, Item

log = logging.getLogger("lsgan.serve")


class Busy(Exception):
    """The server holds as many requests as it may; try again after ``retry_after`` seconds."""

    def __init__(self, message: str, retry_after: int = 1) -> None:
        super().__init__(message)
        self.retry_after = retry_after


@dataclass
class Job:
    item: Item
    future: Future = field(default_factory=Future)
    queued_at: float = field(default_factory=time.perf_counter)
    started_at: float = 0.0  # when its pass began


class Batcher:
    """One worker thread feeding ``engine.run`` with batches of queued jobs."""

    def __init__(self, engine: Engine, *, gather_ms: float = 1.0, max_batch: int = 16,
                 max_in_flight: int = 64) -> None:
        self.engine, self.gather_s = engine, gather_ms / 1e3
        self.max_batch, self.max_in_flight = max_batch, max_in_flight
        self._queue: queue.Queue[Job | None] = queue.Queue()
        self._carry: Job | None = None  # a job that did not fit in the last pass
        self._lock = threading.Lock()
        self.in_flight = 0
        self.passes = 0
        self._worker = threading.Thread(target=self._loop, name="lsgan-engine", daemon=True)
        self._worker.start()

    def submit(self, item: Item) -> Job:
        """Queue ``item``; :class:`Busy` when ``max_in_flight`` requests are already admitted. Call :meth:`done`
        once the request is answered (or given up)."""
        with self._lock:
            if self.in_flight >= self.max_in_flight:
                raise Busy(f"server busy: {self.in_flight} requests in flight (the limit); retry shortly")
            self.in_flight += 1
        job = Job(item)
        self._queue.put(job)
        return job

    def done(self, job: Job) -> None:
        """The request of ``job`` is answered or abandoned: free its place, and skip it if not started."""
        job.future.cancel()
        with self._lock:
            self.in_flight -= 1

    def close(self, timeout: float = 30.0) -> None:
        """Finish the queued passes and stop the worker."""
        self._queue.put(None)
        self._worker.join(timeout)

    def _gather(self, first: Job) -> list[Job]:
        """``first`` and the jobs that join it within the gathering window, up to ``max_batch`` motions."""
        jobs, motions = [first], first.item.num
        deadline = time.perf_counter() + self.gather_s
        while motions < self.max_batch:
            alone = self.in_flight <= len(jobs)  # no other request admitted: waiting could only add latency
            try:
                job = self._queue.get(timeout=0.0 if alone else max(0.0, deadline - time.perf_counter()))
            except queue.Empty:
                break
            if job is None:  # closing: finish this pass, stop after it
                self._queue.put(None)
                break
            if motions + job.item.num > self.max_batch:
                self._carry = job
                break
            jobs.append(job)
            motions += job.item.num
        return jobs

    def _loop(self) -> None:
        while True:
            first, self._carry = self._carry or self._queue.get(), None
            if first is None:
                return
            jobs = [j for j in self._gather(first) if j.future.set_running_or_notify_cancel()]
            if jobs:
                self._run(jobs)

    def _run(self, jobs: list[Job]) -> None:
        """One engine pass for ``jobs``; when it fails, each job alone, so one bad job fails only itself."""
        now = time.perf_counter()
        for j in jobs:
            j.started_at = now
        self.passes += 1
        fault_point("serve.pass")  # tests/test_serve.py: SIGTERM while this pass's requests are in flight
        try:
            results = self.engine.run([j.item for j in jobs])
        except Exception as e:  # noqa: BLE001 - reported to the waiting request, the worker keeps running
            if len(jobs) == 1:
                log.exception("engine pass failed")
                jobs[0].future.set_exception(e)
                return
            for j in jobs:
                self._run([j])
            return
        for j, r in zip(jobs, results):
            j.future.set_result(r)
