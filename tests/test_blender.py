"""Blender imports our BVH and GLB at their own length and speed with the settings ``lsgan export`` prints.

Runs Blender as a Python module (``pip install bpy`` in a separate virtual environment; CI does) named by
LSGAN_BLENDER_PYTHON; skips with that instruction otherwise. Motions of 131 and 300 frames (shorter and longer
than Blender's default 250-frame scene) are exported at 20 and 30 fps; Blender imports each file fresh, once with
its defaults (to show what goes wrong: the test asserts it does) and once with the printed settings (the BVH with
both 'Update Scene' boxes ticked, then the printed frame range), plays the scene's range and reports the scene rate,
frame range, the imported action's key range and the root bone's place on the first and last frame played.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lsgan.data.synthetic import generate
from lsgan.export.blender import scene_settings

BLENDER_PYTHON = os.environ.get("LSGAN_BLENDER_PYTHON")
pytestmark = pytest.mark.skipif(
    not BLENDER_PYTHON or not Path(BLENDER_PYTHON).exists(),
    reason="set LSGAN_BLENDER_PYTHON to a Python with bpy (python3 -m venv v && v/bin/pip install bpy), as CI does")

FRAMES = 300
SCRIPT = r"""
import json, sys, bpy
fmt, path, settings = sys.argv[-3], sys.argv[-2], json.loads(sys.argv[-1])
out = {}
for mode in ("defaults", "settings"):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    if fmt == "bvh":
        flags = dict(update_scene_fps=True, update_scene_duration=True) if mode == "settings" else {}
        bpy.ops.import_anim.bvh(filepath=path, global_scale=0.01, **flags)
    else:
        if mode == "settings":
            scene.render.fps, scene.render.fps_base = settings["fps"], settings["fps_base"]
        bpy.ops.import_scene.gltf(filepath=path)
    if mode == "settings":
        scene.frame_start, scene.frame_end = settings["frame_start"], settings["frame_end"]
    keys = [tuple(a.frame_range) for a in bpy.data.actions]
    arm = [o for o in scene.objects if o.type == "ARMATURE"][0]
    root = [b for b in arm.pose.bones if b.parent is None][0]
    played = {}
    for f in range(scene.frame_start, scene.frame_end + 1):  # play the scene's range
        scene.frame_set(f)
        if f in (scene.frame_start, scene.frame_end):
            played[str(f)] = list(arm.matrix_world @ root.head)
    out[mode] = {"rate": scene.render.fps / scene.render.fps_base, "start": scene.frame_start,
                 "end": scene.frame_end, "keys": [min(k[0] for k in keys), max(k[1] for k in keys)],
                 "root": [played[str(scene.frame_start)], played[str(scene.frame_end)]]}
print("REPORT" + json.dumps(out))
"""


def _report(script: str, *args) -> dict:
    """Run ``script`` in LSGAN_BLENDER_PYTHON with ``args`` (the last items of its sys.argv); its REPORT line."""
    out = subprocess.run([BLENDER_PYTHON, "-c", script, *map(str, args)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    line = [x for x in out.stdout.splitlines() if x.startswith("REPORT")]
    assert line, out.stdout[-2000:] + out.stderr[-2000:]
    return json.loads(line[0][len("REPORT"):])


def _blender(fmt: str, path: Path, fps: float, frames: int = FRAMES) -> dict:
    return _report(SCRIPT, fmt, path, json.dumps(scene_settings(fmt, fps, frames).__dict__))


@pytest.fixture(scope="module")
def motion(tmp_path_factory) -> Path:
    joints = np.concatenate([generate(1, seed=s)[0].joints for s in range(8)])[:FRAMES].astype(np.float32)
    assert len(joints) == FRAMES
    path = tmp_path_factory.mktemp("blender") / "walk_joints.npy"
    np.save(path, joints)
    return path


@pytest.mark.parametrize("fmt", ["bvh", "glb"])
@pytest.mark.parametrize("fps", [20.0, 30.0])
@pytest.mark.parametrize("frames", [131, FRAMES])
def test_blender_plays_the_whole_motion_at_its_speed(motion, tmp_path, fmt, fps, frames):
    joints = np.load(motion)[:frames]
    np.save(tmp_path / "m_joints.npy", joints)
    exported = tmp_path / f"m.{fmt}"
    run = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", f"--{fmt}", str(tmp_path / "m_joints.npy"),
                          "--fps", str(fps), "-o", str(exported)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    wanted = scene_settings(fmt, fps, frames)
    assert "Blender:" in run.stderr and f"{round(fps)} fps" in run.stderr  # the printed advice, with the range
    assert f"Start {wanted.frame_start}, End {wanted.frame_end}" in run.stderr
    report = _blender(fmt, exported, fps, frames)
    good = report["settings"]
    assert good["rate"] == pytest.approx(fps)
    assert [good["start"], good["end"]] == pytest.approx(good["keys"], abs=1e-3)  # the scene is the animation
    assert good["end"] - good["start"] + 1 == frames and (fmt != "bvh" or good["end"] == frames)
    assert (good["end"] - good["start"] + 1) / good["rate"] == pytest.approx(frames / fps, abs=1e-3)  # seconds
    for place, frame in zip(good["root"], (0, -1)):  # the first and last frame played are the motion's
        x, y, z = joints[frame, 0]
        assert place == pytest.approx([x, -z, y], abs=1e-3)
    bad = report["defaults"]  # without them: a 24 fps scene of frames 1-250, whatever the motion's length
    assert bad["rate"] == 24 and [bad["start"], bad["end"]] == [1, 250]
    if fmt == "bvh":  # one key per frame whatever the scene's rate: too fast at 20 fps, and cut at frame 250
        assert bad["keys"][1] == pytest.approx(frames)
    else:  # keys in seconds: the speed is kept, the motion is cut once it is longer than 250 / 24 s
        assert bad["keys"][1] == pytest.approx((frames - 1) / fps * 24, abs=1e-3)


@pytest.mark.parametrize("fps", [12.5, 29.97])
def test_a_glb_at_a_fractional_rate_plays_at_its_speed(motion, tmp_path, fps):
    """The outside check's case: Blender's glTF importer puts a key at t x fps x fps_base, so the printed whole rate
    (base 1) and end frame make the scene end on the last key, at the motion's own time."""
    np.save(tmp_path / "m_joints.npy", np.load(motion)[:120])
    run = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--glb", str(tmp_path / "m_joints.npy"),
                          "--fps", str(fps), "-o", str(tmp_path / "m.glb")], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    good = _blender("glb", tmp_path / "m.glb", fps, 120)["settings"]
    assert good["keys"][1] == pytest.approx(good["end"], abs=0.5)  # the scene ends on the last key
    assert good["keys"][1] / good["rate"] == pytest.approx(119 / fps, abs=1e-3)  # at the motion's own time


def test_update_scene_duration_never_shortens(motion, tmp_path):
    """Why the printed settings name the end frame: a 131-frame BVH imported with both 'Update Scene' boxes ticked
    and no more still plays over frames 1-250."""
    np.save(tmp_path / "m_joints.npy", np.load(motion)[:131])
    run = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--bvh", str(tmp_path / "m_joints.npy"),
                          "-o", str(tmp_path / "m.bvh")], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    report = _report(UPDATE_ONLY, tmp_path / "m.bvh")
    assert report["rate"] == 20 and report["end"] == 250 and report["keys"] == [1, 131]


UPDATE_ONLY = r"""
import json, sys, bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_anim.bvh(filepath=sys.argv[-1], global_scale=0.01, update_scene_fps=True, update_scene_duration=True)
scene = bpy.context.scene
print("REPORT" + json.dumps({"rate": scene.render.fps / scene.render.fps_base, "end": scene.frame_end,
                             "keys": list(bpy.data.actions[0].frame_range)}))
"""


ARMATURE_SCRIPT = r"""
import json, sys, bpy
path, frames = sys.argv[-2], json.loads(sys.argv[-1])
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.fps, scene.render.fps_base = 20, 1.0
bpy.ops.import_scene.gltf(filepath=path)
arms = [o for o in scene.objects if o.type == "ARMATURE"]
shapes = {pb.custom_shape for a in arms for pb in a.pose.bones if pb.custom_shape is not None}
meshes = [o for o in scene.objects if o.type == "MESH" and o not in shapes]  # not the importer's bone display
out = {"armatures": len(arms), "meshes": len(meshes), "bones": [b.name for b in arms[0].data.bones] if arms else [],
       "deformed": [any(m.type == "ARMATURE" and m.object == arms[0] for m in o.modifiers) for o in meshes] if arms else [],
       "heads": {}}
for f in frames:
    scene.frame_set(f)
    mw = arms[0].matrix_world
    out["heads"][str(f)] = {b.name: list(mw @ b.head) for b in arms[0].pose.bones}
print("REPORT" + json.dumps(out))
"""


def test_blender_imports_the_skeleton_glb_as_an_armature(motion, tmp_path):
    """One armature of our 22 joints and one mesh it deforms (not 22 loose objects); posed at a frame, each
    bone's head sits on the joint (Blender's Z-up: x, -z, y of ours) within 1 mm."""
    from lsgan.data.skeleton import JOINT_NAMES

    joints = np.load(motion)
    path = tmp_path / "walk.glb"
    run = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--glb", str(motion), "-o", str(path)],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    frames = [0, 150, FRAMES - 1]
    report = _report(ARMATURE_SCRIPT, path, json.dumps(frames))
    assert report["armatures"] == 1 and report["meshes"] == 1 and report["deformed"] == [True]
    assert sorted(report["bones"]) == sorted(JOINT_NAMES)
    for f in frames:
        heads = report["heads"][str(f)]
        ours = np.array([heads[name] for name in JOINT_NAMES])
        expected = joints[f][:, [0, 2, 1]] * [1.0, -1.0, 1.0]  # glTF (x, y, z) -> Blender (x, -z, y)
        assert np.abs(ours - expected).max() < 1e-3, (f, np.abs(ours - expected).max())


@pytest.mark.parametrize("rig", ["mixamo", "bandai"])
def test_blender_imports_the_rig_glb_as_an_armature(motion, tmp_path, request, rig):
    """``--glb --rig``: one armature with the rig's bones (its names) deforming one mesh; with the printed settings
    the whole motion plays at its speed; posed at a frame, each bone's head is where the rig BVH's forward
    kinematics puts the joint (the same solve), within 1 mm. The rigs: test_retarget's Mixamo-named one and a real
    Bandai file (../shared)."""
    from test_retarget import RIG, _mixamo_rig

    from lsgan.data.bvh import forward_kinematics, read_bvh

    if rig == "bandai":
        rig_path = request.getfixturevalue("bandai_dir") / "data" / f"{RIG}.bvh.gz"
    else:
        rig_path = tmp_path / "rig.bvh"
        _mixamo_rig(rig_path)
    for fmt in ("glb", "bvh"):
        run = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", f"--{fmt}", str(motion), "--rig",
                              str(rig_path), "--preset", rig, "-o", str(tmp_path / f"m.{fmt}")],
                             capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
    assert "Blender:" in run.stderr and "20 fps" in run.stderr
    good = _blender("glb", tmp_path / "m.glb", 20.0)["settings"]
    assert good["rate"] == 20 and good["keys"] == pytest.approx([0, FRAMES - 1], abs=1e-3)
    assert good["start"] <= good["keys"][0] and good["end"] >= good["keys"][1]

    frames = [0, 150, FRAMES - 1]
    report = _report(ARMATURE_SCRIPT, tmp_path / "m.glb", json.dumps(frames))
    bvh = read_bvh(tmp_path / "m.bvh")
    assert report["armatures"] == 1 and report["meshes"] == 1 and report["deformed"] == [True]
    assert sorted(report["bones"]) == sorted(bvh.names)
    fk = forward_kinematics(bvh)[frames] * 0.01  # both rigs: centimetres, Y up
    heads = np.array([[report["heads"][str(f)][name] for name in bvh.names] for f in frames])
    error = np.abs(heads - fk[..., [0, 2, 1]] * [1.0, -1.0, 1.0]).max()  # glTF (x, y, z) -> Blender (x, -z, y)
    print(f"{rig}: {len(bvh.names)} bones, Blender's bone heads vs the rig BVH's joints: max {error * 1000:.4f} mm")
    assert error < 1e-3


BODY_SCRIPT = r"""
import json, sys, bpy
path, settings, frames = sys.argv[-3], json.loads(sys.argv[-2]), json.loads(sys.argv[-1])
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.fps, scene.render.fps_base = settings["fps"], settings["fps_base"]
bpy.ops.import_scene.gltf(filepath=path)
scene.frame_start, scene.frame_end = settings["frame_start"], settings["frame_end"]
arms = [o for o in scene.objects if o.type == "ARMATURE"]
shapes = {pb.custom_shape for a in arms for pb in a.pose.bones if pb.custom_shape is not None}
meshes = [o for o in scene.objects if o.type == "MESH" and o not in shapes]  # not the importer's bone display
out = {"armatures": len(arms), "meshes": len(meshes)}
if len(arms) == 1 and len(meshes) == 1:
    arm, body = arms[0], meshes[0]
    out.update(bones=[b.name for b in arm.data.bones], groups=[g.name for g in body.vertex_groups],
               parent=body.parent == arm, parent_type=body.parent_type,
               modifier=[m.object == arm for m in body.modifiers if m.type == "ARMATURE"],
               rest=[list(body.matrix_world @ v.co) for v in body.data.vertices],
               keys=[list(a.frame_range) for a in bpy.data.actions], start=scene.frame_start, end=scene.frame_end,
               vertices={}, heads={})
    for f in frames:
        scene.frame_set(f)
        evaluated = body.evaluated_get(bpy.context.evaluated_depsgraph_get())
        mesh = evaluated.to_mesh()
        out["vertices"][str(f)] = [list(evaluated.matrix_world @ v.co) for v in mesh.vertices]
        evaluated.to_mesh_clear()
        out["heads"][str(f)] = {pb.name: list(arm.matrix_world @ pb.head) for pb in arm.pose.bones}
print("REPORT" + json.dumps(out))
"""


@pytest.fixture(scope="module")
def body_models(tmp_path_factory) -> Path:
    from body_models import write_models

    return write_models(tmp_path_factory.mktemp("body_models"))


@pytest.mark.parametrize("model_type", ["smpl", "smplh", "smplx"])
def test_blender_imports_the_body_glb_and_deforms_it_like_lsgan(motion, body_models, tmp_path, model_type):
    """``--glb --body-model``: one armature with the model's joints (the GLB's names) and one mesh it deforms,
    with a vertex group per joint; with the printed settings the whole motion plays at its speed (without, it is
    cut at frame 250); at each checked frame Blender's evaluated mesh (depsgraph, Armature modifier) lies on the
    GLB's linear blend skinning (tests/gltf_reader.py) and on smplx's forward pass of the fitted .npz, within 1 mm,
    and its bones' heads on the GLB's joints within 0.1 mm. The stand-in models (tests/body_models.py) have
    vertices in no face (the joint regressor's, SMPL-X's padding): Blender's importer drops them, so the mesh has
    the vertices the faces use, in the file's order (checked on the bind pose)."""
    from gltf_reader import accessor, node_index, parse, skinned_vertices, world_matrices
    from scipy.spatial.transform import Rotation
    from test_export_body import smplx_output

    from lsgan.data.body_model import read_body_model

    path = tmp_path / "body.glb"
    run = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--glb", str(motion), "--body-model",
                          str(body_models), "--model-type", model_type, "-o", str(path)],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "Blender:" in run.stderr and "20 fps" in run.stderr and f"Start 0, End {FRAMES - 1}" in run.stderr  # advice
    model = read_body_model(body_models, model_type=model_type)
    doc, blob = parse(path.read_bytes())
    names = node_index(doc)
    joint_names = [doc["nodes"][k]["name"] for k in doc["skins"][0]["joints"]]
    assert joint_names == list(model.joint_names)

    speed = _blender("glb", path, 20.0)  # the frame range, as for the skeleton GLB
    good, bad = speed["settings"], speed["defaults"]
    assert good["rate"] == 20 and good["keys"] == pytest.approx([0, FRAMES - 1], abs=1e-3)
    assert good["start"] <= good["keys"][0] and good["end"] >= good["keys"][1]
    assert bad["rate"] == 24 and bad["end"] == 250 and bad["keys"][1] == pytest.approx((FRAMES - 1) / 20 * 24, abs=1e-3)

    frames = [0, 150, FRAMES - 1]
    report = _report(BODY_SCRIPT, path, json.dumps(scene_settings("glb", 20.0, FRAMES).__dict__), json.dumps(frames))
    assert report["armatures"] == 1 and report["meshes"] == 1
    assert sorted(report["bones"]) == sorted(joint_names) and len(report["bones"]) == model.num_joints
    assert sorted(report["groups"]) == sorted(joint_names)
    assert report["parent"] and (report["parent_type"] == "ARMATURE" or report["modifier"] == [True])
    assert report["keys"] == [[0, FRAMES - 1]] and report["start"] == 0 and report["end"] == FRAMES - 1

    prim = doc["meshes"][0]["primitives"][0]
    used = np.unique(accessor(doc, blob, prim["indices"]))
    assert len(used) == len(np.unique(model.faces)) and len(report["rest"]) == len(used)
    to_blender = lambda a: np.asarray(a)[..., [0, 2, 1]] * [1.0, -1.0, 1.0]  # noqa: E731  glTF (x,y,z) -> (x,-z,y)
    rest = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)[used]
    assert np.abs(np.array(report["rest"]) - to_blender(rest)).max() < 1e-6  # the same vertices, in order

    with np.load(path.with_suffix(".npz"), allow_pickle=False) as npz:
        oracle = smplx_output(body_models, model_type, npz["poses"][frames], npz["trans"][frames], npz["betas"])[1]
    blender = np.array([report["vertices"][str(f)] for f in frames])
    a, b = blender[0] - blender[0].mean(axis=0), blender[1] - blender[1].mean(axis=0)
    rigid = Rotation.align_vectors(b, a)[0].apply(a)  # the best rigid motion of frame 0's mesh onto frame 150's
    moved = np.linalg.norm(b - rigid, axis=-1).max()
    assert moved > 0.05, moved  # the body bends between the frames, beyond moving and turning as a whole
    vertex_error = joint_error = smplx_error = 0.0
    for i, f in enumerate(frames):
        ours = to_blender(skinned_vertices(doc, blob, f)[used])
        vertex_error = max(vertex_error, np.abs(blender[i] - ours).max())
        smplx_error = max(smplx_error, np.abs(blender[i] - to_blender(oracle[i][used])).max())
        world = world_matrices(doc, blob, f)
        heads = np.array([report["heads"][str(f)][name] for name in joint_names])
        joint_error = max(joint_error, np.abs(heads - to_blender(world[[names[n] for n in joint_names], :3, 3])).max())
    print(f"{model_type}: {len(used)} vertices, {model.num_joints} bones; Blender's evaluated mesh vs lsgan's skinning "
          f"max {vertex_error * 1000:.4f} mm, vs smplx {smplx_error * 1000:.4f} mm; bone heads vs the GLB's joints "
          f"max {joint_error * 1000:.4f} mm; frames {frames[0]} and {frames[1]} differ by {moved:.3f} m beyond a "
          "rigid motion")
    assert vertex_error < 1e-3 and smplx_error < 1e-3 and joint_error < 1e-4
