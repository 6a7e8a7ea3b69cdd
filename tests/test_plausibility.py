"""Import plausibility checks (lsgan.data.plausibility): real mocap passes, wrong `up` and wrong `scale` are
flagged with their cause, and each threshold fires exactly where docs/plausibility.md says."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from lsgan.data.joint_maps import PRESETS, Between
from lsgan.data.plausibility import (
    DEFAULT_THRESHOLDS,
    HUMAN_HEIGHT_M,
    KINDS,
    Thresholds,
    clip_checks,
    clip_warnings,
    facing,
    findings,
    format_summary,
    skeleton_height,
    spine_cos,
    summarise,
)
from lsgan.data.skeleton import PARENTS, TARGET_OFFSETS, bone_lengths
from lsgan.data.sources.bvh import BvhSource
from lsgan.data.synthetic import FAMILIES, generate

T = 100
CONTENTS = ("walk", "walk-turn-left", "walk-turn-right", "run", "wave-both-hands", "wave-left-hand",
            "wave-right-hand", "raise-up-both-hands", "raise-up-left-hand", "raise-up-right-hand")
STYLES = ("active", "elderly", "exhausted", "feminine", "masculine", "normal", "youthful")


# ---------------------------------------------------------------------------------------------------------
# Constructed clips: the HumanML3D target skeleton standing (arms down), posed per frame


def standing(frames: int = T) -> np.ndarray:
    """(frames,22,3): the target skeleton in its rest pose, walking slowly along +z, lowest joint at y=0."""
    pose = np.zeros((22, 3))
    for k in range(1, 22):
        pose[k] = pose[PARENTS[k]] + TARGET_OFFSETS[k]
    pose[:, 1] -= pose[:, 1].min()
    clip = np.repeat(pose[None], frames, axis=0)
    clip[:, :, 2] += np.linspace(0.0, 1.0, frames)[:, None]
    return clip


def turned(clip: np.ndarray, frames: np.ndarray, axis: str, degrees: float) -> np.ndarray:
    """The clip with the given frames rotated about the pelvis and put back on the floor (lowest joint y=0):
    a person lying on the floor (90 about x) or standing on their hands (180 about z)."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    rot = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
    out = clip.copy()
    local = out[frames] - out[frames, :1]
    out[frames] = local @ np.array(rot).T + out[frames, :1]
    out[frames, :, 1] -= out[frames, :, 1].min(axis=1, keepdims=True)
    return out


def kinds(joints: np.ndarray, thresholds: Thresholds = DEFAULT_THRESHOLDS) -> list[str]:
    return [k for k, _ in findings(clip_checks(joints, thresholds), thresholds)]


def test_standing_figure_passes_with_expected_figures():
    c = clip_checks(standing())
    assert kinds(standing()) == []
    assert c["frames"] == T and abs(c["skeleton_height_m"] - HUMAN_HEIGHT_M) < 0.01
    assert c["upright_fraction"] == 1.0 and c["inverted_fraction"] == 0.0 and c["vertical_facing_fraction"] == 0.0
    assert c["head_above_pelvis_fraction"] == 1.0 and c["contact_fraction"] == 1.0 and c["bone_variation"] < 1e-6
    assert 0.9 < c["head_height_m"] / c["skeleton_height_m"] < 1.0  # the head joint sits forward of the neck
    json.dumps(c, allow_nan=False)


@pytest.mark.parametrize("height,flagged", [(0.74, True), (0.76, False), (1.8, False), (2.39, False), (2.41, True)])
def test_height_threshold(height, flagged):
    clip = standing() * (height / HUMAN_HEIGHT_M)
    assert kinds(clip) == (["scale"] if flagged else [])


@pytest.mark.parametrize("factor,hint", [(100.0, "0.01x"), (0.01, "100x"), (2.54, "0.394x")])
def test_scale_warning_names_the_cause_and_the_factor(factor, hint):
    (w,) = clip_warnings("clip7", clip_checks(standing() * factor))
    assert w.startswith("clip7: figure ") and "wrong `scale`" in w and f"try about {hint}" in w


@pytest.mark.parametrize("lying,flagged", [(0, False), (30, False), (75, False), (80, False), (81, True), (100, True)])
def test_upright_fraction_threshold(lying, flagged):
    """Lying on the floor in up to 80% of the frames is a performance; in more, the up axis is suspect."""
    clip = turned(standing(), np.arange(lying), "x", 90.0)
    c = clip_checks(clip)
    assert c["upright_fraction"] == pytest.approx(1 - lying / T)
    assert kinds(clip) == (["up"] if flagged else [])


@pytest.mark.parametrize("inverted,flagged", [(20, False), (49, False), (50, True), (100, True)])
def test_handstand_threshold(inverted, flagged):
    """A handstand in part of the clip is fine; upside down in half the frames or more is an up axis sign."""
    clip = turned(standing(), np.arange(T - inverted, T), "z", 180.0)
    assert clip_checks(clip)["inverted_fraction"] == pytest.approx(inverted / T)
    assert kinds(clip) == (["up"] if flagged else [])
    if flagged:
        assert "upside down" in clip_warnings("h", clip_checks(clip))[0]


def test_lying_figure_faces_up_and_names_the_up_axis():
    c = clip_checks(turned(standing(), np.arange(T), "x", -90.0))
    assert c["vertical_facing_fraction"] == 1.0 and c["upright_fraction"] == 0.0
    (w,) = clip_warnings("lying", c)
    assert "wrong `up` axis" in w and "lying figure" in w and "scale" not in w


@pytest.mark.parametrize("amplitude,flagged", [(0.09, False), (0.11, True)])
def test_bone_variation_threshold(amplitude, flagged):
    """The left forearm stretches by amplitude * sqrt(2) * sin: relative std = amplitude."""
    clip = standing()
    stretch = amplitude * np.sqrt(2) * np.sin(2 * np.pi * 4 * np.arange(T) / T)
    clip[:, 20] += (clip[:, 20] - clip[:, 18]) * stretch[:, None]
    c = clip_checks(clip)
    assert c["bone_variation"] == pytest.approx(amplitude, rel=1e-6) and c["worst_bone"] == 20
    assert kinds(clip) == (["bones"] if flagged else [])
    if flagged:
        assert "left_elbow->left_wrist" in clip_warnings("b", c)[0]


def test_jitter_on_short_bones_is_not_bone_variation():
    """5 mm of noise on the 5.7 cm spine2->spine3 bone is 9% of it, but 3.4% of the floor (10% of the height)."""
    clip = standing()
    clip[:, 9, 1] += np.random.default_rng(0).normal(0.0, 0.005, T)
    assert clip_checks(clip)["bone_variation"] < 0.05 and kinds(clip) == []


@pytest.mark.parametrize("airborne,flagged", [(50, False), (80, False), (81, True), (100, False)])
def test_contact_threshold(airborne, flagged):
    """Feet off the floor in 81% of frames is flagged; a clip lifted as a whole just has a higher floor."""
    clip = standing()
    clip[:airborne, :, 1] += 0.3
    assert kinds(clip) == (["floor"] if flagged else [])


@pytest.mark.parametrize("lift,flagged", [(0.4, False), (0.6, True)])
def test_head_height_threshold(lift, flagged):
    """On the floor in 25% of the frames, lifted by ``lift`` skeleton heights in the others."""
    clip = standing()
    clip[25:, :, 1] += lift * HUMAN_HEIGHT_M
    c = clip_checks(clip)
    assert c["contact_fraction"] == 0.25
    assert kinds(clip) == (["floor"] if flagged else [])


def test_floor_ignores_a_foot_glitching_through_it():
    clip = standing()
    clip[40, 10, 1] -= 0.10
    c = clip_checks(clip)
    assert c["contact_fraction"] == 1.0 and kinds(clip) == []


def test_custom_thresholds_apply_and_are_frozen():
    strict = Thresholds(min_height_m=1.6)
    assert kinds(standing(), strict) == ["scale"]
    assert "(humans 1.6-2.4 m)" in clip_warnings("s", clip_checks(standing()), strict)[0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        DEFAULT_THRESHOLDS.max_height_m = 3.0  # type: ignore[misc]


def test_helpers_are_batched():
    clips = np.stack([standing(), turned(standing(), np.arange(T), "x", 90.0)])
    assert spine_cos(clips).shape == (2, T) and facing(clips).shape == (2, T, 3)
    assert np.allclose(spine_cos(clips)[0], 1.0) and np.allclose(spine_cos(clips)[1], 0.0, atol=1e-9)
    assert skeleton_height(bone_lengths(clips)).shape == (2, T)


def swapped(clip: np.ndarray, a: int, b: int, frames: int | None = None) -> np.ndarray:
    """The clip with joints ``a`` and ``b`` exchanged (in its first ``frames`` frames): a joint map naming each
    one's source joint for the other."""
    out = clip.copy()
    out[:frames, [a, b]] = out[:frames, [b, a]]
    return out


@pytest.mark.parametrize("pair,a,b", [("knees", 4, 5), ("elbows", 18, 19), ("knees", 1, 2), ("elbows", 16, 17)],
                         ids=["knees", "elbows", "hips", "shoulders"])
def test_swapped_left_and_right_joints_are_flagged(pair, a, b):
    clip = standing()
    assert clip_checks(clip)[f"{pair}_crossed_fraction"] == 0.0
    c = clip_checks(swapped(clip, a, b))
    assert c[f"{pair}_crossed_fraction"] == 1.0 and kinds(swapped(clip, a, b)) == ["bones"]
    (w,) = clip_warnings("s", c)
    assert w.startswith(f"s: right {pair[:-1]} on the body's left of the left {pair[:-1]} in 100% of frames")
    assert f"left and right {pair} (or their parents) swapped in the joint map?" in w


@pytest.mark.parametrize("frames,flagged", [(30, False), (49, False), (50, True)])
def test_crossed_threshold(frames, flagged):
    """Knees crossed in half the frames or more: real mocap crosses them in none (docs/plausibility.md)."""
    clip = swapped(standing(), 4, 5, frames)
    assert clip_checks(clip)["knees_crossed_fraction"] == pytest.approx(frames / T)
    assert kinds(clip) == (["bones"] if flagged else [])


@pytest.mark.parametrize("shape", [(0, 22, 3), (10, 21, 3), (10, 22)])
def test_rejects_bad_shapes(shape):
    with pytest.raises(ValueError, match="expected joints"):
        clip_checks(np.zeros(shape))


def test_summary_counts_names_and_formats():
    lying = turned(standing(), np.arange(T), "x", 90.0)
    checks = {"ok": clip_checks(standing()), "big": clip_checks(standing() * 100)}
    checks |= {f"lying{i}": clip_checks(lying) for i in range(5)}
    s = summarise(checks)
    json.dumps(s, allow_nan=False)
    assert s["clips"] == 7 and s["flagged"] == 6
    assert s["counts"] == {"scale": 1, "up": 5, "bones": 0, "floor": 0}
    assert s["flagged_clips"]["scale"] == ["big"] and s["flagged_clips"]["up"][0] == "lying0"
    assert s["ranges"]["skeleton_height_m"]["max"] == pytest.approx(100 * HUMAN_HEIGHT_M, rel=0.01)
    assert set(s["warnings"]) == set(checks) - {"ok"} and s["thresholds"]["min_height_m"] == 0.75
    text = format_summary(s)
    assert text.splitlines()[0] == "plausibility: 7 clips checked, 6 flagged"
    assert "up: 5 clips (lying0, lying1, lying2 and 2 more): wrong `up`" in text
    assert "scale: 1 clips (big): wrong `scale`" in text
    assert format_summary(summarise({})).startswith("plausibility: 0 clips checked, 0 flagged")


def test_synthetic_clips_give_no_warnings():
    clips = generate(4 * len(FAMILIES), seed=3)
    s = summarise({c.name: clip_checks(c.joints) for c in clips})
    assert s["flagged"] == 0, s["warnings"]


# ---------------------------------------------------------------------------------------------------------
# Real data from ../shared


def map_file(tmp_path: Path, preset: str, **changes) -> str:
    """The preset's joint map as a user JSON file, with fields changed (e.g. up="z")."""
    jmap = PRESETS[preset]
    joints = {k: v if isinstance(v, str) else {"between": [v.a, v.b], "t": v.t} for k, v in jmap.joints.items()}
    assert all(isinstance(v, (str, Between)) for v in jmap.joints.values())
    data = {"joints": joints, "scale": jmap.scale, "up": jmap.up, "fps": jmap.fps, "handedness": jmap.handedness}
    path = tmp_path / f"{preset}-{'-'.join(f'{k}{v}' for k, v in changes.items())}.json"
    path.write_text(json.dumps(data | changes))
    return str(path)


def real_checks(files: list[tuple[str, Path]], **source_args) -> dict[str, dict]:
    """Checks of real BVH clips read with lsgan's own reader; ``source_args`` per preset, e.g. joint_map."""
    out = {}
    for preset, path in files:
        args = source_args.get(preset, {})
        (clip,) = BvhSource(root=str(path), preset=preset, **args).load(str(path))
        out[clip.name] = clip_checks(clip.joints)
    return out


@pytest.fixture(scope="module")
def real_files(bandai_dir, cmu_dir) -> list[tuple[str, Path]]:
    """Take 001 of every Bandai content and style (70 clips) and the three CMU clips."""
    files = [("bandai", bandai_dir / "data" / f"dataset-2_{c}_{s}_001.bvh.gz") for c in CONTENTS for s in STYLES]
    return files + [("cmu", cmu_dir / f"131_0{i}.bvh") for i in (1, 2, 3)]


def few(files: list[tuple[str, Path]]) -> list[tuple[str, Path]]:
    """One Bandai clip per content (alternating styles) and the CMU clips."""
    return [f for i, f in enumerate(files) if f[0] == "cmu" or i % len(STYLES) == (i // len(STYLES)) % len(STYLES)]


def test_real_mocap_gives_no_warnings(real_files):
    s = summarise(real_checks(real_files))
    assert s["clips"] == 73 and s["flagged"] == 0, s["warnings"]


def test_real_humanml3d_clip_gives_no_warnings(hml_fixtures):
    joints = np.load(hml_fixtures / "new_joints" / "012314.npy")
    assert clip_warnings("012314", clip_checks(joints)) == []


def test_wrong_up_axis_is_flagged_as_up_not_scale(real_files, tmp_path):
    args = {p: {"joint_map": map_file(tmp_path, p, up="z")} for p in PRESETS}
    checks = real_checks(few(real_files), **args)
    s = summarise(checks)
    assert s["flagged"] == len(checks) == 13
    assert s["counts"]["up"] == len(checks) and s["counts"]["scale"] == 0 and s["counts"]["floor"] == 0
    for name, c in checks.items():
        (w,) = clip_warnings(name, c)
        assert w.startswith(f"{name}: figure upright in only 0% of frames") and "wrong `up` axis" in w


@pytest.mark.parametrize("factor", [100.0, 0.01])
def test_wrong_scale_is_flagged_as_scale_not_up(real_files, factor):
    args = {p: {"scale": PRESETS[p].scale * factor} for p in PRESETS}
    checks = real_checks(few(real_files), **args)
    s = summarise(checks)
    assert s["flagged"] == len(checks) and s["counts"] == {"scale": len(checks), "up": 0, "bones": 0, "floor": 0}
    for name, c in checks.items():
        (w,) = clip_warnings(name, c)
        assert w.startswith(f"{name}: figure ") and "wrong `scale`" in w and "wrong `up`" not in w


def swap_map(tmp_path: Path, preset: str, a: str, b: str) -> str:
    """The preset's joint map as a user file with the source joints of SMPL joints ``a`` and ``b`` exchanged."""
    jmap = PRESETS[preset]
    joints = {k: v if isinstance(v, str) else {"between": [v.a, v.b], "t": v.t} for k, v in jmap.joints.items()}
    joints[a], joints[b] = joints[b], joints[a]
    path = tmp_path / f"{preset}-{a}-{b}.json"
    path.write_text(json.dumps({"joints": joints, "scale": jmap.scale, "up": jmap.up, "fps": jmap.fps}))
    return str(path)


@pytest.mark.parametrize("pair", ["knees", "elbows"])
def test_swapped_knees_or_elbows_are_flagged_on_real_clips(real_files, tmp_path, pair):
    """docs/plausibility.md: every one of the 2,905 Bandai and CMU clips with the knees (elbows) swapped in the
    joint map is flagged; here the 73 clips of ``real_files``."""
    a, b = f"left_{pair[:-1]}", f"right_{pair[:-1]}"
    checks = real_checks(real_files, **{p: {"joint_map": swap_map(tmp_path, p, a, b)} for p in PRESETS})
    s = summarise(checks)
    assert s["flagged"] == len(checks) == 73 and s["counts"] == {"scale": 0, "up": 0, "bones": 73, "floor": 0}
    assert all(c[f"{pair}_crossed_fraction"] == 1.0 for c in checks.values())
    assert all(f"left and right {pair}" in w[0] for w in s["warnings"].values())


def test_real_clip_lying_down_in_part_passes_and_throughout_is_flagged(bandai_dir):
    path = bandai_dir / "data" / "dataset-2_walk_normal_001.bvh.gz"
    (clip,) = BvhSource(root=str(path)).load(str(path))
    n = len(clip.joints)
    for part, axis, deg in ((0.3, "x", 90.0), (0.3, "z", 180.0)):
        assert kinds(turned(clip.joints, np.arange(int(part * n)), axis, deg)) == []
    assert kinds(turned(clip.joints, np.arange(n), "x", 90.0)) == ["up"]
    assert kinds(turned(clip.joints, np.arange(n), "z", 180.0)) == ["up"]


def test_kinds_are_documented():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "plausibility.md").read_text()
    for field in [f.name for f in dataclasses.fields(Thresholds)] + list(KINDS):
        assert f"`{field}`" in doc
