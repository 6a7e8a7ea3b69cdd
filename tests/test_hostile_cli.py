"""Random trees of user files, links and registries around random sequences of real lsgan commands (with and
without --force and --resume): no byte of a file lsgan did not write changes, nothing outside the working
folder is touched, and every failure is one ``error:`` line.

The commands run in this process (click's entry point, as the ``lsgan`` script calls it), on the tiny pipeline
made once; budget: 60 examples of up to 3 commands, about a minute on a 2-core CPU.
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from cli_runs import run_here, tiny_pipeline
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st
from trees import snapshot, work_and_outside

from lsgan import outputs

pytestmark = pytest.mark.slow

# names that lsgan's commands write, or may be asked to write, in the working folder
PLACES = ["out.h5", "out.h5.report.json", "out.h5.parts", "run", "run/log.csv", "run/train.log", "run/last",
          "run/tb", "run/notes.tex", ".out.h5.2023.old", "report.json", "gen", "gen/backup", "run/backup"]
OUTS = ["out.h5", "run/x.h5", "run", "synth.h5", "notes.tex", "new/deep/out.h5"]
REPORTS = [None, "out.h5", "synth.h5", "report.json", "run/log.csv", "run"]
RUNS = ["run", "run2", "synth.h5", "out.h5.parts", ".", "vae"]
GENERATED = ["gen", "gan/samples", "vae", "run", "out.h5", ".", "gen/backup"]


@pytest.fixture(scope="module")
def seed_dir(tmp_path_factory) -> Path:
    """tiny.yaml, synth.h5, vae/, cache.h5 and gan/ of the tiny pipeline (lsgan's own files, recorded)."""
    return tiny_pipeline(tmp_path_factory.mktemp("hostile-seed"))


def plant(work: Path, outside: Path, tree) -> None:
    """The user's things: files, folders holding a file, links and hard links to files outside, registries."""
    for place, kind, data in tree:
        p = work / place
        if p.exists() or p.is_symlink() or (p.parent != work and not p.parent.is_dir() and p.parent.exists()):
            continue
        p.parent.mkdir(parents=True, exist_ok=True)
        if kind == "file":
            p.write_bytes(data)
        elif kind == "dir":
            p.mkdir()
            (p / "config.json").write_bytes(data)
        elif kind == "link":
            p.symlink_to(outside / "secret.txt")
        elif kind == "hardlink":
            os.link(outside / "linked.txt", p)
        elif kind == "copy":  # the user's backup of a run lsgan wrote, with the registry that came along
            shutil.copytree(work / "vae", p)
        else:  # a registry copied from elsewhere or forged, beside the user's file
            p.write_bytes(data)
            entries = {p.name: {"size": 3, "sha256": "0" * 64}, "../outside/secret.txt": {"size": 6},
                       "config.json": {"dir": True, "content": "f" * 64}}
            (p.parent / outputs.REGISTRY).write_text(json.dumps({"entries": entries}))


KINDS = ["file", "dir", "link", "hardlink", "forged", "copy"]
trees = st.lists(st.tuples(st.sampled_from(PLACES), st.sampled_from(KINDS), st.binary(min_size=1, max_size=16)),
                 max_size=5)
flags = st.sampled_from([[], ["--force"], ["--resume"]])
preprocess = st.tuples(st.just("preprocess"), st.sampled_from(OUTS), st.sampled_from(REPORTS), flags)
train = st.tuples(st.just("train-vae"), st.sampled_from(RUNS), st.none(), flags)
generate = st.tuples(st.just("generate"), st.sampled_from(GENERATED), st.none(), st.sampled_from([[], ["--force"]]))
commands = st.lists(st.one_of(preprocess, train, generate), min_size=1, max_size=3)


def argv(command) -> list:
    name, out, report, flags = command
    if name == "preprocess":
        return ["preprocess", "--source", "synthetic", "--num-clips", 8, "-o", out, *flags,
                *(["--report", report] if report else [])]
    if name == "generate":
        return ["generate", "--gan", "gan", "--vae", "vae", "--text", "a person walks", "--frames", 40, "-o", out,
                *flags]
    return ["train-vae", "--data", "synth.h5", "--recipe", "tiny.yaml", "--out", out, "--max-steps", 2, *flags]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                   HealthCheck.too_slow])
@given(tree=trees, cmds=commands)
@example(tree=[("gen/backup", "copy", b"x")],  # the outside check's B1: a backup copied into the output
         cmds=[("generate", "gen", None, ["--force"]), ("generate", "gen", None, ["--force"])])
@example(tree=[("run/backup", "copy", b"x"), ("run/notes.tex", "forged", b"x")],
         cmds=[("train-vae", "run", None, ["--resume"]), ("train-vae", "run", None, ["--force"])])
def test_commands_never_touch_what_lsgan_did_not_write(seed_dir, tmp_path_factory, monkeypatch, tree, cmds):
    monkeypatch.setenv("LSGAN_THREADS", "1")
    monkeypatch.delenv("LSGAN_DEBUG", raising=False)
    work, outside = work_and_outside(tmp_path_factory.mktemp("hostile"))
    for name in ("synth.h5", "tiny.yaml", outputs.REGISTRY, "vae", "gan"):  # lsgan's (copies, with their record)
        (shutil.copytree if (seed_dir / name).is_dir() else shutil.copy2)(seed_dir / name, work / name)
    plant(work, outside, tree)
    before, before_outside = snapshot(work), snapshot(outside)
    for cmd in cmds:
        code, err = run_here(work, *argv(cmd))
        assert code in (0, 1, 2), (cmd, code, err)
        event(f"{cmd[0]} exit {code}")
        errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
        assert "Traceback" not in err and (code == 0 or len(errors) == 1), (cmd, err)
    after = snapshot(work)
    ours = ("synth.h5", "vae", "gan")
    forced = {c[1] for c in cmds if c[3]}  # outputs named with --force or --resume
    copies = tuple(f"{place}/" for place, kind, _ in tree if kind == "copy" and place in forced)
    changed = [rel for rel, what in before.items() if rel.split("/")[0] not in ours and after.get(rel) != what
               and not rel.startswith(copies)]  # copies of lsgan's files, with their registry, in a forced output
    assert not changed, f"changed or gone: {changed} after {cmds}"
    assert snapshot(outside) == before_outside
