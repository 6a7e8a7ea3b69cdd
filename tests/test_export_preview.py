"""Tests of the stick-figure GIF and MP4 previews (lsgan.export.preview)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

PIL = pytest.importorskip("PIL")
from PIL import Image  # noqa: E402

from lsgan.data.synthetic import generate  # noqa: E402
from lsgan.export import preview  # noqa: E402
from lsgan.export.preview import (  # noqa: E402
    LEFT_COLOUR,
    RIGHT_COLOUR,
    EncodeError,
    render_frames,
    write_gif,
    write_mp4,
)

SIZE = 160


@pytest.fixture(scope="module")
def joints() -> np.ndarray:
    return generate(1, seed=0)[0].joints[:24]


def _has_colour(im: Image.Image, colour, tol: int = 0) -> bool:
    a = np.asarray(im.convert("RGB")).astype(int)
    return bool((np.abs(a - np.array(colour)).max(-1) <= tol).any())


def test_write_gif_frames_size_duration(tmp_path, joints):
    out = write_gif(tmp_path / "sub" / "m.gif", joints, title="a person walks", fps=20.0, size=SIZE)
    assert out == tmp_path / "sub" / "m.gif" and out.is_file()
    assert sorted(p.name for p in out.parent.iterdir()) == [".lsgan-outputs.json", "m.gif"]  # no temporary left
    with Image.open(out) as im:
        assert im.format == "GIF"
        assert im.n_frames == len(joints)
        assert im.size == (SIZE, SIZE)
        assert im.info["duration"] == 50
        assert im.info["loop"] == 0
        im.seek(len(joints) - 1)
        assert _has_colour(im, LEFT_COLOUR, tol=8) and _has_colour(im, RIGHT_COLOUR, tol=8)


def test_gif_duration_follows_fps(tmp_path, joints):
    with Image.open(write_gif(tmp_path / "m.gif", joints[:3], fps=10.0, size=64)) as im:
        assert im.info["duration"] == 100


def _delays(path) -> list[int]:
    """Each frame's delay (ms) as Pillow reads it back."""
    with Image.open(path) as im:
        out = []
        for k in range(im.n_frames):
            im.seek(k)
            out.append(im.info["duration"])
        return out


@pytest.mark.parametrize("fps", [20, 24, 25, 30, 60, 120])
def test_gif_lasts_as_long_as_the_motion(tmp_path, joints, fps):
    """Read back, the delays add up to frames / fps (to the 10 ms a GIF holds), none is under 20 ms (browsers
    play shorter ones as 100 ms), and no frame is shown 10 ms longer than its neighbours on average."""
    motion = np.concatenate([joints, joints[::-1]])  # 48 frames
    delays = _delays(write_gif(tmp_path / f"m{fps}.gif", motion, fps=float(fps), size=64))
    assert sum(delays) == 10 * round(100 * len(motion) / fps)
    assert min(delays) >= 20 and max(delays) - min(delays) <= 10
    if fps <= 50:
        assert len(delays) == len(motion)  # every frame kept
    else:
        assert len(delays) == int(len(motion) * 50 / fps)  # resampled to 50 fps


def test_gif_timing_resamples_in_time_order():
    positions, delays = preview.gif_timing(120, 60.0)
    assert len(positions) == 100 and positions[0] == 0 and np.all(np.diff(positions) == pytest.approx(1.2))
    assert delays == [20] * 100
    positions, delays = preview.gif_timing(99, 30.0)
    assert np.array_equal(positions, np.arange(99)) and sum(delays) == 3300
    moved = preview.resample(np.arange(3 * 22 * 3, dtype=float).reshape(3, 22, 3), np.array([0.0, 0.5, 2.0]))
    assert np.allclose(moved[1], moved[0] + 0.5 * 66) and np.allclose(moved[2], 2 * 66 + moved[0])


def test_frames_in_image_and_differ(joints):
    frames = render_frames(joints, size=SIZE)
    assert len(frames) == len(joints)
    for im in frames:
        assert im.size == (SIZE, SIZE) and im.mode == "RGB"
        # Both sides of the body are drawn in every frame, i.e. the figure lies inside the image.
        assert _has_colour(im, LEFT_COLOUR) and _has_colour(im, RIGHT_COLOUR)
    a0, a_last = (np.asarray(frames[i]) for i in (0, -1))
    assert not np.array_equal(a0, a_last)
    # The figure itself moved, not only the progress bar at the bottom.
    assert not np.array_equal(a0[:-8], a_last[:-8])


def test_static_motion_still_has_distinct_frames(tmp_path, joints):
    static = np.repeat(joints[:1], 5, axis=0)
    with Image.open(write_gif(tmp_path / "s.gif", static, size=64)) as im:
        assert im.n_frames == 5


def test_title_changes_top_rows(joints):
    plain = np.asarray(render_frames(joints[:1], size=SIZE)[0])
    titled = np.asarray(render_frames(joints[:1], title="a person walks forward", size=SIZE)[0])
    assert not np.array_equal(plain[:12], titled[:12])
    assert (titled[:12] < 100).all(-1).any()  # dark text pixels at the top


def test_long_title_wraps(joints):
    def body_top(a):  # the first row holding a body colour: the figure is laid out below the title
        rows = [np.flatnonzero((a == np.array(c)).all(-1).any(-1)).min() for c in (LEFT_COLOUR, RIGHT_COLOUR)]
        return min(rows)

    short = np.asarray(render_frames(joints[:1], title="walk", size=SIZE)[0])
    long = np.asarray(render_frames(joints[:1], title="a person " * 12 + "walks", size=SIZE)[0])
    assert body_top(long) > body_top(short) + 10  # several lines of title push the figure down
    assert (long[:SIZE // 3, :2] == 255).all() and (long[:SIZE // 3, -2:] == 255).all()  # text stays inside


@pytest.mark.parametrize(
    "bad",
    [np.zeros((10, 21, 3), np.float32), np.zeros((22, 3), np.float32), np.zeros((0, 22, 3), np.float32)],
)
def test_bad_shape_raises(bad, tmp_path):
    with pytest.raises(ValueError):
        render_frames(bad)
    with pytest.raises(ValueError):
        write_gif(tmp_path / "x.gif", bad)
    assert not (tmp_path / "x.gif").exists()


def test_nan_raises(joints, tmp_path):
    bad = joints.copy()
    bad[3, 5, 1] = np.nan
    with pytest.raises(ValueError):
        render_frames(bad)
    with pytest.raises(ValueError):
        write_gif(tmp_path / "x.gif", bad)
    assert list(tmp_path.iterdir()) == []


def test_export_command_titles_previews_with_the_manifest_prompts(tmp_path):
    folder = tmp_path / "gen"
    folder.mkdir()
    np.save(folder / "000_wave_joints.npy", generate(1, seed=0)[0].joints[:20])
    (folder / "manifest.json").write_text(json.dumps({"motions": [{"joints": "000_wave_joints.npy", "text": "a man waves"}]}))
    out = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--gif", str(folder), "-o", str(tmp_path / "p")],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    with Image.open(tmp_path / "p" / "000_wave.gif") as im:
        assert im.n_frames == 20
    untitled = subprocess.run([sys.executable, "-m", "lsgan.cli", "export", "--gif", "--title", "", str(folder / "000_wave_joints.npy"),
                               "-o", str(tmp_path / "u.gif")], capture_output=True, text=True)
    assert untitled.returncode == 0, untitled.stderr
    with Image.open(tmp_path / "p" / "000_wave.gif") as titled, Image.open(tmp_path / "u.gif") as plain:
        top_t = np.asarray(titled.convert("RGB"))[:20]
        top_p = np.asarray(plain.convert("RGB"))[:20]
        assert (top_t < 100).any() and not (top_p < 100).any()  # the prompt is drawn; an empty title is not


def _read_mp4(path) -> tuple[dict, list[np.ndarray]]:
    """The metadata ffmpeg reports for ``path`` and its decoded RGB frames."""
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    w, h = meta["size"]
    return meta, [np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in reader]


def test_write_mp4_is_h264_with_every_frame_in_order(tmp_path, joints):
    title = "a person walks"
    out = write_mp4(tmp_path / "sub" / "m.mp4", joints, title=title, fps=29.97, size=SIZE)
    assert out == tmp_path / "sub" / "m.mp4" and out.is_file()
    assert sorted(p.name for p in out.parent.iterdir()) == [".lsgan-outputs.json", "m.mp4"]  # no temporary left
    meta, decoded = _read_mp4(out)
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert meta["size"] == (SIZE, SIZE) and meta["fps"] == pytest.approx(29.97)
    assert len(decoded) == len(joints)
    rendered = [np.asarray(im).astype(int) for im in render_frames(joints, title=title, size=SIZE)]
    for t in (0, len(joints) // 2, len(joints) - 1):
        diffs = [np.abs(decoded[t] - r).mean() for r in rendered]
        assert diffs[t] < 3  # lossy, but close to the frame it encodes ...
        assert int(np.argmin(diffs)) == t  # ... and closer to it than to any other frame
        assert (decoded[t] < 100).all(-1).sum() > 50  # the joints and the title are there, not a blank frame


def test_mp4_odd_size_is_rounded_up_to_even(tmp_path, joints):
    meta, decoded = _read_mp4(write_mp4(tmp_path / "m.mp4", joints[:2], size=65))
    assert meta["size"] == (66, 66) and len(decoded) == 2


def test_mp4_bad_input_raises_before_writing(tmp_path, joints):
    bad = joints.copy()
    bad[3, 5, 1] = np.nan
    for args, kwargs in [((bad,), {}), ((joints[:, :21],), {}), ((joints,), {"fps": 0}), ((joints,), {"size": 32})]:
        with pytest.raises(ValueError):
            write_mp4(tmp_path / "x.mp4", *args, **kwargs)
    assert list(tmp_path.iterdir()) == []


@pytest.fixture
def old_target(tmp_path):
    target = tmp_path / "m.mp4"
    target.write_bytes(b"the previous video")
    return target


@pytest.mark.skipif(sys.platform == "win32", reason="the stand-in ffmpeg is a shell script")
def test_failed_encode_keeps_the_target_and_leaves_no_partial_file(tmp_path, joints, old_target, monkeypatch):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    fake = tmp_path / "bin" / "ffmpeg"
    fake.parent.mkdir()
    fake.write_text('#!/bin/sh\nfor last; do :; done\necho partial > "$last"\necho "no such encoder" >&2\nexit 1\n')
    fake.chmod(0o755)
    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", lambda: str(fake))
    with pytest.raises(EncodeError, match="no such encoder"):
        write_mp4(old_target, joints, size=64)
    assert old_target.read_bytes() == b"the previous video"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bin", "m.mp4"]


def test_interrupted_render_stops_ffmpeg_and_leaves_no_partial_file(tmp_path, joints, old_target, monkeypatch):
    real = preview.iter_frames

    def failing(*args, **kwargs):
        frames = real(*args, **kwargs)
        yield from (next(frames) for _ in range(3))
        raise KeyboardInterrupt

    started = []
    popen = subprocess.Popen

    def recording_popen(*args, **kwargs):
        started.append(popen(*args, **kwargs))
        return started[-1]

    monkeypatch.setattr(preview, "iter_frames", failing)
    monkeypatch.setattr(subprocess, "Popen", recording_popen)
    with pytest.raises(KeyboardInterrupt):
        write_mp4(old_target, joints, size=64)
    assert len(started) == 1 and started[0].poll() is not None  # ffmpeg was started, and is gone
    assert old_target.read_bytes() == b"the previous video"
    assert [p.name for p in tmp_path.iterdir()] == ["m.mp4"]


def test_export_command_writes_mp4_previews(tmp_path):
    folder = tmp_path / "gen"
    folder.mkdir()
    np.save(folder / "000_wave_joints.npy", generate(1, seed=0)[0].joints[:20])
    manifest = {"motions": [{"joints": "000_wave_joints.npy", "text": "a man waves"}]}
    (folder / "manifest.json").write_text(json.dumps(manifest))

    def export(*args):
        cmd = [sys.executable, "-m", "lsgan.cli", "export", *map(str, args)]
        return subprocess.run(cmd, capture_output=True, text=True)

    out = export("--mp4", folder, "-o", tmp_path / "p")
    assert out.returncode == 0, out.stderr
    meta, decoded = _read_mp4(tmp_path / "p" / "000_wave.mp4")
    assert meta["codec"] == "h264" and meta["fps"] == 20 and len(decoded) == 20
    assert (decoded[0][:20] < 100).any()  # the prompt is drawn as the title
    single = export("--mp4", folder / "000_wave_joints.npy", "--fps", 30, "-o", tmp_path / "w.mp4")
    assert single.returncode == 0, single.stderr
    assert _read_mp4(tmp_path / "w.mp4")[0]["fps"] == 30
    both = export("--mp4", "--gif", folder, "-o", tmp_path / "x")
    assert both.returncode != 0 and "--mp4" in both.stderr
