"""Atomic writes: a file or folder appears whole at its final path, or not at all.

Temporaries are made and recorded by :mod:`lsgan.outputs` (``.NAME.<pid>.*`` beside the target, noted in the
folder's registry with their process), so the next run removes a dead process's leftovers and nothing else.
Whatever is published here is recorded as lsgan's own; what is not lsgan's is never replaced.
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from lsgan import outputs
from lsgan.errors import name_write_error


def atomic_path(path: str | os.PathLike) -> tuple[int, str]:
    """A recorded temporary file beside ``path`` (same filesystem, so the rename is atomic): fd and name."""
    return outputs.temp_file(path)


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Move a finished temporary into place and record it as lsgan's (:func:`lsgan.outputs.publish`)."""
    outputs.publish(tmp, path)


def discard(tmp: str | os.PathLike) -> None:
    """Remove a temporary of :func:`atomic_path` after a failed write."""
    outputs.discard_temp(tmp)


@contextmanager
def atomic_folder(target: str | os.PathLike) -> Iterator[Path]:
    """Build a folder in a temporary one beside ``target``; on success it replaces ``target`` whole.

    On an error (or Ctrl-C) the temporary folder is removed and ``target`` is left as it was. A ``target``
    that is not lsgan's is never replaced (:func:`lsgan.outputs.publish` refuses it).
    """
    tmp = outputs.temp_folder(target)
    try:
        yield tmp
        outputs.publish(tmp, target)
    except BaseException as e:
        name_write_error(e, target, tmp)
        outputs.discard_temp(tmp)
        raise


@contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "wb", encoding: str | None = None) -> Iterator[IO]:
    """An open temporary file beside ``path``; when the block ends without error it replaces ``path``."""
    fd, tmp = outputs.temp_file(path)
    try:
        with os.fdopen(fd, mode, encoding=encoding) as f:
            yield f
        outputs.publish(tmp, path)
    except BaseException as e:
        name_write_error(e, path, tmp)
        outputs.discard_temp(tmp)
        raise
