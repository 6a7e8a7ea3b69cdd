"""Browser test of the GLB export: three.js (GLTFLoader + AnimationMixer) in headless Chromium plays our file,
and the joints must land where the source motion has them. An independent glTF reader catches what our own
evaluation in test_export_glb.py would share with the exporter (axis, quaternion order, node-tree mistakes).

The rendered frame is saved as an artifact for a person to look at: ``$LSGAN_ARTIFACTS/glb_three.png``, or
``tests/artifacts/glb_three.png`` (git-ignored) when the variable is unset.

Needs Debian's Chromium (``apt-get install -y chromium chromium-driver``) and ``npm ci`` in tools/three-check;
.ci/run does both, elsewhere the test skips.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from lsgan.data.skeleton import JOINT_NAMES
from lsgan.data.synthetic import generate
from lsgan.export.glb import write_glb

THREE_CHECK = Path(__file__).resolve().parents[1] / "tools" / "three-check"
CHROMIUM = Path("/usr/bin/chromium")
ARTIFACTS = Path(os.environ.get("LSGAN_ARTIFACTS") or Path(__file__).resolve().parent / "artifacts")
NODES = ["pelvis", "head", "left_wrist", "right_elbow", "left_ankle", "right_foot"]


def three_check(glb: Path, times: list[float], nodes: list[str], screenshot: Path, *,
                screenshot_time: float | None = None, timeout: float = 120.0) -> dict:
    """Run tools/three-check/check.mjs on ``glb`` and return its JSON report: ``positions[node]`` is a list of
    world positions [x,y,z], one per time, plus ``clip_duration``, ``mesh_count``, ``skinned_mesh_count`` and
    ``webgl``. It also writes a PNG of the pose at ``screenshot_time`` (default: the first time) to ``screenshot``.
    Skips the calling test when node, Chromium or the npm packages are missing."""
    if shutil.which("node") is None:
        pytest.skip("node is not installed: the three.js check runs in Node (CI installs it)")
    if not CHROMIUM.exists():
        pytest.skip(f"no {CHROMIUM}: install it with `apt-get install -y chromium chromium-driver` (CI does)")
    for package in ("three", "playwright-core"):
        if not (THREE_CHECK / "node_modules" / package).exists():
            pytest.skip(f"{package} is not installed: run `npm ci` in tools/three-check (CI does)")
    cmd = ["node", str(THREE_CHECK / "check.mjs"), "--glb", str(glb), "--times", ",".join(repr(float(t)) for t in times),
           "--nodes", ",".join(nodes), "--screenshot", str(screenshot), "--timeout", str(timeout)]
    if screenshot_time is not None:
        cmd += ["--time-for-screenshot", repr(float(screenshot_time))]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout + 30)
    assert out.returncode == 0, f"check.mjs failed ({out.returncode}):\n{out.stderr}"
    return json.loads(out.stdout)


def test_three_js_plays_glb_like_source_joints(tmp_path):
    fps = 20.0
    joints = generate(1, seed=0)[0].joints.astype(np.float64)
    frames = joints.shape[0]
    glb = write_glb(tmp_path / "walk.glb", joints, fps=fps)
    keys = [0, frames // 3, 2 * frames // 3, frames - 1]
    between = frames // 2
    screenshot = ARTIFACTS / "glb_three.png"
    screenshot.unlink(missing_ok=True)

    report = three_check(glb, [k / fps for k in keys] + [(between + 0.5) / fps], NODES, screenshot,
                         screenshot_time=keys[1] / fps)

    assert report["clip_duration"] == pytest.approx((frames - 1) / fps, abs=1e-6)
    assert report["mesh_count"] == 1 and report["skinned_mesh_count"] == 1  # one skinned skeleton mesh
    assert report["webgl"], "three.js got no WebGL context in Chromium: the screenshot shows nothing"
    columns = [JOINT_NAMES.index(name) for name in NODES]
    seen = np.stack([np.asarray(report["positions"][name]) for name in NODES], axis=1)  # (times, nodes, 3)

    error = np.abs(seen[:len(keys)] - joints[keys][:, columns]).max()
    assert error < 1e-3, f"three.js joint positions at frame times are {error * 1000:.3f} mm off"
    # Between frames three.js slerps each joint's rotation, which bends the bone chain slightly away from the
    # straight line between the two source positions: close, not equal.
    halfway = 0.5 * (joints[between] + joints[between + 1])[columns]
    gap = np.abs(seen[len(keys)] - halfway).max()
    assert gap < 0.02, f"three.js pose between frames is {gap * 100:.2f} cm from the interpolated source"

    from PIL import Image

    assert screenshot.exists() and screenshot.stat().st_size > 0
    pixels = np.asarray(Image.open(screenshot).convert("RGB"), dtype=np.int16)
    assert pixels.reshape(-1, 3).std(axis=0).max() > 5, "the screenshot is one flat colour"
    orange = (pixels[..., 0] - pixels[..., 2] > 60).mean()  # the skeleton's material; background and grid are grey
    assert orange > 0.005, f"the skeleton covers {orange:.2%} of the screenshot"


def test_three_js_plays_the_skinned_body_glb(tmp_path):
    """The SMPL export: one SkinnedMesh whose skeleton three.js animates to the fitted joints."""
    from body_models import write_models

    from lsgan.data.body_model import read_body_model
    from lsgan.export.body import body_joints, fit_body
    from lsgan.export.glb import write_body_glb

    model = read_body_model(write_models(tmp_path / "models"))
    joints = generate(1, seed=0)[0].joints
    fit = fit_body(joints, model)
    glb = write_body_glb(tmp_path / "body.glb", fit, model)
    expected = body_joints(fit, model)
    frames = len(joints)
    keys = [0, frames // 2, frames - 1]
    screenshot = ARTIFACTS / "glb_body_three.png"
    screenshot.unlink(missing_ok=True)

    report = three_check(glb, [k / fit.fps for k in keys], NODES, screenshot, screenshot_time=keys[1] / fit.fps)

    assert report["skinned_mesh_count"] == 1 and report["mesh_count"] == 1
    assert report["clip_duration"] == pytest.approx((frames - 1) / fit.fps, abs=1e-6)
    columns = [JOINT_NAMES.index(name) for name in NODES]
    seen = np.stack([np.asarray(report["positions"][name]) for name in NODES], axis=1)
    error = np.abs(seen - expected[keys][:, columns]).max()
    assert error < 1e-3, f"three.js body joints are {error * 1000:.3f} mm from the fitted body's"
    assert np.abs(seen - joints[keys][:, columns]).max() < 0.05  # and near the motion itself (fit error)
    from PIL import Image

    pixels = np.asarray(Image.open(screenshot).convert("RGB"), dtype=np.int16)
    assert pixels.reshape(-1, 3).std(axis=0).max() > 5, "the screenshot is one flat colour"
