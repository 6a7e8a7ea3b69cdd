"""A general BVH reader and vectorised forward kinematics.

BVH stores a joint hierarchy (offsets in the parent's frame, a channel list per joint) and one line of
channel values per frame. Every joint may carry its own channel order and position channels; ``End Site``
blocks only close a chain and are not joints. The reader parses the MOTION block in one numpy call on the
whole text, so a dataset of thousands of files loads in seconds. A UTF-8 byte-order mark and CR or CRLF
line ends are read as plain text. The header's frame count and frame time are checked before anything of
their size is allocated (:data:`MAX_JOINT_FRAMES`, :data:`MIN_FRAME_TIME`, :data:`MAX_FRAME_TIME`).
"""
from __future__ import annotations

import re
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lsgan.data.clip import ClipError

POSITION_CHANNELS = ("Xposition", "Yposition", "Zposition")
ROTATION_CHANNELS = ("Xrotation", "Yrotation", "Zrotation")
_CANONICAL = {c.lower(): c for c in POSITION_CHANNELS + ROTATION_CHANNELS}
MIN_FRAME_TIME, MAX_FRAME_TIME = 1e-4, 1.0
REST_FRAME_TIME = 1.0 / 30.0  # the frame time of a rig read with no frames (never used by retargeting)
"""Frame times read, in seconds: 10,000 to 1 frames per second. Mocap records at 24-480 fps and keyframed
exports at 1 fps or more; outside the range the header is damaged (resampling 'Frame Time: 100000' to 20 fps
would make 2,000,000 frames of each one)."""

MAX_JOINT_FRAMES = 10_000_000
"""Most frames x joints a file may declare: forward kinematics holds about 200 bytes per joint and frame
(rotations and positions, local and global, in float64), so about 2 GB. The largest real clip here holds
38,657 (CMU 131_02: 1,247 frames of 31 joints); an hour at 120 fps of 22 joints (Bandai's), 9,504,000."""

MAX_VALUE_BYTES = 32
"""Most text one MOTION value may take with its separator when a ``.bvh.gz`` is inflated: a float64 prints in at
most 24 characters ('-1.2345678901234567e-308'), exporters write 6-12; the rest is room for padding and CRLF."""

MAX_HEADER_BYTES = 16 << 20
"""Most inflated text before the MOTION header of a ``.bvh.gz`` (a hierarchy of 1,000 joints takes about 150 KB)."""

MOTION_SLACK = 1 << 20
"""Inflated text allowed past the values the header declares (trailing blank lines, notes)."""

_PIECE = 1 << 20  # bytes inflated at a time
_SNIFF = 65536  # where the HIERARCHY keyword must appear

_TOKEN = re.compile(r"[{}]|[^\s{}]+")
_MOTION = re.compile(
    rb"^[ \t]*MOTION[ \t]*\n\s*Frames:[ \t]*(\S+)\s*Frame[ \t]+Time:[ \t]*(\S+)[ \t]*(?:\n|$)", re.MULTILINE,
)


@dataclass(frozen=True)
class Bvh:
    """One parsed BVH file.

    ``names``/``parents``/``offsets`` (J,3) describe the joints in file order (a parent always precedes its
    children; roots have parent -1). ``channels[j]`` lists joint j's channel names in file order and
    ``motion`` (F,C) holds the values, C = total channel count, joints' channels consecutive in file order.
    ``end_sites`` keeps each End Site's joint and offset, so a writer can reproduce the hierarchy.
    """

    path: str
    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    frame_time: float
    motion: np.ndarray
    end_sites: tuple[tuple[int, tuple[float, float, float]], ...] = ()  # (joint, offset) of each End Site

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def fps(self) -> float:
        """Frames per second from the frame time, snapped to an integer when the file rounded 1/fps."""
        return fps_from_frame_time(self.frame_time)

    @property
    def channel_starts(self) -> np.ndarray:
        """Column of ``motion`` where each joint's channels begin, (J,)."""
        counts = np.array([len(c) for c in self.channels], dtype=np.int64)
        return np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)


def fps_from_frame_time(frame_time: float) -> float:
    """1/frame_time, snapped to the nearest integer when within 1e-4 relative (0.0333333 -> 30, 0.0083333 -> 120).

    Files print the frame time with a few digits; without the snap, 120 fps reads as 120.0005 and the
    exact integer-stride downsampling to 20 fps is lost. 29.97 fps stays 29.97.
    """
    fps = 1.0 / frame_time
    nearest = round(fps)
    if nearest > 0 and abs(fps - nearest) <= 1e-4 * fps:
        return float(nearest)
    return fps


def _read_bytes(path: str | Path) -> bytes:
    """File contents, gunzipped when the file starts with the gzip magic number (whatever its name), without a
    UTF-8 byte-order mark and with every line ending in LF (CR-only and CRLF files read as LF ones)."""
    try:
        data = Path(path).read_bytes()
        if data[:2] == b"\x1f\x8b":
            data = _gunzip(path, data)
    except (OSError, EOFError, zlib.error) as exc:
        raise ClipError(f"{path}: cannot read: {exc}") from exc
    data = data.removeprefix(b"\xef\xbb\xbf")
    return data.replace(b"\r\n", b"\n").replace(b"\r", b"\n") if b"\r" in data else data


def _gunzip(path: str | Path, data: bytes) -> bytes:
    """Inflate gzip ``data`` (one member or several) a piece at a time, refusing (ClipError) as soon as it holds
    more text than its MOTION header can account for (:func:`_text_limit`): a 3 MB file of spaces would otherwise
    take 3 GB before any check. Stops early when the text already shows a parse error (no BVH, a bad header)."""
    out, limit = bytearray(), None
    inflater, rest = zlib.decompressobj(wbits=31), data  # 31: a gzip header and trailer (CRC checked)
    while True:
        piece = inflater.decompress(rest, _PIECE)
        rest = inflater.unconsumed_tail
        out += piece
        limit = _text_limit(out) if limit is None else limit
        if limit == 0:
            return bytes(out)
        if len(out) > (limit or MAX_HEADER_BYTES):
            why = "more than the frames and channels of its MOTION header can take" if limit else \
                "with no MOTION header in them"
            raise ClipError(f"{path}: refused: inflates to more than {limit or MAX_HEADER_BYTES:,} bytes, {why} "
                            "(a gzip bomb?)")
        if inflater.eof:
            rest = inflater.unused_data.lstrip(b"\0")  # gzip's own reader skips zero padding between members
            if not rest:
                return bytes(out)
            inflater = zlib.decompressobj(wbits=31)
        elif not piece and not rest:
            raise EOFError("compressed file ended before the end-of-stream marker was reached")


def _text_limit(text: bytes) -> int | None:
    """How many bytes a BVH that starts with ``text`` may take: the header, then MAX_VALUE_BYTES per value its
    frames x channels declare (at most MAX_JOINT_FRAMES x 6) plus MOTION_SLACK; None while the MOTION header is not
    in yet; 0 when ``text`` already fails to parse (no HIERARCHY, a frame count that is not a positive number)."""
    if len(text) > _SNIFF and re.search(rb"^[ \t]*HIERARCHY\b", text[:_SNIFF], re.MULTILINE) is None:
        return 0
    if b"MOTION" not in text:  # a fast scan first: this runs on every piece until the header is in
        return None
    lf = text.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    motion = _MOTION.search(lf)
    if motion is None:
        return None
    try:
        frames = int(motion.group(1))
    except ValueError:
        return 0
    channels = sum(min(int(n), 6) for n in re.findall(rb"CHANNELS\s+(\d+)", lf[:motion.start()], re.I))
    values = min(max(frames, 0) * channels, MAX_JOINT_FRAMES * 6)
    return 0 if values == 0 else len(text) + values * MAX_VALUE_BYTES + MOTION_SLACK


def _parse_hierarchy(path: str, header: str) -> tuple[list[str], list[int], list[list[float]], list[tuple[str, ...]],
                                                     list[tuple[int, list[float]]]]:
    """Joint names, parents, offsets, channel lists and End Sites from the text between HIERARCHY and MOTION."""
    h = _Hierarchy(path)
    for lineno, line in enumerate(header.splitlines(), start=1):
        h.lineno, tokens = lineno, _TOKEN.findall(line)
        i = 0
        while i < len(tokens):
            i = h.read(tokens, i)
    if h.stack:
        raise ClipError(f"{path}: hierarchy has {len(h.stack)} unclosed '{{'")
    if not h.names:
        raise ClipError(f"{path}: hierarchy declares no joints")
    return h.names, h.parents, h.offsets, h.channels, h.end_sites


MAX_JOINTS = 4096  # joints in one hierarchy: character-creator rigs with every twist and finger bone have a few hundred


class _Hierarchy:
    """What a HIERARCHY section has declared so far, read one keyword at a time (one method per keyword)."""

    def __init__(self, path: str) -> None:
        self.path, self.lineno = path, 0
        self.names: list[str] = []
        self.parents: list[int] = []
        self.offsets: list[list[float]] = []
        self.channels: list[tuple[str, ...]] = []
        self.end_sites: list[tuple[int, list[float]]] = []
        self.stack: list[int] = []  # joint index per open brace; -1 - k for End Site k
        self.pending: int | None = None  # a joint or End Site declared, its '{' not yet read

    def fail(self, problem: str) -> ClipError:
        return ClipError(f"{self.path}: {problem} (hierarchy line {self.lineno})")

    def read(self, tokens: list[str], i: int) -> int:
        """Read the keyword ``tokens[i]`` and what it takes; returns the index of the next keyword."""
        tok = tokens[i]
        key = tok.upper()
        if key in ("ROOT", "JOINT"):
            return self.joint(tok, tokens, i + 1)
        if key == "END":
            return self.end_site(tokens, i)
        if tok == "{":
            if self.pending is None:
                raise self.fail("'{' without a ROOT, JOINT or End Site")
            self.stack.append(self.pending)
            self.pending = None
            return i + 1
        if tok == "}":
            if not self.stack:
                raise self.fail("unbalanced '}'")
            self.stack.pop()
            return i + 1
        if key == "OFFSET":
            return self.offset(tokens, i)
        if key == "CHANNELS":
            return self.channel_list(tokens, i)
        raise self.fail(f"unexpected {tok!r}")

    def joint(self, tok: str, tokens: list[str], i: int) -> int:
        """``ROOT name`` or ``JOINT name`` (a name may hold spaces): up to its '{'."""
        rest = []
        while i < len(tokens) and tokens[i] != "{":
            rest.append(tokens[i])
            i += 1
        if not rest:
            raise self.fail(f"{tok} without a name")
        if tok.upper() == "JOINT" and not self.stack:
            raise self.fail("JOINT outside any ROOT")
        if self.stack and self.stack[-1] < 0:
            raise self.fail("JOINT inside an End Site")
        if len(self.names) >= MAX_JOINTS:
            raise self.fail(f"more than {MAX_JOINTS:,} joints: not a character's skeleton")
        self.names.append(" ".join(rest))
        self.parents.append(self.stack[-1] if self.stack else -1)
        self.offsets.append([0.0, 0.0, 0.0])
        self.channels.append(())
        self.pending = len(self.names) - 1
        return i

    def end_site(self, tokens: list[str], i: int) -> int:
        if i + 1 < len(tokens) and tokens[i + 1].upper() == "SITE":
            i += 1
        if not self.stack:
            raise self.fail("End Site outside any joint")
        if self.stack[-1] < 0:
            raise self.fail("End Site inside an End Site")
        self.end_sites.append((self.stack[-1], [0.0, 0.0, 0.0]))
        self.pending = -len(self.end_sites)
        return i + 1

    def offset(self, tokens: list[str], i: int) -> int:
        values = tokens[i + 1 : i + 4]
        try:
            vec = [float(v) for v in values]
        except ValueError:
            vec = []
        if len(vec) != 3:
            raise self.fail(f"OFFSET needs 3 numbers, got {' '.join(values)!r}")
        if not self.stack:
            raise self.fail("OFFSET outside any joint")
        top = self.stack[-1]
        if top >= 0:
            self.offsets[top] = vec
        else:
            self.end_sites[-1 - top] = (self.end_sites[-1 - top][0], vec)
        return i + 4

    def channel_list(self, tokens: list[str], i: int) -> int:
        if not self.stack or self.stack[-1] < 0:
            raise self.fail("CHANNELS outside a joint")
        try:
            count = int(tokens[i + 1])
        except (IndexError, ValueError):
            raise self.fail("CHANNELS without a count") from None
        given = tokens[i + 2 : i + 2 + count]
        if len(given) != count:
            raise self.fail(f"CHANNELS {count} lists {len(given)} names")
        canon = []
        for name in given:
            if name.lower() not in _CANONICAL:
                raise self.fail(f"unknown channel {name!r} of joint {self.names[self.stack[-1]]!r}")
            canon.append(_CANONICAL[name.lower()])
        if len(set(canon)) != len(canon):
            raise self.fail(f"repeated channel in {' '.join(given)}")
        self.channels[self.stack[-1]] = tuple(canon)
        return i + 2 + count


def _check_header(path: str, frames: int, frame_time: float, channels: int, joints: int, body: int,
                  rest_only: bool = False) -> None:
    """Refuse a MOTION header that cannot be right before its frames are parsed or allocated: ``body`` bytes
    of text hold at most (body + 1) // 2 values (a digit and a separator each). ``rest_only``: zero frames is
    fine (a rig's file may carry its hierarchy alone)."""
    if frames < 0 or (frames == 0 and not rest_only):
        raise ClipError(f"{path}: {'zero' if frames == 0 else 'a negative number of'} frames")
    if not MIN_FRAME_TIME <= frame_time <= MAX_FRAME_TIME:  # also NaN
        raise ClipError(f"{path}: frame time {frame_time:g} s is outside {MIN_FRAME_TIME:g}-{MAX_FRAME_TIME:g} s "
                        "(10,000 to 1 frames per second): a damaged MOTION header")
    if channels == 0:
        raise ClipError(f"{path}: no joint has channels")
    if frames * channels > (body + 1) // 2:
        raise ClipError(f"{path}: header says {frames:,} frames of {channels} channels, more values than the "
                        f"{body:,} bytes after it can hold: truncated file or a wrong 'Frames:' line")
    if frames * joints > MAX_JOINT_FRAMES:
        raise ClipError(f"{path}: {frames:,} frames of {joints} joints is more than MAX_JOINT_FRAMES "
                        f"({MAX_JOINT_FRAMES:,}); split the clip")


def _motion_values(path: str, body: bytes) -> np.ndarray:
    """The numbers of a MOTION block, flat; none for a blank one (numpy reads whitespace alone as [-1])."""
    if not body.strip():
        return np.zeros(0)
    try:
        with warnings.catch_warnings():  # numpy < 2 warns (and stops early) where numpy 2 raises
            warnings.simplefilter("error", DeprecationWarning)
            return np.fromstring(body.decode("latin-1"), dtype=np.float64, sep=" ")
    except (ValueError, DeprecationWarning) as exc:
        raise ClipError(f"{path}: MOTION block holds something other than numbers") from exc


def read_bvh(path: str | Path, *, rest_only: bool = False) -> Bvh:
    """Parse a ``.bvh`` or gzip-compressed ``.bvh.gz`` file; any problem raises :class:`ClipError` naming the file.
    ``rest_only`` (a rig, whose motion is optional): ``Frames: 0``, or no MOTION block at all, reads as a skeleton
    with no frames (whose frame time, never used, may be anything)."""
    path = str(path)
    data = _read_bytes(path)
    start = re.search(rb"^[ \t]*HIERARCHY\b", data[:65536], re.MULTILINE)
    if start is None:
        raise ClipError(f"{path}: not a BVH file (no HIERARCHY keyword)")
    motion = _MOTION.search(data, start.end())
    if motion is None and not (rest_only and not re.search(rb"^[ \t]*MOTION\b", data, re.MULTILINE)):
        raise ClipError(f"{path}: no MOTION block with 'Frames:' and 'Frame Time:' lines")
    try:
        header = data[start.end() : motion.start() if motion else len(data)].decode("utf-8", errors="replace")
        num_frames = int(motion.group(1)) if motion else 0
        frame_time = float(motion.group(2)) if motion else REST_FRAME_TIME
    except ValueError as exc:
        raise ClipError(f"{path}: bad MOTION header: {exc}") from exc
    names, parents, offsets, channels, end_sites = _parse_hierarchy(path, header)
    num_channels = sum(len(c) for c in channels)
    body = data[motion.end() :] if motion else b""
    if rest_only and num_frames == 0:
        frame_time = frame_time if MIN_FRAME_TIME <= frame_time <= MAX_FRAME_TIME else REST_FRAME_TIME
    _check_header(path, num_frames, frame_time, num_channels, len(names), len(body), rest_only)
    values = _motion_values(path, body)
    if values.size % num_channels:
        raise ClipError(
            f"{path}: truncated MOTION block: {values.size} values are not a multiple of the "
            f"{num_channels} channels"
        )
    found = values.size // num_channels
    if found != num_frames:
        raise ClipError(f"{path}: frame count mismatch: header says {num_frames} frames, the data holds {found}")
    if not np.isfinite(values).all():
        raise ClipError(f"{path}: MOTION block holds NaN or infinite values")
    return Bvh(
        path=path,
        names=tuple(names),
        parents=np.array(parents, dtype=np.int64),
        offsets=np.array(offsets, dtype=np.float64).reshape(-1, 3),
        channels=tuple(channels),
        frame_time=frame_time,
        motion=values.reshape(num_frames, num_channels),
        end_sites=tuple((j, (v[0], v[1], v[2])) for j, v in end_sites),
    )


def axis_rotation(axis: str, degrees: np.ndarray) -> np.ndarray:
    """Right-handed rotation matrices about 'X', 'Y' or 'Z' for angles in degrees, (...,) -> (..., 3, 3)."""
    a = np.deg2rad(np.asarray(degrees, dtype=np.float64))
    c, s = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    if axis == "X":
        rows = ((one, zero, zero), (zero, c, -s), (zero, s, c))
    elif axis == "Y":
        rows = ((c, zero, s), (zero, one, zero), (-s, zero, c))
    elif axis == "Z":
        rows = ((c, -s, zero), (s, c, zero), (zero, zero, one))
    else:
        raise ValueError(f"axis must be X, Y or Z, got {axis!r}")
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def local_transforms(bvh: Bvh) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame local rotation (F,J,3,3) and translation (F,J,3) of every joint.

    Rotation channels compose in file order, R = R_c1 @ R_c2 @ R_c3 (BVH's intrinsic convention);
    a position channel replaces that component of the joint's offset.
    """
    f, j = bvh.num_frames, len(bvh.names)
    rotations = np.broadcast_to(np.eye(3), (f, j, 3, 3)).copy()
    translations = np.broadcast_to(bvh.offsets, (f, j, 3)).copy()
    starts = bvh.channel_starts
    groups: dict[tuple[str, ...], tuple[list[int], list[list[int]]]] = {}
    for k, chans in enumerate(bvh.channels):
        rot_cols = []
        for c, name in enumerate(chans):
            col = int(starts[k]) + c
            if name in POSITION_CHANNELS:
                translations[:, k, POSITION_CHANNELS.index(name)] = bvh.motion[:, col]
            else:
                rot_cols.append(col)
        if rot_cols:
            order = tuple(name[0] for name in chans if name in ROTATION_CHANNELS)
            joints, cols = groups.setdefault(order, ([], []))
            joints.append(k)
            cols.append(rot_cols)
    for order, (joints, cols) in groups.items():
        angles = bvh.motion[:, np.array(cols)]  # (F, G, len(order))
        r = axis_rotation(order[0], angles[..., 0])
        for n in range(1, len(order)):
            r = r @ axis_rotation(order[n], angles[..., n])
        rotations[:, joints] = r
    return rotations, translations


def forward_kinematics(bvh: Bvh) -> np.ndarray:
    """Global joint positions (F,J,3) in file units: G_j = G_parent @ R_j, p_j = p_parent + G_parent @ t_j."""
    rotations, translations = local_transforms(bvh)
    f, j = bvh.num_frames, len(bvh.names)
    global_rot = np.empty((f, j, 3, 3))
    positions = np.empty((f, j, 3))
    for k, parent in enumerate(bvh.parents):
        if parent < 0:
            global_rot[:, k] = rotations[:, k]
            positions[:, k] = translations[:, k]
        else:
            g = global_rot[:, parent]
            positions[:, k] = positions[:, parent] + np.einsum("fij,fj->fi", g, translations[:, k])
            global_rot[:, k] = g @ rotations[:, k]
    return positions
