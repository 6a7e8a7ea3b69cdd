"""SMPL-family body export: model files, fitting, the fitted .npz read back through smplx, and the skinned GLB.

The body models are small generated files with smplx's keys (tests/body_models.py); smplx itself is the
oracle for joints and vertices.
"""
from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
import smplx
import torch
from body_models import make_model, write_models
from gltf_reader import (
    frame_count,
    node_index,
    parse,
    skinned_vertices,
    validate,
    world_matrices,
)
from scipy.spatial.transform import Rotation

from lsgan.data.body_model import BodyModelError, find_body_model, read_body_model
from lsgan.data.skeleton import JOINT_NAMES
from lsgan.data.synthetic import generate
from lsgan.export.body import body_joints, fit_body, write_fit_npz
from lsgan.export.glb import body_gltf_document, pack_glb, write_body_glb

TYPES = ("smpl", "smplh", "smplx")


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> Path:
    return write_models(tmp_path_factory.mktemp("body_models"))


def smplx_output(folder: Path, model_type: str, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray):
    """smplx's own forward pass, called the documented way, for full-layout poses (N,3J)."""
    n = len(poses)
    ext = "pkl" if model_type == "smpl" else "npz"
    kwargs = dict(model_type=model_type, gender="neutral", ext=ext, num_betas=10, batch_size=n)
    if model_type != "smpl":
        kwargs.update(use_pca=False, flat_hand_mean=True)
    if model_type == "smplx":
        kwargs.update(num_expression_coeffs=10)
    else:
        kwargs.update(vertex_ids={"nose": 0, "reye": 1, "leye": 2, "rear": 3, "lear": 4}, use_feet_keypoints=False,
                      use_hands=False)
    model = smplx.create(str(folder), **kwargs)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    p = t(poses)
    args = dict(global_orient=p[:, :3], body_pose=p[:, 3:66], betas=t(np.repeat(betas[None, :10], n, 0)),
                transl=t(trans))
    if model_type == "smpl":
        args["body_pose"] = p[:, 3:72]
    elif model_type == "smplh":
        args.update(left_hand_pose=p[:, 66:111], right_hand_pose=p[:, 111:156])
    else:
        args.update(jaw_pose=p[:, 66:69], leye_pose=p[:, 69:72], reye_pose=p[:, 72:75],
                    left_hand_pose=p[:, 75:120], right_hand_pose=p[:, 120:165])
    with torch.no_grad():
        out = model(**args)
    return out.joints.numpy(), out.vertices.numpy()


def model_motion(model_type: str, frames: int = 40, seed: int = 1):
    """A smooth random body motion of the model itself: (poses (T,3J), trans (T,3), betas (10,))."""
    rng = np.random.default_rng(seed)
    n_joints = {"smpl": 24, "smplh": 52, "smplx": 55}[model_type]
    t = np.linspace(0, 1, frames)[:, None]
    amp, phase = rng.normal(0, 0.35, (1, 22 * 3)), rng.uniform(0, 2 * np.pi, (1, 22 * 3))
    poses = np.zeros((frames, n_joints * 3))
    poses[:, :66] = amp * np.sin(2 * np.pi * t + phase)
    trans = np.concatenate([0.3 * t, 0.05 * np.sin(6 * t), 0.8 * t], axis=1)
    betas = np.zeros(10)
    betas[0] = -0.8
    return poses, trans, betas


def test_model_files_are_found_and_read(models):
    for model_type, joints in (("smpl", 24), ("smplh", 52), ("smplx", 55)):
        m = read_body_model(models, model_type=model_type)
        assert (m.model_type, m.num_joints, len(m.joint_names)) == (model_type, joints, joints)
        assert m.joint_names[:22] == tuple(JOINT_NAMES)
        assert np.allclose(m.weights.sum(axis=1), 1.0)
    assert find_body_model(models)[1] == "smpl"  # auto: the first type found
    single = models / "smplh" / "SMPLH_NEUTRAL.npz"
    assert read_body_model(single).model_type == "smplh"  # a file path; the type comes from the joint count


def test_amass_layout_is_read(tmp_path):
    (tmp_path / "male").mkdir()
    np.savez(tmp_path / "male" / "model.npz", **make_model("smplh"))
    model = read_body_model(tmp_path, gender="male")
    assert model.model_type == "smplh" and model.path.endswith("male/model.npz")


def test_missing_or_wrong_model_path_says_what_is_expected(tmp_path, models):
    with pytest.raises(BodyModelError) as err:
        read_body_model(tmp_path / "nowhere")
    assert "does not exist" in str(err.value) and "smpl/SMPL_NEUTRAL.pkl" in str(err.value)
    with pytest.raises(BodyModelError) as err:
        read_body_model(tmp_path, model_type="smplx", gender="female")
    assert "SMPLX_FEMALE.npz" in str(err.value) and "smpl/SMPL_NEUTRAL" not in str(err.value)
    with pytest.raises(BodyModelError, match="is smplh, not smplx"):
        read_body_model(models / "smplh" / "SMPLH_NEUTRAL.npz", model_type="smplx")
    broken = tmp_path / "SMPL_NEUTRAL.npz"
    np.savez(broken, v_template=np.zeros((3, 3)))
    with pytest.raises(BodyModelError, match="missing shapedirs"):
        read_body_model(tmp_path)


class _RunsCode:
    def __reduce__(self):
        return (print, ("this must never run",))


def test_pickled_code_in_a_model_file_is_refused(tmp_path, capsys):
    (tmp_path / "smpl").mkdir()
    with open(tmp_path / "smpl" / "SMPL_NEUTRAL.pkl", "wb") as fh:
        pickle.dump({"v_template": _RunsCode()}, fh)
    with pytest.raises(BodyModelError, match="SMPL_NEUTRAL.pkl: refused to unpickle .builtins.print."):
        read_body_model(tmp_path)
    assert "must never run" not in capsys.readouterr().out


@pytest.mark.parametrize("model_type", TYPES)
def test_fit_recovers_a_motion_of_the_model_and_smplx_reads_the_npz(models, tmp_path, model_type):
    poses, trans, betas = model_motion(model_type)
    target = smplx_output(models, model_type, poses, trans, betas)[0][:, :22]
    model = read_body_model(models, model_type=model_type)
    fit = fit_body(target, model, iterations=150)
    assert fit.mean_error_mm < 1.0 and fit.max_joint_error_mm < 3.0, (fit.mean_error_mm, fit.max_joint_error_mm)
    assert abs(fit.betas[0] - betas[0]) < 0.1  # the size beta is found
    path = write_fit_npz(tmp_path / "fit.npz", fit)
    with np.load(path, allow_pickle=False) as npz:
        assert npz["poses"].shape == (len(target), 3 * model.num_joints)
        assert str(npz["surface_model_type"]) == model_type and str(npz["up_axis"]) == "Y"
        joints = smplx_output(models, model_type, npz["poses"], npz["trans"], npz["betas"])[0][:, :22]
    assert np.abs(joints - fit.joints).max() < 1e-4
    assert np.abs(body_joints(fit, model)[:, :22] - fit.joints).max() < 1e-5


def test_fit_on_a_generated_motion_reports_its_error(models):
    joints = generate(1, seed=3)[0].joints
    model = read_body_model(models)
    fit = fit_body(joints, model)
    per_frame = np.linalg.norm(fit.joints - joints, axis=-1).mean(axis=1)
    assert np.allclose(fit.error_m, per_frame, atol=1e-6)
    assert fit.mean_error_mm < 10.0  # the synthetic skeleton's layout differs a little from the model's
    assert fit_body(joints, model).poses.tobytes() == fit.poses.tobytes()  # deterministic
    with pytest.raises(ValueError, match="NaN"):
        fit_body(np.full_like(joints, np.nan), model)


def test_twist_is_continuous_when_an_arm_crosses_the_body(models):
    """Swing-from-rest IK flips the twist when the arm passes the opposite of its rest direction."""
    model = read_body_model(models)
    joints = generate(1, seed=0)[0].joints[:1].repeat(41, axis=0)
    shoulder, elbow, wrist = 16, 18, 20
    upper = np.linalg.norm(joints[0, elbow] - joints[0, shoulder])
    fore = np.linalg.norm(joints[0, wrist] - joints[0, elbow])
    for t, a in enumerate(np.linspace(-0.5 * np.pi, 0.5 * np.pi, 41)):  # left arm sweeps down, across, up
        d = np.array([-np.cos(a) * 0.999, np.sin(a), 0.04])
        d /= np.linalg.norm(d)
        joints[t, elbow] = joints[t, shoulder] + upper * d
        joints[t, wrist] = joints[t, elbow] + fore * d
    fit = fit_body(joints, model)
    rot = Rotation.from_rotvec(fit.poses.reshape(len(joints), -1, 3)[:, shoulder])
    step = (rot[:-1].inv() * rot[1:]).magnitude()
    assert step.max() < 0.2, step.max()  # the sweep is pi/40 per frame; plain swing-from-rest IK jumps 2.4 rad


@pytest.mark.parametrize("model_type", TYPES)
def test_body_glb_skins_like_smplx_and_validates(models, tmp_path, model_type):
    poses, trans, betas = model_motion(model_type, frames=12)
    _, smplx_vertices = smplx_output(models, model_type, poses, trans, betas)
    model = read_body_model(models, model_type=model_type)
    target = smplx_output(models, model_type, poses, trans, betas)[0][:, :22]
    fit = fit_body(target, model, iterations=150)
    path = write_body_glb(tmp_path / "body.glb", fit, model)
    doc, blob = parse(path.read_bytes())
    assert len(doc["meshes"]) == 1 and len(doc["skins"]) == 1 and frame_count(doc, blob) == 12
    assert len(doc["skins"][0]["joints"]) == model.num_joints
    names = node_index(doc)
    assert set(model.joint_names) <= set(names)
    _, fitted_vertices = smplx_output(models, model_type, fit.poses, fit.trans, fit.betas)
    for frame in (0, 5, 11):
        vertices = skinned_vertices(doc, blob, frame)
        assert np.abs(vertices - fitted_vertices[frame]).max() < 1e-4  # glTF skinning == smplx (no posedirs)
        world = world_matrices(doc, blob, frame)
        pelvis = world[names["pelvis"], :3, 3]
        assert np.abs(pelvis - target[frame, 0]).max() < 3e-3
    assert np.abs(fitted_vertices - smplx_vertices).mean() < 0.01  # same body up to twists about bones
    report = validate(path)
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"]


def test_body_glb_loads_in_trimesh(models, tmp_path):
    import trimesh

    model = read_body_model(models)
    fit = fit_body(generate(1, seed=0)[0].joints[:20], model, iterations=20)
    path = write_body_glb(tmp_path / "body.glb", fit, model)
    scene = trimesh.load(path, force="scene")
    assert len(scene.geometry) == 1
    mesh = next(iter(scene.geometry.values()))
    assert len(mesh.faces) == len(model.faces)
    assert set(model.joint_names) <= set(scene.graph.nodes)
    doc, _ = parse(pack_glb(*body_gltf_document(fit, model)))
    assert doc["extras"]["frames"] == 20 and abs(doc["extras"]["fit_mean_error_mm"] - fit.mean_error_mm) < 1e-9


def test_export_command_with_body_model(models, tmp_path):
    from click.testing import CliRunner

    from lsgan.cli import main

    folder = tmp_path / "gen"
    folder.mkdir()
    for k, clip in enumerate(generate(2, seed=5)):
        np.save(folder / f"{k:03d}_clip_joints.npy", clip.joints[:30])
    runner = CliRunner()
    result = runner.invoke(main, ["export", "--glb", str(folder), "--body-model", str(models), "--model-type", "smplh",
                                  "-o", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    for k in range(2):
        glb, params = tmp_path / "out" / f"{k:03d}_clip.glb", tmp_path / "out" / f"{k:03d}_clip.npz"
        doc, _ = parse(glb.read_bytes())
        assert doc["extras"]["body_model"] == "smplh" and len(doc["skins"][0]["joints"]) == 52
        with np.load(params, allow_pickle=False) as npz:
            assert npz["poses"].shape == (30, 156)
    assert result.output.count("body fit error mean") == 2

    wrong = runner.invoke(main, ["export", "--glb", str(folder), "--body-model", str(tmp_path / "missing"),
                                 "-o", str(tmp_path / "x")])
    assert wrong.exit_code != 0 and "SMPL_NEUTRAL" in wrong.output and "does not exist" in wrong.output
    assert not (tmp_path / "x").exists()
    misuse = runner.invoke(main, ["export", "--bvh", str(folder), "--body-model", str(models), "-o", str(tmp_path / "y")])
    assert misuse.exit_code == 2 and "--body-model goes with --glb" in misuse.output
