"""The procedural synthetic motions: determinism, exact skeleton, contacts, sides and captions."""
from __future__ import annotations

import numpy as np
import pytest

from lsgan.data.clip import Caption, ClipError, RawClip
from lsgan.data.skeleton import BONE_LENGTHS, FPS, mirror_joints
from lsgan.data.sources.synthetic import SyntheticSource
from lsgan.data.synthetic import FAMILIES, generate, generate_clip, synthetic_clip
from lsgan.data.tokens import tokenize

FEET = [7, 8, 10, 11]


def _clips(family: str, n: int, seed: int = 0) -> list[tuple[np.ndarray, list[str]]]:
    out = []
    for i in range(n):
        joints, captions, action = generate_clip(family, np.random.default_rng([seed, i]))
        assert action == family
        out.append((joints, captions))
    return out


def _facing(joints: np.ndarray) -> np.ndarray:
    """Forward direction on the floor, (T,2) as (x, z), from the hips and shoulders."""
    across = (joints[:, 2] - joints[:, 1]) + (joints[:, 17] - joints[:, 16])
    forward = np.stack([across[:, 2], -across[:, 0]], -1)  # up x across
    return forward / np.linalg.norm(forward, axis=-1, keepdims=True)


def _direction(captions: list[str]) -> str:
    words = {"forward": ("forward", "ahead"), "backward": ("backward", "backpedal"), "left": ("left",),
             "right": ("right",)}
    found = {d for c in captions for d, keys in words.items() if any(k in c for k in keys)}
    assert len(found) == 1, captions
    return found.pop()


@pytest.fixture(scope="module")
def every_family() -> list:
    return generate(len(FAMILIES) * 3, seed=7)


def test_same_seed_same_data_other_seed_differs() -> None:
    a, b, c = generate(13, seed=3), generate(13, seed=3), generate(13, seed=4)
    for x, y in zip(a, b):
        assert x.name == y.name and x.action == y.action and x.captions == y.captions
        assert x.joints.dtype == np.float32 and np.array_equal(x.joints, y.joints)
    assert any(x.joints.shape != z.joints.shape or not np.array_equal(x.joints, z.joints) for x, z in zip(a, c))


def test_clip_depends_only_on_seed_and_index() -> None:
    clip = synthetic_clip(5, seed=2)
    again = generate(8, seed=2)[5]
    assert clip.name == "synth_000005" and np.array_equal(clip.joints, again.joints) and clip.captions == again.captions


def test_shapes_durations_and_balanced_families() -> None:
    clips = generate(100, seed=1)
    counts = {f: sum(c.action == f for c in clips) for f in FAMILIES}
    assert set(c.action for c in clips) == set(FAMILIES)
    assert max(counts.values()) - min(counts.values()) <= 1
    for c in clips:
        assert c.joints.ndim == 3 and c.joints.shape[1:] == (22, 3) and np.isfinite(c.joints).all()
        assert 2 * FPS <= len(c.joints) <= 8 * FPS
        assert len(c.captions) == 3 and len(set(c.captions)) >= 2


def test_families_argument_restricts_and_rejects_unknown() -> None:
    clips = generate(6, families=("squat", "jump"))
    assert [c.action for c in clips] == ["squat", "jump"] * 3
    with pytest.raises(ValueError):
        generate(2, families=("moonwalk",))


def test_bone_lengths_are_exact(every_family) -> None:
    for c in every_family:
        lengths = np.linalg.norm(c.joints[:, 1:] - c.joints[:, [0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14,
                                                                16, 17, 18, 19]], axis=-1)
        assert np.abs(lengths - BONE_LENGTHS[1:]).max() < 1e-5, c.action


def test_feet_on_the_floor(every_family) -> None:
    for c in every_family:
        assert c.joints[..., 1].min() >= -1e-6, c.action  # nothing below the floor
        if c.action != "jump":
            assert abs(c.joints[..., 1].min()) < 0.01, c.action
    for joints, _ in _clips("walk", 10):
        lowest_foot = joints[:, FEET, 1].min(1)
        assert np.mean(lowest_foot < 0.01) > 0.9


def test_walk_stance_foot_is_planted() -> None:
    for joints, captions in _clips("walk", 12):
        feet = joints[:, [10, 11]]
        speed = np.linalg.norm(np.diff(feet[..., [0, 2]], axis=0), axis=-1) * FPS  # (T-1,2)
        height = feet[1:, :, 1]
        lowest = height == height.min(1, keepdims=True)
        planted = lowest & (height < 0.02)
        assert planted.sum() > len(joints) // 2
        assert np.median(speed[planted]) < 0.15, captions


@pytest.mark.parametrize("family", ["walk", "run"])
def test_gait_moves_the_way_the_captions_say(family: str) -> None:
    seen = set()
    for joints, captions in _clips(family, 30):
        direction = _direction(captions)
        seen.add(direction)
        dx, dz = joints[-1, 0, [0, 2]] - joints[0, 0, [0, 2]]
        speed = np.hypot(dx, dz) / ((len(joints) - 1) / FPS)
        if direction == "forward":
            assert dz > 1.0 and abs(dx) < 0.2 * dz, captions
        elif direction == "backward":
            assert dz < -0.5 and abs(dx) < 0.2 * abs(dz), captions
        else:
            sign = 1.0 if direction == "left" else -1.0  # the character's left is +x
            assert sign * dx > 0.4 and abs(dz) < 0.2 * abs(dx), captions
        assert (speed > 1.1) if family == "run" else (speed < 2.0), (captions, speed)
    assert {"forward", "backward", "left", "right"} <= seen


def test_raise_left_hand_uses_the_left_arm_and_mirrors_to_right() -> None:
    for joints, _ in _clips("raise-left-hand", 6):
        y = joints[..., 1]
        assert (y[:, 20] - y[:, 16]).max() > 0.1 and (y[:, 20] - y[:, 15]).max() > 0.0
        assert (y[:, 21] < y[:, 17]).all()
        m = mirror_joints(joints)[..., 1]
        assert (m[:, 21] - m[:, 17]).max() > 0.1 and (m[:, 20] < m[:, 16]).all()
    for joints, _ in _clips("raise-right-hand", 6):
        y = joints[..., 1]
        assert (y[:, 21] - y[:, 17]).max() > 0.1 and (y[:, 20] < y[:, 16]).all()
    for joints, _ in _clips("raise-both-hands", 6):
        y = joints[..., 1]
        assert (y[:, 20] - y[:, 16]).max() > 0.1 and (y[:, 21] - y[:, 17]).max() > 0.1


@pytest.mark.parametrize("side", ["left", "right"])
def test_wave_and_kick_move_the_named_side(side: str) -> None:
    hand, other = (20, 21) if side == "left" else (21, 20)
    shoulder, other_shoulder = (16, 17) if side == "left" else (17, 16)
    for joints, _ in _clips(f"wave-{side}-hand", 6):
        y = joints[..., 1]
        assert (y[:, hand] - y[:, shoulder]).max() > 0.1 and (y[:, other] < y[:, other_shoulder]).all()
        sway = np.ptp(joints[:, hand, 0] - joints[:, 0, 0])
        assert sway > 2 * np.ptp(joints[:, other, 0] - joints[:, 0, 0])
    foot, other_foot = (10, 11) if side == "left" else (11, 10)
    for joints, _ in _clips(f"kick-{side}", 6):
        assert joints[:, foot, 1].max() > 0.25 and joints[:, other_foot, 1].max() < 0.02
        assert (joints[:, foot, 2] - joints[:, 0, 2]).max() > 0.4  # a front kick


@pytest.mark.parametrize("side", ["left", "right"])
def test_turns_end_facing_the_named_side(side: str) -> None:
    for joints, _ in _clips(f"turn-{side}", 8):
        start, end = _facing(joints[[0, -1]])
        assert start[1] > 0.95  # facing +z at the start
        turned = np.degrees(np.arctan2(end[0], end[1]) % (2 * np.pi))  # counter-clockwise seen from +y
        if side == "left":  # towards the character's left, +x
            assert 35 < turned < 200, turned
        else:
            assert 160 < turned < 325, turned


def test_jump_leaves_the_floor_and_squat_goes_down() -> None:
    for joints, _ in _clips("jump", 6):
        assert joints[:, FEET, 1].min(1).max() > 0.1
    for joints, _ in _clips("squat", 6):
        assert np.ptp(joints[:, 0, 1]) > 0.25


def test_captions_name_the_right_side(every_family) -> None:
    for c in every_family:
        for text in c.captions:
            words = set(text.replace(",", " ").split())
            if "left" in c.action or "right" in c.action:
                side = "left" if "left" in c.action else "right"
                assert side in words and ({"left", "right"} - {side}).isdisjoint(words), (c.action, text)
            elif c.action in ("jump", "squat", "raise-both-hands"):
                assert {"left", "right"}.isdisjoint(words), (c.action, text)
            if c.action == "raise-both-hands":
                assert "both" in words or "arms" in words, text


def test_source_items_and_clips() -> None:
    src = SyntheticSource(num_clips=5, seed=2, families=("wave-left-hand", "squat"))
    assert src.name == "synthetic" and src.inputs() == []
    items = src.scan()
    assert items == sorted(items) == ["000000", "000001", "000002", "000003", "000004"]
    (clip,) = src.load("000003")
    ref = synthetic_clip(3, seed=2, families=("wave-left-hand", "squat"))
    assert isinstance(clip, RawClip) and clip.name == "synth_000003" and clip.source_file == "synthetic"
    assert clip.action == "squat" and clip.mirror is False and np.array_equal(clip.joints, ref.joints)
    assert [c.text for c in clip.captions] == list(ref.captions)
    assert clip.captions == [Caption(text=t, tokens=tokenize(t)) for t in ref.captions]  # tagged once, at import
    assert SyntheticSource(num_clips=5, seed=2, mirror=True).load("000001")[0].mirror is True
    with pytest.raises(ClipError):
        src.load("000005")
    with pytest.raises(ValueError):
        SyntheticSource(families=("moonwalk",))
