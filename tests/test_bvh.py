"""BVH reader, forward kinematics, joint maps and the BVH source, on synthetic files and on real mocap."""
from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lsgan.data.bvh import Bvh, forward_kinematics, read_bvh
from lsgan.data.captions import bandai_captions
from lsgan.data.clip import ClipError, swap_left_right
from lsgan.data.joint_maps import PRESETS, apply_joint_map, load_joint_map
from lsgan.data.resample import resample
from lsgan.data.skeleton import BONE_LENGTHS, JOINT_NAMES, PARENTS, RAW_OFFSETS, bone_lengths
from lsgan.data.sources.bvh import BvhSource, bandai_labels, clip_name

# A small hierarchy: mixed rotation orders, a 6-channel non-root joint whose channels interleave
# rotations and positions, a 3-channel leaf, End Sites.
SMALL_HIERARCHY = """HIERARCHY
ROOT Root
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT A
  {
    OFFSET 0 1 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT B
    {
      OFFSET 1 0 0
      CHANNELS 6 Yrotation Xposition Yposition Zposition Xrotation Zrotation
      End Site
      {
        OFFSET 0 0 1
      }
    }
  }
  JOINT C
  {
    OFFSET -1 0 0
    CHANNELS 3 Xrotation Zrotation Yrotation
    End Site
    {
      OFFSET 0 -1 0
    }
  }
}
"""
SMALL_CHANNELS = 6 + 3 + 6 + 3


def bvh_text(hierarchy: str, motion: np.ndarray, frame_time: float = 1 / 30, frames: int | None = None) -> str:
    lines = [" ".join(f"{v:.6f}" for v in row) for row in np.atleast_2d(motion)]
    count = len(lines) if frames is None else frames
    return hierarchy + f"MOTION\nFrames: {count}\nFrame Time: {frame_time:.7f}\n" + "\n".join(lines) + "\n"


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def small_frame(**values: float) -> np.ndarray:
    """One frame of the small hierarchy, zero rotations, offsets in the position channels, overrides by name."""
    cols = {
        "root_x": 0, "root_y": 1, "root_z": 2, "root_rz": 3, "root_rx": 4, "root_ry": 5,
        "a_rz": 6, "a_ry": 7, "a_rx": 8,
        "b_ry": 9, "b_x": 10, "b_y": 11, "b_z": 12, "b_rx": 13, "b_rz": 14,
        "c_rx": 15, "c_rz": 16, "c_ry": 17,
    }
    row = np.zeros(SMALL_CHANNELS)
    row[cols["b_x"]] = 1.0  # B's position channels carry its offset by default
    for key, v in values.items():
        row[cols[key]] = v
    return row


def scipy_fk(bvh: Bvh) -> np.ndarray:
    """Independent FK oracle: scipy's intrinsic Euler rotations (upper-case order), joint by joint."""
    f, j = bvh.num_frames, len(bvh.names)
    rot = [None] * j
    pos = np.zeros((f, j, 3))
    col = 0
    for k in range(j):
        chans = bvh.channels[k]
        values = bvh.motion[:, col : col + len(chans)]
        col += len(chans)
        t = np.tile(bvh.offsets[k], (f, 1))
        order, angles = "", []
        for c, name in enumerate(chans):
            if name.endswith("position"):
                t[:, "XYZ".index(name[0])] = values[:, c]
            else:
                order += name[0]
                angles.append(values[:, c])
        local = Rotation.from_euler(order, np.stack(angles, -1), degrees=True) if order else Rotation.identity(f)
        p = bvh.parents[k]
        if p < 0:
            rot[k], pos[:, k] = local, t
        else:
            pos[:, k] = pos[:, p] + rot[p].apply(t)
            rot[k] = rot[p] * local
    return pos


# ---------------------------------------------------------------- reader and FK, synthetic


def test_read_small_hierarchy(tmp_path):
    path = write(tmp_path / "small.bvh", bvh_text(SMALL_HIERARCHY, np.stack([small_frame()] * 4)))
    bvh = read_bvh(path)
    assert bvh.names == ("Root", "A", "B", "C")  # End Sites are not joints
    assert bvh.parents.tolist() == [-1, 0, 1, 0]
    np.testing.assert_array_equal(bvh.offsets, [[0, 0, 0], [0, 1, 0], [1, 0, 0], [-1, 0, 0]])
    assert bvh.channels[2] == ("Yrotation", "Xposition", "Yposition", "Zposition", "Xrotation", "Zrotation")
    assert bvh.motion.shape == (4, SMALL_CHANNELS)
    assert bvh.fps == 30.0
    assert bvh.channel_starts.tolist() == [0, 6, 9, 15]


def test_fk_hand_computed(tmp_path):
    frames = np.stack([
        small_frame(),                                  # rest pose
        small_frame(a_rz=90),                           # A turns 90 deg about z: B swings from +x to +y
        small_frame(a_rz=90, b_x=2),                    # B's position channel replaces its offset
        small_frame(root_x=5, root_y=1, root_ry=90),    # root moves; +90 about y sends +x to -z
        small_frame(c_rx=90, b_rz=45),                  # leaf rotations move no joint positions
    ])
    bvh = read_bvh(write(tmp_path / "hand.bvh", bvh_text(SMALL_HIERARCHY, frames)))
    p = forward_kinematics(bvh)
    np.testing.assert_allclose(p[0], [[0, 0, 0], [0, 1, 0], [1, 1, 0], [-1, 0, 0]], atol=1e-9)
    np.testing.assert_allclose(p[1, 2], [0, 2, 0], atol=1e-9)
    np.testing.assert_allclose(p[2, 2], [0, 3, 0], atol=1e-9)
    np.testing.assert_allclose(p[3], [[5, 1, 0], [5, 2, 0], [5, 2, -1], [5, 1, 1]], atol=1e-9)
    np.testing.assert_allclose(p[4], p[0], atol=1e-9)


def test_fk_matches_scipy_for_every_channel_order(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.uniform(-180, 180, size=(7, SMALL_CHANNELS))
    frames[:, [0, 1, 2, 10, 11, 12]] = rng.normal(size=(7, 6))
    bvh = read_bvh(write(tmp_path / "random.bvh", bvh_text(SMALL_HIERARCHY, frames)))
    np.testing.assert_allclose(forward_kinematics(bvh), scipy_fk(bvh), atol=1e-9)
    # Each order on its own, round-tripped through scipy: angles -> matrix -> angles -> same positions.
    for order in ("ZXY", "ZYX", "XYZ", "YXZ", "XZY", "YZX"):
        angles = rng.uniform(-80, 80, size=(5, 3))
        back = Rotation.from_euler(order, angles, degrees=True).as_euler(order, degrees=True)
        hier = SMALL_HIERARCHY.replace("CHANNELS 3 Zrotation Yrotation Xrotation",
                                       "CHANNELS 3 " + " ".join(f"{a}rotation" for a in order))
        motion = np.zeros((5, SMALL_CHANNELS))
        motion[:, 10] = 1.0
        motion[:, 6:9] = back
        bvh = read_bvh(write(tmp_path / f"order_{order}.bvh", bvh_text(hier, motion)))
        expected = np.array([0, 1, 0]) + Rotation.from_euler(order, angles, degrees=True).apply([1, 0, 0])
        np.testing.assert_allclose(forward_kinematics(bvh)[:, 2], expected, atol=1e-6)


def test_gzip_and_crlf_read_the_same(tmp_path):
    rng = np.random.default_rng(1)
    text = bvh_text(SMALL_HIERARCHY, rng.uniform(-90, 90, size=(6, SMALL_CHANNELS)))
    plain = read_bvh(write(tmp_path / "x.bvh", text))
    gz = tmp_path / "x.bvh.gz"
    gz.write_bytes(gzip.compress(text.encode()))
    crlf = tmp_path / "crlf.bvh"
    crlf.write_bytes(text.replace("\n", "\r\n").encode())
    for other in (read_bvh(gz), read_bvh(crlf)):
        assert other.names == plain.names and other.channels == plain.channels
        np.testing.assert_array_equal(other.motion, plain.motion)
        np.testing.assert_array_equal(forward_kinematics(other), forward_kinematics(plain))


@pytest.mark.parametrize("bom,eol,gz", [(True, "\n", False), (False, "\r", False), (True, "\r\n", False),
                                        (True, "\r", True)], ids=["bom", "cr", "bom-crlf", "bom-cr-gz"])
def test_bom_and_cr_line_ends_read_the_same(tmp_path, bom, eol, gz):
    """A UTF-8 byte-order mark and CR-only line ends (old Mac exporters) were refused as 'not a BVH file'."""
    rng = np.random.default_rng(2)
    text = bvh_text(SMALL_HIERARCHY, rng.uniform(-90, 90, size=(5, SMALL_CHANNELS)))
    plain = read_bvh(write(tmp_path / "plain.bvh", text))
    data = (b"\xef\xbb\xbf" if bom else b"") + text.replace("\n", eol).encode()
    path = tmp_path / ("other.bvh.gz" if gz else "other.bvh")
    path.write_bytes(gzip.compress(data) if gz else data)
    other = read_bvh(path)
    assert other.names == plain.names and other.channels == plain.channels and other.frame_time == plain.frame_time
    np.testing.assert_array_equal(other.motion, plain.motion)
    np.testing.assert_array_equal(other.offsets, plain.offsets)


def test_gzip_members_and_padding_read_the_same_and_bombs_are_refused_while_inflating(tmp_path):
    """A .bvh.gz is inflated a piece at a time: several members and zero padding read as one text, and inflating
    stops with a refusal once the text outgrows what its MOTION header declares (a 3 MB file of spaces is 3 GB),
    or 16 MiB go by with no MOTION header."""
    text = bvh_text(SMALL_HIERARCHY, np.random.default_rng(3).uniform(-90, 90, size=(6, SMALL_CHANNELS))).encode()
    plain = read_bvh(write(tmp_path / "plain.bvh", text.decode()))
    members = tmp_path / "members.bvh.gz"
    members.write_bytes(gzip.compress(text[:100]) + gzip.compress(text[100:]) + b"\0" * 8)
    np.testing.assert_array_equal(read_bvh(members).motion, plain.motion)
    padded = tmp_path / "padded.bvh.gz"
    padded.write_bytes(gzip.compress(text + b" " * (4 << 20), compresslevel=1))
    headless = tmp_path / "headless.bvh.gz"
    headless.write_bytes(gzip.compress(text.split(b"MOTION")[0] + b" " * (17 << 20), compresslevel=1))
    for path, why in ((padded, "more than the frames and channels of its MOTION header can take (a gzip bomb?)"),
                      (headless, "with no MOTION header in them (a gzip bomb?)")):
        with pytest.raises(ClipError) as err:
            read_bvh(path)
        assert str(err.value).startswith(f"{path}: refused: inflates to more than ") and why in str(err.value)


@pytest.mark.parametrize("frames", [100_000_000, 10**12, 5000])
def test_frame_counts_the_file_cannot_hold_are_refused_before_allocating(tmp_path, frames):
    """A 20 KB file saying 'Frames: 100000000' is refused from its size, before any frame is parsed."""
    text = bvh_text(SMALL_HIERARCHY, np.zeros((200, SMALL_CHANNELS)), frames=frames)
    path = write(tmp_path / "huge.bvh", text)
    assert path.stat().st_size < 40_000
    with pytest.raises(ClipError) as err:
        read_bvh(path)
    assert str(err.value).startswith(f"{path}: header says {frames:,} frames of {SMALL_CHANNELS} channels, more "
                                     "values than the")


def test_joints_without_channels_cannot_ask_for_huge_kinematics(tmp_path):
    """Frames x joints is bounded too: joints need no channels, so a small file could ask forward kinematics for
    gigabytes (200 bytes per joint and frame)."""
    joints = "".join(f"  JOINT J{k}\n  {{\n    OFFSET 0 1 0\n    CHANNELS 0\n  }}\n" for k in range(2000))
    hierarchy = "HIERARCHY\nROOT Root\n{\n  OFFSET 0 0 0\n  CHANNELS 1 Yposition\n" + joints + "}\n"
    path = write(tmp_path / "wide.bvh", bvh_text(hierarchy, np.zeros((6000, 1))))
    with pytest.raises(ClipError, match=r"6,000 frames of 2001 joints is more than MAX_JOINT_FRAMES \(10,000,000\)"):
        read_bvh(path)


@pytest.mark.parametrize("frame_time", ["100000", "0", "-0.0333", "nan", "inf", "1e-9"])
def test_absurd_frame_times_are_refused(tmp_path, frame_time):
    """'Frame Time: 100000' made the resampling to 20 fps ask for 58 GiB; 0, negative, NaN and 1e-9 are as wrong."""
    text = bvh_text(SMALL_HIERARCHY, np.zeros((3, SMALL_CHANNELS))).replace("Frame Time: 0.0333333",
                                                                            f"Frame Time: {frame_time}")
    path = write(tmp_path / "slow.bvh", text)
    with pytest.raises(ClipError, match="is outside 0.0001-1 s") as err:
        read_bvh(path)
    assert str(err.value).startswith(f"{path}: frame time ")


@pytest.mark.parametrize("frame_time,frames", [("1", 21), ("0.0001", 1)])
def test_frame_times_at_the_limits_resample(tmp_path, frame_time, frames):
    """1 fps is upsampled 20x (the most resample allows); 10,000 fps is downsampled by 500."""
    text = bvh_text(SMALL_HIERARCHY, np.zeros((2, SMALL_CHANNELS))).replace("Frame Time: 0.0333333",
                                                                            f"Frame Time: {frame_time}")
    path = write(tmp_path / "limit.bvh", text)
    bvh = read_bvh(path)
    assert len(resample(forward_kinematics(bvh), bvh.fps, 20.0)) == frames


def test_an_fps_override_cannot_upsample_without_bound(tmp_path):
    path = write(tmp_path / "small.bvh", bvh_text(SMALL_HIERARCHY, np.zeros((3, SMALL_CHANNELS))))
    (tmp_path / "map.json").write_text(json.dumps({"joints": {n: "Root" for n in JOINT_NAMES}}))
    with pytest.raises(ClipError, match="would multiply the frames by more than 20: a wrong frame rate") as err:
        BvhSource(str(path), preset="cmu", joint_map=str(tmp_path / "map.json"), fps=0.001).load(str(path))
    assert str(err.value).startswith(str(path))
    with pytest.raises(ValueError, match="more than 20"):
        resample(np.zeros((3, 22, 3)), 0.5, 20.0)


# ---------------------------------------------------------------- bad input


def _bad_cases(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    good = bvh_text(SMALL_HIERARCHY, np.stack([small_frame()] * 3))
    lines = good.rstrip("\n").split("\n")
    half_line = lines[-1].split()[: SMALL_CHANNELS // 2]
    cases = {
        "missing_frame": ("\n".join(lines[:-1]) + "\n", "frame count mismatch"),
        "half_line": ("\n".join(lines[:-1] + [" ".join(half_line)]) + "\n", "not a multiple"),
        "nan": (good.replace("1.000000", "nan", 1), "NaN"),
        "no_hierarchy": (good.replace("HIERARCHY", "SKELETON"), "HIERARCHY"),
        "unknown_channel": (good.replace("Xrotation Zrotation Yrotation", "Xrotation Zrotation Wrotation"),
                            "unknown channel"),
        "zero_frames": (SMALL_HIERARCHY + "MOTION\nFrames: 0\nFrame Time: 0.0333333\n", "zero frames"),
        "words_in_motion": (good.replace("1.000000", "one", 1), "other than numbers"),
        "no_motion": (SMALL_HIERARCHY, "MOTION"),
    }
    out = {}
    for name, (text, why) in cases.items():
        out[name] = (write(tmp_path / f"{name}.bvh", text), why)
    garbage = tmp_path / "garbage.bvh"
    garbage.write_bytes(np.random.default_rng(2).integers(0, 256, 4000, dtype=np.uint8).tobytes())
    out["garbage"] = (garbage, "")
    broken_gz = tmp_path / "broken.bvh.gz"
    broken_gz.write_bytes(gzip.compress(good.encode())[:60])
    out["broken_gz"] = (broken_gz, "")
    return out


@pytest.mark.parametrize(
    "case",
    ["missing_frame", "half_line", "nan", "no_hierarchy", "unknown_channel", "zero_frames", "words_in_motion",
     "no_motion", "garbage", "broken_gz"],
)
def test_bad_input_raises_clip_error_naming_the_file(tmp_path, case):
    path, why = _bad_cases(tmp_path)[case]
    with pytest.raises(ClipError) as err:
        read_bvh(path)
    assert str(path) in str(err.value)
    assert why in str(err.value)


def test_unmapped_skeleton_names_missing_joints(tmp_path):
    path = write(tmp_path / "small.bvh", bvh_text(SMALL_HIERARCHY, np.stack([small_frame()] * 3)))
    with pytest.raises(ClipError) as err:
        BvhSource(str(path), preset="bandai").load(str(path))
    message = str(err.value)
    assert str(path) in message and "unmapped skeleton" in message
    assert "UpperLeg_L" in message and "Hand_R" in message


# ---------------------------------------------------------------- a user JSON map on a synthetic humanoid


def humanoid_hierarchy(z_up: bool) -> str:
    """SMPL's 22-joint tree named 'src_<name>' without spine2, offsets = target skeleton in cm; rest pose."""
    offsets = RAW_OFFSETS * BONE_LENGTHS[:, None] * 100.0
    if z_up:
        offsets = np.stack([offsets[:, 0], -offsets[:, 2], offsets[:, 1]], axis=-1)  # inverse of Z-up -> Y-up
    children: dict[int, list[int]] = {}
    for k, p in enumerate(PARENTS):
        children.setdefault(p, []).append(k)

    def block(k: int, offset: np.ndarray, depth: int) -> list[str]:
        pad = "  " * depth
        head = "ROOT" if k == 0 else "JOINT"
        chans = "3 Zrotation Xrotation Yrotation"
        if k == 0:
            chans = "6 Xposition Yposition Zposition Zrotation Yrotation Xrotation"
        lines = [f"{pad}{head} src_{JOINT_NAMES[k]}", f"{pad}{{",
                 f"{pad}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}", f"{pad}  CHANNELS {chans}"]
        for c in children.get(k, []):
            if JOINT_NAMES[c] == "spine2":  # absent: its child hangs from spine1 with both offsets added
                for g in children[c]:
                    lines += block(g, offsets[c] + offsets[g], depth + 1)
            else:
                lines += block(c, offsets[c], depth + 1)
        if k not in children:
            lines += [f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET 0 0 0", f"{pad}  }}"]
        return lines + [f"{pad}}}"]

    return "HIERARCHY\n" + "\n".join(block(0, offsets[0], 0)) + "\n"


def rest_positions() -> np.ndarray:
    offsets = RAW_OFFSETS * BONE_LENGTHS[:, None]
    pos = np.zeros((22, 3))
    for k in range(1, 22):
        pos[k] = pos[PARENTS[k]] + offsets[k]
    return pos


@pytest.mark.parametrize("up", ["y", "z"])
def test_user_json_map(tmp_path, up):
    hier = humanoid_hierarchy(z_up=up == "z")
    channels = 6 + 3 * 20
    bvh_path = write(tmp_path / "rest.bvh", bvh_text(hier, np.zeros((31, channels)), frame_time=1 / 30))
    joints = {name: f"src_{name}" for name in JOINT_NAMES}
    # Halfway between spine1 and spine3 is not the target spine2 (bones 0.143 vs 0.057): t makes it exact.
    t = BONE_LENGTHS[6] / (BONE_LENGTHS[6] + BONE_LENGTHS[9])
    joints["spine2"] = {"between": ["src_spine1", "src_spine3"], "t": t}
    map_path = tmp_path / "map.json"
    map_path.write_text(json.dumps({"joints": joints, "scale": 0.01, "up": up, "fps": None}))

    source = BvhSource(str(bvh_path), joint_map=str(map_path), preset="cmu")
    assert str(map_path) in source.inputs()
    [clip] = source.load(str(bvh_path))
    assert clip.name == "rest" and clip.action is None and clip.captions == []
    assert clip.joints.dtype == np.float32 and clip.joints.shape == (21, 22, 3)  # 1 s at 30 fps -> 20 fps
    np.testing.assert_allclose(clip.joints[0], rest_positions(), atol=1e-5)
    assert clip.joints[0, 1, 0] > 0 > clip.joints[0, 2, 0]  # left hip on +x


def test_bad_user_maps(tmp_path):
    incomplete = tmp_path / "incomplete.json"
    incomplete.write_text(json.dumps({"joints": {"pelvis": "Hips"}}))
    with pytest.raises(ClipError, match="lacks SMPL joints"):
        load_joint_map(incomplete)
    bad_up = tmp_path / "up.json"
    bad_up.write_text(json.dumps({"joints": {n: n for n in JOINT_NAMES}, "up": "x"}))
    with pytest.raises(ClipError, match="up must be"):
        load_joint_map(bad_up)
    not_json = write(tmp_path / "broken.json", "{joints:")
    with pytest.raises(ClipError, match="broken.json"):
        load_joint_map(not_json)


# ---------------------------------------------------------------- source: scan, names, labels, captions


def test_scan_names_and_fps_override(tmp_path):
    text = bvh_text(SMALL_HIERARCHY, np.stack([small_frame()] * 31))
    (tmp_path / "sub" / "deeper").mkdir(parents=True)
    write(tmp_path / "b.bvh", text)
    (tmp_path / "sub" / "a.bvh.gz").write_bytes(gzip.compress(text.encode()))
    write(tmp_path / "sub" / "deeper" / "c.BVH", text)
    write(tmp_path / "notes.txt", "not a bvh")
    items = BvhSource(str(tmp_path)).scan()
    assert items == sorted(items) and len(items) == 3
    assert [clip_name(i) for i in items] == ["b", "a", "c"]
    assert BvhSource(items[0]).scan() == [items[0]]
    humanoid = write(tmp_path / "humanoid.bvh", bvh_text(humanoid_hierarchy(False), np.zeros((31, 66))))
    map_path = tmp_path / "map.json"
    joints: dict[str, object] = {n: f"src_{n}" for n in JOINT_NAMES}
    joints["spine2"] = {"between": ["src_spine1", "src_spine3"]}
    map_path.write_text(json.dumps({"joints": joints, "scale": 0.01}))
    assert len(BvhSource(str(humanoid), joint_map=str(map_path)).load(str(humanoid))[0].joints) == 21  # 30 fps file
    assert len(BvhSource(str(humanoid), joint_map=str(map_path), fps=60).load(str(humanoid))[0].joints) == 11


def test_bandai_labels_from_json_and_from_name(tmp_path):
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "content_label.txt").write_text("dataset-2_walk\ndataset-2_walk-turn-left\n")
    (tmp_path / "cfg" / "style_label.txt").write_text("dataset-2_active\ndataset-2_elderly\n")
    (tmp_path / "data").mkdir()
    labelled = tmp_path / "data" / "take.bvh.gz"
    (tmp_path / "data" / "take.json").write_text(json.dumps({"content": 1, "style": 1}))
    assert bandai_labels(labelled) == ("walk-turn-left", "elderly")
    assert bandai_labels(tmp_path / "data" / "dataset-2_raise-up-left-hand_youthful_007.bvh") == (
        "raise-up-left-hand", "youthful")
    assert bandai_labels(tmp_path / "data" / "unlabelled.bvh") is None


def test_bandai_captions():
    captions = bandai_captions("walk-turn-left", "elderly")
    assert len(captions) >= 3 and len(set(captions)) == len(captions)
    assert "an elderly person walks forward and turns left" in captions
    assert bandai_captions("walk-turn-left", "elderly") == captions  # deterministic
    for content in ("walk", "run", "wave-left-hand", "raise-up-right-hand", "raise-up-both-hands"):
        for style in ("active", "normal", "youthful", "exhausted", "feminine", "masculine"):
            assert len(set(bandai_captions(content, style))) >= 3
    mirrored = [swap_left_right(c) for c in bandai_captions("wave-left-hand", "normal")]
    assert all("right" in c and "left" not in c for c in mirrored)
    assert len(bandai_captions("somersault", "sleepy")) >= 3


# ---------------------------------------------------------------- real data


def facing(joints: np.ndarray) -> np.ndarray:
    """HumanML3D's facing direction per frame: up x ((r_hip - l_hip) + (r_shoulder - l_shoulder)), unit."""
    across = (joints[:, 2] - joints[:, 1]) + (joints[:, 17] - joints[:, 16])
    f = np.cross([0.0, 1.0, 0.0], across)
    return f / np.linalg.norm(f, axis=-1, keepdims=True)


def check_rigid(path: Path, preset: str, rigid_bones: list[int]) -> None:
    """Bones between directly mapped joints keep their length in every frame at the file's rate.

    (After linear resampling from 30 to 20 fps a fast wrist's bone shrinks by a few mm, so this is
    checked before resampling.)
    """
    bvh = read_bvh(path)
    lengths = bone_lengths(apply_joint_map(forward_kinematics(bvh), bvh.names, PRESETS[preset], str(path)))
    assert lengths[:, rigid_bones].std(0).max() < 1e-4


def check_human(joints: np.ndarray) -> None:
    """Human bone lengths, a human head height, feet on the floor."""
    mean = bone_lengths(joints).mean(0)
    for k, (lo, hi) in {4: (0.3, 0.55), 5: (0.3, 0.55), 7: (0.3, 0.55), 8: (0.3, 0.55),
                        18: (0.2, 0.4), 19: (0.2, 0.4), 20: (0.15, 0.35), 21: (0.15, 0.35)}.items():
        assert lo < mean[k] < hi, (JOINT_NAMES[k], mean[k])
    y = joints[..., 1]
    feet = [7, 8, 10, 11]
    assert y[:, feet].min() - y.min() < 0.03
    assert np.unravel_index(np.argmin(y), y.shape)[1] in feet
    assert -0.05 < y.min() < 0.12  # the floor is at y = 0, foot joints a few cm above it
    # Upright head height. The head joint sits at the base of the skull, 10-25 cm under the top of the head:
    # a stature of 1.4-2.0 m puts it 1.2-1.9 m above the floor.
    standing = np.percentile(y[:, 15], 95) - y.min()
    assert 1.2 < standing < 1.9, standing


def forward_distance(joints: np.ndarray) -> float:
    return float((joints[-1, 0] - joints[0, 0]) @ facing(joints[:1])[0])


BANDAI_RIGID = [4, 5, 7, 8, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21]


@pytest.mark.shared
def test_bandai_raise_up_left_hand(bandai_dir):
    path = bandai_dir / "data" / "dataset-2_raise-up-left-hand_normal_001.bvh.gz"
    source = BvhSource(str(bandai_dir / "data"))
    [clip] = source.load(str(path))
    assert clip.name == "dataset-2_raise-up-left-hand_normal_001" and clip.mirror
    assert clip.action == "raise-up-left-hand"
    assert "a person raises the left hand up" in [c.text for c in clip.captions]
    assert all(c.start == 0 and c.end == 0 for c in clip.captions)
    j = clip.joints
    assert j.dtype == np.float32 and j.shape[1:] == (22, 3)
    assert len(j) == (read_bvh(path).num_frames - 1) * 2 // 3 + 1  # 30 -> 20 fps over the same span
    head = j[:, 15, 1]
    assert (j[:, 20, 1] - head).max() > 0.05  # the left wrist goes above the head
    assert (j[:, 21, 1] - head).max() < -0.2  # the right wrist stays low
    check_human(j)
    check_rigid(path, "bandai", BANDAI_RIGID)
    assert any(p.endswith("content_label.txt") for p in source.inputs())


@pytest.mark.shared
@pytest.mark.parametrize(
    "take", ["dataset-2_walk_normal_001", "dataset-2_walk_elderly_003", "dataset-2_run_active_002"]
)
def test_bandai_locomotion_moves_forward(bandai_dir, take):
    path = bandai_dir / "data" / f"{take}.bvh.gz"
    [clip] = BvhSource(str(path)).load(str(path))
    check_human(clip.joints)
    check_rigid(path, "bandai", BANDAI_RIGID)
    assert forward_distance(clip.joints) > 1.0


@pytest.mark.shared
@pytest.mark.parametrize("content, sign", [("walk-turn-left", 1.0), ("walk-turn-right", -1.0)])
def test_bandai_turns_to_the_labelled_side(bandai_dir, content, sign):
    """Seen from above (Y up) a left turn is counter-clockwise: cross(facing_start, facing_end) points up."""
    path = bandai_dir / "data" / f"dataset-2_{content}_normal_001.bvh.gz"
    [clip] = BvhSource(str(path)).load(str(path))
    assert clip.action == content
    start, end = facing(clip.joints[[0, -1]])
    assert sign * np.cross(start, end)[1] > 0.7  # a turn of about 90 degrees
    assert forward_distance(clip.joints) > 1.0


@pytest.mark.shared
def test_bandai_fk_matches_scipy_on_a_real_file(bandai_dir):
    bvh = read_bvh(bandai_dir / "data" / "dataset-2_wave-left-hand_feminine_002.bvh.gz")
    np.testing.assert_allclose(forward_kinematics(bvh), scipy_fk(bvh), atol=1e-6)


CMU_RIGID = [1, 2, 4, 5, 7, 8, 10, 11, 12, 15, 18, 19, 20, 21]


@pytest.mark.shared
@pytest.mark.parametrize("take", ["131_01", "131_02", "131_03"])
def test_cmu_clips(cmu_dir, take):
    path = cmu_dir / f"{take}.bvh"
    [clip] = BvhSource(str(path), preset="cmu").load(str(path))
    assert clip.name == take and clip.action is None and clip.captions == []
    bvh = read_bvh(path)
    assert bvh.fps == 120.0 and len(clip.joints) == (bvh.num_frames - 1) // 6 + 1
    np.testing.assert_allclose(forward_kinematics(bvh)[:20], scipy_fk(bvh)[:20], atol=1e-6)
    check_human(clip.joints)
    check_rigid(path, "cmu", CMU_RIGID)
    if take in ("131_01", "131_02"):  # start, walk, stop
        assert forward_distance(clip.joints) > 1.0


@pytest.mark.shared
def test_cmu_with_bandai_map_is_unmapped(cmu_dir):
    path = cmu_dir / "131_01.bvh"
    with pytest.raises(ClipError, match="unmapped skeleton"):
        apply_joint_map(forward_kinematics(read_bvh(path)), read_bvh(path).names, PRESETS["bandai"], str(path))


def test_a_hierarchy_of_a_million_joints_is_refused_while_it_is_read(tmp_path):
    """More joints than any character has are refused at the first one past the bound, with a short message."""
    from lsgan.data.bvh import MAX_JOINTS, read_bvh

    joints = "".join(f"JOINT j{k}\n{{\nOFFSET 0 1 0\nCHANNELS 3 Zrotation Xrotation Yrotation\n" for k in
                     range(MAX_JOINTS + 5))
    text = ("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 3 Zrotation Xrotation Yrotation\n" + joints
            + "}\n" * (MAX_JOINTS + 6) + "MOTION\nFrames: 1\nFrame Time: 0.05\n0 0 0\n")
    path = tmp_path / "many.bvh"
    path.write_text(text)
    with pytest.raises(Exception, match="more than 4,096 joints") as e:
        read_bvh(path)
    assert len(str(e.value)) < 300

