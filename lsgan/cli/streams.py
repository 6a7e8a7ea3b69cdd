"""The program's standard streams while a command runs: a failed write names the stream, and stderr remembers where
its last line ended, so that the line after a Ctrl-C starts where it should."""
from __future__ import annotations

import errno
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager

_PLAIN = {errno.EPIPE: "its reader closed the pipe; the output is incomplete",
          errno.EBADF: "it is closed; the output is lost"}


class Stream:
    """A text stream (or None: the descriptor was closed when the program started) whose write and flush raise an
    OSError naming it (``stdout``) with a plain problem; everything else is the stream's own. ``at_line_start``:
    whether what was written so far ends a line; ``line_ended``: when a write last ended one (time.monotonic)."""

    def __init__(self, stream, name: str) -> None:
        self._stream, self.name = stream, name
        self.failed = False
        self.at_line_start, self.line_ended = True, 0.0

    def write(self, text: str) -> int:
        if not isinstance(text, str):  # as a text stream does (click tells text from binary streams so)
            raise TypeError(f"write() argument must be str, not {type(text).__name__}")
        if not text:
            return 0
        n = self._guard(lambda: self._stream.write(text))
        self.at_line_start = text.endswith("\n")
        if self.at_line_start:
            self.line_ended = time.monotonic()
        return n

    def flush(self) -> None:
        if self._stream is not None:
            self._guard(self._stream.flush)

    def _guard(self, act):
        if self._stream is None:
            raise OSError(errno.EBADF, _PLAIN[errno.EBADF], self.name)
        try:
            return act()
        except OSError as e:
            self.failed = True
            # no errno for a broken pipe: click's main would end the program on one silently, with exit code 1
            number = None if e.errno == errno.EPIPE else e.errno
            raise OSError(number, _PLAIN.get(e.errno, e.strerror), self.name) from None

    def __getattr__(self, name: str):
        if self._stream is None and name in ("encoding", "errors"):
            return {"encoding": "utf-8", "errors": "strict"}[name]
        return getattr(self._stream, name)


@contextmanager
def named_streams() -> Iterator[tuple[Stream, Stream]]:
    """sys.stdout and sys.stderr as :class:`Stream` for the block, the originals back after it. A stdout that failed
    is pointed at /dev/null (the program's own, not a test's), so the interpreter's last flush of what it still
    holds cannot print a second report."""
    saved = sys.stdout, sys.stderr
    out, err = Stream(sys.stdout, "stdout"), Stream(sys.stderr, "stderr")
    sys.stdout, sys.stderr = out, err
    try:
        yield out, err
    finally:
        sys.stdout, sys.stderr = saved
        if out.failed and saved[0] is sys.__stdout__ and saved[0] is not None:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, saved[0].fileno())
            os.close(devnull)
