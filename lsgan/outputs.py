"""Which files are lsgan's, and the one place that deletes, renames into place or sweeps them.

Every file or folder lsgan writes is fingerprinted in a small registry beside it, ``.lsgan-outputs.json`` in
the same folder: a file by its size and SHA-256, a folder by the names, kinds, sizes and SHA-256 of everything
in it. A path is lsgan's only while its name is a plain name listed in the registry of its own folder and its
content still matches the entry: a file the user edited, or a folder they added to, is theirs again, and a
registry naming ``../x`` or ``/abs`` names nothing.

By construction (tests/test_outputs.py walks the package's syntax tree to keep it so):

* :func:`remove` is the only code in lsgan that deletes a file or folder. It removes an entry that matches its
  record, a temporary whose recorded process is gone, or an empty folder lsgan made; anything else is refused
  with one line naming it.
* :func:`publish` is the only code that renames into place. It refuses to replace anything that is not lsgan's,
  whatever its caller checked before, and records the new content before the rename (as ``pending``) and after
  it, so that a kill at any instant leaves a path that is still known as lsgan's.
* Temporaries (:func:`temp_file`, :func:`temp_folder`) are recorded when made, with their process and inode;
  :func:`sweep_temps` removes only recorded ones whose process is gone.

Commands claim their outputs before writing: an output that does not exist (or an empty folder) is free; an
existing one is refused unless ``force``, and with ``force`` only lsgan's own entries are replaced or cleared;
an output that is, holds or lies inside one of the command's inputs is refused outright.
"""
from __future__ import annotations

import hashlib
import json
import os
import secrets
import signal
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from lsgan.faults import fault_point
from lsgan.interrupts import signals_held

try:
    import fcntl
except ImportError:  # not on Windows: registries are then not locked against concurrent lsgan processes
    fcntl = None

REGISTRY = ".lsgan-outputs.json"
SMALL_FOLDER = 64  # a folder of up to this many entries is recorded file by file, so a refusal can name the file
_REGISTRY_TMP = REGISTRY + ".tmp"  # written under the folder's lock only, so one name serves every writer


class OutputError(ValueError):
    """An output that may not be written or removed: the message names it and says why."""


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def plain_name(name: str) -> bool:
    """A name of an entry in its own folder: no separator, not '.', '..' or empty, not the registry."""
    return name not in ("", ".", "..", REGISTRY, _REGISTRY_TMP) and not any(c in name for c in "/\\\0")


def _listing(folder: Path) -> dict[str, str]:
    """Everything under ``folder`` (links not followed): relative name -> kind, size and SHA-256."""
    found = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = Path(root) / name
            rel = p.relative_to(folder).as_posix()
            if p.is_symlink():
                found[rel] = f"link {os.readlink(p)}"
            elif p.is_dir():
                found[rel] = "dir"
            else:
                found[rel] = f"file {p.stat().st_size} {file_sha256(p)}"
    return found


def _content(listing: dict[str, str]) -> str:
    """One hash of a listing, unambiguous whatever the names hold (JSON-encoded pairs)."""
    return hashlib.sha256(json.dumps(sorted(listing.items())).encode()).hexdigest()


def _legacy_tree(folder: Path) -> str:
    """The folder fingerprint of earlier registries, so that their runs still resume."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        st = p.lstat()
        h.update(f"{p.relative_to(folder).as_posix()}|{p.is_dir()}|{st.st_size}|{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def fingerprint(path: Path) -> dict | None:
    """What a registry entry records of ``path``; None for a link, a missing path or a special file."""
    if path.is_symlink() or not path.exists():
        return None
    if path.is_dir():
        listing = _listing(path)
        fp = {"dir": True, "content": _content(listing)}
        return {**fp, "files": listing} if len(listing) <= SMALL_FOLDER else fp
    if path.is_file():
        return {"size": path.stat().st_size, "sha256": file_sha256(path)}
    return None


def _matches(entry: dict | None, path: Path) -> bool:
    """Whether ``path`` is what ``entry`` recorded: its content, or the content it was being replaced with."""
    if not entry or entry.get("temp") or entry.get("folder"):
        return False
    if "tree" in entry:  # a folder recorded before content hashes: names, sizes and modification times
        return path.is_dir() and not path.is_symlink() and entry["tree"] == _legacy_tree(path)
    fp = fingerprint(path)
    if fp is None:
        return False
    return any(_same(fp, e) for e in (entry, entry.get("pending")))


def _same(fp: dict, entry: object) -> bool:
    keys = ("dir", "content") if fp.get("dir") else ("size", "sha256")
    return isinstance(entry, dict) and all(fp.get(k) == entry.get(k) for k in keys)


def why_not_ours(path: str | os.PathLike) -> str:
    """In words, why ``path`` is not lsgan's (for refusals): not recorded, or which file changed."""
    path = Path(path)
    entry = _read_entries(path.parent).get(path.name) if plain_name(path.name) else None
    if not entry or entry.get("temp") or entry.get("folder"):
        return "lsgan has no record of writing it"
    before, now = entry.get("files"), fingerprint(path) or {}
    if isinstance(before, dict) and isinstance(now.get("files"), dict):
        for rel in sorted(set(before) | set(now["files"])):
            if before.get(rel) != now["files"].get(rel):
                how = "added" if rel not in before else "removed" if rel not in now["files"] else "changed"
                return f"{rel} was {how} since lsgan wrote it"
    return "it was changed since lsgan wrote it"


def made_folder(path: str | os.PathLike) -> bool:
    """Whether lsgan made the folder ``path`` (:func:`make_folder`); what it holds may be anyone's."""
    path = Path(path)
    return plain_name(path.name) and _made_folder(_read_entries(path.parent).get(path.name) or {}, path)


def _made_folder(entry: dict, path: Path) -> bool:
    """A folder lsgan made (:func:`make_folder`), whatever it holds now: the same inode, and the same random id in
    its own registry as in its parent's entry (a new folder that got the inode back, with a registry copied into
    it, is the user's)."""
    try:
        st = path.lstat()
    except OSError:
        return False
    if not (entry.get("folder") and path.is_dir() and not path.is_symlink() and st.st_ino == entry.get("ino")):
        return False
    return isinstance(entry.get("id"), str) and _folder_id(path) == entry["id"]


def _folder_id(folder: Path) -> str | None:
    """The id :func:`make_folder` put in the folder's own registry (None if there is none)."""
    found = _registry_data(folder).get("id")
    return found if isinstance(found, str) else None


# ----------------------------------------------------------------------------------------------- registry


def _registry_data(folder: Path) -> dict:
    """The folder's registry as read from its file; {} when missing, unreadable, not an object, or a link."""
    if (folder / REGISTRY).is_symlink():
        return {}
    try:
        data = json.loads((folder / REGISTRY).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # a forged file nested beyond the decoder's depth too
        return {}
    return data if isinstance(data, dict) else {}


def _read_entries(folder: Path) -> dict:
    """The registry's entries with plain names only; a missing, unreadable or linked registry lists nothing."""
    entries = _registry_data(folder).get("entries")
    if not isinstance(entries, dict):
        return {}
    return {k: v for k, v in entries.items() if isinstance(k, str) and plain_name(k) and isinstance(v, dict)}


def _is_registry_file(path: Path, partial: bool = False) -> bool:
    """Whether ``path`` is a plain file holding a registry (so lsgan may replace it); ``partial``: or the start
    of one, as a write killed midway leaves it."""
    if path.is_symlink() or not path.is_file():
        return False
    try:
        text = path.read_text(encoding="utf-8")
        if partial and (text == "" or text.startswith('{\n"entries"')):
            return True
        data = json.loads(text)
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(data, dict) and isinstance(data.get("entries"), dict)


class _Registry:
    """One folder's registry, held under an exclusive lock of the folder (see :func:`_registry`)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.entries = _read_entries(folder)
        self.id = _folder_id(folder)  # set by make_folder: this folder is lsgan's
        self._saved = self._state()

    def _state(self) -> str:
        return json.dumps({"entries": self.entries, **({"id": self.id} if self.id else {})}, sort_keys=True)

    def save(self) -> None:
        """Write the registry through ``.lsgan-outputs.json.tmp`` and a rename, when it changed; one that lists
        nothing and is no made folder's is removed."""
        text = json.dumps(json.loads(self._state()), indent=0, sort_keys=True)
        if self._state() == self._saved:
            return
        reg, tmp = self.folder / REGISTRY, self.folder / _REGISTRY_TMP
        for p in (reg, tmp):
            if (p.exists() or p.is_symlink()) and not _is_registry_file(p, partial=p == tmp):
                raise OutputError(f"{p}: is not lsgan's registry of outputs; move it away (lsgan records what it "
                                  "writes in that file)")
        if not self.entries and not self.id:  # nothing of lsgan's is left here: no registry either (checked above)
            reg.unlink(missing_ok=True)
            self._saved = self._state()
            return
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0), 0o666)
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(text)
            os.replace(tmp, reg)
        except BaseException as e:  # an interrupt too: the temporary is this process's own, made under the lock
            if isinstance(e, OSError):  # name the registry (a full disk or a read-only folder says nothing of it)
                e.filename = e.filename or str(reg)
            tmp.unlink(missing_ok=True)
            raise
        self._saved = self._state()


@contextmanager
def _registry(folder: Path) -> Iterator[_Registry]:
    """``folder``'s registry, locked against other lsgan processes; saved when the block ends without error.
    Never nested: a second lock on the same folder would wait for the first."""
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        reg = _Registry(folder)
        yield reg
        reg.save()
    finally:
        os.close(fd)


def record(*paths: str | os.PathLike) -> None:
    """Note files or folders lsgan has just written (all in one folder per call is cheapest)."""
    by_folder: dict[Path, list[Path]] = {}
    for p in map(Path, paths):
        by_folder.setdefault(p.parent, []).append(p)
    for folder, items in by_folder.items():
        with _registry(folder) as reg:
            for p in items:
                fp = fingerprint(p)
                if fp is not None and plain_name(p.name):
                    reg.entries[p.name] = fp


def record_tree(folder: str | os.PathLike) -> None:
    """Note every file under ``folder`` (one registry per sub-folder), e.g. a folder built whole."""
    folder = Path(folder)
    for sub in [folder, *sorted(p for p in folder.rglob("*") if p.is_dir() and not p.is_symlink())]:
        files = [p for p in sub.iterdir() if p.name != REGISTRY]
        if files:
            record(*files)


def make_folder(path: str | os.PathLike) -> Path:
    """Make the folder ``path`` and any missing parents, recording each new one as lsgan's in its parent's
    registry (so that it can be removed once empty); an existing folder is used as it is."""
    path = Path(path)
    if path.is_dir():
        return path
    if path.exists() or path.is_symlink():
        raise OutputError(f"{path}: cannot write into it: exists and is not a folder")
    make_folder(path.parent)
    try:
        path.mkdir()
    except FileExistsError:  # another process made it meanwhile
        if path.is_dir():
            return path
        raise
    made = secrets.token_hex(8)
    with _registry(path) as inner:
        inner.id = made
    with _registry(path.parent) as reg:  # a writer's note on this name stays
        reg.entries[path.name] = {**reg.entries.get(path.name, {}), "folder": True, "ino": path.lstat().st_ino,
                                  "id": made}
    return path


def is_ours(path: str | os.PathLike) -> bool:
    """Whether ``path`` is still exactly what lsgan wrote there."""
    path = Path(path)
    return plain_name(path.name) and _matches(_read_entries(path.parent).get(path.name), path)


# ------------------------------------------------------------------------------------ the one deleting place


def _delete(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()


def _only_registry(folder: Path) -> bool:
    """Whether a folder holds nothing but lsgan's registry, and that registry lists nothing that still exists."""
    names = [p.name for p in folder.iterdir()]
    if names and (names != [REGISTRY] or not _is_registry_file(folder / REGISTRY)):
        return False
    return not any((folder / n).exists() or (folder / n).is_symlink() for n in _read_entries(folder))


def _listed_files(entry: dict | None, path: Path) -> dict[str, str] | None:
    """What of the folder ``path`` lsgan can still vouch for: for a folder it wrote whole (recorded file by file
    in its parent's registry), the files whose content is unchanged, by relative name; else None."""
    if not entry or not entry.get("dir") or not isinstance(entry.get("files"), dict) or not path.is_dir() \
            or path.is_symlink():
        return None
    now = _listing(path)
    return {rel: v for rel, v in entry["files"].items() if v.startswith("file ") and now.get(rel) == v}


def _removable(entry: dict | None, path: Path) -> bool:
    if entry is None:
        return False
    if entry.get("folder"):
        return _made_folder(entry, path) and _only_registry(path)
    if entry.get("temp"):
        return _own_temp(entry, path)
    return _matches(entry, path)


def _own_temp(entry: dict, path: Path) -> bool:
    try:
        return path.lstat().st_ino == entry.get("ino") and not path.is_symlink()
    except OSError:
        return False


def remove(path: str | os.PathLike, *, missing_ok: bool = False) -> None:
    """Delete ``path`` if it is lsgan's: an entry of its folder's registry, under a plain name, whose content
    still matches; a recorded temporary; or a folder lsgan made that is now empty. Anything else is refused
    (OutputError naming it). This is the only function in lsgan that deletes."""
    path = Path(path)
    if missing_ok and not (path.exists() or path.is_symlink()):
        return
    if not plain_name(path.name) or not path.parent.is_dir():
        raise OutputError(f"{path}: not removed: lsgan removes only entries of its own registry")
    with _registry(path.parent) as reg:
        entry = reg.entries.get(path.name)
        if not _removable(entry, path):
            raise OutputError(f"{path}: not removed: it is not something lsgan wrote (or it was changed since)")
        _remove_entry(reg, path)


def _remove_entry(reg: _Registry, path: Path) -> None:
    """Delete a checked entry and drop it from the registry (saved when the caller's block ends)."""
    if reg.entries[path.name].get("folder"):
        (path / REGISTRY).unlink(missing_ok=True)
        path.rmdir()
    else:
        _delete(path)
    del reg.entries[path.name]


# ------------------------------------------------------------------------------------------------ temporaries


PID_MAX = 2**22  # Linux's highest pid (pid_max at most 4,194,304); a forged registry may hold any number


def _alive(pid: object) -> bool:
    if not isinstance(pid, int) or isinstance(pid, bool) or not 0 < pid <= PID_MAX:
        return False
    if pid == os.getpid():
        return True  # this process's own temporaries: removed by the code that made them
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_temps(folder: str | os.PathLike) -> None:
    """Remove the recorded temporaries in ``folder`` whose process is gone; a folder that was being replaced
    when its process died is put back instead, when nothing took its place."""
    folder = Path(folder)
    if not folder.is_dir() or not (folder / REGISTRY).is_file():
        return
    with _registry(folder) as reg:
        for name, entry in list(reg.entries.items()):
            if not entry.get("temp") or _alive(entry.get("pid")):
                continue
            p = folder / name
            if _own_temp(entry, p):
                back = entry.get("restore")
                if isinstance(back, str) and plain_name(back) and not (folder / back).exists():
                    os.rename(p, folder / back)
                    reg.entries[back] = {k: v for k, v in (reg.entries.get(back) or {}).items() if k != "pending"}
                else:
                    _delete(p)
            del reg.entries[name]


def _temp_entry(path: Path, **more) -> dict:
    return {"temp": True, "pid": os.getpid(), "ino": path.lstat().st_ino, **more}


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def temp_file(path: str | os.PathLike) -> tuple[int, str]:
    """A new temporary file beside ``path`` (same filesystem, so the rename is atomic), recorded as a
    temporary of this process, with the usual permissions; an open descriptor and its name."""
    path = Path(path)
    make_folder(path.parent)
    sweep_temps(path.parent)
    with signals_held(signal.SIGINT, signal.SIGTERM):  # made and recorded, or neither: an interrupt waits for both
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)
        os.chmod(tmp, 0o666 & ~_umask())
        with _registry(path.parent) as reg:
            reg.entries[Path(tmp).name] = _temp_entry(Path(tmp))
    return fd, tmp


def temp_folder(target: str | os.PathLike) -> Path:
    """A new temporary folder beside ``target``, recorded as a temporary of this process."""
    target = Path(target)
    make_folder(target.parent)
    sweep_temps(target.parent)
    with signals_held(signal.SIGINT, signal.SIGTERM):  # made and recorded, or neither: an interrupt waits for both
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.{os.getpid()}.", dir=target.parent))
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it private (0700); the finished folder gets the usual mode
        with _registry(target.parent) as reg:
            reg.entries[tmp.name] = _temp_entry(tmp)
    return tmp


def discard_temp(tmp: str | os.PathLike) -> None:
    """Remove a temporary of this process (after a failed write); a path not recorded as one is left alone."""
    tmp = Path(tmp)
    if not (tmp.exists() or tmp.is_symlink()) or not tmp.parent.is_dir():
        return
    try:
        with _registry(tmp.parent) as reg:
            entry = reg.entries.get(tmp.name)
            if entry is not None and entry.get("temp") and _own_temp(entry, tmp):
                _remove_entry(reg, tmp)
    except OSError:
        pass  # e.g. a full disk: the temporary is gone already, and the next sweep drops its stale entry


# ----------------------------------------------------------------------------------- the one publishing place


def _replaceable(entry: dict | None, path: Path) -> bool:
    """Whether ``path`` may be replaced: absent, lsgan's, or a folder holding nothing but its registry."""
    if not (path.exists() or path.is_symlink()):
        return True
    if path.is_dir() and not path.is_symlink() and _only_registry(path):
        return True
    return _matches(entry, path)


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Move a finished temporary file or folder into place at ``path`` and record it as lsgan's.

    Refuses (OutputError) to replace what is not lsgan's. A folder in the way is first renamed aside (recorded
    as a temporary to put back), then removed once the new one is in place."""
    tmp, path = Path(tmp), Path(path)
    if tmp.parent.resolve() != path.parent.resolve() or not plain_name(path.name):
        raise OutputError(f"{path}: cannot write: its temporary is not beside it")
    fp = fingerprint(tmp)
    with _registry(path.parent) as reg:
        entry = reg.entries.get(path.name)
        if not _replaceable(entry, path):
            raise OutputError(f"{path}: exists and is not something lsgan wrote (or it was changed since); "
                              "not replaced")
        ours_now = path.exists() and _matches(entry, path)
        current = {k: v for k, v in entry.items() if k != "pending"} if ours_now else {}
        reg.entries[path.name] = {**current, "pending": fp}
        old = None
        if path.is_dir() and not path.is_symlink():  # renamed aside first: a folder cannot replace a full one
            old = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.old")
            reg.entries[old.name] = _temp_entry(path, restore=path.name)  # a rename keeps the inode
        reg.save()
        fault_point("publish.recorded")
        try:
            if old is not None:
                os.rename(path, old)
                fault_point("publish.aside")
            os.replace(tmp, path)
        except BaseException:
            if old is not None and old.exists() and not path.exists():
                os.rename(old, path)
            raise
        fault_point("publish.placed")
        reg.entries[path.name] = fp
        reg.entries.pop(tmp.name, None)
        reg.save()
        if old is not None:
            _remove_entry(reg, old)


def replace_by(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (a recorded temporary, then :func:`publish`)."""
    fd, tmp = temp_file(path)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        publish(tmp, path)
    except BaseException:
        discard_temp(tmp)
        raise


# -------------------------------------------------------------------------------------------------- claiming


def _inside(a: Path, b: Path) -> bool:
    """Whether ``a`` is ``b`` or lies under it (resolved paths)."""
    return a == b or b in a.parents


def check_inputs(output: str | os.PathLike, inputs: Iterable[str | os.PathLike]) -> None:
    """Refuse an output that is an input, holds one, or lies inside an input folder."""
    output = Path(output)
    out = output.resolve()
    for i in inputs:
        i = Path(i).resolve()
        if _inside(i, out):
            raise OutputError(f"{output}: {'is' if i == out else 'holds'} the input {i}; choose an output outside "
                              "the inputs")
        if i.is_dir() and _inside(out, i):
            raise OutputError(f"{output}: lies inside the input folder {i}; choose an output outside the inputs")


def _start_time(pid: int) -> str:
    """When process ``pid`` started (Linux: its start tick), so that a reused pid is not taken for it."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return ""


def _writer_running(writer: object) -> bool:
    """Whether the process noted by :func:`reserve` (``[pid, start]``) is another one, still running."""
    if not (isinstance(writer, list) and len(writer) == 2 and isinstance(writer[0], int)):
        return False
    pid, start = writer
    return pid != os.getpid() and _alive(pid) and isinstance(start, str) and start != "" and _start_time(pid) == start


def _noted(path: Path) -> Path:
    """Where a writer's note on ``path`` goes: ``path`` itself, or its highest missing ancestor (which the command
    will make) when its folder does not exist yet."""
    while not path.parent.is_dir() and path.parent != path:
        path = path.parent
    return path


def _me() -> list:
    return [os.getpid(), _start_time(os.getpid())]


def _running(entry: dict, folder: Path, path: Path) -> tuple[list, Path] | None:
    """Another running lsgan process noted on an entry of ``folder``, and the output it writes there, when that
    output is ``path``, holds it or lies inside it: the entry itself (``writer``), or an output below it when the
    process will make the entry as a folder (``makers``: each with the output's path relative to ``folder``)."""
    notes = [(entry.get("writer"), "")]
    makers = entry.get("makers") if isinstance(entry.get("makers"), list) else []
    notes += [(m.get("by"), m.get("output")) for m in makers if isinstance(m, dict) and isinstance(m.get("output"), str)]
    for writer, output in notes:
        target = folder / output if output else None
        if _writer_running(writer) and (target is None or _inside(target, path) or _inside(path, target)):
            return writer, target
    return None


def check_writer(path: str | os.PathLike) -> None:
    """Refuse ``path`` when another lsgan process that is still running noted that it writes it, a folder above
    it or an output inside it (two commands writing one output would each replace the other's work). Commands
    that only make the same missing folders for different outputs (``runs/a``, ``runs/b``) may run side by side."""
    given, path = path, Path(os.path.realpath(path))  # a linked folder names the same outputs as its target
    for p in [path, *path.parents]:
        note = _running(_read_entries(p.parent).get(p.name, {}), p.parent, path) if p.parent.is_dir() else None
        if note:
            writer, target = note
            raise OutputError(f"{given}: another lsgan process (pid {writer[0]}) is writing {target or p}; wait for "
                              "it to end or choose another output")
        if p.parent.is_dir() and not (p.parent / REGISTRY).is_file():
            break


_claimed: list[Path] | None = None
"""The paths the running command reserved (:func:`claims`); None outside a command (library use)."""


@contextmanager
def claims() -> Iterator[None]:
    """The span of one command: what it claims is noted in the registries for other lsgan processes to see
    (:func:`reserve`), and the notes are taken back when it ends, whatever the outcome, so that a refused or
    failed command leaves every registry as it found it. Library calls outside it note nothing."""
    global _claimed
    _claimed, outer = [], _claimed
    try:
        yield
    finally:
        mine, _claimed = _claimed, outer
        for path in mine:
            _release(path)


def reserve(path: str | os.PathLike) -> None:
    """Note in the registry that this command writes ``path`` (after :func:`check_writer`), or, when its folder
    is missing, that it makes the highest missing one (``makers``: other commands may make it too), during
    :func:`claims` only."""
    path = Path(os.path.realpath(path))
    noted = _noted(path)
    if _claimed is None or not plain_name(noted.name) or not noted.parent.is_dir():
        return
    with _registry(noted.parent) as reg:
        entry = reg.entries.get(noted.name, {})
        if _running(entry, noted.parent, path):  # noted by another process since this one's check_writer
            check_writer(path)
        if noted == path:
            entry = {**entry, "writer": _me()}
        else:  # the notes of processes that are gone are dropped
            makers = [m for m in entry.get("makers", []) if isinstance(m, dict) and _writer_running(m.get("by"))] \
                if isinstance(entry.get("makers"), list) else []
            entry = {**entry, "makers": [*makers, {"by": _me(), "output": path.relative_to(noted.parent).as_posix()}]}
        reg.entries[noted.name] = entry
    _claimed.append(noted)


def _release(path: Path) -> None:
    """Take back this process's notes on ``path`` (a registry that is then empty goes too)."""
    if not path.parent.is_dir():
        return
    try:
        with _registry(path.parent) as reg:
            entry = reg.entries.get(path.name)
            if not entry:
                return
            rest = {k: v for k, v in entry.items() if not (k == "writer" and v == _me())}
            if isinstance(rest.get("makers"), list):
                rest["makers"] = [m for m in rest["makers"] if not (isinstance(m, dict) and m.get("by") == _me())]
                rest = rest if rest["makers"] else {k: v for k, v in rest.items() if k != "makers"}
            reg.entries.pop(path.name) if not rest else reg.entries.update({path.name: rest})
    except (OSError, OutputError):
        pass  # a note left behind names a process that is gone: it blocks nothing


def check_apart(*paths: str | os.PathLike) -> None:
    """Refuse outputs of one command that are the same path or lie one inside another."""
    for k, a in enumerate(paths):
        for b in paths[k + 1:]:
            ra, rb = Path(a).resolve(), Path(b).resolve()
            if _inside(ra, rb) or _inside(rb, ra):
                raise OutputError(f"{a}: is also the output {b} (or lies inside it); give each output its own path")


NAME_MAX = 255  # bytes in one file name on Linux and macOS file systems


def _check_name(path: Path) -> None:
    """Refuse an output named like the registry, or too long for the temporary written beside it."""
    if path.name in (REGISTRY, _REGISTRY_TMP):
        raise OutputError(f"{path}: is the name of lsgan's registry of outputs; choose another name")
    temp = len(f".{path.name}.{os.getpid()}.abcdefgh.old".encode())
    if temp > NAME_MAX:
        raise OutputError(f"{path}: name too long: the temporary written beside it would take {temp} bytes "
                          f"(at most {NAME_MAX}); choose a shorter name")


def claim_file(path: str | os.PathLike, *, force: bool = False, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Before writing the file ``path``: refuse what may not be replaced, sweep dead temporaries, and note
    that this process writes it (:func:`reserve`)."""
    path = Path(path)
    _check_name(path)
    check_inputs(path, inputs)
    if path.is_dir():
        raise OutputError(f"{path}: cannot write: is a folder (give a file name)")
    if path.parent.exists() and not path.parent.is_dir():
        raise OutputError(f"{path}: cannot write: {path.parent} is not a folder")
    sweep_temps(path.parent)
    check_writer(path)
    check_replaceable([path], force=force)
    reserve(path)
    return path


def check_replaceable(paths: Iterable[str | os.PathLike], *, force: bool = False) -> None:
    """Refuse, before anything is written, the first of ``paths`` that exists and may not be replaced: any without
    ``force``, one lsgan did not write (or that changed since) even with it. A command writing several files checks
    them all first, so that a refusal leaves none of them written."""
    for path in map(Path, paths):
        if path.exists() or path.is_symlink():
            if not force:
                raise OutputError(f"{path}: exists; pass --force to replace it (lsgan replaces only files it wrote)")
            if not is_ours(path):
                raise OutputError(f"{path}: exists and is not a file lsgan wrote (or it was changed since); "
                                  "not replaced, even with --force")


def foreign(folder: Path) -> list[Path]:
    """Entries of ``folder`` (recursively) that are not lsgan's, shallowest first."""
    out: list[Path] = []
    entries = _read_entries(folder)
    for p in sorted(folder.iterdir()):
        entry = entries.get(p.name)
        listed = _listed_files(entry, p)
        if (p.name == REGISTRY and _is_registry_file(p)) or _matches(entry, p):
            continue
        if _made_folder(entry or {}, p):
            out += foreign(p)
        elif listed is not None:
            out += [q for q in sorted(p.rglob("*")) if not q.is_dir() and q.relative_to(p).as_posix() not in listed]
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
    _check_name(path)
    check_inputs(path, inputs)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: cannot write: exists and is not a folder")
    sweep_temps(path.parent) if path.parent.is_dir() else None
    check_writer(path)
    if not path.exists() or _only_registry(path):
        reserve(path)
        return path
    if whole and is_ours(path):
        if not force:
            raise OutputError(f"{path}: exists; pass --force to replace it (lsgan replaces only what it wrote)")
        reserve(path)
        return path
    if not force:
        raise OutputError(f"{path}: exists and is not empty; pass --force to replace what lsgan wrote there "
                          "(other files are never touched)")
    others = foreign(path)
    if others and whole:
        names = ", ".join(str(p.relative_to(path)) for p in others[:5]) + (" ..." if len(others) > 5 else "")
        raise OutputError(f"{path}: holds files lsgan did not write ({names}); not replaced, even with --force")
    reserve(path)
    clear_ours(path)
    return path


def clear_ours(folder: Path) -> list[Path]:
    """Delete what in ``folder`` is still exactly what lsgan wrote (:func:`clear_path` of each entry its registry
    lists); returns what was removed. Everything else stays."""
    sweep_temps(folder)
    removed: list[Path] = []
    for name in sorted(_read_entries(folder)):
        p = folder / name
        if p.exists() or p.is_symlink():
            removed += clear_path(p)
    return removed


def clear_path(path: Path) -> list[Path]:
    """Remove what lsgan wrote at ``path``: a file or folder still as written; the files of a folder it wrote
    whole that the record of it still vouches for; the contents of a folder it made (by that folder's registry),
    then the folder once empty. A folder the user put there, whatever registry it holds, is theirs."""
    entry = _read_entries(path.parent).get(path.name) if plain_name(path.name) else None
    removed: list[Path] = []
    if entry is None or entry.get("temp"):
        return removed
    listed = _listed_files(entry, path)
    if _made_folder(entry, path):
        removed += clear_ours(path)
    elif listed is not None and not _matches(entry, path):  # a folder lsgan wrote whole, since added to
        for rel in sorted(listed):
            (path / rel).unlink()
            removed.append(path / rel)
    try:
        remove(path)
        removed.append(path)
    except OutputError:
        pass  # changed, or still holding the user's files: it stays
    return removed
