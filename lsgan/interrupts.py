"""Ctrl-C that is never lost, for a command that must exit 130 whenever it was interrupted.

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
from collections.abc import Callable, Iterator
from contextlib import contextmanager

REPOST_S = 0.01  # how soon a swallowed interrupt is raised again


class InterruptGuard:
    """Counts SIGINTs and raises KeyboardInterrupt only where the command can handle it (see the module).

    ``exiting``: the process ends when the guard stops (the lsgan program), so SIGINT is ignored from then on;
    otherwise (a command run inside a longer-lived process, e.g. a test) the previous handler comes back.
    Installed only in the main thread and only when SIGINT is at Python's default: a process started with
    SIGINT ignored (a background job) keeps ignoring it.
    """

    def __init__(self, *, exiting: bool = False) -> None:
        self.received = 0
        self.exiting = exiting
        self._frame = None
        self._previous = (signal.getsignal(signal.SIGINT), sys.unraisablehook)
        self.active = (threading.current_thread() is threading.main_thread()
                       and self._previous[0] is signal.default_int_handler)
        if self.active:
            signal.signal(signal.SIGINT, self._handle)
            sys.unraisablehook = self._unraisable

    def call(self, fn: Callable[..., object], *args, **kwargs) -> object:
        """``fn(*args, **kwargs)``, the part of the command that a Ctrl-C interrupts (also one that came before
        it started)."""
        self._frame = sys._getframe()
        try:
            if self.received:
                raise KeyboardInterrupt
            return fn(*args, **kwargs)
        finally:
            self._frame = None

    def stop(self) -> bool:
        """The command is over: SIGINT is ignored from here to the process's exit (``exiting``: Python's own
        handler would raise where nothing catches it, and late in the exit the signal would kill the process)
        or goes back to the previous handler; whether a SIGINT came while the guard was on."""
        if self.active:
            # signal.signal runs a pending handler before it replaces it: a SIGINT that came is counted
            signal.signal(signal.SIGINT, signal.SIG_IGN if self.exiting else self._previous[0])
            sys.unraisablehook = self._previous[1]
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
        if isinstance(sys.exc_info()[1], KeyboardInterrupt) or not self._inside_call(frame):
            return  # one is being handled, or the command has not started or is over: counting is enough
        raise KeyboardInterrupt

    def _unraisable(self, unraisable) -> None:
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            self._previous[1](unraisable)
            return
        try:  # raise it again from the main thread's next safe step, outside this finaliser
            timer = threading.Timer(REPOST_S, _thread.interrupt_main)
            timer.daemon = True
            timer.start()
        except RuntimeError:  # no new threads at interpreter shutdown: the count still says it came
            pass


@contextmanager
def sigint_held() -> Iterator[None]:
    """SIGINT held back for the block: the processes and threads started in it inherit the blocked mask and never
    see one, and a SIGINT that comes meanwhile (handled by another thread) is only recorded, then raised again
    when the block ends, at the caller's next step."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    came: list[int] = []
    handler = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    if handler is not None:  # None: set outside Python, or not the main thread; then the mask alone
        signal.signal(signal.SIGINT, lambda signum, frame: came.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        if handler is not None:
            signal.signal(signal.SIGINT, handler)  # runs the recorder first for one still pending
            if came:
                signal.raise_signal(signal.SIGINT)
