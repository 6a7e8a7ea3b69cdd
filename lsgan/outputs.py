"""Which files are lsgan's: nothing of the user's is replaced or deleted, even with ``--force``.

Every file or folder lsgan writes atomically is fingerprinted in a small registry beside it,
``.lsgan-outputs.json`` in the same folder (a file by size and SHA-256; a folder by the names, sizes and
modification times of everything in it). A path is lsgan's only while it still matches its entry: a file
the user edited, or a folder they added to, is theirs again. Commands claim their outputs before writing:

* an output that does not exist (or an empty folder) is free;
* an existing one is refused unless ``force``; with ``force`` only lsgan's own entries are replaced or
  cleared, and anything else is named and left alone;
* an output that is, holds or lies inside one of the command's inputs is refused outright.

Temporary files of an interrupted write (``.NAME.<pid>.*.tmp`` and folders ``.NAME.<pid>.*``) are swept
when their process is gone.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path

REGISTRY = ".lsgan-outputs.json"


class OutputError(ValueError):
    """An output that may not be written: the message names it and says why."""


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _tree(folder: Path) -> str:
    """A fingerprint of everything under ``folder``: relative names, sizes and modification times."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        st = p.lstat()
        h.update(f"{p.relative_to(folder).as_posix()}|{p.is_dir()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def fingerprint(path: Path) -> dict:
    if path.is_dir():
        return {"dir": True, "tree": _tree(path)}
    return {"size": path.stat().st_size, "sha256": file_sha256(path)}


def _read_registry(folder: Path) -> dict:
    try:
        data = json.loads((folder / REGISTRY).read_text(encoding="utf-8"))
        return data if isinstance(data, dict) and isinstance(data.get("entries"), dict) else {"entries": {}}
    except (OSError, ValueError):
        return {"entries": {}}


def _write_registry(folder: Path, data: dict) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f"{REGISTRY}.{os.getpid()}.", suffix=".tmp", dir=folder)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=0, sort_keys=True)
        os.replace(tmp, folder / REGISTRY)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def record(*paths: str | os.PathLike) -> None:
    """Note files or folders lsgan has just written (all in one folder per call is cheapest)."""
    by_folder: dict[Path, list[Path]] = {}
    for p in map(Path, paths):
        by_folder.setdefault(p.parent, []).append(p)
    for folder, items in by_folder.items():
        data = _read_registry(folder)
        for p in items:
            if p.exists():
                data["entries"][p.name] = fingerprint(p)
        _write_registry(folder, data)


def record_tree(folder: str | os.PathLike) -> None:
    """Note every file under ``folder`` (one registry per sub-folder), e.g. a folder built whole."""
    folder = Path(folder)
    for sub in [folder, *sorted(p for p in folder.rglob("*") if p.is_dir())]:
        files = [p for p in sub.iterdir() if p.name != REGISTRY]
        if files:
            record(*files)


def forget(path: Path) -> None:
    data = _read_registry(path.parent)
    if data["entries"].pop(path.name, None) is not None:
        _write_registry(path.parent, data)


def is_ours(path: str | os.PathLike) -> bool:
    """Whether ``path`` is still exactly what lsgan wrote there."""
    path = Path(path)
    entry = _read_registry(path.parent)["entries"].get(path.name)
    if entry is None or not path.exists():
        return False
    if entry.get("dir"):
        return path.is_dir() and entry.get("tree") == _tree(path)
    return path.is_file() and entry.get("size") == path.stat().st_size and entry.get("sha256") == file_sha256(path)


def _inside(a: Path, b: Path) -> bool:
    """Whether ``a`` is ``b`` or lies under it (resolved paths)."""
    return a == b or b in a.parents


def check_inputs(output: Path, inputs: Iterable[str | os.PathLike]) -> None:
    """Refuse an output that is an input, holds one, or lies inside an input folder."""
    out = output.resolve()
    for i in inputs:
        i = Path(i).resolve()
        if _inside(i, out):
            raise OutputError(f"{output}: {'is' if i == out else 'holds'} the input {i}; choose an output outside "
                              "the inputs")
        if i.is_dir() and _inside(out, i):
            raise OutputError(f"{output}: lies inside the input folder {i}; choose an output outside the inputs")


def sweep_temps(path: Path) -> None:
    """Remove temporaries of ``path`` left by a killed lsgan process (never those of a live one)."""
    sweep_folder_temps(path.parent, path.name)


def sweep_folder_temps(folder: Path, name: str | None = None) -> None:
    """Remove the temporaries in ``folder`` (of ``name`` only, when given) whose lsgan process is gone."""
    if not folder.is_dir():
        return
    # mkstemp/mkdtemp names (8 random characters) and atomic_folder's ".old"; nothing else matches
    pattern = re.compile(rf"^\.{re.escape(name) if name else '.+?'}\.(\d+)\.([a-z0-9_]{{8}}(\.tmp)?|old)$")
    for p in folder.iterdir():
        m = pattern.match(p.name)
        if m and not _alive(int(m.group(1))):
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # our own leftovers from an earlier, interrupted attempt in this process
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def claim_file(path: str | os.PathLike, *, force: bool = False, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Before writing the file ``path``: refuse what may not be replaced, sweep dead temporaries."""
    path = Path(path)
    check_inputs(path, inputs)
    if path.is_dir():
        raise OutputError(f"{path}: cannot write: is a folder (give a file name)")
    if path.parent.exists() and not path.parent.is_dir():
        raise OutputError(f"{path}: cannot write: {path.parent} is not a folder")
    sweep_temps(path)
    if path.exists() or path.is_symlink():
        if not force:
            raise OutputError(f"{path}: exists; pass --force to replace it (lsgan replaces only files it wrote)")
        if not is_ours(path):
            raise OutputError(f"{path}: exists and is not a file lsgan wrote (or it was changed since); "
                              "not replaced, even with --force")
    return path


def foreign(folder: Path) -> list[Path]:
    """Entries of ``folder`` (recursively) that are not lsgan's, shallowest first."""
    out: list[Path] = []
    for p in sorted(folder.iterdir()):
        if p.name == REGISTRY or is_ours(p):
            continue
        if p.is_dir() and not p.is_symlink():
            out += foreign(p) if any(p.iterdir()) else []
        else:
            out.append(p)
    return out


def claim_folder(path: str | os.PathLike, *, force: bool = False, inputs: Iterable[str | os.PathLike] = (),
                 whole: bool = False) -> Path:
    """Before writing into the folder ``path``.

    An empty or missing folder is free. A non-empty one needs ``force``; then lsgan's own entries in it are
    removed (``whole``: the folder will be replaced as a unit, so it must hold nothing else).
    """
    path = Path(path)
    check_inputs(path, inputs)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: cannot write: exists and is not a folder")
    sweep_temps(path)
    if not path.exists() or not any(p.name != REGISTRY for p in path.iterdir()):
        return path
    if whole and is_ours(path):
        if not force:
            raise OutputError(f"{path}: exists; pass --force to replace it (lsgan replaces only what it wrote)")
        return path
    if not force:
        raise OutputError(f"{path}: exists and is not empty; pass --force to replace what lsgan wrote there "
                          "(other files are never touched)")
    others = foreign(path)
    if others and whole:
        names = ", ".join(str(p.relative_to(path)) for p in others[:5]) + (" ..." if len(others) > 5 else "")
        raise OutputError(f"{path}: holds files lsgan did not write ({names}); not replaced, even with --force")
    clear_ours(path)
    return path


def clear_ours(folder: Path) -> list[Path]:
    """Delete the entries of ``folder`` that are still exactly what lsgan wrote; returns them."""
    removed = []
    data = _read_registry(folder)
    for name in list(data["entries"]):
        p = folder / name
        if is_ours(p):
            shutil.rmtree(p) if p.is_dir() else p.unlink()
            removed.append(p)
        data["entries"].pop(name)
    for p in folder.iterdir():
        if p.is_dir() and not p.is_symlink() and (p / REGISTRY).exists():
            removed += clear_ours(p)
            if not any(q.name != REGISTRY for q in p.iterdir()):
                (p / REGISTRY).unlink(missing_ok=True)
                p.rmdir()
    if data["entries"]:
        _write_registry(folder, data)
    else:
        (folder / REGISTRY).unlink(missing_ok=True)
    return removed
