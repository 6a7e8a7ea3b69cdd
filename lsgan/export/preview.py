"""Stick-figure GIF and MP4 previews of a (T,22,3) joint motion (metres, Y up, +z forward, SMPL joint order).

Frames are drawn with Pillow (no matplotlib); GIFs are written by Pillow, MP4s (H.264) by the ffmpeg binary
that ships inside the ``imageio-ffmpeg`` wheel, so no system ffmpeg is needed. One fixed perspective camera
per motion, placed at a 3/4 view (in front of the figure, to its right and above), looking at the centre of
the motion's bounds over all frames, and zoomed so that every joint of every frame fits in the image. Each
frame draws, back to front: a ground grid on y=0 (1 m spacing), the root's ground trajectory (the whole
path, faint, and the part walked so far, stronger), the skeleton as lines along the five ``KINEMATIC_CHAIN``
chains (left side blue, right side red, spine dark grey; chains sorted far to near), the joints as small
dots, the title at the top (Pillow's default font, word-wrapped to the image width) and a progress bar at
the bottom (which also keeps consecutive frames distinct, so a GIF keeps exactly one frame per motion
frame). Both file formats take the same frames from ``iter_frames``.
"""
from __future__ import annotations

import os
import subprocess
import tempfile
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from lsgan.data.skeleton import KINEMATIC_CHAIN, NUM_JOINTS
from lsgan.io import atomic_file, atomic_path, discard, publish

BACKGROUND = (255, 255, 255)
GRID_COLOUR = (205, 205, 205)
TRAJECTORY_COLOUR = (120, 200, 120)
TRAJECTORY_DONE_COLOUR = (30, 140, 30)
LEFT_COLOUR = (30, 90, 220)
RIGHT_COLOUR = (220, 40, 40)
SPINE_COLOUR = (60, 60, 60)
JOINT_COLOUR = (0, 0, 0)
TITLE_COLOUR = (0, 0, 0)
PROGRESS_COLOUR = (150, 150, 150)

# Chain index -> colour: KINEMATIC_CHAIN is (right leg, left leg, spine, right arm, left arm).
CHAIN_COLOURS = (RIGHT_COLOUR, LEFT_COLOUR, SPINE_COLOUR, RIGHT_COLOUR, LEFT_COLOUR)

AZIMUTH_DEG = 35.0  # camera direction from the centre, rotated from +z (the front) towards +x
ELEVATION_DEG = 22.0
MIN_SIZE = 64
_PROGRESS_HEIGHT = 4


def _check_joints(joints) -> np.ndarray:
    j = np.asarray(joints)
    if j.ndim != 3 or j.shape[1:] != (NUM_JOINTS, 3) or j.shape[0] < 1:
        raise ValueError(f"joints must have shape (T, {NUM_JOINTS}, 3) with T >= 1, got {j.shape}")
    if not np.issubdtype(j.dtype, np.number):
        raise ValueError(f"joints must be numeric, got dtype {j.dtype}")
    j = j.astype(np.float64)
    if not np.isfinite(j).all():
        raise ValueError("joints contain NaN or infinite values")
    return j


class _Camera:
    """A pinhole camera at a 3/4 view framing ``joints`` (all frames), mapping world points to pixels."""

    def __init__(self, joints: np.ndarray, width: int, top: int, bottom: int, margin: int):
        pts = joints.reshape(-1, 3)
        lo, hi = pts.min(0), pts.max(0)
        lo[1], hi[1] = min(lo[1], 0.0), max(hi[1], 0.0)  # frame the floor under the figure too
        centre = (lo + hi) / 2
        radius = max(float(np.linalg.norm(hi - lo)) / 2, 0.5)
        az, el = np.radians(AZIMUTH_DEG), np.radians(ELEVATION_DEG)
        back = np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])  # centre -> eye
        # Far enough that the grid (bounds + 1 m) stays well in front of the camera.
        self.eye = centre + back * (3.0 * radius + 3.0)
        fwd = -back
        right = np.cross(fwd, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        self.rot = np.stack([right, up, fwd])  # rows: camera axes in world coordinates
        # Fit the projected joints of all frames (and their floor shadows) into the drawing area.
        shadow = pts * np.array([1.0, 0.0, 1.0])
        uv = self._project_normalised(np.concatenate([pts, shadow]))
        uv_lo, uv_hi = uv.min(0), uv.max(0)
        span = np.maximum(uv_hi - uv_lo, 1e-6)
        avail_w, avail_h = width - 2 * margin, (bottom - top) - 2 * margin
        self.scale = float(min(avail_w / span[0], avail_h / span[1]))
        uv_mid = (uv_lo + uv_hi) / 2
        self.offset = np.array([width / 2, (top + bottom) / 2]) - self.scale * uv_mid * np.array([1.0, -1.0])

    def depth(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points) - self.eye) @ self.rot[2]

    def _project_normalised(self, points: np.ndarray) -> np.ndarray:
        cam = (np.asarray(points, dtype=np.float64) - self.eye) @ self.rot.T
        z = np.maximum(cam[..., 2], 1e-3)
        return cam[..., :2] / z[..., None]

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> pixel coordinates (..., 2) (x right, y down)."""
        uv = self._project_normalised(points)
        return uv * self.scale * np.array([1.0, -1.0]) + self.offset


def _wrap(text: str, font, draw: ImageDraw.ImageDraw, max_width: int) -> list[str]:
    """Greedy word wrap of ``text`` to lines at most ``max_width`` pixels wide (long words are split)."""
    def width(s: str) -> float:
        return draw.textlength(s, font=font)

    lines: list[str] = []
    for paragraph in text.splitlines() or [""]:
        line = ""
        for word in paragraph.split():
            while width(word) > max_width and len(word) > 1:  # a word wider than the image: split it
                cut = len(word) - 1
                while cut > 1 and width(word[:cut]) > max_width:
                    cut -= 1
                if line:
                    lines.append(line)
                    line = ""
                lines.append(word[:cut])
                word = word[cut:]
            candidate = f"{line} {word}" if line else word
            if line and width(candidate) > max_width:
                lines.append(line)
                line = word
            else:
                line = candidate
        if line:
            lines.append(line)
    return lines


def _draw_title(draw: ImageDraw.ImageDraw, title: str, size: int) -> int:
    """Draw the wrapped title at the top; return the y below it (0 if no title)."""
    if not title.strip():
        return 0
    font = ImageFont.load_default()
    pad = 6
    lines = _wrap(title.strip(), font, draw, size - 2 * pad)
    line_h = int(np.ceil(draw.textbbox((0, 0), "Ag", font=font)[3])) + 3
    max_lines = max(1, (size // 3) // line_h)  # never let the title eat more than a third of the image
    if len(lines) > max_lines:
        lines = lines[:max_lines]
        lines[-1] = lines[-1].rstrip(".") + "..."
    y = pad
    for line in lines:
        x = (size - draw.textlength(line, font=font)) / 2
        draw.text((x, y), line, fill=TITLE_COLOUR, font=font)
        y += line_h
    return y + pad


def _grid_segments(joints: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Lines of the y=0 grid (1 m spacing) covering the motion's ground footprint plus a 1 m border."""
    xz = joints[..., [0, 2]].reshape(-1, 2)
    x0, z0 = np.floor(xz.min(0)) - 1
    x1, z1 = np.ceil(xz.max(0)) + 1
    segs = []
    for x in np.arange(x0, x1 + 0.5):
        segs.append((np.array([x, 0.0, z0]), np.array([x, 0.0, z1])))
    for z in np.arange(z0, z1 + 0.5):
        segs.append((np.array([x0, 0.0, z]), np.array([x1, 0.0, z])))
    return segs


def _clip_segment(cam: _Camera, a: np.ndarray, b: np.ndarray, near: float = 0.05):
    """Clip a world segment to the part in front of the camera's near plane; None if wholly behind."""
    da, db = float(cam.depth(a)), float(cam.depth(b))
    if da < near and db < near:
        return None
    if da < near:
        a = a + (b - a) * (near - da) / (db - da)
    elif db < near:
        b = b + (a - b) * (near - db) / (da - db)
    return a, b


def iter_frames(joints, *, title: str = "", size: int = 480) -> Iterator[Image.Image]:
    """The frames of ``joints`` (T,22,3) as ``size`` x ``size`` RGB stick-figure images, rendered lazily.

    The arguments are checked at once (ValueError on a wrong shape, non-finite values or a size below 64
    pixels); each frame is drawn only when the iterator reaches it, so an encoder can consume them as they come.
    """
    j = _check_joints(joints)
    size = int(size)
    if size < MIN_SIZE:
        raise ValueError(f"size must be at least {MIN_SIZE}, got {size}")
    T = j.shape[0]

    # The static layer: background, title, grid, full trajectory (drawn once, copied per frame).
    base = Image.new("RGB", (size, size), BACKGROUND)
    draw = ImageDraw.Draw(base)
    title_bottom = _draw_title(draw, str(title), size)
    margin = max(8, size // 24)
    cam = _Camera(j, size, title_bottom, size - _PROGRESS_HEIGHT - 2, margin)
    grid_w = max(1, size // 480)
    for a, b in _grid_segments(j):
        seg = _clip_segment(cam, a, b)
        if seg is not None:
            p = cam.project(np.stack(seg))
            draw.line([tuple(p[0]), tuple(p[1])], fill=GRID_COLOUR, width=grid_w)
    traj = j[:, 0, :] * np.array([1.0, 0.0, 1.0])
    traj_px = [tuple(p) for p in cam.project(traj)]
    if T > 1:
        draw.line(traj_px, fill=TRAJECTORY_COLOUR, width=max(1, size // 240), joint="curve")
    # Redraw the title on top in case the grid ran under it.
    if title_bottom:
        draw.rectangle([0, 0, size, title_bottom - 1], fill=BACKGROUND)
        _draw_title(draw, str(title), size)

    bone_w = max(2, round(size / 120))
    dot_r = max(1.5, size / 200)
    px = cam.project(j)  # (T,22,2)
    depth = cam.depth(j)  # (T,22)

    def frame(t: int) -> Image.Image:
        im = base.copy()
        d = ImageDraw.Draw(im)
        if t > 0:
            d.line(traj_px[: t + 1], fill=TRAJECTORY_DONE_COLOUR, width=max(2, size // 160), joint="curve")
        order = sorted(range(len(KINEMATIC_CHAIN)), key=lambda c: -depth[t, list(KINEMATIC_CHAIN[c])].mean())
        for c in order:
            chain = KINEMATIC_CHAIN[c]
            d.line([tuple(px[t, k]) for k in chain], fill=CHAIN_COLOURS[c], width=bone_w, joint="curve")
        for k in np.argsort(-depth[t]):
            x, y = px[t, k]
            d.ellipse([x - dot_r, y - dot_r, x + dot_r, y + dot_r], fill=JOINT_COLOUR)
        bar = size * (t + 1) / T
        d.rectangle([0, size - _PROGRESS_HEIGHT, bar, size - 1], fill=PROGRESS_COLOUR)
        return im

    return map(frame, range(T))


def render_frames(joints, *, title: str = "", size: int = 480) -> list[Image.Image]:
    """Every frame of ``joints`` (T,22,3) as a ``size`` x ``size`` RGB stick-figure image (see ``iter_frames``)."""
    return list(iter_frames(joints, title=title, size=size))


def _check_fps(fps) -> float:
    fps = float(fps)
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    return fps


GIF_MAX_FPS = 50.0  # GIF delays are whole hundredths of a second, and browsers play 0-1 cs as 10 cs: >= 2 cs


def gif_timing(frames: int, fps: float) -> tuple[np.ndarray, list[int]]:
    """Where a GIF samples a motion of ``frames`` frames at ``fps``, and each GIF frame's delay in ms.

    Returns (source positions (M,) in fractional frame indices, delays (M,) in ms, multiples of 10). The delays
    are rounded cumulatively, so the loop lasts exactly ``frames / fps`` s (to the 10 ms a GIF can hold) at any
    fps, instead of every frame's 1000/fps being rounded alike (at 30 fps that played 4.93 s in 4.44 s). Above
    GIF_MAX_FPS the motion is resampled to at most that rate, so no delay is under 20 ms.
    """
    seconds = frames / fps
    m = frames if fps <= GIF_MAX_FPS else max(1, int(np.floor(seconds * GIF_MAX_FPS + 1e-9)))
    positions = np.arange(m) * (frames / m)  # uniform in time over the same span
    ends = np.round(np.arange(1, m + 1) * (100.0 * seconds / m)).astype(int)  # cumulative hundredths
    return positions, (10 * np.diff(ends, prepend=0)).tolist()


def resample(joints: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """joints (T,J,3) at fractional frame ``positions`` (M,): linear between neighbouring frames."""
    lo = np.clip(np.floor(positions).astype(int), 0, len(joints) - 1)
    hi = np.minimum(lo + 1, len(joints) - 1)
    w = (positions - lo)[:, None, None]
    return joints[lo] * (1.0 - w) + joints[hi] * w


def write_gif(path, joints, *, title: str = "", fps: float = 20.0, size: int = 480) -> Path:
    """Render ``joints`` and write a looping GIF to ``path`` atomically; return the path.

    The GIF lasts as long as the motion (:func:`gif_timing`): its delays, whole hundredths of a second, are
    rounded cumulatively, and motions above 50 fps are resampled to 50 fps or below.
    """
    fps = _check_fps(fps)
    joints = _check_joints(joints)
    positions, delays = gif_timing(len(joints), fps)
    frames = render_frames(resample(joints, positions), title=title, size=size)
    path = Path(path)
    with atomic_file(path) as f:
        frames[0].save(
            f, format="GIF", save_all=True, append_images=frames[1:],
            duration=delays, loop=0, disposal=1,
        )
    return path


class EncodeError(RuntimeError):
    """ffmpeg could not be found or failed to encode a video."""


# H.264 as browsers and QuickTime play it: 4:2:0 chroma (yuv420p), and the index at the front of the file
# so that playback can start before the download ends.
_H264_ARGS = ("-c:v", "libx264", "-preset", "medium", "-tune", "animation", "-crf", "20",
              "-pix_fmt", "yuv420p", "-movflags", "+faststart")


def write_mp4(path, joints, *, title: str = "", fps: float = 20.0, size: int = 480) -> Path:
    """Render ``joints`` and write an H.264 MP4 to ``path`` atomically; return the path.

    Encoded by the ffmpeg binary inside the imageio-ffmpeg wheel (no system ffmpeg needed), into a temporary
    file beside ``path`` that replaces it only once ffmpeg succeeded. yuv420p needs even dimensions, so an odd
    ``size`` is rounded up by one pixel. A fractional ``fps`` is kept exact (29.97 is stored as 2997/100).
    Raises ValueError on bad arguments and EncodeError when ffmpeg fails; ``path`` is then left as it was.
    """
    import imageio_ffmpeg  # here, so that the other exports work without it

    fps = _check_fps(fps)
    size = int(size)
    size += size % 2
    frames = iter_frames(joints, title=title, size=size)
    try:
        exe = imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError as e:
        raise EncodeError(str(e)) from e
    path = Path(path)
    fd, tmp = atomic_path(path)
    os.close(fd)
    rate = Fraction(fps).limit_denominator()
    cmd = [exe, "-y", "-v", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{size}x{size}",
           "-framerate", str(rate), "-i", "-", "-an", *_H264_ARGS, "-f", "mp4", tmp]
    try:
        with tempfile.TemporaryFile() as log:
            proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log)
            try:
                try:
                    for im in frames:
                        proc.stdin.write(im.tobytes())
                    proc.stdin.close()
                except BrokenPipeError:
                    pass  # ffmpeg stopped reading: its exit code and log say why
                code = proc.wait()
            finally:
                if proc.poll() is None:  # rendering failed or was interrupted: stop ffmpeg
                    proc.kill()
                    proc.wait()
            if code != 0:
                log.seek(0)
                message = log.read().decode(errors="replace").strip()[-2000:]
                raise EncodeError(f"ffmpeg failed (exit code {code}) writing {path}: {message}")
        publish(tmp, path)
    except BaseException:
        discard(tmp)
        raise
    return path
