"""Clean feet (lsgan.motion.feet): plants and steps by leg IK on generated motions, and ``lsgan export --fix-feet``."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_runs import linked_pipeline, lsgan
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lsgan.data.features import joints_to_features, recover_from_ric
from lsgan.data.sources.bvh import BvhSource
from lsgan.data.synthetic import generate as synthetic_clips
from lsgan.data.synthetic.gait import _gait_pose
from lsgan.data.synthetic.rig import _assemble, _finish
from lsgan.motion.quality import foot_pops, foot_skating_ratio, toe_above
from lsgan.export.bvh import load_motion_joints
from lsgan.motion.feet import (
    CHANNEL_JOINTS,
    LEG_JOINTS,
    REACH,
    SIDES,
    TOE_LIFT,
    contacts_from_features,
    estimate_contacts,
    fix_feet,
    held_spans,
    stance_frames,
)

LEG_BONES = ((1, 4), (4, 7), (7, 10), (2, 5), (5, 8), (8, 11))
OTHER = [k for k in range(22) if k not in LEG_JOINTS]


def sliding_motions(n: int = 6, drift: float = 0.03) -> list[tuple[np.ndarray, np.ndarray]]:
    """Synthetic clips (planted feet) through the feature pipeline, then made to slide as a generator's do: the
    whole body drifts ``drift`` m/frame (3 cm: skating by GMD's 2.5 cm rule; the Bandai model glides at ~5) while
    the contact channels still say the feet are planted."""
    out = []
    for clip in synthetic_clips(n, seed=3):
        features = joints_to_features(clip.joints)
        joints = recover_from_ric(features.astype(np.float64)).astype(np.float32)
        shift = np.arange(len(joints), dtype=np.float32)[:, None] * np.float32([drift, 0.0, 0.0])
        out.append((joints + shift[:, None], features))
    return out


def floor_travel(joints: np.ndarray, contacts: np.ndarray) -> tuple[float, float]:
    """Horizontal toe travel (m) on frame pairs marked in contact (ankle or toe channel of the side) with the toe
    within 2 cm of its lowest height in both frames (a slide, not a step), and the share of those marked pairs in
    which the toe moves less than 5 mm (as benchmarks/feet.py measures)."""
    travel = still = pairs = 0.0
    for side, toe in enumerate((10, 11)):
        either = contacts[:, 2 * side] | contacts[:, 2 * side + 1]
        marked = either[:-1] & either[1:]
        step = np.linalg.norm(np.diff(joints[:, toe][:, [0, 2]].astype(np.float64), axis=0), axis=-1)
        low = joints[:, toe, 1] - joints[:, toe, 1].min() < 0.02
        travel += step[marked & low[:-1] & low[1:]].sum()
        still += (step[marked] < 0.005).sum()
        pairs += marked.sum()
    return travel, still / max(pairs, 1)


def check_fixed(joints: np.ndarray, fixed: np.ndarray, contacts: np.ndarray) -> int:
    """The module's promises on one motion; returns the number of held frames checked."""
    assert fixed.dtype == joints.dtype and np.isfinite(fixed).all()
    assert np.array_equal(fixed[:, OTHER], joints[:, OTHER])  # bit for bit
    for a, b in LEG_BONES:
        before = np.linalg.norm(joints[:, b] - joints[:, a], axis=-1)
        after = np.linalg.norm(fixed[:, b] - fixed[:, a], axis=-1)
        assert np.abs(after - before).max() < 1e-4
    for k in LEG_JOINTS:  # nothing is put below the floor (y = 0), or below where it already was
        assert (fixed[:, k, 1] >= np.minimum(joints[:, k, 1], 0.0) - 1e-6).all(), k
    for hip, knee, ankle, _ in SIDES:  # no leg is stretched past REACH, or past the original's own stretch
        legs = sum(np.linalg.norm(joints[:, b] - joints[:, a], axis=-1) for a, b in ((hip, knee), (knee, ankle)))
        limit = np.maximum(REACH * legs, np.linalg.norm(joints[:, ankle] - joints[:, hip], axis=-1))
        assert (np.linalg.norm(fixed[:, ankle] - fixed[:, hip], axis=-1) <= limit + 1e-5).all()
    assert np.array_equal(fix_feet(joints, contacts), fixed)  # deterministic
    if foot_skating_ratio(joints) == 0.0:  # clean by the field's rule: every stance is left, so nothing changes
        assert np.array_equal(fixed, joints)
    checked = 0
    spans = held_spans(joints, contacts)
    for k, joint in enumerate(CHANNEL_JOINTS):
        toe = CHANNEL_JOINTS[k | 1]
        foot_length = np.linalg.norm(joints[:, toe] - joints[:, joint], axis=-1)
        for first, last in spans[k]:
            step = np.linalg.norm(np.diff(fixed[first:last + 1, joint][:, [0, 2]], axis=0), axis=-1)
            # a held ankle whose toe is held too moves along the foot by the input's own foot-length change
            slack = np.abs(np.diff(foot_length[first:last + 1])) if joint != toe else 0.0
            assert (step < 0.002 + slack).all(), (joint, first, last, step.max())
            checked += last - first
    return checked


def test_locks_sliding_feet() -> None:
    held = 0
    for joints, features in sliding_motions():
        contacts = contacts_from_features(features)
        fixed = fix_feet(joints, contacts)
        held += check_fixed(joints, fixed, contacts)
        assert foot_skating_ratio(fixed) <= foot_skating_ratio(joints)
        assert not np.array_equal(fixed, joints)
    assert held > 100


def test_gliding_feet_plant_and_step() -> None:
    """A body gliding at 3 and 5 cm/frame: the feet slide much less and catch up by steps that lift the toe, not by
    sliding along the floor; where the original's own fastest foot move leaves room for steps (no foot may move
    faster than it plus 2 cm), they stay still on most contact frames."""
    before = after = 0.0
    for drift in (0.03, 0.05):
        for joints, features in sliding_motions(6, drift):
            contacts = contacts_from_features(features)
            fixed = fix_feet(joints, contacts)
            check_fixed(joints, fixed, contacts)
            (slid, still_before), (slid_after, still) = floor_travel(joints, contacts), floor_travel(fixed, contacts)
            assert slid_after < 0.5 * slid
            room = np.linalg.norm(np.diff(joints[:, list(CHANNEL_JOINTS)], axis=0), axis=-1).max() + 0.02
            assert still > still_before + 0.3 or room < 2 * drift, (drift, still, room)
            before, after = before + slid, after + slid_after
            spans = held_spans(joints, contacts)
            for toe, held in ((10, spans[1]), (11, spans[3])):  # each step between two plants lifts the toe
                for (_, a), (b, _) in zip(held[:-1], held[1:]):
                    length = np.linalg.norm(fixed[b, toe, [0, 2]] - fixed[a, toe, [0, 2]])
                    lift = fixed[a + 1: b, toe, 1].max() - max(fixed[a, toe, 1], fixed[b, toe, 1])
                    assert length < 0.1 or lift > 0.3 * TOE_LIFT * length, (toe, a, b, length, lift)
    assert after < 0.2 * before  # 0.15 before the speed limit: a standing body gliding has little room to step


def test_feet_take_turns() -> None:
    """A walking turn whose body glides 3 cm/frame, its feet marked in contact 70% of the time: each foot plants
    and steps, in turn (a walk, not a hop: both are off their plants on few frames)."""
    joints, features = sliding_motions(6, 0.03)[3]
    contacts = contacts_from_features(features)
    assert stance_frames(joints, contacts).mean() > 0.6
    spans = held_spans(joints, contacts)
    held = np.zeros((len(joints), 2), dtype=bool)
    for side, toe_spans in enumerate((spans[1], spans[3])):
        assert len(toe_spans) >= 4  # each foot steps
        for a, b in toe_spans:
            held[a: b + 1, side] = True
    assert (~held.any(axis=1)).mean() < 0.15


@pytest.mark.parametrize("clip", ["dataset-2_walk_normal_001", "dataset-2_walk-turn-left_normal_001"])
def test_real_bandai_walk(bandai_dir, clip: str) -> None:
    """A real walk (Bandai mocap through the importer and the features) already plants its feet: the fix stays
    close to it (legs within 2 cm on average, GMD's ratio about the same) and adds no slide (its stances that GMD's
    rule counts as clean, slow slides included, are left as they are)."""
    path = bandai_dir / "data" / f"{clip}.bvh.gz"
    features = joints_to_features(BvhSource(root=str(path), preset="bandai", mirror=False).load(str(path))[0].joints)
    joints = recover_from_ric(features.astype(np.float64)).astype(np.float32)
    contacts = contacts_from_features(features)
    fixed = fix_feet(joints, contacts)
    check_fixed(joints, fixed, contacts)
    assert np.linalg.norm(fixed[:, list(LEG_JOINTS)] - joints[:, list(LEG_JOINTS)], axis=-1).mean() < 0.02
    assert foot_skating_ratio(fixed) < foot_skating_ratio(joints) + 0.03
    assert floor_travel(fixed, contacts)[0] <= floor_travel(joints, contacts)[0] + 1e-6


def gait(seed: int, kind: str, direction: str, speed: str, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """A synthetic walk or run (a fast forward run is a sprint, 3.5-4.2 m/s) through the features, as a generated
    motion comes: recovered joints and the features."""
    clip = _finish(_assemble(_gait_pose(np.random.default_rng(seed), frames, kind, direction, speed)))
    features = joints_to_features(clip)
    return recover_from_ric(features.astype(np.float64)).astype(np.float32), features


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**16), kind=st.sampled_from(["walk", "run"]),
       direction=st.sampled_from(["forward", "backward", "left", "right"]),
       speed=st.sampled_from(["slow", "normal", "fast"]), frames=st.integers(40, 120),
       glide=st.floats(0.0, 0.12), heading=st.floats(0.0, 2 * np.pi), noise=st.floats(0.0, 0.01),
       marks=st.sampled_from(["features", "all", "random"]))
def test_no_foot_pops(seed, kind, direction, speed, frames, glide, heading, noise, marks) -> None:
    """Walks, runs and sprints made to glide (up to 12 cm/frame: 2.4 m/s on top of the gait), jitter and carry
    wrong contact marks: no ankle or toe of the fixed motion moves more in a frame than the original foot's
    fastest move plus 2 cm, and the module's other promises hold."""
    joints, features = gait(seed, kind, direction, speed, frames)
    rng = np.random.default_rng(seed)
    frames = len(joints)  # the features have one frame fewer than the clip
    shift = np.arange(frames)[:, None] * glide * np.array([np.cos(heading), 0.0, np.sin(heading)])
    joints = (joints + shift[:, None] + rng.normal(0.0, noise, joints.shape)).astype(np.float32)
    contacts = {"features": contacts_from_features(features), "all": np.ones((frames, 4), dtype=bool),
                "random": rng.random((frames, 4)) < 0.8}[marks]
    fixed = fix_feet(joints, contacts)
    assert foot_pops(joints, fixed) == 0
    check_fixed(joints, fixed, contacts)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), kind=st.sampled_from(["walk", "run"]),
       direction=st.sampled_from(["forward", "backward", "left", "right"]),
       speed=st.sampled_from(["slow", "normal", "fast"]), frames=st.integers(40, 120))
def test_clean_feet_stay_clean(seed, kind, direction, speed, frames) -> None:
    """A walk or run whose feet are planted already (synthetic: no slide) comes back nearly as it was: leg joints
    within 3 mm on average, GMD's ratio no higher, no pop."""
    joints, features = gait(seed, kind, direction, speed, frames)
    fixed = fix_feet(joints, contacts_from_features(features))
    change = np.linalg.norm(fixed[:, list(LEG_JOINTS)] - joints[:, list(LEG_JOINTS)], axis=-1)
    assert change.mean() < 0.003, change.mean()
    assert foot_skating_ratio(fixed) <= foot_skating_ratio(joints) + 1e-9
    assert foot_pops(joints, fixed) == 0


@pytest.mark.parametrize("marked", [True, False], ids=["marked", "unmarked"])
@pytest.mark.parametrize("kind,speed", [("walk", "fast"), ("run", "normal"), ("run", "fast")])
def test_sprints_planted_throughout(kind: str, speed: str, marked: bool) -> None:
    """A gait gliding on at 10 cm/frame (3.6-5.9 m/s in all), feet marked in contact all along, or never (the
    channels' speed rule cannot mark a foot carried by so fast a body, and generated sprints come so): the feet are
    planted after the first second too (the toes held on a quarter of those frames or more) and skate less there."""
    joints, _ = gait(1, kind, "forward", speed, 121)
    joints = joints + (np.arange(120)[:, None] * np.float32([0.0, 0.0, 0.1]))[:, None]
    contacts = np.full((120, 4), marked)
    fixed = fix_feet(joints, contacts)
    spans = held_spans(joints, contacts)
    later = sum(b - max(a, 20) + 1 for toe in (spans[1], spans[3]) for a, b in toe if b >= 20)
    assert later >= 0.25 * 100, later
    assert foot_skating_ratio(fixed[20:]) < 0.8 * foot_skating_ratio(joints[20:])
    assert foot_pops(joints, fixed) == 0


def test_foot_pops_and_toe_above() -> None:
    """The two figures the fix is measured by: an 8 cm snap of one toe over a motion whose feet move at most 2 cm a
    frame is one pop (two frame pairs: out and back); one toe lifted on half the frames is a quarter of toe-frames."""
    joints = np.zeros((10, 22, 3))
    joints[:, [7, 10, 8, 11], 0] = np.arange(10)[:, None] * 0.02
    snapped = joints.copy()
    snapped[5, 10, 0] += 0.08
    assert foot_pops(joints, joints) == 0 and foot_pops(joints, snapped) == 2
    assert foot_pops(np.stack([joints, joints]), np.stack([joints, snapped])).tolist() == [0, 2]
    lifted = joints.copy()
    lifted[:5, 11, 1] = 0.06
    assert toe_above(lifted) == 0.25


def test_estimated_contacts_and_no_contact() -> None:
    joints, _ = sliding_motions(2)[1]
    fixed = fix_feet(joints, estimate_contacts(joints))
    check_fixed(joints, fixed, estimate_contacts(joints))
    assert np.array_equal(fix_feet(joints, np.zeros((len(joints), 4))), joints)


def test_bad_input() -> None:
    joints, _ = sliding_motions(1)[0]
    with pytest.raises(ValueError, match="contacts must be"):
        fix_feet(joints, np.ones((3, 4)))
    bad = joints.copy()
    bad[5, 3, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fix_feet(bad, np.ones((len(joints), 4)))


@pytest.fixture(scope="module")
def pipe(serve_models: Path, tmp_path_factory) -> Path:
    return linked_pipeline(serve_models, tmp_path_factory.mktemp("feet"),
                           ("generate", "--gan", "gan", "--vae", "vae", "--text", "a person walks", "--num", 3,
                            "--frames", 60, "--fix-feet", "-o", "gen"))


@pytest.mark.slow
def test_generated_motions_and_cli(pipe: Path) -> None:
    """``generate --fix-feet`` holds the feet once, on the motion of record; ``export`` shows it as it is (the
    default and --no-fix-feet agree), and holds them again only when asked."""
    from lsgan.data.features import recover_from_ric
    from lsgan.motion.rigid import make_rigid

    gen = pipe / "gen"
    for path in sorted(gen.glob("*_joints.npy")):
        joints = np.load(path)
        features = np.load(str(path).replace("_joints.npy", "_features.npy"))
        contacts = contacts_from_features(features)
        rigid = make_rigid(recover_from_ric(features))
        np.testing.assert_allclose(joints, fix_feet(rigid, contacts), atol=1e-6, rtol=0)
        check_fixed(rigid, joints, contacts)
    for flag, out in (((), "on"), (("--no-fix-feet",), "off"), (("--fix-feet",), "forced")):
        run = lsgan("export", "--bvh", gen, *flag, "-o", out, cwd=pipe)
        assert run.returncode == 0, run.stderr
    original = dict(load_motion_joints(gen))
    from lsgan.export.bvh import joints_to_bvh
    for name, joints in original.items():
        stem = name.removesuffix("_joints")
        assert (pipe / "off" / f"{stem}.bvh").read_text() == joints_to_bvh(joints)
        assert (pipe / "on" / f"{stem}.bvh").read_bytes() == (pipe / "off" / f"{stem}.bvh").read_bytes()
    # a plain joints file: off by default, estimated contacts with --fix-feet
    plain = pipe / "plain.npy"
    np.save(plain, next(iter(original.values())))
    assert lsgan("export", "--bvh", plain, "-o", "plain_off.bvh", cwd=pipe).returncode == 0
    assert lsgan("export", "--bvh", plain, "--fix-feet", "-o", "plain_on.bvh", cwd=pipe).returncode == 0
    assert (pipe / "plain_off.bvh").read_text() == joints_to_bvh(np.load(plain))
    assert (pipe / "plain_on.bvh").read_text() != (pipe / "plain_off.bvh").read_text()
