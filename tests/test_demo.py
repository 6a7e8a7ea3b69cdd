"""``lsgan demo``: its settings at each scale, and the whole run shrunk (LSGAN_DEMO_SCALE=0.05) through the real
CLI: Ctrl-C in the middle of a training stage, the run that continues it, and a third run that reuses everything."""
from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from gltf_reader import parse

from lsgan.demo.markers import STAGES
from lsgan.demo.settings import MIN_CLIPS, demo_settings, scale_from_env
from lsgan.recipes import load_recipe

TINY = "0.05"


def test_settings_follow_the_recipe_and_shrink_with_floors(monkeypatch):
    monkeypatch.delenv("LSGAN_DEMO_SCALE", raising=False)
    recipe = load_recipe("demo")
    full = demo_settings()
    assert full.scale == 1.0
    assert full.vae_steps == recipe["vae"]["train"]["max_steps"]
    assert full.gan_steps == recipe["gan"]["train"]["max_steps"]
    assert full.evaluator_steps == recipe["evaluator"]["text"]["train"]["max_steps"]
    assert full.clips == recipe["demo"]["clips"] and len(full.prompts) == 5
    assert full.replications == recipe["demo"]["replications"]

    monkeypatch.setenv("LSGAN_DEMO_SCALE", TINY)
    tiny = demo_settings()
    assert tiny.scale == 0.05 and tiny.clips == MIN_CLIPS  # the test split must keep 32+ windows
    assert tiny.vae_steps == max(10, round(full.vae_steps * 0.05)) and tiny.gan_steps < full.gan_steps
    assert tiny.replications == 1 and tiny.mm_captions < full.mm_captions
    assert "1 replication (the protocol: 20)" in tiny.reduced
    assert demo_settings(0.5).scale == 0.5  # an explicit scale wins over the variable

    for bad in ("x", "0", "-1", "nan", "1e308", "101"):
        with pytest.raises(ValueError, match="number > 0"):
            scale_from_env(bad)


@pytest.mark.parametrize("text, phrase", [
    ("demo: {frames: 300}\nvae: {model: {max_len: 256}}", "r.yaml: demo: frames 300 is more than the VAE decodes"),
    ("demo: {prompts: walk}", "r.yaml: demo.prompts: 'walk' is not a list of text"),
    ("demo: {prompts: []}", "r.yaml: demo: prompts must be a list of 1 to 100 sentences"),
    ("demo: {prompts: [\"walk\\0\"]}", "r.yaml: demo: prompts must be a list of 1 to 100 sentences of printable"),
    ("vae: {train: {min_frames: 100, max_frames: 40}}", "r.yaml: vae.train: min_frames (100) is more than max_frames"),
    ("demo: {clips: 0}", "r.yaml: demo.clips: 0 is not from 1 to 1,000,000,000"),
    ("demo: {clips: 60}", "r.yaml: demo: clips must be at least 400"),
    ("text_encoder: none", "r.yaml: text_encoder is none, but the demo trains a text-to-motion GAN"),
    ("demo: {seed: -1}", "r.yaml: demo.seed: -1 is not from 0 to 9,223,372,036,854,775,807"),
    ("demo: {1: 2, zz: 3}", "r.yaml: demo: unknown key(s) ['1', 'zz']"),
    ("vae: {model: {num_heads: 0}}", "r.yaml: vae.model.num_heads: 0 is not from 1 to 1,024"),
    ("evaluator: {text: {train: {val_every: 0}}}", "r.yaml: evaluator.text.train.val_every: 0 is not from 1"),
    ("demo: {replications: 2.5}", "r.yaml: demo.replications: 2.5 is not a whole number"),
    ("demo: {mm_sample: 3}", "r.yaml: demo: unknown key(s) ['mm_sample']"),
    ("gan: {train: {max_steps: many}}", "r.yaml: gan.train.max_steps: 'many' is not a whole number"),
])
def test_a_bad_demo_section_is_refused_before_any_stage_runs(tmp_path, text, phrase):
    (tmp_path / "r.yaml").write_text(text + "\n")
    with pytest.raises(ValueError) as e:
        demo_settings(1, tmp_path / "r.yaml")
    assert phrase in str(e.value)


def _demo(out: Path, cwd: Path, **kw) -> subprocess.Popen:
    env = {**os.environ, "LSGAN_DEMO_SCALE": TINY, "OMP_NUM_THREADS": "1"}
    # SIGINT at its default in the child (it is ignored when pytest itself runs in the background)
    return subprocess.Popen([sys.executable, "-m", "lsgan.cli", "demo", "-o", str(out)], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL), **kw)


def _leftovers(out: Path) -> list[str]:
    """Temporary files or folders of the atomic writes (dot names other than the stage markers' folder)."""
    return [str(p) for p in out.rglob(".*") if p.name not in (".stages", ".lsgan-outputs.json")]


@pytest.mark.slow
def test_demo_interrupted_continued_and_reused(tmp_path):
    out = tmp_path / "demo"
    # 1. Ctrl-C once the VAE has written its first checkpoint
    proc = _demo(out, tmp_path)
    deadline = time.monotonic() + 600
    while not (out / "runs" / "vae" / "last" / "config.json").exists() and proc.poll() is None:
        assert time.monotonic() < deadline, "the demo wrote no VAE checkpoint in 10 minutes"
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 130, stderr[-3000:]
    m = re.search(r"interrupted: during \[(\d)/8\] ([a-z-]+)", stderr)
    assert m, stderr[-3000:]
    assert f"lsgan demo -o {out}" in stderr and "again to continue" in stderr
    assert not _leftovers(out)
    interrupted = m.group(2)
    assert not (out / ".stages" / f"{interrupted}.json").exists()

    # 2. The next run continues: earlier stages reused, the interrupted training resumed
    proc = _demo(out, tmp_path)
    stdout, stderr = proc.communicate(timeout=900)
    assert proc.returncode == 0, stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    status = {s["name"]: s["status"] for s in summary["stages"]}
    assert list(status) == list(STAGES)
    assert status["preprocess"] == "reused"
    if interrupted == "train-vae":
        assert status["train-vae"] == "resumed"
        assert "[2/8] train-vae: resumed and done in" in stderr
    for i, name in enumerate(STAGES, start=1):
        assert f"[{i}/8] {name}" in stderr
    assert "Text-to-motion" in stdout and "| Real |" in stdout and "1 replication" in stdout
    assert "summary.json" in stdout and "glb" in stdout

    # the outputs
    gan_row = summary["gan_row"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert list(metrics["rows"]) == ["Real", gan_row]
    for row in metrics["rows"].values():
        for col in ("r_precision_top1", "r_precision_top3", "fid", "mm_dist", "diversity"):
            assert math.isfinite(row[col]["mean"])
    assert "multimodality" in metrics["rows"][gan_row]
    assert "| Real |" in (out / "metrics.md").read_text()
    glb = sorted((out / "glb").glob("*.glb"))
    gif = sorted((out / "gif").glob("*.gif"))
    assert len(glb) == 5 and len(gif) == 5
    for path in glb:
        doc, _ = parse(path.read_bytes())
        assert doc["animations"] and doc["animations"][0]["channels"]
    for path in gif:
        assert path.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    manifest = json.loads((out / "motions" / "manifest.json").read_text())
    assert [m["text"] for m in manifest["motions"]] == list(summary["settings"]["prompts"])
    assert summary["metrics"][gan_row]["fid"]["mean"] == metrics["rows"][gan_row]["fid"]["mean"]
    assert all(s["seconds"] >= 0 for s in summary["stages"]) and summary["stages_seconds"] > 0
    assert not _leftovers(out)

    # 3. A third run reuses every stage and prints the same table
    t0 = time.monotonic()
    proc = _demo(out, tmp_path)
    stdout2, stderr2 = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr2[-3000:]
    assert all(s["status"] == "reused" for s in json.loads((out / "summary.json").read_text())["stages"])
    assert stderr2.count("done earlier") == len(STAGES)
    assert stdout2.split("Text-to-motion")[1] == stdout.split("Text-to-motion")[1]
    assert time.monotonic() - t0 < 120

    # 4. Another scale in the same folder is refused with a way out
    env = {**os.environ, "LSGAN_DEMO_SCALE": "0.06"}
    other = subprocess.run([sys.executable, "-m", "lsgan.cli", "demo", "-o", str(out)], env=env, capture_output=True,
                           text=True, timeout=300)
    assert other.returncode == 1 and "other settings" in other.stderr and "--fresh" in other.stderr

    # 5. --fresh removes the demo's own files and keeps the user's, wherever they were put
    _fresh_keeps_user_files(out)


def _fresh_keeps_user_files(out: Path) -> None:
    """Issue 28, B6: what ``demo --fresh`` clears of a finished demo holding the user's files here and there."""
    from lsgan.demo.folder import _clear_demo

    mine = {out / "glb" / "my.glb": b"glb", out / "motions" / "notes.txt": b"n", out / "data" / "mocap.h5": b"h",
            out / "runs" / "vae" / "thesis.tex": b"t", out / "notes.md": b"m"}
    for path, data in mine.items():
        path.write_bytes(data)
    _clear_demo(out)
    assert all(path.read_bytes() == data for path, data in mine.items())
    left = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and p.name != ".lsgan-outputs.json")
    assert left == sorted(str(p.relative_to(out)) for p in mine), left


def test_demo_help_documents_the_scale():
    out = subprocess.run([sys.executable, "-m", "lsgan.cli", "demo", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    assert "LSGAN_DEMO_SCALE" in out.stdout and "--scale" in out.stdout and "Examples:" in out.stdout
