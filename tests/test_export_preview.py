"""Tests of the stick-figure GIF preview (lsgan.export.preview)."""
from __future__ import annotations

import numpy as np
import pytest

PIL = pytest.importorskip("PIL")
from PIL import Image  # noqa: E402

from lsgan.data.synthetic import generate  # noqa: E402
from lsgan.export.preview import LEFT_COLOUR, RIGHT_COLOUR, render_frames, write_gif  # noqa: E402

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
    assert [p.name for p in out.parent.iterdir()] == ["m.gif"]  # no temporary file left behind
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
    import json
    import subprocess
    import sys

    from PIL import Image

    from lsgan.data.synthetic import generate

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
