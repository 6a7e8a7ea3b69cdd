"""Control (lsgan.control, lsgan.constraints): constraints met by optimising the generator's noise and then the
latent, through the real tiny pipeline's generator and decoder; the root closed onto a path exactly; the files
constraints come from; what a manifest records."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lsgan.constraints import (Constraints, check_reach, close_root, measure, path_points, read_keyframe,
                               read_path)
from lsgan.control import ControlSettings, control
from lsgan.data.features import recover_from_ric, recover_root
from lsgan.generate import Request, _conditions, draw_noise, generate_loaded, load_models

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def loaded(serve_models: Path):
    return load_models(serve_models / "gan", serve_models / "vae", device="cpu")


def _stats(loaded):
    extra = loaded.meta["extra"]
    return dict(latent_mean=torch.tensor(extra["latent_mean"]), latent_std=torch.tensor(extra["latent_std"]),
                feat_mean=torch.from_numpy(loaded.vae_meta["mean"]), feat_std=torch.from_numpy(loaded.vae_meta["std"]))


def _run(loaded, constraints: list[Constraints], seed: int = 0, **kw):
    stats = _stats(loaded)
    cond = _conditions(loaded.model, loaded.meta["extra"], "gan", [Request(text="a person walks", frames=40)] *
                       len(constraints), loaded.device, loaded.encoder, {})
    noise, _ = draw_noise(seed, len(constraints), loaded.model.config.noise_dim)
    z, report = control(lambda n: loaded.model.generator(n, cond), loaded.decoder, noise, constraints,
                        settings=ControlSettings(**kw), frozen=(loaded.model,), **stats)
    lengths = torch.tensor([c.frames for c in constraints])
    mask = torch.arange(int(lengths.max()))[None] < lengths[:, None]
    with torch.no_grad():
        x = loaded.decoder.decode(z, mask) * stats["feat_std"] + stats["feat_mean"]
    return z, report, recover_from_ric(x).numpy()


def test_a_reachable_keyframe_is_approached_and_the_report_measures_what_was_decoded(loaded):
    """A wrist of another seed's motion (so a latent meets it exactly): the optimised motion is much closer than
    the seed's own, the weights are untouched, and the reported error is the decoded joints'."""
    _, _, other = _run(loaded, [Constraints(40)], seed=7, noise_steps=0, latent_steps=0)
    pose = np.full((22, 3), np.nan, np.float32)
    pose[21] = other[0, 30, 21]
    weights = [p.clone() for p in loaded.model.parameters()] + [p.clone() for p in loaded.decoder.parameters()]
    _, report, joints = _run(loaded, [Constraints(40, keyframes={30: pose})], noise_steps=20, latent_steps=60, lr=0.1)
    assert report["mean_error_m"][0] < 0.5 * report["mean_error_m_before"][0], report
    assert np.isclose(report["mean_error_m"][0], np.linalg.norm(joints[0, 30, 21] - pose[21]), atol=1e-4)
    after = list(loaded.model.parameters()) + list(loaded.decoder.parameters())
    assert all(torch.equal(a, b) for a, b in zip(weights, after))
    assert all(p.requires_grad for p in after)  # given back as they were


def test_the_same_seed_and_constraints_give_the_same_latent_and_free_rows_stay_free(loaded):
    path = path_points(np.array([[0.5, 0.0, 0.0], [1.5, 0.0, 1.0]]), 40)  # frames before 0.5 s and after 1.5 s free
    assert np.isnan(path[:10]).all() and np.isnan(path[31:]).all() and not np.isnan(path[10:31]).any()
    c = [Constraints(40, path=path), Constraints(40)]
    z1, r1, _ = _run(loaded, c, noise_steps=5, latent_steps=5)
    z2, r2, _ = _run(loaded, c, noise_steps=5, latent_steps=5)
    assert torch.equal(z1, z2) and r1 == r2
    assert r1["mean_error_m"][1] == 0.0  # no constraint: nothing to miss


# ---- closing the root onto a path -----------------------------------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(feats=arrays(np.float32, (30, 263), elements=st.floats(-0.25, 0.25, width=32)),
       points=arrays(np.float32, (30, 2), elements=st.floats(-4, 4, width=32)),
       free=arrays(bool, 30), scale=st.sampled_from([0.0, 1.0, 20.0]))
def test_a_closed_path_is_met_exactly_and_nothing_but_the_root_velocity_changes(feats, points, free, scale):
    """Any decoded features, any set of path points (frame 0 at the origin or free): the root passes through every
    set point, heading, height, pose and contacts are untouched, and from 10 frames after the last set point the
    velocity is the decoded one (the root carries on as it was going, after a fade)."""
    feats[:, 0] *= scale / 20  # turning from none to fast
    path = points.copy()
    path[free] = np.nan
    path[0] = np.nan if free[0] else 0.0
    out = close_root(feats, path)
    _, root = recover_root(out.astype(np.float64))
    on = ~np.isnan(path).any(-1)
    assert np.abs(root[on][:, [0, 2]] - path[on]).max(initial=0) < 1e-4
    assert np.array_equal(out[:, [0, *range(3, 263)]], feats[:, [0, *range(3, 263)]])
    last = np.nonzero(on)[0].max(initial=0)
    np.testing.assert_allclose(out[last + 10:-1, 1:3], feats[last + 10:-1, 1:3], atol=1e-5)


def test_nothing_to_close_leaves_the_features_as_they_are():
    feats = np.random.default_rng(0).normal(size=(20, 263)).astype(np.float32)
    assert np.array_equal(close_root(feats, None), feats)
    assert np.array_equal(close_root(feats, np.full((20, 2), np.nan)), feats)


@settings(max_examples=40, deadline=None)
@given(shift=st.tuples(st.floats(-50, 50), st.floats(-50, 50)), k=st.integers(2, 6), per_frame=st.booleans(),
       as_json=st.booleans())
def test_a_path_file_is_read_as_written_and_moved_to_the_motions_start(tmp_path_factory, shift, k, per_frame,
                                                                      as_json):
    rng = np.random.default_rng(k)
    if per_frame:
        rows = np.cumsum(rng.uniform(-0.05, 0.05, (k * 5, 2)), 0) + shift
    else:
        rows = np.column_stack([np.arange(k) * 0.35, np.cumsum(rng.uniform(-1, 1, (k, 2)), 0) + shift])
    d = tmp_path_factory.mktemp("p")
    f = d / ("p.json" if as_json else "p.csv")
    if as_json:
        f.write_text(json.dumps({"points": rows.tolist()}))
    else:
        f.write_text("# drawn by hand\n" + ("x,z\n" if per_frame else "t,x,z\n") +
                     "\n".join(",".join(repr(float(v)) for v in r) for r in rows))
    path = read_path(f, 40)
    xz = rows[:, -2:] - rows[0, -2:]
    if per_frame:
        np.testing.assert_allclose(path[: len(rows)], xz, atol=1e-5)
        assert np.isnan(path[len(rows):]).all()
    else:
        frames = np.round(rows[:, 0] * 20).astype(int)
        np.testing.assert_allclose(path[frames[frames < 40]], xz[frames < 40], atol=1e-5)
        assert np.isnan(path[frames[-1] + 1:]).all()
    assert np.array_equal(path[0], [0, 0])


def test_a_keyframe_file_sets_the_joints_it_names(tmp_path):
    (tmp_path / "hand.json").write_text('{"right_wrist": [0.3, 1.2, 0.4], "0": [0, 0.9, 0]}')
    f, pose = read_keyframe(f"12:{tmp_path / 'hand.json'}", 40)
    assert f == 12 and np.allclose(pose[21], [0.3, 1.2, 0.4]) and np.allclose(pose[0], [0, 0.9, 0])
    assert np.isnan(np.delete(pose, [0, 21], axis=0)).all()
    np.save(tmp_path / "p.npy", np.ones((22, 3), np.float32))
    assert np.array_equal(read_keyframe(f"0:{tmp_path / 'p.npy'}", 40)[1], np.ones((22, 3)))


@pytest.mark.parametrize("make, phrase", [
    (lambda: Constraints(40, path=np.zeros((39, 2))), "is (40, 2) ground points"),
    (lambda: Constraints(40, path=np.full((40, 2), np.inf)), "infinite"),
    (lambda: __import__("lsgan.constraints").constraints.Placement(float("nan"), 0, 0), "a finite turn"),
    (lambda: Constraints(40, path=np.ones((40, 2))), "a path's point on frame 0 is the motion's start"),
    (lambda: Constraints(40, keyframes={40: np.zeros((22, 3))}), "keyframe 40 is not a frame of the motion: its 40 "
     "frames are 0..39"),
    (lambda: Constraints(40, keyframes={3: np.vstack([[0, -0.3, 0]] + [[np.nan] * 3] * 21)}),
     "keyframe 3: pelvis at y = -0.30 m is below the ground"),
    (lambda: Constraints(40, keyframes={3: np.zeros((24, 3))}), "a pose is 22 joints"),
    (lambda: path_points(np.array([[1.0, 0, 0], [0.5, 1, 1]]), 40), "waypoint times must increase"),
    (lambda: path_points(np.array([[0.0, np.nan, 0]]), 40), "finite (time, x, z)"),
    (lambda: check_reach(Constraints(40, path=path_points(np.array([[0, 0, 0], [1, 9, 0]]), 40)), 5.0),
     "the root would move at 9.0 m/s from the path at"),
    (lambda: check_reach(Constraints(40, path=np.vstack([[np.nan, np.nan], [3.0, 0]] + [[np.nan] * 2] * 38)), 5.0),
     "the root would move at 60.0 m/s from the start (the origin) at 0.00 s to the path at 0.05 s"),
    (lambda: Constraints(40, keyframes={0: np.vstack([[1.0, 0.9, 1.0]] + [[np.nan] * 3] * 21)}),
     "keyframe 0's root on frame 0 is the motion's start"),
    (lambda: Constraints(40, keyframes={3: np.full((22, 3), np.nan)}), "keyframe 3 sets no joint"),
    (lambda: Constraints(40, keyframes={2.5: np.zeros((22, 3))}), "a keyframe's frame is a whole number, not 2.5"),
    (lambda: Constraints(0), "at least 2 frames"),
    (lambda: Constraints(40, keyframes={3: np.full((22, 3), 2e4)}), "beyond 10000 m"),
    (lambda: check_reach(Constraints(40, keyframes={5: np.eye(22, 3, dtype=np.float32) * 3}), 50.0,
                         np.full(22, 0.1)), "keyframe 5: its bones are"),
])
def test_bad_constraints_are_refused_with_what_is_wrong(make, phrase):
    with pytest.raises(ValueError, match=phrase.replace("(", r"\(").replace(")", r"\)")):
        make()


# ---- through generate ----------------------------------------------------------------------------------------

def test_generate_meets_a_path_exactly_says_how_far_the_keyframes_are_and_is_deterministic(loaded):
    """The motion of record (rigid joints) runs through every set path point within a millimetre, the manifest's
    figures are those of the motion written, and the same seed gives the same motion."""
    path = path_points(np.array([[0, 0, 0], [1.0, 0.4, 0.8], [1.95, 0.0, 1.6]]), 40)
    pose = np.full((22, 3), np.nan, np.float32)
    pose[20] = [0.2, 1.3, 0.9]
    c = Constraints(40, path=path, keyframes={25: pose})
    req = [Request(text="a person walks", frames=40)]
    g1 = generate_loaded(loaded, req, num=2, seed=3, constraints=c, control_settings=ControlSettings(5, 5))
    g2 = generate_loaded(loaded, req, num=2, seed=3, constraints=c, control_settings=ControlSettings(5, 5))
    for m1, m2 in zip(g1.motions, g2.motions):
        assert np.array_equal(m1.joints, m2.joints) and m1.control == m2.control
        assert np.abs(m1.joints[:, 0][:, [0, 2]] - path).max() < 1e-3
        assert m1.control == measure(m1.joints, c)
        assert np.isclose(m1.control["keyframes_m"]["max"], np.linalg.norm(m1.joints[25, 20] - pose[20]))
    assert g1.control["path"][0] == [0, 0.0, 0.0] and list(g1.control["keyframes"]) == ["25"]
    assert g1.control["keyframes"]["25"] == {"20": pytest.approx([0.2, 1.3, 0.9])}
    assert g1.timings_s["control"] > 0


def test_constraints_for_another_length_are_refused(loaded):
    with pytest.raises(ValueError, match="the constraints are for 30 frames, the motion has 40"):
        generate_loaded(loaded, [Request(text="walk", frames=40)], constraints=Constraints(30))


# ---- continuing and in-betweening -------------------------------------------------------------------------------

@settings(max_examples=50, deadline=None)
@given(yaw=st.floats(-np.pi, np.pi), x=st.floats(-20, 20), z=st.floats(-20, 20),
       pose=arrays(np.float32, (22, 3), elements=st.floats(-1, 1, width=32)))
def test_a_placement_is_undone_exactly_and_a_frame_puts_its_pose_at_the_origin_facing_z(yaw, x, z, pose):
    from lsgan.constraints import Placement, facing_yaw, frame_at

    p = Placement(yaw, x, z)
    np.testing.assert_allclose(p.undo(p.apply(pose)), pose, atol=1e-4)
    across = (pose[2] - pose[1]) + (pose[17] - pose[16])
    if np.hypot(across[0], across[2]) > 1e-2:  # a pose with a facing: turned by the placement's yaw
        assert np.isclose(np.angle(np.exp(1j * (facing_yaw(p.apply(pose)) - facing_yaw(pose) - yaw))), 0, atol=1e-3)
    local = frame_at(pose[None], 0).undo(pose)
    assert np.allclose(local[0, [0, 2]], 0, atol=1e-4) and np.isclose(local[0, 1], pose[0, 1], atol=1e-5)


def test_a_continuation_starts_where_the_motion_it_continues_ends(loaded, tmp_path):
    """generate, then generate --continue from it: the new motion's first frames stand where the old one's last
    frames are (its root exactly), and the manifest's figure is the gap measured in that shared frame."""
    from cli_runs import lsgan

    run = lsgan("generate", "--gan", loaded.gan, "--vae", loaded.vae, "--text", "a person walks", "--frames", 40,
                "--seed", 1, "-o", tmp_path / "a", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    first = next((tmp_path / "a").glob("*_joints.npy"))
    run = lsgan("generate", "--gan", loaded.gan, "--vae", loaded.vae, "--text", "a person sits", "--frames", 40,
                "--continue", first, "-o", tmp_path / "b", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert "keyframe joints: missed by" in run.stderr
    a, b = np.load(first), np.load(next((tmp_path / "b").glob("*_joints.npy")))
    manifest = json.loads((tmp_path / "b" / "manifest.json").read_text())
    gap = np.linalg.norm(a[-5:] - b[:5], axis=-1)  # (5, 22)
    assert np.abs(a[-5:, 0][:, [0, 2]] - b[:5, 0][:, [0, 2]]).max() < 1e-3
    assert np.isclose(manifest["motions"][0]["control"]["keyframes_m"]["mean"], gap.mean(), atol=1e-4)
    assert manifest["control"]["placement"]["x_m"] == pytest.approx(float(a[-5, 0, 0]), abs=1e-5)


def test_an_inbetween_is_pinned_at_both_ends(loaded):
    from lsgan.constraints import inbetween

    a = generate_loaded(loaded, [Request(text="walk", frames=30)], seed=1).motions[0].joints
    b = generate_loaded(loaded, [Request(text="jump", frames=30)], seed=2).motions[0].joints + [1.0, 0, 0.5]
    c, place = inbetween(a, b, 40)
    g = generate_loaded(loaded, [Request(text="turn", frames=40)], seed=3, constraints=c, placement=place,
                        control_settings=ControlSettings(10, 0))
    j = g.motions[0].joints
    assert np.abs(j[:5, 0][:, [0, 2]] - a[-5:, 0][:, [0, 2]]).max() < 1e-3
    assert np.abs(j[-5:, 0][:, [0, 2]] - b[:5, 0][:, [0, 2]]).max() < 1e-3


def test_a_pose_facing_nowhere_sets_no_facing_and_the_callers_keyframes_are_not_changed():
    """A pose whose hips and shoulders are on one vertical line has no facing (not the pi that atan2(0, -0.0)
    gives), so closing the root does not turn the body for it; Constraints copies the caller's poses."""
    from lsgan.constraints import facing_yaw, has_facing

    pose = np.zeros((22, 3), np.float32)
    pose[:, 1] = np.linspace(0, 1.7, 22)
    assert not has_facing(pose) and facing_yaw(pose) == 0.0
    given = {7: pose.astype(np.float64)}
    c = Constraints(40, keyframes=given)
    assert c.root_yaws() is None and given[7].dtype == np.float64


def test_after_a_run_of_set_frames_the_root_fades_into_its_own_velocity_without_a_jump():
    """A path set on frames 0..9 at 1 m/s while the decoded root stands still: the closed root's step after frame 9
    starts at the path's step and shrinks smoothly (no frame-to-frame change above the path's step / 3)."""
    feats = np.zeros((40, 263), np.float32)
    path = np.full((40, 2), np.nan, np.float32)
    path[:10] = np.stack([np.zeros(10), np.arange(10) * 0.05], -1)
    _, root = recover_root(close_root(feats, path, fade=10).astype(np.float64))
    step = np.diff(root[:, 2])
    assert np.allclose(step[:9], 0.05, atol=1e-6) and np.allclose(step[20:], 0.0, atol=1e-6)
    assert np.abs(np.diff(step[8:21])).max() < 0.05 / 3


def test_the_seam_velocity_is_the_change_of_step_where_whole_keyframes_end():
    from lsgan.constraints import measure

    pose = np.zeros((22, 3), np.float32)
    pose[:, 1] = np.linspace(0, 1.7, 22)
    walk = np.stack([pose + [0, 0, 0.05 * t] for t in range(12)])  # 1 m/s forward
    c = Constraints(12, keyframes={t: walk[t] for t in range(5)})
    assert measure(walk, c)["seam_velocity_m_s"]["max"] < 1e-5  # carries on at the same velocity
    stop = walk.copy()
    stop[5:] = stop[4]  # stands still from frame 5: its step changes by 1 m/s
    assert np.isclose(measure(stop, c)["seam_velocity_m_s"]["max"], 1.0, atol=1e-4)


def test_between_two_runs_of_set_frames_the_root_velocity_has_no_jump():
    """An in-between's shape: the root set on frames 0-4 and 30-34, walking at 1 m/s (the second run 1.5 m to the
    side), over a decoded root that stands: every set point is met, and the step changes smoothly everywhere."""
    feats = np.zeros((40, 263), np.float32)
    path = np.full((40, 2), np.nan, np.float32)
    path[:5] = np.stack([np.zeros(5), np.arange(5) * 0.05], -1)
    path[30:35] = np.stack([np.full(5, 1.5), 1.5 + np.arange(5) * 0.05], -1)
    _, root = recover_root(close_root(feats, path, fade=10).astype(np.float64))
    on = ~np.isnan(path).any(-1)
    assert np.abs(root[on][:, [0, 2]] - path[on]).max() < 1e-5
    step = np.diff(root[:, [0, 2]], axis=0)  # (39, 2)
    assert np.linalg.norm(np.diff(step[:34], axis=0), axis=-1).max() < 0.03  # no frame-to-frame jump


def test_an_action_model_takes_the_same_constraints(serve_models: Path):
    """An action-conditioned GAN (the tiny pipeline's act-gan): a path is met exactly and a keyframe's miss shrinks
    (with latent steps: this tiny GAN's motions hardly depend on its noise), through the same generate call as
    text."""
    act = load_models(serve_models / "act-gan", serve_models / "vae", device="cpu")
    action = act.meta["extra"]["action_names"][0]
    req = [Request(action=action, frames=40)]
    free = generate_loaded(act, req, seed=2).motions[0].joints
    wrist = np.full((22, 3), np.nan, np.float32)
    wrist[21] = free[20, 21] + [0.2, 0.1, 0.0]
    g = generate_loaded(act, req, seed=2, constraints=Constraints(40, keyframes={20: wrist}),
                        control_settings=ControlSettings(10, 40, lr=0.1))  # the latent too: its noise does little
    assert g.motions[0].control["keyframes_m"]["max"] < 0.8 * np.linalg.norm(free[20, 21] - wrist[21])
    path = Constraints(40, path=path_points(np.array([[0, 0, 0], [1.9, -0.4, 0.9]]), 40))
    g = generate_loaded(act, req, seed=2, constraints=path, control_settings=ControlSettings(5))
    assert g.motions[0].control["path_m"]["max"] < 1e-3 and g.motions[0].request.action == action


def _chain_pose(seed: int) -> np.ndarray:
    """A plausible standing pose: the demo skeleton's rest offsets, bent a little at random."""
    from lsgan.data.skeleton import PARENTS

    rest = np.array([[0, 0.9, 0], [0.1, 0.9, 0], [-0.1, 0.9, 0], [0, 1.0, 0], [0.1, 0.5, 0.02], [-0.1, 0.5, 0.02],
                     [0, 1.15, 0], [0.1, 0.08, 0], [-0.1, 0.08, 0], [0, 1.22, 0], [0.12, 0.02, 0.1],
                     [-0.12, 0.02, 0.1], [0, 1.44, 0], [0.07, 1.34, 0], [-0.07, 1.34, 0], [0, 1.53, 0.05],
                     [0.2, 1.33, 0], [-0.2, 1.33, 0], [0.22, 1.07, 0], [-0.22, 1.07, 0], [0.24, 0.82, 0.05],
                     [-0.24, 0.82, 0.05]])
    rng = np.random.default_rng(seed)
    pose = rest.copy()
    for j in range(1, 22):  # each bone turned a little, its length kept, children carried
        bone = rest[j] - rest[PARENTS[j]]
        pose[j] = pose[PARENTS[j]] + np.linalg.norm(bone) * (lambda v: v / np.linalg.norm(v))(
            bone + rng.normal(0, 0.05, 3))
    return pose


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**16), joint=st.sampled_from([20, 21, 15, 10, 11, 12, 18]),
       offset=arrays(np.float64, 3, elements=st.floats(-0.25, 0.25)), also_root=st.booleans())
def test_ik_meets_reachable_joints_keeps_every_bone_and_moves_nothing_else(seed, joint, offset, also_root):
    """A joint moved up to 25 cm within its chain's reach (and the root, sometimes): reached within a tenth of a
    millimetre, every bone length kept, and every joint that does not hang from the solved chain where it was (the
    chains start below the branching joints, whose layout the rigid fit keeps), but for the legs of a body moved
    down, which keep the feet on their ground."""
    from hypothesis import assume

    from lsgan.data.skeleton import PARENTS, bone_lengths
    from lsgan.motion.ik import CHAINS, reach_pose

    pose = _chain_pose(seed)
    chain = list(next(c for c in CHAINS if joint in c[1:]))
    segment = chain[: chain.index(joint) + 1]
    links = np.linalg.norm(np.diff(pose[segment], axis=0), axis=-1)
    inner = max(0.0, 2 * links.max() - links.sum())  # nearer than this the longest link cannot fold back
    assume(inner + 0.02 < np.linalg.norm(pose[joint] + offset - pose[segment[0]]) < 0.98 * links.sum())
    target = np.full((22, 3), np.nan)
    target[joint] = pose[joint] + offset
    shift = np.array([0.1, -0.05, 0.2]) if also_root else np.zeros(3)
    if also_root:
        target[0] = pose[0] + shift
        target[joint] += shift
    out = reach_pose(pose, target)
    assert np.linalg.norm(out[joint] - target[joint]) < 1e-4
    assert np.abs(bone_lengths(out) - bone_lengths(pose)).max() < 1e-6
    moved = set(segment[1:]) | ({4, 5, 7, 8, 10, 11} if also_root else set())  # a sunk body's legs are re-solved
    for j in range(1, 22):
        if PARENTS[j] in moved:
            moved.add(j)
    still = [j for j in range(22) if j not in moved]
    assert np.allclose(out[still], pose[still] + shift, atol=1e-9)
    feet = [f for f in (10, 11) if f not in segment]
    if also_root:  # the feet go along sideways and stay on their ground
        assert np.allclose(out[feet], pose[feet] + shift * [1, 0, 1], atol=1e-4)


def test_ik_stretches_towards_an_unreachable_joint_and_keeps_free_coordinates():
    from lsgan.motion.ik import reach_pose

    pose = _chain_pose(1)
    target = np.full((22, 3), np.nan)
    target[20] = [3.0, 1.3, 0.0]  # far beyond the arm
    out = reach_pose(pose, target)
    arm = out[[13, 16, 18, 20]]
    direction = (target[20] - out[13]) / np.linalg.norm(target[20] - out[13])
    assert np.allclose(np.cross(arm[1:] - out[13], direction), 0, atol=1e-9)  # a straight arm pointing at it
    target = np.full((22, 3), np.nan)
    target[15, 1] = pose[15, 1] - 0.1  # only the head's height
    out = reach_pose(pose, target)
    assert abs(out[15, 1] - target[15, 1]) < 1e-4
    target[15, 1] = pose[15, 1] + 0.15  # higher than the spine reaches: the body rises as far as the legs let it
    out = reach_pose(pose, target)
    assert out[0, 1] >= pose[0, 1] - 1e-9 and out[15, 1] > pose[15, 1] + 0.1  # straight legs: no rise left
    assert np.abs(out[[10, 11]] - pose[[10, 11]]).max() < 1e-4
    target = np.full((22, 3), np.nan)
    target[0, 1] = 0.3  # a deep crouch: the ankles and feet stay, the knees bend up, not through the floor
    out = reach_pose(pose, target)
    assert abs(out[0, 1] - 0.3) < 1e-9 and np.abs(out[[7, 8, 10, 11]] - pose[[7, 8, 10, 11]]).max() < 1e-4
    assert out[[4, 5], 1].min() >= 0.05 - 1e-9


def test_a_keyframe_of_some_joints_is_met_through_ik_in_the_motion_of_record(loaded):
    """A wrist and the other foot at points the motion does not go near: met within 3 cm by the rigid joints every
    output shows (the warp reaches them exactly; making the motion rigid moves them by millimetres)."""
    free = generate_loaded(loaded, [Request(text="a person walks", frames=40)], seed=4).motions[0].joints
    pose = np.full((22, 3), np.nan, np.float32)
    pose[21] = free[20, 21] + [0.15, 0.2, -0.1]
    pose[10, [0, 2]] = free[20, 10, [0, 2]] + [0.1, 0.1]
    c = Constraints(40, keyframes={20: pose})
    g = generate_loaded(loaded, [Request(text="a person walks", frames=40)], seed=4, constraints=c,
                        control_settings=ControlSettings(noise_steps=0))
    assert g.motions[0].control["keyframes_m"]["max"] < 0.03, g.motions[0].control


def test_facing_turns_the_root_along_the_path_where_it_moves(loaded):
    """An L-shaped path with ``facing``: the motion of record faces the way the path goes within a few degrees
    wherever it moves (from frame 10: every motion starts facing +z), the manifest says by how much, and a path
    that stands still sets no facing."""
    from lsgan.constraints import facing_yaw, path_yaws

    path = path_points(np.array([[0, 0, 0], [0.9, 0.0, 1.0], [1.95, -1.0, 1.0]]), 40)
    c = Constraints(40, path=path, facing=True)
    g = generate_loaded(loaded, [Request(text="a person walks", frames=40)], seed=2, constraints=c,
                        control_settings=ControlSettings(noise_steps=0))
    m = g.motions[0]
    want = path_yaws(path)
    assert np.isnan(want[:10]).all()  # the start faces +z; the root turns into the path's facing by frame 10
    assert np.isclose(want[12], 0.0, atol=1e-6) and np.isclose(want[-5], -np.pi / 2, atol=1e-6)
    miss = np.degrees(np.abs(np.angle(np.exp(1j * (facing_yaw(m.joints) - want)))))
    assert np.nanmax(miss) < 5 and m.control["facing_deg"]["max"] == pytest.approx(np.nanmax(miss))
    assert np.abs(m.joints[:, 0][:, [0, 2]] - path).max() < 1e-3 and g.control["facing"] is True
    assert np.isnan(path_yaws(np.zeros((10, 2)))).all()
    with pytest.raises(ValueError, match="facing along the path needs a path"):
        Constraints(10, facing=True)


def test_a_keyframe_file_may_leave_coordinates_free_with_null(tmp_path):
    """{"head": [null, 1.6, null]} sets the head's height only; the file's other rules still hold."""
    f = tmp_path / "k.json"
    f.write_text('{"head": [null, 1.6, null], "left_foot": [0.1, 0.0, null]}')
    frame, pose = read_keyframe(f"7:{f}", 40)
    assert frame == 7 and np.isnan(pose[15, [0, 2]]).all() and pose[15, 1] == pytest.approx(1.6)
    assert pose[10, 0] == pytest.approx(0.1) and np.isnan(pose[10, 2]) and np.isnan(pose[0]).all()


SHARED_CMU = Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu" / "131_01.bvh"


@pytest.mark.skipif(not SHARED_CMU.is_file(), reason="../shared/data/cmu (a CMU BVH clip) is not beside the project")
def test_a_bvh_frame_is_a_pose_taken_wherever_the_motion_is(loaded):
    """--keyframe 30:clip.bvh@100 through the CMU joint map: a pose of another rig, retargeted onto the motion's
    skeleton (its bone directions; the hips', spine's, neck's and collars' layout is the motion's own), taken where
    the motion stands and faces on frame 30: every other bone points as the clip's does within a few degrees, and
    the manifest's figure is the motion of record's."""
    from lsgan.constraints import facing_frame, read_bvh_pose
    from lsgan.data.skeleton import PARENTS

    frame, pose = read_bvh_pose(f"30:{SHARED_CMU}@100", 40)
    assert frame == 30 and pose.shape == (22, 3) and np.abs(pose[0, [0, 2]]).max() < 1e-6
    assert read_bvh_pose(f"30:{SHARED_CMU}@100", 40, "cmu")[1] == pytest.approx(pose)
    c = Constraints(40, poses={30: pose})
    g = generate_loaded(loaded, [Request(text="a person walks", frames=40)], seed=1, constraints=c,
                        control_settings=ControlSettings(noise_steps=0))
    m = g.motions[0]
    got, want = facing_frame(m.joints[30].astype(np.float64)), pose.astype(np.float64)
    bones = [(got[j] - got[p], want[j] - want[p]) for j, p in enumerate(PARENTS) if p not in (-1, 0, 9)]
    cosines = [a @ b / np.linalg.norm(a) / np.linalg.norm(b) for a, b in bones]
    assert min(cosines) > np.cos(np.radians(5)), np.degrees(np.arccos(np.clip(cosines, -1, 1))).max()
    assert m.control["poses_m"]["max"] < 0.02 and np.allclose(g.control["poses"]["30"], pose)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), units=st.sampled_from([0.01, 1.0, 100.0]))
def test_a_pose_is_retargeted_whatever_its_units(seed, units):
    """A pose in centimetres, metres or hundreds of metres lands on the motion's skeleton at the same place: bone
    directions from the pose, lengths and the feet's height in proportion to the motion's legs."""
    from lsgan.constraints import on_skeleton
    from lsgan.data.skeleton import bone_lengths

    pose, motion = _chain_pose(seed), np.stack([_chain_pose(seed + 1)] * 3)
    pose[:, 1] += 0.05  # standing 5 cm above its floor
    got = on_skeleton(pose * units, motion)
    assert np.allclose(got, on_skeleton(pose, motion), atol=1e-9)
    assert np.allclose(bone_lengths(got), bone_lengths(motion[0]), atol=1e-9)
