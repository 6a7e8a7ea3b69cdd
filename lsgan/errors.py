"""Errors that name their file: what goes wrong while a file's content is interpreted becomes one line starting
with the file's path, so that ``lsgan`` never prints a bare exception text (``'optimizer'``, ``string indices
must be integers``) that leaves the user guessing which file is damaged.

``with reading(path, "a generate manifest"):`` around the code that interprets ``path`` turns the exceptions that
damaged or foreign content raises (KeyError, TypeError, AttributeError, IndexError, ValueError, torch's
RuntimeError) into a :class:`FileContentError`; an error that already starts with an existing path (lsgan's own
messages) passes unchanged.
(:func:`lsgan.models.checkpoint.checkpoint_reader` does the same for the functions that build a model from a
checkpoint folder.)
"""
from __future__ import annotations

import errno
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

CONTENT_ERRORS = (KeyError, IndexError, TypeError, AttributeError, ValueError, RuntimeError)


class FileContentError(ValueError):
    """A file whose content is not what lsgan expects; the message starts with the file's path."""


def reason(error: BaseException) -> str:
    """An exception in a few words: a missing key as ``no 'key'``, else its type and first line."""
    if isinstance(error, KeyError) and error.args:
        return f"no {error.args[0]!r}"
    mark, problem = getattr(error, "problem_mark", None), getattr(error, "problem", None)
    if mark is not None and problem:  # a parser's error with its place (yaml)
        return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0][:200]}" if text else type(error).__name__


def names_a_file(error: BaseException) -> bool:
    """Whether the message starts with the path of an existing file or folder (``PATH: problem``)."""
    head = str(error).split(": ", 1)[0]
    return bool(head) and len(head) < 4096 and os.path.exists(head)


def _device_error(error: BaseException) -> bool:
    """torch's RuntimeErrors of the device (out of memory, a CUDA failure), which no file caused."""
    return isinstance(error, RuntimeError) and any(w in str(error) for w in ("out of memory", "CUDA", "cuDNN"))


@contextmanager
def reading(path: str | os.PathLike, what: str, also: tuple[type[BaseException], ...] = ()) -> Iterator[None]:
    """Errors of interpreting ``path`` as ``what`` (e.g. 'a generate manifest') as one line naming it; ``also``:
    a parser's own exceptions (e.g. yaml.YAMLError)."""
    try:
        yield
    except (*CONTENT_ERRORS, *also) as e:
        if isinstance(e, FileContentError) or names_a_file(e) or _device_error(e):
            raise
        raise FileContentError(f"{path}: not {what} ({reason(e)})") from e


def name_write_error(error: BaseException, path: str | os.PathLike, written: str | os.PathLike | None = None) -> None:
    """Give an OSError of writing ``path`` that names no file (a full disk, a file-size limit) the name of ``path``,
    and a short write without an errno (numpy's "N requested and M written") its cause when it can be told from
    ``written`` (the file being written), so that the error line can say "disk full" or "file too large"."""
    if not isinstance(error, OSError) or error.filename is not None:
        return
    error.filename = str(path)
    cause = _short_write_cause(Path(written)) if error.errno is None and written is not None else None
    if cause is not None:
        error.errno, error.strerror = cause, os.strerror(cause)


def _short_write_cause(written: Path) -> int | None:
    """ENOSPC when the file system of ``written`` has no block left, EFBIG when the file reached this process's
    file-size limit, else None."""
    try:
        if os.statvfs(written.parent).f_bavail == 0:
            return errno.ENOSPC
        import resource

        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        if limit != resource.RLIM_INFINITY and written.stat().st_size >= limit:
            return errno.EFBIG
    except (OSError, ImportError, AttributeError):
        return None
    return None


def debugging() -> bool:
    """Whether tracebacks are asked for (``LSGAN_DEBUG`` set to anything but 0)."""
    return os.environ.get("LSGAN_DEBUG", "") not in ("", "0")


# OSErrors of writing in the words a user acts on (the bare strerror of ENOSPC does not say "disk full")
PLAIN_ERRNO = {errno.ENOSPC: "disk full (no space left on the device)",
               errno.EFBIG: "file too large (over the file system's or this process's file-size limit)",
               errno.EDQUOT: "disk quota exceeded"}


def describe(error: BaseException) -> str:
    """An exception as the one line ``error:`` prints: the file first, then the problem. A KeyError or
    IndexError (``'optimizer'``) names nothing a user can act on: it is an internal error, to be reported."""
    if isinstance(error, OSError) and error.filename is not None:
        said = PLAIN_ERRNO.get(error.errno) or error.strerror or f"cannot write it ({error.args[0]})"
        return f"{error.filename}: {said[:1].lower()}{said[1:]}"
    if isinstance(error, MemoryError) or (isinstance(error, RuntimeError) and "alloc" in str(error)
                                          and "bytes" in str(error)):  # torch's allocator says it so
        return _out_of_memory(error)
    if isinstance(error, (ValueError, OSError, RuntimeError)) and str(error):
        return " ".join(str(error).split("\n"))
    return (f"internal error: {type(error).__name__}: {error} (please report it; LSGAN_DEBUG=1 or --debug "
            "shows the traceback)")


def _out_of_memory(error: BaseException) -> str:
    """A MemoryError no reader refused beforehand, in one line: the allocation that failed (numpy says its size)
    and the file being worked on, the ``path`` of the innermost function of the traceback that has one."""
    lines = str(error).strip().splitlines()
    detail = lines[0][:200] if lines else "an allocation failed"
    path, tb = None, error.__traceback__
    while tb is not None:
        value = tb.tb_frame.f_locals.get("path")
        path = value if isinstance(value, (str, os.PathLike)) else path
        tb = tb.tb_next
    return f"{path}: out of memory ({detail})" if path is not None else f"out of memory ({detail})"
