"""Long takes (``lsgan generate --timeline``): one continuous motion from a list of ``prompt#frames`` segments.

Each segment is generated on its own at its length plus ``overlap`` frames (the last at its length), all in one
batch, so segment i is exactly what ``generate --prompts`` makes for the same ``prompt#length`` lines and seed.
Consecutive segments are cross-faded over the overlap, and the joints are recovered once from the joined features
and made rigid once (:func:`lsgan.generation.decoded_motion`).

Why join in feature space: HumanML3D features are root-relative. Channels 0-2 are the root's yaw velocity and
its linear velocity in the root's own heading frame, channel 3 its height, and the pose channels (positions,
rotations, velocities) are expressed in that heading frame too; ``recover_from_ric`` integrates the yaw and the
velocities from the first frame. A new segment's features therefore hold no absolute position or heading: joined
and integrated once, it starts where and facing where the previous one stands, with nothing to estimate. Blending
joints instead would need a rigid transform per segment (fitted from the last frames, noisy for turns) and a blend
of positions that may be metres apart. In the blend every channel is a convex combination of the two segments'
values, so the root's step and turn per frame at a seam never exceed the larger of the two motions' own.

Layout, for frames n_i and overlap v (n_i > v): segment i fills frames [s_i, s_i + n_i) of the result,
s_i = n_0 + ... + n_(i-1), total sum(n_i). Frames [s_i, s_i + v) for i > 0 blend the previous segment's v extra
frames into segment i's first v frames with the raised-cosine weight w_k = (1 - cos(pi (k+1) / (v+1))) / 2 on
segment i; every other frame is one segment's own features. ``overlap`` 0 is a hard cut (root still carried).
Blending two poses' joints shortens the bones between them, so each blended frame's joints are put back on the
bones the two segments have (their median lengths, weighted alike; :func:`lsgan.data.bones.on_skeleton`): a
VAE that decodes one skeleton (``rigid_output``) gives a timeline on that skeleton, seams included.
"""
from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lsgan.generation import Generation, Request, decoded_motion
from lsgan.data.bones import on_skeleton, skeleton_lengths

DEFAULT_OVERLAP = 10
JOINS = ("crossfade", "continue")
MIN_FRAMES = 4  # what ``generate`` asks of a motion
FORMAT = "'prompt#frames', e.g. 'walk forward#80'"


class TimelineError(ValueError):
    """A timeline that cannot be read; ``inline``: it was given on the command line, not in a file."""

    def __init__(self, message: str, inline: bool) -> None:
        super().__init__(message)
        self.inline = inline


@dataclass(frozen=True)
class Segment:
    text: str
    frames: int
    where: str  # where it was read, for messages: "FILE: line 3" or "--timeline: item 2"


def parse_timeline(value: str) -> tuple[list[Segment], str | None]:
    """(segments, the file read or None) of ``--timeline VALUE``.

    VALUE naming an existing file is read as that file: one ``prompt#frames`` per line, no blank lines. Any other
    VALUE holding '#' is the timeline itself, segments separated by ';' (a trailing ';' is allowed); anything else
    is a file that does not exist.
    """
    path = Path(value)
    if os.path.isfile(value):  # not Path.is_file: it raises on a name too long for the filesystem
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except UnicodeDecodeError:
            raise TimelineError(f"{value}: not a UTF-8 text file", inline=False) from None
        return _segments(lines, [f"{value}: line {n}" for n in range(1, len(lines) + 1)], value, False), value
    if "#" not in value:
        raise TimelineError(f"{value}: no such timeline file (an inline timeline holds '#': {FORMAT}; ...)",
                            inline=False)
    items = value.strip()
    items = (items[:-1] if items.endswith(";") else items).split(";")
    return _segments(items, [f"--timeline: item {n}" for n in range(1, len(items) + 1)], "--timeline", True), None


def _segments(items: list[str], where: list[str], name: str, inline: bool) -> list[Segment]:
    out = []
    for item, at in zip(items, where):
        item = item.strip()
        text, hash_, frames = item.rpartition("#")
        problem = ("is blank" if not item else "has no '#frames'" if not hash_ else
                   "has no prompt before '#'" if not text.strip() else
                   f"'{frames.strip()}' is not a whole number of frames" if not frames.strip().isdigit() else None)
        if problem:
            raise TimelineError(f"{at} {problem} (each segment is {FORMAT})", inline)
        out.append(Segment(text.strip(), int(frames), at))
    if not out:
        raise TimelineError(f"{name}: no segments (each is {FORMAT})", inline)
    return out


def check_segments(segments: list[Segment], overlap: int, max_frames: int) -> None:
    """ValueError naming the segment when one is shorter than the overlap (or 4 frames) or, with the overlap, longer
    than the model decodes."""
    if overlap < 0:
        raise ValueError(f"overlap must be >= 0 frames, got {overlap}")
    least = max(MIN_FRAMES, overlap + 1)
    for i, s in enumerate(segments):
        if s.frames < least:
            raise ValueError(f"{s.where}: {s.frames} frames; a segment needs at least {least} "
                             f"(4, and more than the overlap of {overlap})")
        extra = overlap if i < len(segments) - 1 else 0
        if s.frames + extra > max_frames:
            raise ValueError(f"{s.where}: {s.frames} frames{f' + {extra} of overlap' if extra else ''} is more than "
                             f"this model decodes at once ({max_frames}); split it into two segments")


def segment_requests(segments: list[Segment], overlap: int) -> list[Request]:
    """What is generated: each segment at its length plus the overlap into the next (the last at its length)."""
    last = len(segments) - 1
    return [Request(text=s.text, frames=s.frames + (overlap if i < last else 0)) for i, s in enumerate(segments)]


def crossfade(overlap: int) -> np.ndarray:
    """(overlap,) weights of the incoming segment over a seam: raised cosine, strictly between 0 and 1."""
    k = np.arange(1, overlap + 1, dtype=np.float64)
    return (1.0 - np.cos(math.pi * k / (overlap + 1))) / 2.0


def join_features(parts: list[np.ndarray], frames: list[int], overlap: int) -> np.ndarray:
    """One (sum(frames), 263) feature sequence from segments generated as :func:`segment_requests` asks."""
    want = [n + (overlap if i < len(frames) - 1 else 0) for i, n in enumerate(frames)]
    if [len(p) for p in parts] != want:
        raise ValueError(f"segments of {[len(p) for p in parts]} frames; expected {want}")
    w = crossfade(overlap)[:, None]
    out = []
    for i, (part, n) in enumerate(zip(parts, frames)):
        own = np.array(part[:n], dtype=np.float64)
        if i > 0 and overlap:
            before = np.asarray(parts[i - 1], np.float64)
            tail = before[frames[i - 1] : frames[i - 1] + overlap]
            blend = (1.0 - w) * tail + w * own[:overlap]
            bones = (1.0 - w) * skeleton_lengths(before) + w * skeleton_lengths(own)  # (overlap, 21)
            own[:overlap] = on_skeleton(blend, bones)
        out.append(own)
    return np.concatenate(out).astype(np.float32)


def join_generation(result: Generation, segments: list[Segment], overlap: int, source: str | None) -> Generation:
    """``result`` (one motion per segment, in order) as one joined motion, with the timeline for the manifest."""
    frames = [s.frames for s in segments]
    features = join_features([m.features for m in result.motions], frames, overlap)
    motion, starts = take_motion(segments, features, result.fix_feet)
    timeline = {
        "source": str(source) if source else "inline",
        "overlap": overlap,
        "join": "features cross-faded over the overlap (raised cosine), root integrated once (lsgan.timeline)",
        "segments": [{"text": s.text, "frames": s.frames, "start": int(a), "generated_frames": len(m.features)}
                     for s, a, m in zip(segments, starts, result.motions)],
    }
    return dataclasses.replace(result, motions=[motion], timeline=timeline)


def take_motion(segments: list[Segment], features: np.ndarray, fix_feet: bool):
    """The take's one motion of record from its joined features (joints recovered and made rigid once), and each
    segment's first frame in it."""
    text = "; ".join(s.text for s in segments)
    motion = decoded_motion(Request(text=text, frames=len(features)), 0, features, fix_feet)
    return motion, np.concatenate([[0], np.cumsum([s.frames for s in segments])[:-1]]).tolist()


def timeline_motion(segments: list[Segment], overlap: int, run: Callable[[list[Request]], Generation],
                    max_frames: int, source: str | None = None) -> Generation:
    """Check the segments, generate them with ``run`` (requests -> one motion each) and join them."""
    check_segments(segments, overlap, max_frames)
    return join_generation(run(segment_requests(segments, overlap)), segments, overlap, source)


def generate_timeline(gan: str | os.PathLike, vae: str | os.PathLike | None, segments: list[Segment], *,
                      overlap: int = DEFAULT_OVERLAP, source: str | None = None, seed: int = 0,
                      device: str = "auto", text_encoder_path: str | None = None, batch_size: int = 256,
                      steps: int | None = None, guidance: float | None = None, fix_feet: bool = False,
                      join: str = "crossfade") -> Generation:
    """One motion of sum(frames) from ``segments``, by the generator's torch checkpoints (an ONNX export's:
    :func:`lsgan.deploy.runtime.generate_timeline_onnx`). Deterministic under ``seed``, like ``generate``;
    ``fix_feet`` as there. ``join``: "crossfade" (the module docstring) or "continue" (:func:`continued_motion`;
    ``overlap`` is not used)."""
    from lsgan.generate import generate_loaded, load_models

    if join not in JOINS:
        raise ValueError(f"join must be one of {', '.join(JOINS)}, not {join!r}")
    loaded = load_models(gan, vae, device=device, text_encoder_path=text_encoder_path)
    if join == "continue":
        return continued_motion(loaded, segments, seed=seed, batch_size=batch_size, steps=steps, guidance=guidance,
                                fix_feet=fix_feet, source=source)
    run = lambda r: generate_loaded(loaded, r, seed=seed, batch_size=batch_size, steps=steps,  # noqa: E731
                                    guidance=guidance, fix_feet=fix_feet)
    return timeline_motion(segments, overlap, run, loaded.max_frames, source)


def continued_motion(loaded, segments: list[Segment], *, seed: int, source: str | None = None, fix_feet: bool = False,
                     **options) -> Generation:
    """``--join continue``: segment 0 as ``generate`` makes it (seed ``seed``); each later segment i generated from
    seed ``seed + i`` at its length plus the 5 frames it shares with the motion so far, optimised and closed to
    start with that motion's last 5 frames (:func:`lsgan.constraints.continuing`, in the root frame the features
    have there), and its features put in place of those frames. The features are then one sequence, as a
    cross-faded timeline's: joints are recovered and made rigid once."""
    from lsgan.constraints import CONTINUE_FRAMES, continuing, root_frame
    from lsgan.data.features import recover_from_ric
    from lsgan.generate import generate_loaded
    from lsgan.motion.rigid import make_rigid

    check_continued(segments, loaded.max_frames)
    k = CONTINUE_FRAMES
    first = generate_loaded(loaded, [Request(text=segments[0].text, frames=segments[0].frames)], seed=seed, **options)
    feats, reports, timings = first.motions[0].features, [None], dict(first.timings_s)
    for i, seg in enumerate(segments[1:], 1):
        where = root_frame(feats, len(feats) - k)
        joints = make_rigid(recover_from_ric(feats))[-k:]
        constraints, _ = continuing(joints, seg.frames + k, overlap=k, frame=where)
        part = generate_loaded(loaded, [Request(text=seg.text, frames=seg.frames + k)], seed=seed + i,
                               constraints=constraints, **options)
        feats = np.concatenate([feats[: len(feats) - k], part.motions[0].features])
        reports.append(part.motions[0].control)
        timings = {name: timings.get(name, 0.0) + t for name, t in part.timings_s.items()}
    motion, starts = take_motion(segments, feats, fix_feet)
    timeline = {
        "source": str(source) if source else "inline",
        "join": f"continue: each segment starts with the motion so far's last {k} frames (lsgan.constraints."
                "continuing), its features in place of them; root integrated once (lsgan.timeline). A segment's "
                "control figures are measured on it as generated, before the take is made rigid as one (they differ "
                "by millimetres)",
        "segments": [{"text": s.text, "frames": s.frames, "start": int(a), "seed": seed + i,
                      **({"control": r} if r is not None else {})}
                     for i, (s, a, r) in enumerate(zip(segments, starts, reports))],
    }
    return dataclasses.replace(first, motions=[motion], timeline=timeline, timings_s=timings, control=None)


def check_continued(segments: list[Segment], max_frames: int) -> None:
    """ValueError naming the segment that ``--join continue`` cannot make: too short to hold more than the shared
    frames, or with them longer than the model decodes."""
    from lsgan.constraints import CONTINUE_FRAMES

    for i, s in enumerate(segments):
        extra = CONTINUE_FRAMES if i else 0
        least = max(MIN_FRAMES, CONTINUE_FRAMES) if len(segments) > 1 else MIN_FRAMES
        if s.frames < least or s.frames + extra > max_frames:
            raise ValueError(f"{s.where}: {s.frames} frames{f' + {extra} shared' if extra else ''}; a segment "
                             f"needs {least} to {max_frames - extra} with --join continue (the next segment "
                             f"starts with the last {CONTINUE_FRAMES} frames of the take)")
