"""Metrics on embeddings (numpy in, floats out)."""
from __future__ import annotations

import numpy as np
from scipy import linalg


def gaussian_stats(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and covariance (D,D) of samples (N,D), in float64."""
    x = np.asarray(x, dtype=np.float64)
    return x.mean(0), np.cov(x, rowvar=False)


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray, eps: float = 1e-6) -> float:
    """||mu1-mu2||^2 + Tr(S1 + S2 - 2 sqrt(S1 S2)): the distance behind FID."""
    diff = mu1 - mu2
    covmean = linalg.sqrtm(sigma1 @ sigma2)
    if not np.isfinite(covmean).all():
        offset = np.eye(len(sigma1)) * eps
        covmean = linalg.sqrtm((sigma1 + offset) @ (sigma2 + offset))
    covmean = covmean.real
    return float(diff @ diff + np.trace(sigma1) + np.trace(sigma2) - 2.0 * np.trace(covmean))


def fid(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance between two sets of embeddings (N,D) and (M,D)."""
    return frechet_distance(*gaussian_stats(a), *gaussian_stats(b))


# ---------------------------------------------------------------------------------------------------------------
# Shared helpers
# ---------------------------------------------------------------------------------------------------------------

def _as_rng(rng) -> np.random.Generator:
    """A Generator from a Generator or an int seed (never the global numpy state)."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None:
        raise ValueError("this metric samples at random: pass rng (a np.random.Generator or an int seed)")
    return np.random.default_rng(rng)


def pairwise_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distances (..., N, M) between rows of a (..., N, D) and b (..., M, D), in float64."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    d2 = (a * a).sum(-1)[..., :, None] + (b * b).sum(-1)[..., None, :] - 2.0 * a @ np.swapaxes(b, -1, -2)
    return np.sqrt(np.maximum(d2, 0.0))


# ---------------------------------------------------------------------------------------------------------------
# Text-to-motion (T2M / Guo et al. 2022; same numbers as MLD's TM2TMetrics)
# ---------------------------------------------------------------------------------------------------------------

def retrieval_metrics(text_emb: np.ndarray, motion_emb: np.ndarray, *, top_k: int = 3, group_size: int = 32,
                      rng=None) -> tuple[np.ndarray, float]:
    """R-precision top-1..top-k (cumulative, shape (top_k,)) and MM-Dist, the T2M protocol.

    Row i of text_emb (N, D) is the caption of row i of motion_emb (N, D). The pairs are shuffled together (when
    rng, a Generator or int seed, is given; otherwise kept in order), cut into groups of group_size (32), the
    remainder that does not fill a group is dropped; in each group every caption ranks the group's motions by
    Euclidean distance and counts a hit at k when its own motion is among the k nearest (ties broken by position,
    a stable sort, so a collapsed generator scores chance, not 1). MM-Dist is the mean distance between matched
    caption and motion over the same groups. As T2M eval_t2m.evaluate_matching_score / MLD TM2TMetrics.compute.
    """
    t = np.asarray(text_emb, dtype=np.float64)
    m = np.asarray(motion_emb, dtype=np.float64)
    if t.ndim != 2 or t.shape != m.shape:
        raise ValueError(f"text_emb and motion_emb must both be (N, D), got {t.shape} and {m.shape}")
    if top_k > group_size:
        raise ValueError(f"top_k={top_k} exceeds group_size={group_size}")
    n_groups = len(t) // group_size
    if n_groups == 0:
        raise ValueError(f"need at least group_size={group_size} pairs, got {len(t)}")
    if rng is not None:
        perm = _as_rng(rng).permutation(len(t))
        t, m = t[perm], m[perm]
    n = n_groups * group_size
    t = t[:n].reshape(n_groups, group_size, -1)
    m = m[:n].reshape(n_groups, group_size, -1)
    dist = pairwise_distances(t, m)  # (G, S, S): caption x motion
    order = np.argsort(dist, axis=-1, kind="stable")[..., :top_k]  # (G, S, k)
    hit = order == np.arange(group_size)[None, :, None]
    top = np.logical_or.accumulate(hit, axis=-1)  # hit within the first k
    r_prec = top.reshape(n, top_k).mean(0)
    mm_dist = float(np.trace(dist, axis1=1, axis2=2).sum() / n)
    return r_prec, mm_dist


def r_precision(text_emb: np.ndarray, motion_emb: np.ndarray, *, top_k: int = 3, group_size: int = 32,
                rng=None) -> np.ndarray:
    """R-precision top-1..top-k (shape (top_k,)), T2M protocol; see retrieval_metrics."""
    return retrieval_metrics(text_emb, motion_emb, top_k=top_k, group_size=group_size, rng=rng)[0]


def matching_score(text_emb: np.ndarray, motion_emb: np.ndarray, *, group_size: int = 32, rng=None) -> float:
    """MM-Dist (matching score): mean caption-motion distance over the full groups, T2M; see retrieval_metrics."""
    return retrieval_metrics(text_emb, motion_emb, top_k=1, group_size=group_size, rng=rng)[1]


def diversity(emb: np.ndarray, *, pairs: int = 300, rng) -> float:
    """Diversity, T2M protocol: mean distance between emb[i] and emb[j] over `pairs` pairs, where the first and
    the second index sets are each drawn without replacement (T2M calculate_diversity; needs N >= pairs)."""
    x = np.asarray(emb, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"emb must be (N, D), got {x.shape}")
    if len(x) < pairs:
        raise ValueError(f"diversity needs at least pairs={pairs} embeddings, got {len(x)}")
    g = _as_rng(rng)
    i = g.choice(len(x), pairs, replace=False)
    j = g.choice(len(x), pairs, replace=False)
    return float(np.linalg.norm(x[i] - x[j], axis=-1).mean())


def multimodality(emb: np.ndarray, *, pairs: int = 10, rng) -> float:
    """MultiModality, T2M protocol: emb (C, S, D) holds S generations for each of C captions; two index sets of
    size `pairs` are drawn from range(S) without replacement (the same sets for every caption, as T2M
    calculate_multimodality) and the mean distance over the C x pairs pairs is returned (needs S >= pairs)."""
    x = np.asarray(emb, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"emb must be (C, S, D), got {x.shape}")
    if x.shape[1] < pairs:
        raise ValueError(f"multimodality needs at least pairs={pairs} samples per condition, got {x.shape[1]}")
    g = _as_rng(rng)
    i = g.choice(x.shape[1], pairs, replace=False)
    j = g.choice(x.shape[1], pairs, replace=False)
    return float(np.linalg.norm(x[:, i] - x[:, j], axis=-1).mean())


def mean_ci(values, axis: int = 0):
    """Mean and 95% confidence half-width 1.96 * std / sqrt(n) over replications (numpy std, ddof=0), as T2M's
    get_metric_statistics. Floats for a 1-D input; arrays when values has more axes (reduced along `axis`)."""
    v = np.asarray(values, dtype=np.float64)
    n = v.shape[axis]
    mean = v.mean(axis)
    half = 1.96 * v.std(axis) / np.sqrt(n)
    if np.ndim(mean) == 0:
        return float(mean), float(half)
    return mean, half


# ---------------------------------------------------------------------------------------------------------------
# Reconstruction: APE / AVE (TEMOS / MLD ComputeMetrics) and MPJPE
# ---------------------------------------------------------------------------------------------------------------

# MLD's ComputeMetrics(force_in_meter=True) divides HumanML3D joints (already metres) by 1000 * 0.75 / 480 = 1.5625,
# i.e. its APE/AVE tables are in units of 1.5625 m. Pass unit_scale=MLD_UNIT_SCALE to reproduce that scale.
MLD_UNIT_SCALE = 480.0 / (1000.0 * 0.75)

# Joint indices MLD's Rifke uses for HumanML3D (mld/utils/joints.py humanml3d_joints), 22-joint SMPL order.
_FEET = (8, 11, 7, 10)  # "LMrot", "LF", "RMrot", "RF" as MLD names them
# get_forward_direction is called by MLD on the poses *without* the root joint, with indices of the full list
# ("RH"=1, "LH"=2, "RS"=16, "LS"=17); reproduced as is, i.e. on joints[1:].
_FWD_RH, _FWD_LH, _FWD_RS, _FWD_LS = 1, 2, 16, 17


def _sequences(x, lengths=None) -> list[np.ndarray]:
    """A list of (T, J, 3) float64 arrays from (T, J, 3), (B, T, J, 3) (+ optional lengths) or a list."""
    if isinstance(x, (list, tuple)):
        seqs = [np.asarray(s, dtype=np.float64) for s in x]
    else:
        a = np.asarray(x, dtype=np.float64)
        if a.ndim == 3:
            seqs = [a]
        elif a.ndim == 4:
            seqs = list(a)
        else:
            raise ValueError(f"joints must be (T, J, 3), (B, T, J, 3) or a list of (T, J, 3), got {a.shape}")
    if lengths is not None:
        if len(lengths) != len(seqs):
            raise ValueError(f"{len(lengths)} lengths for {len(seqs)} sequences")
        seqs = [s[: int(n)] for s, n in zip(seqs, lengths)]
    for s in seqs:
        if s.ndim != 3 or s.shape[-1] != 3:
            raise ValueError(f"each sequence must be (T, J, 3), got {s.shape}")
    return seqs


def _mld_decompose(j: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """MLD ComputeMetrics.transform on one (T, J, 3) sequence: Rifke features and back (numpy port).

    The floor (a soft minimum of the feet heights over the sequence) is subtracted from y; the first frame's root
    is put at the origin of the ground plane and its facing direction is made canonical. Returns
    joints (T, J, 3) so canonicalised, local poses (T, J-1, 3) (ground coordinates relative to the root and rotated
    into the body's own facing frame, y from the floor), root (T, 3) = (traj x, root y, traj z), trajectory (T, 2).
    """
    poses = j.copy()
    foot = poses[:, _FEET, 1].min(-1)  # (T,)
    mx, mn = foot.max(), foot.min()
    floor = mn - np.log(0.5 + np.exp(mn - mx))  # MLD's softmin(softness=0.5) over time
    poses[..., 1] -= floor
    root_y = poses[:, 0, 1].copy()
    traj = poses[:, 0, [0, 2]].copy()
    poses = poses[:, 1:].copy()
    poses[..., [0, 2]] -= traj[:, None, :]
    vel = np.diff(traj, axis=0, prepend=traj[:1])  # first frame 0
    across = poses[:, _FWD_RH] - poses[:, _FWD_LH] + poses[:, _FWD_RS] - poses[:, _FWD_LS]
    fwd = np.stack((-across[:, 2], across[:, 0]), -1)
    fwd = fwd / np.maximum(np.linalg.norm(fwd, axis=-1, keepdims=True), 1e-12)
    sin, cos = fwd[:, 0], fwd[:, 1]
    angles = np.arctan2(sin, cos)
    rot_inv = np.stack((np.stack((cos, sin), -1), np.stack((-sin, cos), -1)), -2)  # (T, 2, 2)
    xz = np.einsum("tlj,tjk->tlk", poses[..., [0, 2]], rot_inv)
    local = np.stack((xz[..., 0], poses[..., 1], xz[..., 1]), -1)  # (T, J-1, 3)
    vel_local = np.einsum("tj,tjk->tk", vel, rot_inv)
    # inverse: integrate heading and trajectory from the first frame
    rel = np.cumsum(np.diff(angles, prepend=angles[:1]))
    rel = rel - rel[0]
    c, s = np.cos(rel), np.sin(rel)
    rot = np.stack((np.stack((c, -s), -1), np.stack((s, c), -1)), -2)
    g = np.einsum("tlj,tjk->tlk", local[..., [0, 2]], rot)
    glob = np.stack((g[..., 0], local[..., 1], g[..., 1]), -1)
    trajectory = np.cumsum(np.einsum("tj,tjk->tk", vel_local, rot), axis=0)
    trajectory = trajectory - trajectory[:1]
    root = np.stack((trajectory[:, 0], root_y, trajectory[:, 1]), -1)
    joints = np.concatenate((np.zeros_like(glob[:, :1]), glob), 1)
    joints[:, 0, 1] = root_y
    joints[..., [0, 2]] += trajectory[:, None, :]
    return joints, local, root, trajectory


def _raw_decompose(j: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The same four parts without canonicalisation: global joints, joints minus the root (J-1), root, root x,z."""
    root = j[:, 0]
    return j, j[:, 1:] - root[:, None], root, root[:, [0, 2]]


def _var(x: np.ndarray) -> np.ndarray:
    """Variance over time (axis 0) with the T-1 denominator (MLD metrics.utils.variance)."""
    return ((x - x.mean(0)) ** 2).sum(0) / (len(x) - 1)


def ape_ave(pred_joints, gt_joints, *, lengths=None, canonicalize: bool = True,
            unit_scale: float = 1.0) -> dict[str, float]:
    """APE and AVE for root, trajectory, mean pose and mean joints (TEMOS / MLD ComputeMetrics, MLD Table 3).

    pred_joints, gt_joints: (T, J, 3), (B, T, J, 3) with optional lengths, or lists of (T_i, J, 3) (HumanML3D
    22-joint order, y up, metres). With canonicalize=True each sequence goes through MLD's Rifke round trip
    (floor removed, first frame at the ground origin facing a canonical direction); root = (trajectory x, root
    height, trajectory z), traj = the 2-d ground trajectory, pose = the J-1 non-root joints in the body's local
    frame (ground coordinates relative to the root, rotated by the body's heading), joints = all canonicalised
    joints. With canonicalize=False: global root, root x,z, joints minus root, global joints.
    APE_* = L2 position error averaged over all frames of all sequences (and over joints for mean_pose /
    mean_joints); AVE_* = L2 between the per-coordinate temporal variances (T-1 denominator) of prediction and
    ground truth, per sequence (and joint), averaged over sequences (and joints); APE is in metres, AVE in square
    metres. The decomposed positions are multiplied by unit_scale (MLD_UNIT_SCALE reproduces MLD's reported numbers).
    """
    preds, gts = _sequences(pred_joints, lengths), _sequences(gt_joints, lengths)
    if len(preds) != len(gts):
        raise ValueError(f"{len(preds)} predicted sequences for {len(gts)} ground-truth ones")
    split = _mld_decompose if canonicalize else _raw_decompose
    names = ("joints", "pose", "root", "traj")
    ape_sum = {k: 0.0 for k in names}
    ave_sum = {k: 0.0 for k in names}
    frames = 0
    for p, g in zip(preds, gts):
        if p.shape != g.shape:
            raise ValueError(f"prediction {p.shape} and ground truth {g.shape} differ")
        if len(p) < 2:
            raise ValueError("AVE needs at least 2 frames per sequence")
        frames += len(p)
        for k, a, b in zip(names, split(p), split(g)):
            # MLD scales the decomposed positions: APE scales with unit_scale, AVE (a variance) with its square
            a, b = a * unit_scale, b * unit_scale
            ape_sum[k] += np.linalg.norm(a - b, axis=-1).mean(-1).sum() if a.ndim == 3 \
                else np.linalg.norm(a - b, axis=-1).sum()
            ave_sum[k] += np.linalg.norm(_var(a) - _var(b), axis=-1).mean()
    n = len(preds)
    key = {"root": "root", "traj": "traj", "pose": "mean_pose", "joints": "mean_joints"}
    out = {}
    for k in ("root", "traj", "pose", "joints"):
        out[f"ape_{key[k]}"] = float(ape_sum[k] / frames)
    for k in ("root", "traj", "pose", "joints"):
        out[f"ave_{key[k]}"] = float(ave_sum[k] / n)
    return out


def mpjpe(pred, gt, *, lengths=None, align_root: bool = False) -> float:
    """Mean per-joint position error (metres for metre input): L2 between predicted and true joint positions,
    averaged over all frames and joints of all sequences (shapes as ape_ave); align_root=True subtracts each
    frame's root joint first (root-relative MPJPE)."""
    preds, gts = _sequences(pred, lengths), _sequences(gt, lengths)
    if len(preds) != len(gts):
        raise ValueError(f"{len(preds)} predicted sequences for {len(gts)} ground-truth ones")
    total, count = 0.0, 0
    for p, g in zip(preds, gts):
        if p.shape != g.shape:
            raise ValueError(f"prediction {p.shape} and ground truth {g.shape} differ")
        if align_root:
            p, g = p - p[:, :1], g - g[:, :1]
        e = np.linalg.norm(p - g, axis=-1)
        total += e.sum()
        count += e.size
    return float(total / count)


# ---------------------------------------------------------------------------------------------------------------
# Action-to-motion (Action2Motion / ACTOR protocol; FID = fid on the recogniser's 30-d features)
# ---------------------------------------------------------------------------------------------------------------

def _labels(x) -> np.ndarray:
    """Integer labels from labels (N,) or scores / logits (N, C) (argmax)."""
    a = np.asarray(x)
    if a.ndim == 2:
        a = a.argmax(-1)
    if a.ndim != 1:
        raise ValueError(f"labels must be (N,) or scores (N, C), got {a.shape}")
    return a.astype(np.int64)


def accuracy(pred_labels, labels) -> float:
    """Recognition accuracy: fraction of pred_labels (or argmax of scores (N, C)) equal to labels (ACTOR)."""
    p, y = _labels(pred_labels), _labels(labels)
    if p.shape != y.shape:
        raise ValueError(f"{p.shape} predictions for {y.shape} labels")
    return float((p == y).mean())


def confusion_matrix(pred, labels, num_classes: int) -> np.ndarray:
    """Confusion counts (num_classes, num_classes), int64, rows = true label, columns = prediction (ACTOR's
    confusion[label][pred]); accuracy = trace / sum."""
    p, y = _labels(pred), _labels(labels)
    if p.shape != y.shape:
        raise ValueError(f"{p.shape} predictions for {y.shape} labels")
    out = np.zeros((num_classes, num_classes), dtype=np.int64)
    np.add.at(out, (y, p), 1)
    return out


def action_diversity(emb: np.ndarray, *, pairs: int = 200, rng) -> float:
    """Action diversity (Action2Motion / ACTOR): mean distance over `pairs` pairs of indices drawn uniformly with
    replacement (np.random.randint in the reference), so a pair may repeat an index."""
    x = np.asarray(emb, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"emb must be (N, D), got {x.shape}")
    g = _as_rng(rng)
    i = g.integers(0, len(x), pairs)
    j = g.integers(0, len(x), pairs)
    return float(np.linalg.norm(x[i] - x[j], axis=-1).mean())


def action_multimodality(emb: np.ndarray, labels, *, pairs: int = 20, rng) -> float:
    """Action multimodality (Action2Motion / ACTOR): for every class present, `pairs` pairs of samples of that
    class drawn uniformly with replacement; mean distance over all these pairs (the reference's label quotas of
    `pairs` per label, divided by pairs x classes)."""
    x = np.asarray(emb, dtype=np.float64)
    y = _labels(labels)
    if x.ndim != 2 or len(x) != len(y):
        raise ValueError(f"emb must be (N, D) with N labels, got {x.shape} and {y.shape}")
    g = _as_rng(rng)
    dists = []
    for c in np.unique(y):
        idx = np.flatnonzero(y == c)
        i = idx[g.integers(0, len(idx), pairs)]
        j = idx[g.integers(0, len(idx), pairs)]
        dists.append(np.linalg.norm(x[i] - x[j], axis=-1))
    return float(np.concatenate(dists).mean())
