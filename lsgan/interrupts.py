"""Ctrl-C that is never lost, for a command that must exit 130 whenever it was interrupted (143 for SIGTERM, which
a command handles as it handles Ctrl-C: a job scheduler's or a container's stop cleans up as a Ctrl-C does).

Python raises KeyboardInterrupt wherever the main thread is when SIGINT arrives. Inside a ``__del__`` method,
a weakref callback or a garbage-collector callback the exception cannot propagate: Python prints "Exception
ignored in ..." and carries on, and the run finishes as if nothing had happened. :class:`InterruptGuard`
replaces Python's handler for the life of a command:

- every SIGINT is counted, so the command can say at its end that it was interrupted even if the exception was
  swallowed on the way (by a finaliser or a library's bare ``except``);
- KeyboardInterrupt is raised only inside :meth:`InterruptGuard.call` (the command's own code) and never while
  an earlier one is being handled (a second Ctrl-C does not break the clean-up of the first);
- one swallowed by a finaliser reaches ``sys.unraisablehook``: the guard drops the "Exception ignored" message
  and raises the interrupt again in the main thread a moment later, where it can propagate.

Worker processes are kept out of it with :func:`sigint_held`: SIGINT is blocked while they are started, and a
child inherits the blocked mask through fork and exec (CPython starts its resource tracker this way), so it
never sees the Ctrl-C that the terminal sends to the whole process group.
"""
from __future__ import annotations

import _thread
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

REPOST_S = 0.01  # how soon a swallowed interrupt is raised again


class Interrupted(KeyboardInterrupt):
    """The KeyboardInterrupt a guard raises. ``signum``: SIGTERM if one came before the report, else SIGINT (when
    both are pending, Python runs SIGINT's handler first); ``came_at``: when the first came (time.monotonic)."""

    def __init__(self, guard: InterruptGuard) -> None:
        super().__init__()
        self.guard = guard

    @property
    def signum(self) -> int:
        return self.guard.signum

    @property
    def came_at(self) -> float:
        return self.guard.first_at


class InterruptGuard:
    """Counts SIGINTs and raises KeyboardInterrupt only where the command can handle it (see the module).

    ``exiting``: the process ends when the guard stops (the lsgan program), so SIGINT and SIGTERM are ignored from
    then on (the exit code already says what came);
    otherwise (a command run inside a longer-lived process, e.g. a test) the previous handler comes back.
    Installed only in the main thread, and for each signal only when it is at Python's default: a process started
    with SIGINT ignored (a background job) keeps ignoring it, and SIGTERM is taken in such a job too. ``signum``
    is the signal to report (SIGTERM once one came), ``first_at`` when the first came (time.monotonic).
    """

    def __init__(self, *, exiting: bool = False) -> None:
        self.received = 0
        self.signum, self.first_at = signal.SIGINT, 0.0
        self.exiting = exiting
        self._frame = None
        self._hook = sys.unraisablehook
        main = threading.current_thread() is threading.main_thread()
        defaults = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}
        self._taken = {s: signal.getsignal(s) for s, default in defaults.items()
                       if main and signal.getsignal(s) == default}  # signal -> the handler it had
        self.active = bool(self._taken)
        for s in self._taken:
            signal.signal(s, self._handle)
        if self.active:
            sys.unraisablehook = self._unraisable

    def call(self, fn: Callable[..., object], *args, **kwargs) -> object:
        """``fn(*args, **kwargs)``, the part of the command that a Ctrl-C interrupts (also one that came before
        it started)."""
        self._frame = sys._getframe()
        try:
            if self.received:
                raise Interrupted(self)
            return fn(*args, **kwargs)
        finally:
            self._frame = None

    def stop(self) -> bool:
        """The command is over: SIGINT is ignored from here to the process's exit (``exiting``: Python's own
        handler would raise where nothing catches it, and late in the exit the signal would kill the process)
        or goes back to the previous handler; whether a SIGINT came while the guard was on."""
        if self.active:
            # signal.signal runs a pending handler before it replaces it: a SIGINT that came is counted
            for s, previous in self._taken.items():
                signal.signal(s, signal.SIG_IGN if self.exiting else previous)
            sys.unraisablehook = self._hook
            self.active = False
        if self.received:
            # A KeyboardInterrupt that left an exec() of a string (dataclasses build their methods so, at import)
            # sets CPython's "unhandled KeyboardInterrupt" flag even when it was caught later, and `python -m`
            # then ends the process by SIGINT instead of with its exit code. Each exec() of a string resets it.
            exec("")  # noqa: S102 - a constant empty string
        return self.received > 0

    def _inside_call(self, frame) -> bool:
        while frame is not None:
            if frame is self._frame:
                return True
            frame = frame.f_back
        return False

    def _handle(self, signum, frame) -> None:
        self.received += 1
        self.first_at = self.first_at or time.monotonic()
        if signum == signal.SIGTERM:
            self.signum = signum
        if _running(frame, InterruptGuard._unraisable.__code__):  # a repost that came before the hook returned:
            self._repost()  # raised here it would be swallowed again (on a loaded machine 10 ms can pass in there)
            return
        if isinstance(sys.exc_info()[1], KeyboardInterrupt) or not self._inside_call(frame):
            return  # one is being handled, or the command has not started or is over: counting is enough
        raise Interrupted(self)

    def _unraisable(self, unraisable) -> None:
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            self._hook(unraisable)
            return
        self._repost()

    def _repost(self) -> None:
        """Raise the interrupt again from the main thread's next safe step, outside this finaliser."""
        try:
            timer = threading.Timer(REPOST_S, _thread.interrupt_main, (self.signum,))
            timer.daemon = True
            timer.start()
        except RuntimeError:  # no new threads at interpreter shutdown: the count still says it came
            pass


def _running(frame, code) -> bool:
    """Whether ``code`` is running in ``frame`` or a frame that called it."""
    while frame is not None:
        if frame.f_code is code:
            return True
        frame = frame.f_back
    return False


@contextmanager
def sigint_held() -> Iterator[None]:
    """SIGINT held back for the block: the processes and threads started in it inherit the blocked mask and never
    see one, and a SIGINT that comes meanwhile (handled by another thread) is only recorded, then raised again
    when the block ends, at the caller's next step."""
    with signals_held(signal.SIGINT):
        yield


@contextmanager
def signals_held(*signums: int) -> Iterator[None]:
    """The signals held back for the block (blocked in this thread; one that another thread receives is recorded
    by the handler put in for the block), then raised again when it ends: a step that must not be cut in two (a
    temporary made and recorded) runs whole, and the interrupt comes right after it."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    came: list[int] = []
    main = threading.current_thread() is threading.main_thread()
    handlers = {s: h for s in signums if main and (h := signal.getsignal(s)) is not None}  # None: set outside Python
    for s in handlers:
        signal.signal(s, lambda signum, frame: came.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, set(signums))
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        for s, handler in handlers.items():
            signal.signal(s, handler)  # runs the recorder first for one still pending
        for s in sorted(set(came), key=lambda s: s != signal.SIGTERM):  # a raising handler ends the loop:
            signal.raise_signal(s)  # SIGTERM first, so that a run stopped by both reports it
