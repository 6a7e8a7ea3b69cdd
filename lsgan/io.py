"""Atomic writes: a file or folder appears whole at its final path, or not at all.

Temporaries are named ``.NAME.<pid>.*`` beside the target, so the next run can tell a dead process's
leftovers (removed by the next write of the same target) from a live one's. Whatever is published here is
recorded as lsgan's own (:mod:`lsgan.outputs`).
"""
from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from lsgan import outputs


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def atomic_path(path: Path) -> tuple[int, str]:
    """A temporary file beside ``path`` (same filesystem, so a rename is atomic), with the usual permissions."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    outputs.sweep_temps(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)
    os.chmod(tmp, 0o666 & ~_umask())
    return fd, tmp


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Move a finished temporary file into place and record it as lsgan's."""
    os.replace(tmp, path)
    outputs.record(path)


@contextmanager
def atomic_folder(target: str | os.PathLike) -> Iterator[Path]:
    """Build a folder in a temporary one beside ``target``; on success it replaces ``target`` whole.

    On an error (or Ctrl-C) the temporary folder is removed and ``target`` is left as it was. Callers
    that replace an existing folder check first that it is lsgan's (:func:`lsgan.outputs.claim_folder`).
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    outputs.sweep_temps(target)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.{os.getpid()}.", dir=target.parent))
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it private (0700); the finished folder gets the usual mode
    try:
        yield tmp
        old = None
        if target.exists():
            old = target.with_name(f".{target.name}.{os.getpid()}.old")
            shutil.rmtree(old, ignore_errors=True)
            target.rename(old)
        try:
            tmp.rename(target)
        except BaseException:  # e.g. Ctrl-C between the two renames: put the previous folder back
            if old is not None and not target.exists():
                old.rename(target)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        outputs.record(target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "wb", encoding: str | None = None) -> Iterator[IO]:
    """An open temporary file beside ``path``; when the block ends without error it replaces ``path``."""
    path = Path(path)
    fd, tmp = atomic_path(path)
    try:
        with os.fdopen(fd, mode, encoding=encoding) as f:
            yield f
        publish(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
