"""Errors that name their file: what goes wrong while a file's content is interpreted becomes one line starting
with the file's path, so that ``lsgan`` never prints a bare exception text (``'optimizer'``, ``string indices
must be integers``) that leaves the user guessing which file is damaged.

``with reading(path, "a generate manifest"):`` around the code that interprets ``path`` turns the exceptions that
damaged or foreign content raises (KeyError, TypeError, AttributeError, IndexError, ValueError, torch's
RuntimeError) into a :class:`FileContentError`; an error that already starts with an existing path (lsgan's own
messages) passes unchanged. :func:`checkpoint_reader` does the same for the functions that build a model from a
checkpoint folder.
"""
from __future__ import annotations

import errno
import functools
import os
from collections.abc import Callable, Iterator
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


def checkpoint_reader(load: Callable) -> Callable:
    """A ``load(path, ..., prefer=...)`` that builds a model from a checkpoint, its errors naming the checkpoint's
    config.json (a damaged one, or one of another lsgan version)."""

    @functools.wraps(load)
    def wrapper(path, *args, **kwargs):
        from lsgan.models.checkpoint import CONFIG, resolve

        folder = resolve(path, kwargs.get("prefer", args[1] if len(args) > 1 else "best"))
        with reading(folder / CONFIG, "a checkpoint config this lsgan version reads"):
            return load(path, *args, **kwargs)

    return wrapper


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
