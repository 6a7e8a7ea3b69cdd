"""Evaluation metrics against closed-form answers (T2M text-to-motion, MLD/TEMOS APE-AVE, ACTOR action metrics)."""
from __future__ import annotations

import numpy as np
import pytest

from lsgan.eval.metrics import (
    MLD_UNIT_SCALE,
    accuracy,
    action_diversity,
    action_multimodality,
    ape_ave,
    confusion_matrix,
    diversity,
    fid,
    matching_score,
    mean_ci,
    mpjpe,
    multimodality,
    r_precision,
    retrieval_metrics,
)

# ----------------------------------------------------------------------------------------------------------- FID


def test_fid_identical_gaussians_is_about_zero():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(20000, 4)), rng.normal(size=(20000, 4))
    assert fid(a, b) < 0.01


def test_fid_mean_shift_gives_squared_norm():
    rng = np.random.default_rng(1)
    s = np.array([2.0, -2.0, 1.0])  # |s|^2 = 9
    a, b = rng.normal(size=(20000, 3)), rng.normal(size=(20000, 3)) + s
    # the estimate's std is about 2|s| sqrt(2/N) = 0.06
    assert fid(a, b) == pytest.approx(9.0, abs=0.3)


def test_fid_scaled_covariance_trace_term():
    rng = np.random.default_rng(2)
    c, d = 2.0, 3
    a, b = rng.normal(size=(20000, d)), c * rng.normal(size=(20000, d))
    # N(0, I) vs N(0, c^2 I): Tr(I + c^2 I - 2 c I) = d (1 - c)^2 = 3
    assert fid(a, b) == pytest.approx(d * (1 - c) ** 2, abs=0.15)
    # exact on the sample itself: stats of c*a are (c mu, c^2 S) -> |mu|^2 (1-c)^2 + Tr(S) (1-c)^2
    mu, cov = a.mean(0), np.cov(a, rowvar=False)
    assert fid(a, c * a) == pytest.approx((1 - c) ** 2 * (mu @ mu + np.trace(cov)), rel=1e-6)


# ------------------------------------------------------------------------------------------ R-precision, MM-Dist


def test_matched_embeddings_give_perfect_r_precision_and_zero_mm_dist():
    rng = np.random.default_rng(3)
    t = rng.normal(size=(320, 16)) * 3.0
    r, mm = retrieval_metrics(t, t.copy(), rng=np.random.default_rng(0))
    np.testing.assert_array_equal(r, [1.0, 1.0, 1.0])
    assert mm == pytest.approx(0.0, abs=1e-6)
    assert matching_score(t, t) == pytest.approx(0.0, abs=1e-6)


def test_random_embeddings_give_chance_r_precision():
    rng = np.random.default_rng(4)
    n = 32 * 2000
    t, m = rng.normal(size=(n, 8)), rng.normal(size=(n, 8))
    r = r_precision(t, m, rng=rng)
    expect = np.array([1, 2, 3]) / 32
    tol = 5 * np.sqrt(expect * (1 - expect) / n)  # binomial std, 5 sigma
    assert np.all(np.abs(r - expect) < tol), (r, expect, tol)
    # MM-Dist of independent N(0, I_8) pairs: E|x - y| = 2 Gamma(4.5)/Gamma(4) = 3.8773...
    assert matching_score(t, m) == pytest.approx(3.8773, abs=0.02)


def test_collapsed_motions_score_chance_not_perfect():
    t = np.random.default_rng(5).normal(size=(64, 8))
    m = np.zeros_like(t)  # every motion the same: all distances tie within each caption's row
    np.testing.assert_allclose(r_precision(t, m), np.array([1, 2, 3]) / 32)


def test_r_precision_known_ranks_and_remainder_dropped():
    # captions at (10 i, 0); even i: own motion 3 above it, and motion i+1 sits 1 below it (nearer) -> rank 2;
    # odd i: own motion is that one, at (10 (i-1), -1), distance sqrt(101), nearer than any other -> rank 1
    g = 32
    t = np.zeros((g, 2))
    t[:, 0] = 10.0 * np.arange(g)
    m = np.zeros((g, 2))
    m[0::2] = t[0::2] + [0.0, 3.0]
    m[1::2] = t[0::2] + [0.0, -1.0]
    r, mm = retrieval_metrics(t, m, top_k=3)
    np.testing.assert_allclose(r, [0.5, 1.0, 1.0])
    assert mm == pytest.approx((16 * 3.0 + 16 * np.sqrt(101.0)) / 32)
    # 6 extra pairs do not fill a group of 32 and are dropped (no shuffle without rng)
    extra = np.random.default_rng(6).normal(size=(6, 2))
    r2, mm2 = retrieval_metrics(np.vstack([t, extra]), np.vstack([m, -extra]), top_k=3)
    np.testing.assert_allclose(r2, r)
    assert mm2 == pytest.approx(mm)
    with pytest.raises(ValueError):
        retrieval_metrics(t[:31], m[:31])


def test_r_precision_is_deterministic_under_rng():
    rng = np.random.default_rng(7)
    t = rng.normal(size=(100, 8))
    m = t + rng.normal(scale=2.0, size=t.shape)
    a = retrieval_metrics(t, m, rng=np.random.default_rng(11))
    b = retrieval_metrics(t, m, rng=11)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1] == b[1]


# ------------------------------------------------------------------------------------ diversity, multimodality


def test_diversity_of_two_clusters():
    n = 20000
    x = np.zeros((n, 3))
    x[n // 2:] = [3.0, 4.0, 0.0]  # distance 5 across clusters, 0 within
    # each index set is uniform over the points: P(pair straddles the clusters) = 1/2
    d = diversity(x, pairs=10000, rng=np.random.default_rng(0))
    assert d == pytest.approx(2.5, abs=0.1)  # std 5 sqrt(.25/10000) = 0.025
    assert diversity(np.ones((300, 4)), pairs=300, rng=0) == 0.0
    assert diversity(x, rng=5) == diversity(x, rng=np.random.default_rng(5))
    with pytest.raises(ValueError):
        diversity(x[:299], pairs=300, rng=0)
    # both index sets are drawn without replacement: with pairs == N each point appears once on each side, so
    # one outlier at distance L gives 2 L / N (or 0 when it is paired with itself), never another value
    n_out, big = 50, 7.0
    y = np.zeros((n_out, 2))
    y[0, 0] = big
    vals = np.array([diversity(y, pairs=n_out, rng=seed) for seed in range(40)])
    assert np.all(np.isclose(vals, 2 * big / n_out) | (vals == 0.0))
    with pytest.raises(ValueError):
        diversity(x, rng=None)


def test_multimodality_identical_and_known_spread():
    c, s = 20, 30
    offsets = np.random.default_rng(1).normal(scale=100.0, size=(c, 1, s))
    assert multimodality(np.repeat(offsets, s, axis=1), pairs=10, rng=0) == 0.0
    # samples of condition k are r_k e_s: distinct samples at r_k sqrt(2), plus a far per-condition offset
    radii = np.linspace(1.0, 3.0, c)
    emb = offsets + radii[:, None, None] * np.eye(s)[None]
    # T2M draws one pair of index sets shared by every condition: the value is f sqrt(2) mean(r) with f the
    # fraction of the 10 index pairs that differ
    vals = np.array([multimodality(emb, pairs=10, rng=seed) for seed in range(300)])
    f = vals / (np.sqrt(2) * radii.mean())
    np.testing.assert_allclose(f * 10, np.round(f * 10), atol=1e-9)
    assert f.mean() == pytest.approx(1 - 1 / s, abs=0.01)  # P(i != j) = 1 - 1/S
    with pytest.raises(ValueError):
        multimodality(emb[:, :9], pairs=10, rng=0)
    # index sets without replacement: with pairs == S, one outlier per condition gives 2 L / S or 0
    one = np.zeros((3, 10, 2))
    one[:, 4, 1] = 5.0
    vals = np.array([multimodality(one, pairs=10, rng=seed) for seed in range(40)])
    assert np.all(np.isclose(vals, 2 * 5.0 / 10) | (vals == 0.0))


def test_mean_ci_known_values():
    m, h = mean_ci([1.0, 2.0, 3.0, 4.0])
    assert m == 2.5
    assert h == pytest.approx(1.96 * np.sqrt(1.25) / 2)  # numpy std, ddof 0
    m2, h2 = mean_ci(np.array([[1.0, 10.0], [3.0, 10.0]]))
    np.testing.assert_allclose(m2, [2.0, 10.0])
    np.testing.assert_allclose(h2, [1.96 * 1.0 / np.sqrt(2), 0.0])


# -------------------------------------------------------------------------------------------------- APE / AVE


def _motion(t_len: int, phase: float = 0.0) -> np.ndarray:
    """A deterministic 22-joint motion (T, 22, 3), y up, walking along x with some sway."""
    t = np.arange(t_len)[:, None] / 20.0
    j = np.arange(22)[None, :]
    x = 0.3 * np.sin(0.7 * j + phase) + 0.8 * t + 0.05 * np.sin(3 * t + j)
    y = 0.9 + 0.4 * np.cos(0.5 * j) + 0.03 * np.cos(2 * t + j + 3 * phase) + 0.1 * phase * t
    z = 0.2 * np.cos(1.3 * j + phase) + 0.1 * np.sin(t) + 0.04 * np.sin(5 * t + 0.3 * j)
    return np.stack([x, y, z], -1)


def test_ape_ave_constant_offset():
    gt = _motion(40)
    d = np.array([0.3, -0.2, 0.6])
    raw = ape_ave(gt + d, gt, canonicalize=False)
    assert raw["ape_mean_joints"] == pytest.approx(np.linalg.norm(d))
    assert raw["ape_root"] == pytest.approx(np.linalg.norm(d))
    assert raw["ape_traj"] == pytest.approx(np.linalg.norm(d[[0, 2]]))
    assert raw["ape_mean_pose"] == pytest.approx(0.0, abs=1e-12)
    for k in ("ave_root", "ave_traj", "ave_mean_pose", "ave_mean_joints"):
        assert raw[k] == pytest.approx(0.0, abs=1e-12)
    # MLD's canonicalisation (floor, first-frame position and heading) removes a constant offset entirely
    mld = ape_ave(gt + d, gt)
    assert max(mld.values()) < 1e-9


def test_ape_ave_mld_ignores_a_global_yaw_about_the_origin():
    gt = _motion(40)
    a = 0.9
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    out = ape_ave(gt @ rot.T + [1.0, 0.0, -2.0], gt)
    assert max(out.values()) < 1e-9
    assert ape_ave(gt @ rot.T, gt, canonicalize=False)["ape_mean_joints"] > 0.1


@pytest.mark.parametrize("canonicalize", [False, True])
def test_ape_ave_root_translation_moves_root_not_pose(canonicalize):
    gt = _motion(41)
    v = np.array([0.03, 0.0, -0.04])  # |v| = 0.05 per frame on the ground plane
    pred = gt + np.arange(41)[:, None, None] * v
    out = ape_ave(pred, gt, canonicalize=canonicalize)
    # frame t is off by t |v|: the mean over frames 0..40 is 20 |v| = 1.0
    assert out["ape_root"] == pytest.approx(1.0)
    assert out["ape_traj"] == pytest.approx(1.0)
    assert out["ape_mean_pose"] == pytest.approx(0.0, abs=1e-9)
    assert out["ave_mean_pose"] == pytest.approx(0.0, abs=1e-9)
    assert out["ave_root"] > 0.0


def test_ave_of_a_scaled_linear_motion():
    t_len, c = 30, 1.5
    v = np.array([0.02, 0.01, -0.03])
    base = np.random.default_rng(0).normal(size=(22, 3))
    gt = base[None] + np.arange(t_len)[:, None, None] * v
    out = ape_ave(c * gt, gt, canonicalize=False)
    var_t = t_len * (t_len + 1) / 12.0  # variance of 0..T-1 with the T-1 denominator
    ave = (c ** 2 - 1) * np.linalg.norm(v ** 2) * var_t  # every joint, the root too, moves with v
    assert out["ave_root"] == pytest.approx(ave)
    assert out["ave_mean_joints"] == pytest.approx(ave)
    assert out["ave_traj"] == pytest.approx((c ** 2 - 1) * np.linalg.norm(v[[0, 2]] ** 2) * var_t)
    assert out["ave_mean_pose"] == pytest.approx(0.0, abs=1e-12)  # joints minus root are constant
    assert out["ape_mean_joints"] == pytest.approx((c - 1) * np.linalg.norm(gt, axis=-1).mean())


def test_ape_ave_matches_mld_compute_metrics():
    # values from a line-by-line torch transcription of MLD's ComputeMetrics (Rifke round trip) on this input
    out = ape_ave(_motion(40, 0.15), _motion(40, 0.0))
    expect = {"ape_root": 0.1416847266218315, "ape_traj": 0.13929485421647714,
              "ape_mean_pose": 0.10033025110010214, "ape_mean_joints": 0.16918526605172948,
              "ave_root": 0.04234895999707743, "ave_traj": 0.04234756760422941,
              "ave_mean_pose": 0.0005303941554555775, "ave_mean_joints": 0.047948665071464044}
    assert out.keys() == expect.keys()
    for k, v in expect.items():
        assert out[k] == pytest.approx(v, rel=1e-9), k
    # MLD's humanml3d unit factor scales positions: APE linearly, AVE (a variance) quadratically
    scaled = ape_ave(_motion(40, 0.15), _motion(40, 0.0), unit_scale=MLD_UNIT_SCALE)
    assert scaled["ape_mean_joints"] == pytest.approx(MLD_UNIT_SCALE * expect["ape_mean_joints"])
    assert scaled["ave_mean_joints"] == pytest.approx(MLD_UNIT_SCALE ** 2 * expect["ave_mean_joints"])


def test_variable_lengths_weight_ape_by_frames_and_ave_by_sequences():
    a, b = _motion(10), _motion(30)
    d1, d2 = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 2.0])
    out = ape_ave([a + d1, b + d2], [a, b], canonicalize=False)
    assert out["ape_mean_joints"] == pytest.approx((10 * 1.0 + 30 * 2.0) / 40)
    assert mpjpe([a + d1, b + d2], [a, b]) == pytest.approx(1.75)
    # a padded batch with lengths gives the same as the list
    pad = np.stack([np.concatenate([a, np.zeros((20, 22, 3))]), b])
    pad_pred = np.stack([np.concatenate([a + d1, np.full((20, 22, 3), 9.0)]), b + d2])
    assert ape_ave(pad_pred, pad, lengths=[10, 30], canonicalize=False) == pytest.approx(out)
    with pytest.raises(ValueError):
        ape_ave(a[:1], a[:1])  # AVE needs two frames


def test_mpjpe_known_values():
    gt = _motion(20)
    d = np.array([0.0, 0.3, 0.4])
    assert mpjpe(gt + d, gt) == pytest.approx(0.5)
    assert mpjpe(gt + d, gt, align_root=True) == pytest.approx(0.0, abs=1e-12)
    pred = gt.copy()
    pred[:, 0] += d  # only the root moves
    assert mpjpe(pred, gt) == pytest.approx(0.5 / 22)
    assert mpjpe(pred, gt, align_root=True) == pytest.approx(0.5 * 21 / 22)


# ------------------------------------------------------------------------------------------------ action metrics


def test_accuracy_and_confusion_matrix():
    labels = np.array([0, 1, 1, 2, 2, 2])
    pred = np.array([0, 1, 2, 2, 2, 0])
    assert accuracy(pred, labels) == pytest.approx(4 / 6)
    cm = confusion_matrix(pred, labels, 4)
    expect = np.zeros((4, 4), dtype=np.int64)
    expect[0, 0], expect[1, 1], expect[1, 2], expect[2, 2], expect[2, 0] = 1, 1, 1, 2, 1
    np.testing.assert_array_equal(cm, expect)  # rows = true label, columns = prediction
    assert np.trace(cm) / cm.sum() == pytest.approx(accuracy(pred, labels))
    logits = np.eye(4)[pred] * 5.0  # scores are reduced by argmax
    assert accuracy(logits, labels) == pytest.approx(4 / 6)


def test_action_diversity_and_multimodality():
    rng = np.random.default_rng(0)
    labels = np.repeat(np.arange(5), 40)
    centres = rng.normal(scale=10.0, size=(5, 30))
    same = centres[labels]  # identical samples within each class
    assert action_multimodality(same, labels, rng=0) == 0.0
    assert action_diversity(same, rng=0) > 0.0
    # two points per class at distance r_c, drawn with replacement: P(differ) = 1/2 -> mean(r) / 2
    r = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    lab2 = np.repeat(np.arange(5), 2)
    emb2 = np.zeros((10, 2))
    emb2[1::2, 0] = r
    mm = action_multimodality(emb2, lab2, pairs=20000, rng=1)
    assert mm == pytest.approx(r.mean() / 2, abs=0.05)  # std about 0.01
    # diversity with replacement over two equal clusters 5 apart: 2.5
    x = np.zeros((1000, 2))
    x[500:] = [3.0, 4.0]
    assert action_diversity(x, pairs=20000, rng=2) == pytest.approx(2.5, abs=0.1)
    # deterministic under the rng, different for another seed
    z = rng.normal(size=(200, 30))
    lz = rng.integers(0, 12, 200)
    assert action_multimodality(z, lz, rng=3) == action_multimodality(z, lz, rng=np.random.default_rng(3))
    assert action_diversity(z, rng=3) == action_diversity(z, rng=3)
    assert action_diversity(z, rng=3) != action_diversity(z, rng=4)
