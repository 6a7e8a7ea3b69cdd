"""A newcomer's first steps, as the README gives them, in a fresh clone and a fresh virtual environment.

What it does:

1. ``git clone`` the repository this file lives in into a temporary folder. A clone holds the committed
   HEAD only: **uncommitted changes are not in it**, so this tests what is committed (run it after
   committing). The test skips when this tree is not a git checkout, and warns when it has uncommitted
   changes to tracked files.
2. Creates a fresh virtual environment there (``python -m venv``; the commands run with its ``bin/`` first on
   PATH, which is what activating it does).
3. Reads the two commands of the README's set-up table (the rows ``main job`` and ``tests`` between
   ``<!-- setup-commands -->`` and ``<!-- /setup-commands -->``), so that it checks what the README says, and runs
   them in the clone with ``bash -c``:

   - the main job (``pip install torch==2.13.0 && pip install -e ".[test]" && lsgan demo``; pip takes the
     local CPU torch wheel as configured on the machine) with the demo shrunk by ``LSGAN_DEMO_SCALE=0.05``;
   - the test command with ``tests/test_cli.py`` appended: it would otherwise run the whole suite again,
     this test included (a recursion). ``LSGAN_CLEAN_CLONE=1`` is set for it as well, and this test skips
     itself when it sees that variable.

4. Checks what the demo left: five GLB files that parse (GLB header, JSON chunk, an animation with channels;
   also through the Khronos glTF-Validator when ``tools/gltf-validate/node_modules`` exists in this tree),
   five GIFs, and ``metrics.json`` with the rows Real and the GAN holding finite values.

It needs git and the package registries (pip installs the dependencies into the new environment; a warm pip
cache makes it faster). A failing command is reported with the tail of its output; the full logs are kept
in the temporary folder, whose path the message gives. About 4-6 minutes on the 2-core CPU machine.
"""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from gltf_reader import parse

ROOT = Path(__file__).resolve().parents[1]
INNER = "LSGAN_CLEAN_CLONE"
VALIDATOR = ROOT / "tools" / "gltf-validate"

pytestmark = pytest.mark.clean_clone


def readme_commands(text: str) -> dict[str, str]:
    """{"main job": command, "tests": command} from the README's marked set-up table."""
    m = re.search(r"<!-- setup-commands[^>]*-->(.*?)<!-- /setup-commands -->", text, re.S)
    assert m, "README.md has no <!-- setup-commands --> ... <!-- /setup-commands --> block"
    found = {}
    for line in m.group(1).splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("|") else []
        # the command cell is the last one: `...` (a command may hold '|' only inside the backticks)
        cmd = re.search(r"\|\s*`([^`]+)`\s*\|\s*$", line)
        if not cells or not cmd:
            continue
        for key in ("main job", "tests"):
            if cells[0].lower().startswith(key):
                found[key] = cmd.group(1)
    assert set(found) == {"main job", "tests"}, f"README set-up table: found {found}"
    return found


def test_readme_names_the_commands():
    cmds = readme_commands((ROOT / "README.md").read_text())
    assert cmds["main job"].rstrip().endswith("lsgan demo")
    assert "pip install torch==2.13.0" in cmds["main job"]
    assert cmds["tests"] == "python -m pytest -q"


def _run(cmd: str, cwd: Path, env: dict, log: Path, timeout: int) -> str:
    """Run ``cmd`` with bash; fail with the tail of its output (stdout and stderr together)."""
    try:
        proc = subprocess.run(["bash", "-c", cmd], cwd=cwd, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as e:
        out = e.stdout.decode(errors="replace") if isinstance(e.stdout, bytes) else (e.stdout or "")
        log.write_text(out)
        pytest.fail(f"`{cmd}` did not finish in {timeout} s; full log {log}; its last output:\n{_tail(out)}")
    log.write_text(proc.stdout)
    if proc.returncode != 0:
        pytest.fail(f"`{cmd}` exited with {proc.returncode}; full log {log}; its last output:\n{_tail(proc.stdout)}")
    return proc.stdout


def _tail(text: str, n: int = 4000) -> str:
    # progress bars redraw with \r: keep the last state of each line
    lines = [line.rsplit("\r", 1)[-1] for line in text.splitlines()]
    return "\n".join(lines)[-n:]


def test_readme_setup_in_a_fresh_clone(tmp_path):
    if os.environ.get(INNER):
        pytest.skip(f"{INNER} is set: this is the test run inside a clean clone (no recursion)")
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    top = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--show-toplevel"], capture_output=True, text=True)
    if top.returncode != 0 or Path(top.stdout.strip()).resolve() != ROOT:
        pytest.skip(f"{ROOT} is not a git checkout: nothing to clone")
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.rstrip()
    if dirty:
        warnings.warn(f"uncommitted changes are not in the clone (it tests HEAD):\n{dirty}", stacklevel=1)

    clone, venv = tmp_path / "lsgan", tmp_path / "venv"
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True, capture_output=True, timeout=300)
    cmds = readme_commands((clone / "README.md").read_text())  # the README as committed
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    env.update(PATH=f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}", VIRTUAL_ENV=str(venv),
               LSGAN_DEMO_SCALE="0.05", OMP_NUM_THREADS="1", PIP_PROGRESS_BAR="off")

    # The main job: install, then the whole demo (shrunk)
    out = _run(cmds["main job"], clone, env, tmp_path / "main-job.log", timeout=2400)
    assert "Text-to-motion" in out and "| Real |" in out, _tail(out)
    python = subprocess.run(["bash", "-c", "command -v python"], env=env, capture_output=True, text=True).stdout.strip()
    assert Path(python).parent == venv / "bin", f"python resolves to {python}, not the clone's venv"

    demo = clone / "demo_out"
    glb = sorted((demo / "glb").glob("*.glb"))
    assert len(glb) == 5, f"{len(glb)} GLB files in {demo / 'glb'}"
    for path in glb:
        doc, _ = parse(path.read_bytes())
        anim = doc.get("animations") or []
        assert anim and anim[0]["channels"] and anim[0]["samplers"], f"{path.name}: no animation"
        assert len(doc["nodes"]) >= 22, f"{path.name}: {len(doc['nodes'])} nodes"
    if shutil.which("node") and (VALIDATOR / "node_modules" / "gltf-validator").exists():
        for path in glb:
            rep = subprocess.run(["node", str(VALIDATOR / "validate.js"), str(path)], capture_output=True, text=True,
                                 timeout=120)
            assert rep.returncode == 0, rep.stderr
            report = json.loads(rep.stdout)
            assert report["errors"] == 0 and report["warnings"] == 0, (path.name, report["messages"])
    assert len(list((demo / "gif").glob("*.gif"))) == 5

    summary = json.loads((demo / "summary.json").read_text())
    metrics = json.loads((demo / "metrics.json").read_text())
    gan_row = summary["gan_row"]
    assert set(metrics["rows"]) == {"Real", gan_row}, metrics["rows"].keys()
    for name, row in metrics["rows"].items():
        for col in ("r_precision_top1", "r_precision_top2", "r_precision_top3", "fid", "mm_dist", "diversity"):
            assert math.isfinite(row[col]["mean"]), (name, col, row[col])
    assert math.isfinite(metrics["rows"][gan_row]["multimodality"]["mean"])

    # The tests, short and without recursion (see the docstring)
    env[INNER] = "1"
    out = _run(f"{cmds['tests']} tests/test_cli.py", clone, env, tmp_path / "tests.log", timeout=900)
    assert re.search(r"\d+ passed", out), _tail(out)
    # Passed: the clone and its venv (2 GB) go now, by rm rather than pytest's teardown, which took 2-3 minutes
    # over them in whole-suite runs (5 s alone).
    subprocess.run(["rm", "-rf", str(clone), str(venv)], check=True, timeout=600)
