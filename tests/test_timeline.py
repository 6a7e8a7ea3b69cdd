"""Long takes: ``lsgan generate --timeline`` and lsgan/timeline.py.

Parsing and joining are tested on their own (joins on real motions: the synthetic clips' features); the command
runs on the tiny trained pipeline of ``serve_models`` (VAE max_len 200), whose output is compared with what
``generate --prompts`` makes for the same segments.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_runs import lsgan

from lsgan.data.features import joints_to_features, recover_from_ric, recover_root
from lsgan.data.skeleton import PARENTS
from lsgan.data.synthetic import generate as synthetic_clips
from lsgan.data.bones import bone_lengths, root_frame_joints, skeleton_lengths
from lsgan.motion.rigid import make_rigid
from lsgan.timeline import (
    TimelineError,
    check_segments,
    crossfade,
    join_features,
    parse_timeline,
    segment_requests,
)

TIMELINE = "a person walks forward#120; a person turns around#110; a person jumps#90"  # 320 frames > max_len 200
SEGMENTS = [("a person walks forward", 120), ("a person turns around", 110), ("a person jumps", 90)]


# ---- parsing --------------------------------------------------------------------------------------------------

BAD_FILES = [  # (file content, phrase of the message after "FILE: ")
    ("walk#40\n\nrun#40\n", "line 2 is blank"),
    ("walk#40\nrun forward\n", "line 2 has no '#frames'"),
    ("#40\n", "line 1 has no prompt before '#'"),
    ("walk#forty\n", "line 1 'forty' is not a whole number of frames"),
    ("walk#-5\n", "line 1 '-5' is not a whole number of frames"),
    ("walk#4.5\n", "line 1 '4.5' is not a whole number of frames"),
    ("", "no segments"),
    ("   \n", "line 1 is blank"),
]


@pytest.mark.parametrize("content,phrase", BAD_FILES, ids=[p for _, p in BAD_FILES])
def test_bad_timeline_files_name_the_file_and_line(tmp_path: Path, content: str, phrase: str) -> None:
    path = tmp_path / "take.txt"
    path.write_text(content)
    with pytest.raises(TimelineError) as e:
        parse_timeline(str(path))
    assert str(e.value).startswith(f"{path}: {phrase}"), str(e.value)
    assert "\n" not in str(e.value) and not e.value.inline


BAD_INLINE = [
    ("walk#40;;run#40", "--timeline: item 2 is blank"),
    ("walk#40; run", "--timeline: item 2 has no '#frames'"),
    ("walk#40; #20", "--timeline: item 2 has no prompt before '#'"),
    ("walk#x", "--timeline: item 1 'x' is not a whole number of frames"),
    (";#", "--timeline: item 1 is blank"),
]


@pytest.mark.parametrize("value,phrase", BAD_INLINE, ids=[v for v, _ in BAD_INLINE])
def test_bad_inline_timelines_name_the_item(value: str, phrase: str) -> None:
    with pytest.raises(TimelineError) as e:
        parse_timeline(value)
    assert str(e.value).startswith(phrase) and e.value.inline, str(e.value)


def test_file_or_inline(tmp_path: Path, monkeypatch) -> None:
    """An existing file is read as the file (even with '#' in its name); other values with '#' are inline."""
    odd = tmp_path / "take#2.txt"
    odd.write_text("walk forward#80\ntake #3 of a turn; slowly#60\n")
    segments, source = parse_timeline(str(odd))
    assert source == str(odd)
    assert [(s.text, s.frames) for s in segments] == [("walk forward", 80), ("take #3 of a turn; slowly", 60)]
    assert segments[1].where == f"{odd}: line 2"
    segments, source = parse_timeline(" walk forward#80 ;turn around # 60; ")  # spaces and a trailing ';'
    assert source is None and [(s.text, s.frames) for s in segments] == [("walk forward", 80), ("turn around", 60)]
    with pytest.raises(TimelineError, match=r"^missing\.txt: no such timeline file") as e:
        parse_timeline("missing.txt")
    assert not e.value.inline
    monkeypatch.chdir(tmp_path)
    (tmp_path / "walk#80").write_text("run#40\n")  # a file of that name wins over the inline reading
    assert [(s.text, s.frames) for s in parse_timeline("walk#80")[0]] == [("run", 40)]
    assert len(parse_timeline("walk#80; " * 200)[0]) == 200  # longer than a file name may be: still inline


def test_segment_lengths_are_checked_against_overlap_and_model() -> None:
    segments = parse_timeline("walk#100; turn#11; jump#200")[0]
    check_segments(segments, 10, 200)  # the last one has no overlap: 200 frames fit
    with pytest.raises(ValueError, match=r"^--timeline: item 2: 11 frames \+ 10 of overlap is more .* \(20\)"):
        check_segments(segments[1:2] * 2, 10, 20)
    with pytest.raises(ValueError, match=r"^--timeline: item 2: 11 frames; a segment needs at least 12"):
        check_segments(segments, 11, 300)
    with pytest.raises(ValueError, match=r"at least 4"):
        check_segments(parse_timeline("walk#3")[0], 0, 300)
    assert [r.frames for r in segment_requests(segments, 10)] == [110, 21, 200]


# ---- joining ------------------------------------------------------------------------------------------------

def test_crossfade_weights() -> None:
    for v in (1, 2, 10, 33):
        w = crossfade(v)
        assert w.shape == (v,) and (w > 0).all() and (w < 1).all() and (np.diff(w) > 0).all()
        np.testing.assert_allclose(w + w[::-1], 1.0, atol=1e-12)  # symmetric about the middle of the seam
    assert crossfade(0).shape == (0,)


def real_parts(overlap: int) -> tuple[list[np.ndarray], list[int]]:
    """Features of three different real motions (a sidestep, a backwards sprint, a curved walk: synthetic clips),
    as the segments of a timeline asking for their full lengths."""
    parts = [joints_to_features(c.joints) for c in synthetic_clips(3, seed=0)]
    return parts, [len(p) - overlap for p in parts[:-1]] + [len(parts[-1])]


def test_join_layout_on_real_motions() -> None:
    """Total length exact; every frame outside a seam is one segment's own; seam frames are the cross-fade."""
    v = 10
    parts, frames = real_parts(v)
    out = join_features(parts, frames, v)
    assert out.shape == (sum(frames), 263) and out.dtype == np.float32
    s1, s2 = frames[0], frames[0] + frames[1]
    np.testing.assert_array_equal(out[:s1], parts[0][:s1])
    np.testing.assert_array_equal(out[s1 + v : s2], parts[1][v : frames[1]])
    np.testing.assert_array_equal(out[s2 + v :], parts[2][v:])
    w = crossfade(v)[:, None]
    blend = (1 - w) * parts[0][s1:] + w * parts[1][:v]
    keep = np.r_[0:4, 67:263]  # every channel but the joints is the cross-fade itself
    np.testing.assert_allclose(out[s1 : s1 + v][:, keep], blend[:, keep], atol=1e-6)
    # the joints are the blend's, each bone along the blend's direction at the motions' one length: no seam shrinks
    joints, blended = root_frame_joints(out.astype(np.float64)), root_frame_joints(blend)
    skeleton = skeleton_lengths(np.asarray(parts[0], np.float64))
    np.testing.assert_allclose(bone_lengths(joints), np.broadcast_to(skeleton, (len(out), 21)), atol=1e-5)
    assert (bone_lengths(blended) < skeleton - 1e-3).any()  # the plain blend did shrink bones
    unit = lambda j: (j[:, 1:] - j[:, PARENTS[1:]]) / bone_lengths(j)[..., None]  # noqa: E731
    np.testing.assert_allclose(unit(joints[s1 : s1 + v]), unit(blended), atol=1e-5)
    with pytest.raises(ValueError, match="expected"):
        join_features(parts, [len(p) for p in parts], v)


def per_frame(features: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame step: root horizontal displacement (m), |yaw change| (rad), largest joint displacement (m)."""
    f = np.asarray(features, np.float64)
    angle, root = recover_root(f)
    joints = recover_from_ric(f)
    return (np.linalg.norm(np.diff(root[:, [0, 2]], axis=0), axis=1), np.abs(np.diff(angle)),
            np.linalg.norm(np.diff(joints, axis=0), axis=-1).max(-1))


def seam_frames(frames: list[int], overlap: int, margin: int = 3) -> np.ndarray:
    """Indices of the per-frame steps in and around each seam."""
    starts = np.cumsum(frames)[:-1]
    return np.unique(np.concatenate([np.arange(s - margin, s + overlap + margin) for s in starts]))


def test_seams_are_continuous_on_real_motions() -> None:
    """Three different real motions joined: at the seams the root's step and turn stay within what the motions do
    themselves (exact: convex combinations), and so does the largest joint step, which a hard cut exceeds by half."""
    parts, frames = real_parts(10)
    root, yaw, joint = per_frame(join_features(parts, frames, 10))
    own = [per_frame(p) for p in parts]
    at = seam_frames(frames, 10)
    assert root[at].max() <= max(o[0].max() for o in own) + 1e-6
    assert yaw[at].max() <= max(o[1].max() for o in own) + 1e-6
    largest_own = max(o[2].max() for o in own)
    assert joint[at].max() <= largest_own
    parts, frames = real_parts(0)
    _, _, cut = per_frame(join_features(parts, frames, 0))
    assert cut[seam_frames(frames, 0)].max() > 1.5 * largest_own


# ---- the command, on a tiny trained pipeline --------------------------------------------------------------------

def run_timeline(models: Path, out: Path, *args) -> tuple[np.ndarray, np.ndarray, dict]:
    res = lsgan("generate", "--gan", "gan", "--vae", "vae", "-o", out, *args, cwd=models)
    assert res.returncode == 0, res.stderr
    manifest = json.loads((out / "manifest.json").read_text())
    entry = manifest["motions"][0]
    return np.load(out / entry["features"]), np.load(out / entry["joints"]), manifest


@pytest.fixture(scope="module")
def take(serve_models: Path, tmp_path_factory) -> tuple[np.ndarray, np.ndarray, dict]:
    return run_timeline(serve_models, tmp_path_factory.mktemp("take") / "out", "--timeline", TIMELINE, "--seed", 3)


@pytest.fixture(scope="module")
def standalone(serve_models: Path, tmp_path_factory) -> list[tuple[np.ndarray, np.ndarray]]:
    """``generate --prompts`` of the segments at the lengths the timeline generates them (frames + overlap)."""
    d = tmp_path_factory.mktemp("alone")
    lengths = [n + 10 for _, n in SEGMENTS[:-1]] + [SEGMENTS[-1][1]]
    (d / "p.txt").write_text("".join(f"{t}#{n}\n" for (t, _), n in zip(SEGMENTS, lengths)))
    res = lsgan("generate", "--gan", "gan", "--vae", "vae", "--prompts", d / "p.txt", "--seed", 3, "-o", d / "out",
                cwd=serve_models)
    assert res.returncode == 0, res.stderr
    entries = json.loads((d / "out" / "manifest.json").read_text())["motions"]
    return [(np.load(d / "out" / e["features"]), np.load(d / "out" / e["joints"])) for e in entries]


@pytest.mark.slow
def test_one_motion_of_the_total_length_beyond_max_len(take, serve_models: Path) -> None:
    features, joints, manifest = take
    max_len = json.loads((serve_models / "vae" / "best" / "config.json").read_text())["config"]["model"]["max_len"]
    assert len(features) == 320 > max_len
    assert features.shape == (320, 263) and joints.shape == (320, 22, 3) and len(manifest["motions"]) == 1
    np.testing.assert_allclose(joints, make_rigid(recover_from_ric(features)), atol=1e-6)
    tl = manifest["timeline"]
    assert tl["source"] == "inline" and tl["overlap"] == 10
    assert [(s["text"], s["frames"], s["start"], s["generated_frames"]) for s in tl["segments"]] == [
        ("a person walks forward", 120, 0, 130), ("a person turns around", 110, 120, 120),
        ("a person jumps", 90, 230, 90)]
    assert manifest["motions"][0]["text"] == "a person walks forward; a person turns around; a person jumps"
    assert manifest["seed"] == 3 and manifest["motions"][0]["frames"] == 320


@pytest.mark.slow
def test_segments_equal_generate_prompts_away_from_the_seams(take, standalone) -> None:
    """What holds exactly: outside the blend frames [s_i, s_i + 10), the features are bit for bit those of
    ``generate --prompts`` with lines 'prompt#(frames + 10)' (the last at its frames) and the same seed (same noise
    rows, same batch); the first segment's decoded joints are equal too, and every later segment's decoded joints
    are those motions' moved rigidly (a turn about Y and a shift), one transform per segment. (The joints written
    are each motion made rigid on its own median bone lengths, which differ between a segment and the take.)"""
    features, _, _ = take
    (f0, _), (f1, _), (f2, _) = standalone
    np.testing.assert_array_equal(features[:120], f0[:120])
    np.testing.assert_array_equal(features[130:230], f1[10:110])
    np.testing.assert_array_equal(features[240:], f2[10:])
    joints, j0, j1, j2 = (recover_from_ric(f) for f in (features, f0, f1, f2))
    np.testing.assert_allclose(joints[:120], j0[:120], atol=1e-6)
    for mine, theirs in ((joints[130:230], j1[10:110]), (joints[240:], j2[10:])):
        assert rigid_residual(theirs, mine) < 1e-4


def rigid_residual(a: np.ndarray, b: np.ndarray) -> float:
    """Largest distance (m) between b and a turned about Y and shifted to fit it best (least squares)."""
    pa, pb = a[..., [0, 2]].reshape(-1, 2), b[..., [0, 2]].reshape(-1, 2)
    ca, cb = pa.mean(0), pb.mean(0)
    u, _, vt = np.linalg.svd((pa - ca).T @ (pb - cb))
    r = (u @ vt).T
    fitted = (pa - ca) @ r.T + cb
    assert np.linalg.det(r) > 0
    dy = np.abs(a[..., 1] - b[..., 1]).max()
    return float(max(np.linalg.norm(fitted - pb, axis=1).max(), dy))


@pytest.mark.slow
def test_root_and_heading_are_continuous_at_each_seam(take, standalone) -> None:
    """No jump at the seams: the root's step and turn per frame stay within the largest the segments' own
    motions make (the cross-faded channels are convex combinations of theirs)."""
    features, _, _ = take
    root, yaw, _ = per_frame(features)
    own = [per_frame(f) for f, _ in standalone]
    at = seam_frames([n for _, n in SEGMENTS], 10)
    assert root[at].max() <= max(o[0].max() for o in own) + 1e-6
    assert yaw[at].max() <= max(o[1].max() for o in own) + 1e-6
    assert np.isfinite(features).all()


@pytest.mark.slow
def test_deterministic_under_seed(take, serve_models: Path, tmp_path: Path) -> None:
    file = tmp_path / "take.txt"
    file.write_text("".join(f"{t}#{n}\n" for t, n in SEGMENTS))
    again, _, manifest = run_timeline(serve_models, tmp_path / "a", "--timeline", file, "--seed", 3)
    np.testing.assert_array_equal(again, take[0])  # a file or the same inline: the same motion
    assert manifest["timeline"]["source"] == str(file)
    other, _, _ = run_timeline(serve_models, tmp_path / "b", "--timeline", TIMELINE, "--seed", 4)
    assert np.abs(other - take[0]).max() > 1e-3


@pytest.mark.slow
def test_overlap_option_and_onnx_runtime(serve_models: Path, tmp_path: Path) -> None:
    features, _, manifest = run_timeline(serve_models, tmp_path / "a", "--timeline", "walk#60; jump#50",
                                         "--overlap", 0)
    assert len(features) == 110 and manifest["timeline"]["overlap"] == 0
    res = lsgan("generate", "--runtime", "onnx", "--gan", "gan-onnx", "--timeline", TIMELINE, "--overlap", 16,
                "-o", tmp_path / "o", cwd=serve_models)
    assert res.returncode == 0, res.stderr
    manifest = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert manifest["motions"][0]["frames"] == 320 and manifest["timeline"]["overlap"] == 16
    assert manifest["runtime"]["name"] == "onnx"


@pytest.mark.slow
@pytest.mark.parametrize("args,phrase", [
    (["--timeline", "walk#40", "--text", "x"], "--text: not used with --timeline"),
    (["--timeline", "walk#40", "--frames", 50], "--frames: not used with --timeline"),
    (["--text", "x", "--overlap", 5], "--overlap and --join go with --timeline"),
    (["--text", "x", "--join", "continue"], "--overlap and --join go with --timeline"),
    (["--timeline", "walk#40; run"], "item 2 has no '#frames'"),
])
def test_usage_errors_exit_2(serve_models: Path, tmp_path: Path, args: list, phrase: str) -> None:
    res = lsgan("generate", "--gan", "gan", "--vae", "vae", "-o", tmp_path / "o", *args, cwd=serve_models)
    assert res.returncode == 2 and phrase in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_continued_segments_start_where_the_take_is_and_repeat_under_the_seed(serve_models: Path, tmp_path: Path):
    """--join continue: one motion of the segments' total length; each later segment was generated from seed + i
    and met the take's last 5 frames (its manifest figure, measured on its own motion of record, is small); the
    take's root path has no jump at a seam beyond the take's own largest step; the same seed repeats it."""
    value = "a person walks forward#60; a person jumps#50; a person turns around#40"
    features, joints, manifest = run_timeline(serve_models, tmp_path / "a", "--timeline", value, "--join",
                                              "continue", "--seed", 2)
    assert features.shape == (150, 263) and joints.shape == (150, 22, 3)
    np.testing.assert_allclose(joints, make_rigid(recover_from_ric(features)), atol=1e-6)
    segments = manifest["timeline"]["segments"]
    assert [(s["start"], s["seed"]) for s in segments] == [(0, 2), (60, 3), (110, 4)]
    assert all(s["control"]["keyframes_m"]["max"] < 0.02 for s in segments[1:]), segments
    step = np.linalg.norm(np.diff(joints[:, 0, [0, 2]], axis=0), axis=-1)
    inside = np.delete(step, [59, 60, 109, 110])
    assert step[[59, 60, 109, 110]].max() <= 1.5 * inside.max()
    again, _, _ = run_timeline(serve_models, tmp_path / "b", "--timeline", value, "--join", "continue", "--seed", 2)
    np.testing.assert_array_equal(again, features)
