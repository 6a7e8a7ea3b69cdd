"""Motion-quality figures on constructed motions whose answers are known by hand."""
from __future__ import annotations

import numpy as np
import pytest

from lsgan.data.skeleton import PARENTS, TARGET_OFFSETS
from lsgan.motion.quality import floating, foot_skating_ratio, ground_penetration, jerk, quality_metrics

FPS = 20


def rest_pose() -> np.ndarray:
    """The HumanML3D rest skeleton (22, 3) standing on y = 0 on both toes (10, 11), its lowest joints.

    Its right leg is 1 cm shorter than its left: the right toe is put on the floor too.
    """
    j = np.zeros((22, 3))
    for k in range(1, 22):
        j[k] = j[PARENTS[k]] + TARGET_OFFSETS[k]
    j[:, 1] -= j[:, 1].min()
    j[11, 1] = 0.0
    assert j[10, 1] == 0.0 and (j[:, 1] >= 0).all()
    return j


def moving(root: np.ndarray) -> np.ndarray:
    """The rest pose carried along a root path (T, 3): (T, 22, 3)."""
    return rest_pose()[None] + np.asarray(root, dtype=np.float64)[:, None, :]


def path_x(step: float, T: int, lift: float = 0.0) -> np.ndarray:
    """x advances ``step`` metres per frame; the body is raised by ``lift``."""
    t = np.arange(T, dtype=np.float64)
    return np.stack([step * t, np.full(T, lift), np.zeros(T)], -1)


# ------------------------------------------------------------------------------------------------- foot skating


def test_a_planted_body_does_not_skate():
    m = moving(path_x(0.0, 30))
    assert foot_skating_ratio(m) == 0.0 and ground_penetration(m) == 0.0 and floating(m) == 0.0 and jerk(m) == 0.0


def test_feet_sliding_5cm_per_frame_on_the_ground_skate_in_every_frame():
    assert foot_skating_ratio(moving(path_x(0.05, 30))) == 1.0


def test_sliding_under_the_threshold_or_off_the_ground_is_no_skating():
    assert foot_skating_ratio(moving(path_x(0.02, 30))) == 0.0  # 0.4 m/s < 0.5 m/s (2.5 cm per frame)
    assert foot_skating_ratio(moving(path_x(0.05, 30, lift=0.10))) == 0.0  # feet 10 cm up: no contact
    assert foot_skating_ratio(moving(path_x(0.05, 30, lift=0.04))) == 1.0  # 4 cm: still under the 5 cm contact line


def test_one_sliding_foot_is_enough():
    m = moving(path_x(0.0, 30))
    m[:, 11, 0] += 0.05 * np.arange(30)  # the right toe slides, the left stays planted
    assert foot_skating_ratio(m) == 1.0


def test_the_ratio_counts_frame_pairs():
    # 21 frames = 20 pairs; the body slides 5 cm per frame over the first 10 pairs, then stands. GMD's 5-frame mean of
    # the speed is 0.6 m/s at the last sliding pair (1, 1, 1, 0, 0): still over 0.5, so exactly 10 of 20 pairs skate.
    x = np.minimum(np.arange(21), 10) * 0.05
    m = moving(np.stack([x, np.zeros(21), np.zeros(21)], -1))
    assert foot_skating_ratio(m) == pytest.approx(0.5)


def test_a_one_frame_glitch_is_not_skating():
    # one pair moves 5 cm (1 m/s), but the 5-frame mean is 0.2 m/s: GMD's window leaves it out
    x = np.where(np.arange(30) >= 15, 0.05, 0.0)
    m = moving(np.stack([x, np.zeros(30), np.zeros(30)], -1))
    assert foot_skating_ratio(m) == 0.0


# ------------------------------------------------------------------------------------------ penetration, floating


def test_penetration_is_the_mean_depth_of_the_lowest_joint():
    root = np.zeros((20, 3))
    root[10:, 1] = -0.03  # sunk 3 cm for the second half
    m = moving(root)
    assert ground_penetration(m) == pytest.approx(0.015)
    m[0, 20, 1] = -0.5  # a hand through the floor in frame 0: the lowest joint counts, whichever it is
    assert ground_penetration(m) == pytest.approx(0.015 + 0.5 / 20)


def test_a_body_hovering_still_floats_by_its_feet_height():
    assert floating(moving(path_x(0.0, 20, lift=0.20))) == pytest.approx(0.20)
    assert floating(moving(path_x(0.0, 20, lift=0.04))) == 0.0  # within the 5 cm contact band: standing


def test_moving_feet_or_one_planted_foot_are_not_floating():
    assert floating(moving(path_x(0.05, 20, lift=0.20))) == 0.0  # the feet move 5 cm per frame: a jump or a stride
    m = moving(path_x(0.0, 20))
    m[:, 10, 1] = 0.30  # a one-legged stand: the left toe held 30 cm up, the right on the floor
    assert floating(m) == 0.0
    m[:, 11, 1] = 0.10  # now both held up, still: floating by the lower one, 10 cm
    assert floating(m) == pytest.approx(0.10)


# -------------------------------------------------------------------------------------------------------- jerk


def test_constant_acceleration_has_no_jerk():
    t = np.arange(40) / FPS
    root = np.stack([0.5 * 3.0 * t**2 + 0.2 * t, 0.5 * -9.81 * t**2 + 2.0 * t + 1.0, -t], -1)
    assert jerk(moving(root)) == pytest.approx(0.0, abs=1e-8)


def test_jerk_of_a_cubic_path_and_of_a_one_frame_jitter():
    t = np.arange(40) / FPS
    assert jerk(moving(np.stack([0.7 * t**3, 0 * t, 0 * t], -1))) == pytest.approx(6 * 0.7, rel=1e-9)
    # +-1 cm every other frame: the third difference is 8 cm per frame^3, i.e. 0.08 * 20^3 = 640 m/s^3
    wobble = 0.01 * (-1.0) ** np.arange(40)
    assert jerk(moving(np.stack([wobble, 0 * t, 0 * t], -1))) == pytest.approx(640.0, rel=1e-9)


# ------------------------------------------------------------------------------------------ batches and averages


def test_batched_figures_equal_one_motion_at_a_time():
    rng = np.random.default_rng(0)
    batch = moving(path_x(0.03, 25))[None] + rng.normal(0, 0.02, (4, 25, 22, 3))
    for fn in (foot_skating_ratio, ground_penetration, floating, jerk):
        got = fn(batch)
        assert got.shape == (4,)
        np.testing.assert_allclose(got, [fn(m) for m in batch], rtol=1e-12)


def test_quality_metrics_averages_over_motions_of_any_length():
    planted, sliding = moving(path_x(0.0, 30)), moving(path_x(0.05, 17))
    sunk = moving(path_x(0.0, 12, lift=-0.02))
    out = quality_metrics([planted, sliding, sunk.astype(np.float32)])
    assert out["num_motions"] == 3
    assert out["foot_skating_ratio"] == pytest.approx(1 / 3)
    assert out["penetration_m"] == pytest.approx(0.02 / 3, rel=1e-6)
    assert out["floating_m"] == 0.0 and out["jerk_m_s3"] == pytest.approx(0.0, abs=1e-8)


def test_a_figure_averages_the_motions_long_enough_for_it():
    """Jerk needs 4 frames, skating 2: shorter motions are left out of those figures, not the table."""
    long, short, single = moving(path_x(0.0, 10)), moving(path_x(0.0, 3)), moving(path_x(0.0, 1))
    q = quality_metrics([long, short, single])
    assert q["jerk_m_s3"] == pytest.approx(float(jerk(long)))
    assert q["foot_skating_ratio"] == pytest.approx((float(foot_skating_ratio(long)) + float(foot_skating_ratio(short))) / 2)
    assert q["num_motions"] == 3 and q["penetration_m"] == pytest.approx(0.0)
    assert np.isnan(quality_metrics([single])["jerk_m_s3"])


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="at least one motion"):
        quality_metrics([])
    with pytest.raises(ValueError, match=r"motion 1: .*\(\.\.\., T, 22, 3\)"):
        quality_metrics([moving(path_x(0.0, 10)), np.zeros((10, 22, 2))])
    with pytest.raises(ValueError, match=r"\(\.\.\., T, 22, 3\)"):
        foot_skating_ratio(np.zeros((10, 22, 2)))
