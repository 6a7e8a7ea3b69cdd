"""Nothing of the user's is lost: one place deletes, one place renames into place, and hostile trees of user
files, registries, links and commands never change a byte that lsgan did not write."""
from __future__ import annotations

import ast
import json
import os
from contextlib import contextmanager
from pathlib import Path

import click
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from trees import snapshot, work_and_outside

from lsgan import outputs
from lsgan.io import atomic_file, atomic_folder

PACKAGE = Path(__file__).resolve().parents[1] / "lsgan"
DELETERS = {("os", "remove"), ("os", "unlink"), ("os", "rmdir"), ("os", "removedirs"), ("os", "replace"),
            ("os", "rename"), ("os", "renames"), ("shutil", "rmtree"), ("shutil", "move")}
PATH_METHODS = {"unlink", "rmdir", "rename"}


def _calls(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            yield node, node.func


def _deleting_calls(source: str) -> list[str]:
    """Calls that delete or rename: os.*/shutil.* by name, Path.unlink/rmdir/rename, and Path.replace(x) (one
    positional argument: str.replace takes two)."""
    found = []
    for node, f in _calls(ast.parse(source)):
        owner = f.value.id if isinstance(f.value, ast.Name) else None
        if (owner, f.attr) in DELETERS or f.attr in PATH_METHODS or (
                f.attr == "replace" and len(node.args) == 1 and not node.keywords):
            found.append(f"line {node.lineno}: {ast.unparse(node.func)}")
    return found


def test_only_outputs_deletes_or_renames():
    """Every removal or rename in lsgan is in lsgan/outputs.py (remove, publish, sweep_temps)."""
    offenders = {}
    for py in sorted(PACKAGE.rglob("*.py")):
        if py.name == "outputs.py" and py.parent == PACKAGE:
            continue
        calls = _deleting_calls(py.read_text(encoding="utf-8"))
        if calls:
            offenders[str(py.relative_to(PACKAGE.parent))] = calls
    assert not offenders, f"delete/rename outside lsgan/outputs.py: {offenders}"


def test_the_structure_check_catches_each_kind_of_call():
    """The walker itself finds what it must (so the check above cannot pass by missing everything)."""
    src = ("import os, shutil\nos.remove(a)\nos.unlink(a)\nshutil.rmtree(a)\nos.rmdir(a)\np.unlink()\n"
           "os.replace(a, b)\nos.rename(a, b)\np.rename(b)\np.replace(b)\nq.rmdir()\n"
           "s.replace('a', 'b')\ndataclasses.replace(r, x=1)\n")
    assert len(_deleting_calls(src)) == 10


def test_nothing_is_appended_in_place():
    """Logs and reports are rewritten through a temporary, never opened for appending (a hard-linked copy of a
    run would change with it)."""
    offenders = []
    for py in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(py.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and any(isinstance(a, ast.Constant) and isinstance(a.value, str)
                                                  and a.value in ("a", "ab", "a+", "at") for a in node.args[1:2]):
                offenders.append(f"{py.name}:{node.lineno}")
    assert not offenders


def test_every_path_option_is_an_input_or_an_output():
    """Each command's path options say what they are, so outputs are checked against inputs by construction."""
    from lsgan.cli import main
    from lsgan.cli.options import In

    loose = [f"{name} {p.name}" for name, cmd in main.commands.items() for p in cmd.params
             if isinstance(p.type, click.Path) and not isinstance(p.type, In)]
    assert not loose
    assert all(isinstance(c, click.Command) and type(c).__name__ == "LsganCommand" for c in main.commands.values())


# ---------------------------------------------------------------------------------------------- the registry


def _write(path: Path, data: bytes) -> Path:
    with atomic_file(path) as f:
        f.write(data)
    return path


def test_remove_refuses_what_is_not_lsgans(tmp_path):
    mine = _write(tmp_path / "a.bin", b"lsgan")
    theirs = tmp_path / "b.bin"
    theirs.write_bytes(b"user")
    with pytest.raises(outputs.OutputError, match="b.bin: not removed"):
        outputs.remove(theirs)
    mine.write_bytes(b"edited")
    with pytest.raises(outputs.OutputError, match="a.bin: not removed"):
        outputs.remove(mine)
    assert mine.read_bytes() == b"edited" and theirs.read_bytes() == b"user"
    ok = _write(tmp_path / "c.bin", b"x")
    outputs.remove(ok)
    assert not ok.exists()


@pytest.mark.parametrize("name", ["../outside.txt", "/etc/hostname", "sub/x", "..", ".", ""])
def test_forged_registry_names_are_ignored(tmp_path, name):
    """A registry naming a path outside its folder names nothing (B5: copied or downloaded folders)."""
    out = tmp_path / "out"
    out.mkdir()
    victim = tmp_path / "outside.txt"
    victim.write_bytes(b"keep me")
    entry = {"size": 7, "sha256": outputs.file_sha256(victim)}
    (out / outputs.REGISTRY).write_text(json.dumps({"entries": {name: entry}}))
    outputs.clear_ours(out)
    outputs.claim_folder(out, force=True)
    assert victim.read_bytes() == b"keep me"
    with pytest.raises(outputs.OutputError):
        outputs.remove(out / name)


def test_publish_never_replaces_a_user_file_whatever_its_caller_checked(tmp_path):
    target = tmp_path / "x.json"
    target.write_text("user")
    with pytest.raises(outputs.OutputError, match="not replaced"):
        with atomic_file(target, "w") as f:
            f.write("lsgan")
    assert target.read_text() == "user"
    assert [p.name for p in tmp_path.iterdir() if p.name != outputs.REGISTRY] == ["x.json"]  # no temporary left


def test_a_registry_that_is_not_lsgans_is_not_overwritten(tmp_path):
    (tmp_path / outputs.REGISTRY).write_text("my notes")
    with pytest.raises(outputs.OutputError, match="not lsgan's registry"):
        _write(tmp_path / "a.bin", b"x")
    assert (tmp_path / outputs.REGISTRY).read_text() == "my notes"


def test_the_registrys_temporary_is_removed_only_when_lsgans(tmp_path, monkeypatch):
    """A user's file under the registry's temporary name is refused and kept; lsgan's own temporary is removed
    when the write is interrupted (a Ctrl-C between writing it and renaming it left it behind)."""
    user = tmp_path / "u"
    user.mkdir()
    (user / (outputs.REGISTRY + ".tmp")).write_text("my notes")
    with pytest.raises(outputs.OutputError, match="not lsgan's registry"):
        _write(user / "a.bin", b"x")
    assert (user / (outputs.REGISTRY + ".tmp")).read_text() == "my notes"

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(outputs.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _write(tmp_path / "b.bin", b"x")
    assert not (tmp_path / (outputs.REGISTRY + ".tmp")).exists()


def test_sweep_removes_only_recorded_temporaries_of_dead_processes(tmp_path):
    """B4: names that look like temporaries are the user's unless the registry recorded them."""
    lookalikes = [tmp_path / ".out.h5.2023.old", tmp_path / ".out.h5.99999999.abcdefgh.tmp"]
    lookalikes[0].mkdir()
    (lookalikes[0] / "thesis.tex").write_text("chapter 1")
    lookalikes[1].write_text("draft")
    fd, tmp = outputs.temp_file(tmp_path / "out.h5")
    os.close(fd)
    reg = json.loads((tmp_path / outputs.REGISTRY).read_text())
    reg["entries"][Path(tmp).name]["pid"] = 2**22 + 12345  # a process that is gone
    (tmp_path / outputs.REGISTRY).write_text(json.dumps(reg))
    outputs.sweep_temps(tmp_path)
    assert not Path(tmp).exists()
    assert (lookalikes[0] / "thesis.tex").read_text() == "chapter 1" and lookalikes[1].read_text() == "draft"


def test_a_made_folder_is_removed_only_when_empty(tmp_path):
    made = outputs.make_folder(tmp_path / "glb")
    (made / "mine.txt").write_text("user file")
    outputs.clear_ours(tmp_path)
    assert (made / "mine.txt").exists()
    with pytest.raises(outputs.OutputError):
        outputs.remove(made)
    (made / "mine.txt").rename(tmp_path / "mine.txt")  # the user takes their file away
    outputs.remove(made)
    assert not made.exists()


def test_a_folder_holding_user_files_is_never_replaced_whole(tmp_path):
    target = tmp_path / "ckpt"
    with atomic_folder(target) as t:
        (t / "w.bin").write_bytes(b"1")
    (target / "notes.txt").write_text("mine")
    with pytest.raises(outputs.OutputError, match="not replaced"):
        with atomic_folder(target) as t:
            (t / "w.bin").write_bytes(b"2")
    assert (target / "notes.txt").read_text() == "mine" and (target / "w.bin").read_bytes() == b"1"


def test_a_copy_of_lsgans_folder_inside_the_output_is_the_users(tmp_path):
    """A backup the user copied (with its registry) into an output folder is theirs: --force clears around it."""
    import shutil

    out = tmp_path / "gen"
    _write(out / "a.npy", b"motion")
    shutil.copytree(out, tmp_path / "copy")
    (tmp_path / "copy").rename(out / "mybackup")
    outputs.claim_folder(out, force=True)
    assert not (out / "a.npy").exists() and (out / "mybackup" / "a.npy").read_bytes() == b"motion"


def test_a_linked_registry_vouches_for_nothing(tmp_path):
    src, bak = tmp_path / "gen", tmp_path / "bak"
    _write(src / "a.npy", b"motion")
    bak.mkdir()
    (bak / "a.npy").write_bytes(b"motion")
    (bak / outputs.REGISTRY).symlink_to(src / outputs.REGISTRY)
    with pytest.raises(outputs.OutputError):
        outputs.claim_folder(bak, force=True)
        _write(bak / "b.npy", b"x")
    assert (bak / "a.npy").read_bytes() == b"motion"


def test_a_users_file_under_the_registrys_name_is_kept(tmp_path):
    """B3: a folder holding only a file named like the registry is not empty and not lsgan's."""
    out = tmp_path / "hm"
    out.mkdir()
    (out / outputs.REGISTRY).write_text("my precious notes")
    with pytest.raises(outputs.OutputError):
        outputs.claim_folder(out, force=True, whole=True)
        with atomic_folder(out) as t:
            (t / "x").write_text("y")
    assert (out / outputs.REGISTRY).read_text() == "my precious notes"
    with pytest.raises(outputs.OutputError, match="registry"):
        outputs.claim_file(tmp_path / outputs.REGISTRY)


@contextmanager
def _held(claim: str, path: Path):
    """Another process that claims ``path`` (``outputs.claim_file`` or ``claim_folder``) and holds it while the
    block runs; yields that process."""
    import subprocess
    import sys

    holder = subprocess.Popen([sys.executable, "-c", "import time; from lsgan import outputs\n"
                               f"with outputs.claims():\n    outputs.{claim}({str(path)!r})\n"
                               "    print('held', flush=True)\n    time.sleep(30)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        yield holder
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.parametrize("name", ["s.h5", "new/deep/s.h5"])
def test_a_second_process_cannot_claim_what_a_running_one_writes(tmp_path, name):
    """B5: two commands writing one output would each replace the other's: the second is refused while the
    first runs, and free once it is gone."""
    import time

    target = tmp_path / name  # B5: also below folders that do not exist yet
    with _held("claim_file", target), pytest.raises(outputs.OutputError, match="another lsgan process"):
        outputs.claim_file(target)
    time.sleep(0.05)
    assert outputs.claim_file(target) == target


def test_commands_may_make_the_same_missing_folders_for_different_outputs(tmp_path):
    """Two trainings into runs/a and runs/b of a runs/ that does not exist yet run side by side; runs/a itself,
    a folder inside it and runs/ as a whole stay refused while the first runs."""
    with _held("claim_folder", tmp_path / "runs" / "a") as holder, outputs.claims():
        assert outputs.claim_folder(tmp_path / "runs" / "b") == tmp_path / "runs" / "b"
        outputs.make_folder(tmp_path / "runs" / "b")  # made here first: the holder's note must still count
        for taken in ("runs/a", "runs/a/best", "runs", "runs/b/../a"):
            with pytest.raises(outputs.OutputError, match=f"pid {holder.pid}. is writing .*runs.a"):
                outputs.claim_folder(tmp_path / taken, force=True)
    notes = json.loads((tmp_path / outputs.REGISTRY).read_text())["entries"]["runs"]
    assert [m["output"] for m in notes["makers"]] == ["runs/a"]  # this process took its own note back


def test_a_linked_parent_names_the_same_output_and_forged_notes_block_nothing(tmp_path):
    """A command writing runs/a is refused through a link to runs (the hostile review's A7); notes a registry was
    forged with (a pid beyond any, a negative one, an empty start time) are no one's."""
    (tmp_path / "runs").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "runs")
    with _held("claim_folder", tmp_path / "runs" / "a"), pytest.raises(outputs.OutputError, match="another lsgan"):
        outputs.claim_folder(tmp_path / "link" / "a", force=True)
    forged = {"q": {"writer": [10**20, "0"], "makers": [{"by": [-1, ""], "output": "q/r"}, {"by": [1, ""],
                                                                                          "output": "q"}, 7]}}
    (tmp_path / outputs.REGISTRY).write_text(json.dumps({"entries": forged}))
    with outputs.claims():
        assert outputs.claim_folder(tmp_path / "q" / "r") == tmp_path / "q" / "r"
        assert outputs.claim_folder(tmp_path / "q", force=True) == tmp_path / "q"


def test_a_new_folder_that_got_a_made_folders_inode_is_the_users(tmp_path):
    """The outside check's B1 (second round): ext4 gives a new folder the inode of one just removed; the random
    id in the made folder's own registry tells them apart."""
    import shutil

    made = outputs.make_folder(tmp_path / "out" / "run")
    entry = json.loads((tmp_path / "out" / outputs.REGISTRY).read_text())["entries"]["run"]
    shutil.rmtree(made)
    backup = tmp_path / "backup"
    _write(backup / "a.npy", b"motion")  # a copy of lsgan's files, with their registry
    backup.rename(made)
    registry = tmp_path / "out" / outputs.REGISTRY
    data = json.loads(registry.read_text())
    data["entries"]["run"] = {**entry, "ino": made.lstat().st_ino}  # as if the inode came back
    registry.write_text(json.dumps(data))
    assert not outputs.made_folder(made)
    outputs.claim_folder(tmp_path / "out", force=True)
    assert (made / "a.npy").read_bytes() == b"motion"


def test_demo_fresh_clears_only_folders_the_demo_made(tmp_path):
    """The outside check's B2: a user's folder named like a demo folder (runs/, motions/) keeps its files."""
    from lsgan.demo.folder import _clear_demo

    _write(tmp_path / "copy" / "a.npy", b"motion")
    (tmp_path / "copy").rename(tmp_path / "runs")
    _write(tmp_path / "demo.json", b"{}")
    _clear_demo(tmp_path)
    assert (tmp_path / "runs" / "a.npy").read_bytes() == b"motion" and not (tmp_path / "demo.json").exists()


def test_a_folder_fingerprint_cannot_be_forged_by_a_file_name(tmp_path):
    """B4: names holding '|' and a newline do not make one file hash like several."""
    three, one = tmp_path / "three", tmp_path / "one"
    three.mkdir()
    one.mkdir()
    for name in ("a", "b"):
        (three / name).write_bytes(b"x")
    listing = outputs.fingerprint(three)["files"]
    (one / "|".join(["a", listing["a"] + "\nb", listing["b"]])).write_bytes(b"x")
    assert outputs.fingerprint(one)["content"] != outputs.fingerprint(three)["content"]


def test_a_forged_file_listing_removes_nothing_outside_its_folder(tmp_path):
    """clear_path deletes a whole-written folder's files only by the names its real listing has: a parent record
    whose ``files`` name ``../victim`` (with the victim's true hash) touches nothing outside."""
    out = tmp_path / "out"
    with atomic_folder(out / "glb") as t:
        (t / "a.glb").write_bytes(b"glb")
    (out / "glb" / "mine.txt").write_text("user")  # the folder is no longer exactly lsgan's
    victim = out / "victim.txt"
    victim.write_bytes(b"keep")
    registry = out / outputs.REGISTRY
    data = json.loads(registry.read_text())
    data["entries"]["glb"]["files"]["../victim.txt"] = f"file 4 {outputs.file_sha256(victim)}"
    registry.write_text(json.dumps(data))
    outputs.clear_path(out / "glb")
    assert victim.read_bytes() == b"keep" and (out / "glb" / "mine.txt").read_text() == "user"
    assert not (out / "glb" / "a.glb").exists()


def test_an_output_name_too_long_for_its_temporary_is_refused_first(tmp_path):
    with pytest.raises(outputs.OutputError, match="name too long"):
        outputs.claim_file(tmp_path / ("b" * 240 + ".h5"))


# ------------------------------------------------------------------------------- hostile trees (Hypothesis)

NAMES = ["a.h5", "a.h5.report.json", ".a.h5.123.abcdefgh.tmp", ".a.h5.2023.old", ".ckpt.77.0a1b2c3d.old", "ckpt",
         "notes.txt", "sub", "log.csv"]
SUBNAMES = ["w.bin", "config.json", "x.npy"]


def _entry_for(content: bytes) -> dict:
    import hashlib

    return {"size": len(content), "sha256": hashlib.sha256(content).hexdigest()}


user_trees = st.lists(st.tuples(
    st.sampled_from(NAMES), st.sampled_from(["file", "dir", "link", "hardlink", "backup"]), st.sampled_from(SUBNAMES),
    st.binary(min_size=1, max_size=32)), max_size=5, unique_by=lambda t: t[0])
registries = st.sampled_from(["none", "forged", "traversal", "stale", "garbage"])
operations = st.lists(st.tuples(
    st.sampled_from(["write_file", "write_folder", "claim_folder", "clear", "sweep", "remove"]),
    st.sampled_from([*NAMES, "new.bin", "sub/new.bin", "ckpt/w.bin"]), st.booleans(), st.binary(max_size=8)),
    min_size=1, max_size=8)


def _plant(out: Path, outside: Path, tree, registry: str) -> None:
    """The user's files in ``out`` (files, folders with a file, links and hard links to files outside)."""
    for name, kind, sub, data in tree:
        p = out / name
        if kind == "file":
            p.write_bytes(data)
        elif kind == "dir":
            p.mkdir()
            (p / sub).write_bytes(data)
        elif kind == "link":
            p.symlink_to(outside / "secret.txt")
        elif kind == "backup":  # a copy of a folder lsgan wrote, its registry vouching for the copy
            p.mkdir()
            (p / sub).write_bytes(data)
            (p / outputs.REGISTRY).write_text(json.dumps({"entries": {sub: _entry_for(data)}}))
        else:
            os.link(outside / "linked.txt", p)
    names = [t[0] for t in tree] + ["new.bin"]
    forged = {
        "none": None,
        "forged": {n: _entry_for(b"not the user's bytes") for n in names},
        "traversal": {"../outside/secret.txt": _entry_for((outside / "secret.txt").read_bytes()),
                      str(outside / "linked.txt"): _entry_for((outside / "linked.txt").read_bytes())},
        "stale": {n: {"dir": True, "content": "0" * 64} for n in names},
        "garbage": "not json at all",
    }[registry]
    if forged is not None:
        text = forged if isinstance(forged, str) else json.dumps({"entries": forged})
        (out / outputs.REGISTRY).write_text(text)


def _apply(out: Path, op, wrote: set[str]) -> None:
    kind, name, force, data = op
    path = out / name
    try:
        if kind == "write_file":
            outputs.claim_file(path, force=force)
            _write(path, data)
            wrote.add(name)
        elif kind == "write_folder":
            wrote.add(f"forced:{name}") if force else None  # --force on this folder: its vouched copies may go
            outputs.claim_folder(path, force=force, whole=True)
            with atomic_folder(path) as tmp:
                (tmp / "w.bin").write_bytes(data)
            wrote.update({name, f"{name}/w.bin"})
        elif kind == "claim_folder":
            outputs.claim_folder(out, force=force)
        elif kind == "clear":
            outputs.clear_ours(out)
        elif kind == "sweep":
            outputs.sweep_temps(out)
        else:  # lsgan removes in the folder it was told to write, not inside what it finds there
            outputs.remove(out / name.split("/")[0])
    except outputs.OutputError as e:
        assert str(e).startswith(str(out)), e  # one line naming the path


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(tree=user_trees, registry=registries, ops=operations)
def test_no_operation_changes_a_byte_lsgan_did_not_write(tmp_path_factory, tree, registry, ops):
    """Random user trees and registries around random writes, claims, clears, sweeps and removals: every
    path lsgan did not write keeps its kind and bytes, and nothing outside the output changes. One exception, by
    design: copies of lsgan's files that came with their registry, in the very folder named as an output with
    ``force``, count as lsgan's there (nested inside an output they are never entered)."""
    out, outside = work_and_outside(tmp_path_factory.mktemp("tree"), "out")
    _plant(out, outside, tree, registry)
    before, before_outside = snapshot(out), snapshot(outside)
    wrote: set[str] = set()
    for op in ops:
        _apply(out, op, wrote)
    after = snapshot(out)
    copies = {f"{name}/{sub}" for name, kind, sub, _ in tree if kind == "backup"}
    for rel, what in before.items():
        if rel in copies and f"forced:{rel.split('/')[0]}" in wrote:
            continue  # a copy of lsgan's files with its registry, in the folder named as the output with force
        if rel not in wrote and not any(rel.startswith(w + "/") for w in wrote):
            assert after.get(rel) == what, f"{rel} changed or vanished after {ops}"
    assert snapshot(outside) == before_outside


# ---------------------------------------------------------------------------------------- runs and resumes


def _vae_run(d: Path, *flags, steps: int = 4) -> tuple[int, str]:
    from cli_runs import TINY_RECIPE, run_here

    if not (d / "tiny.yaml").exists():
        (d / "tiny.yaml").write_text(TINY_RECIPE)
        assert run_here(d, "preprocess", "--source", "synthetic", "--num-clips", 24, "-o", "synth.h5")[0] == 0
    return run_here(d, "train-vae", "--data", "synth.h5", "--recipe", "tiny.yaml", "--out", "run",
                    "--max-steps", steps, *flags)


def test_a_hard_linked_snapshot_of_a_run_keeps_its_bytes(tmp_path, monkeypatch):
    """B11: log.csv and train.log are rewritten through a temporary, so `cp -al` copies stay as they were."""
    monkeypatch.setenv("LSGAN_THREADS", "1")
    assert _vae_run(tmp_path)[0] == 0
    snap = tmp_path / "snap"
    snap.mkdir()
    for name in ("log.csv", "train.log"):
        os.link(tmp_path / "run" / name, snap / name)
    before = {n: (snap / n).read_bytes() for n in ("log.csv", "train.log")}
    code, err = _vae_run(tmp_path, "--resume", steps=6)
    assert code == 0, err
    assert {n: (snap / n).read_bytes() for n in before} == before
    assert (tmp_path / "run" / "log.csv").read_bytes() != before["log.csv"]


@pytest.mark.parametrize("point", ["publish.recorded@9", "publish.aside@2", "publish.placed@9"])
def test_a_kill_at_any_instant_of_a_publish_leaves_a_run_that_resumes(tmp_path, point):
    """SIGKILL between the registry's two records and the renames: the next --resume finds every file of the
    run still lsgan's (none refused as the user's), puts back or sweeps the temporaries, and finishes."""
    from cli_runs import TINY_RECIPE, lsgan

    (tmp_path / "tiny.yaml").write_text(TINY_RECIPE)
    made = lsgan("preprocess", "--source", "synthetic", "--num-clips", 24, "-o", "synth.h5", cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    args = ("train-vae", "--data", "synth.h5", "--recipe", "tiny.yaml", "--out", "run", "--max-steps", 6)
    killed = lsgan(*args, cwd=tmp_path, fault=f"{point}:SIGKILL")
    assert killed.returncode == -9, killed.stderr
    done = lsgan(*args, "--resume", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    run = tmp_path / "run"
    assert all(outputs.is_ours(run / n) for n in ("last", "best", "log.csv", "train.log"))
    assert not [p.name for p in run.iterdir() if p.name.startswith(".") and p.name != outputs.REGISTRY]
