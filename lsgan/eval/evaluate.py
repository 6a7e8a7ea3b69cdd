"""The paper's evaluation tables (``lsgan evaluate``): text-to-motion, VAE reconstruction, action-to-motion.

Text-to-motion follows T2M's protocol: every replication draws one (motion window, caption) pair per test
window (lengths floored to a multiple of 4, one unit shorter with probability 1/3, as MLD), generates a
motion for each caption at the real length, embeds everything with the evaluator (captions as their stored
HumanML3D tokens for the official one) and computes R-precision (groups of 32), MM-Dist, FID, Diversity (300
pairs) and MultiModality (``mm_captions`` captions x ``mm_samples`` motions, 10 pairs). FID's real set is a
second, independent draw (T2M's and MDM's separate pass; ``fid_reference='same'``: for model rows the draw
that gave their captions and lengths, as MLD). The Real row scores the drawn real motions themselves, its FID
against the second draw. Each figure is reported as the mean over replications with its 95% half-width
(1.96 std / sqrt(n)).
"""
from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from lsgan.eval import metrics as M
from lsgan import outputs
from lsgan.io import atomic_file

QUALITY_COLUMNS = ("foot_skating_ratio", "penetration_m", "floating_m", "jerk_m_s3", "bone_std_mm")
"""What animators read (lsgan.motion.quality): GMD's foot-skating ratio, ground penetration, floating, mean jerk,
bone-length variation (before any rigid fit)."""
T2M_COLUMNS = ("r_precision_top1", "r_precision_top2", "r_precision_top3", "fid", "mm_dist", "diversity",
               "multimodality", *QUALITY_COLUMNS)
VAE_COLUMNS = ("ape_root", "ape_traj", "ape_mean_pose", "ape_mean_joints", "ave_root", "ave_traj",
               "ave_mean_pose", "ave_mean_joints", "mpjpe", "mpjpe_rel", "fid", *QUALITY_COLUMNS)
ACTION_COLUMNS = ("fid", "accuracy", "diversity", "multimodality")
FID_REFERENCES = {
    "separate": "each row against a separate pass over the real test data (T2M, MDM)",
    "same": "model rows against the real draw that gave their captions and lengths (MLD); "
            "Real against a separate pass",
}
LABELS = {"r_precision_top1": "R-P top1 ↑", "r_precision_top2": "R-P top2 ↑", "r_precision_top3": "R-P top3 ↑",
          "fid": "FID ↓", "mm_dist": "MM-Dist ↓", "diversity": "Diversity →", "multimodality": "MModality ↑",
          "accuracy": "Accuracy ↑", "mpjpe": "MPJPE (m) ↓", "foot_skating_ratio": "Skating ↓",
          "penetration_m": "Penetration (m) ↓", "floating_m": "Floating (m) ↓", "jerk_m_s3": "Jerk (m/s³) →",
          "mpjpe_rel": "MPJPE root-rel. (m) ↓", "bone_std_mm": "Bone σ (mm) ↓"}


@dataclass
class Table:
    """Rows of per-replication values; ``summary`` gives (mean, 95% half-width) per cell; ``notes`` follow the table."""

    kind: str
    columns: tuple[str, ...]
    rows: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def add(self, row: str, column: str, value: float) -> None:
        self.rows.setdefault(row, {}).setdefault(column, []).append(float(value))

    def note_fid_sample(self, n: int, dim: int) -> None:
        """Say when an FID comes from no more motions than its embedding has dimensions (a small test split):
        the covariances are then singular, and the FID is biased upward and noisy."""
        if n <= dim:
            self.notes.append(f"FID from {n} motions per draw in a {dim}-d embedding: with no more motions than "
                              "dimensions the covariances are singular, so the FID is biased upward and noisy; "
                              "compare it only with FIDs over as many motions.")

    def summary(self) -> dict[str, dict[str, tuple[float, float]]]:
        return {r: {c: M.mean_ci(np.asarray(v)) for c, v in cols.items()} for r, cols in self.rows.items()}

    def to_json(self) -> dict:
        return {"kind": self.kind, "info": self.info, "notes": self.notes,
                "rows": {r: {c: {"mean": m, "ci95": h, "values": self.rows[r][c]} for c, (m, h) in cols.items()}
                         for r, cols in self.summary().items()}}

    def to_markdown(self) -> str:
        head = "| | " + " | ".join(LABELS.get(c, c) for c in self.columns) + " |"
        lines = [head, "| --- |" + " ---: |" * len(self.columns)]
        for r, cols in self.summary().items():
            cells = []
            for c in self.columns:
                if c not in cols:
                    cells.append("–")
                    continue
                m, h = cols[c]
                cells.append(f"{m:.3f}" + (f" ±{h:.3f}" if len(self.rows[r][c]) > 1 else ""))
            lines.append(f"| {r} | " + " | ".join(cells) + " |")
        return "\n".join(lines + ([""] + self.notes if self.notes else []))


def claim_table(out: str | Path, *, force: bool = False) -> tuple[Path, Path]:
    """The table's two files, ``out.md`` and ``out.json``, once it is clear they may be written."""
    out = Path(out)
    md, js = out.with_suffix(".md"), out.with_suffix(".json")
    return outputs.claim_file(md, force=force), outputs.claim_file(js, force=force)


def write_table(table: Table, out: str | Path, *, force: bool = False) -> tuple[Path, Path]:
    """``out.md`` and ``out.json`` (atomic; existing ones only with ``force``, and only lsgan's)."""
    md, js = claim_table(out, force=force)
    with atomic_file(md, "w", encoding="utf-8") as fh:
        fh.write(table.to_markdown() + "\n")
    with atomic_file(js, "w", encoding="utf-8") as fh:
        json.dump(table.to_json(), fh, indent=1)
    return md, js


def _windows(data, split: str, min_frames: int, max_frames: int):
    """The evaluation windows of ``split`` (one per clip); an empty split is an error naming the file."""
    from lsgan.data.dataset import MotionDataset

    dataset = MotionDataset(data, split, min_frames=min_frames, max_frames=max_frames, normalize=False)
    if not len(dataset):
        raise ValueError(f"{data}: no clips of {min_frames}+ frames in the {split!r} split")
    return dataset


class Draw(NamedTuple):
    """One real draw: per test window a crop (de-normalised features), its caption and the caption's tokens."""

    motions: list[np.ndarray]
    captions: list[str]
    tokens: list[str]


def _draw(dataset, seed: int) -> Draw:
    """One real draw: a window crop and a caption per test window (torch RNG seeded, as the loaders)."""
    torch.manual_seed(seed)
    motions, captions, tokens = [], [], []
    for i in range(len(dataset)):
        item = dataset[i]
        motions.append(item["motion"].numpy())
        captions.append(item["caption"])
        tokens.append(item["tokens"])
    return Draw(motions, captions, tokens)


@dataclass
class _Row:
    """One row's motions of a replication (de-normalised features) and their evaluator embeddings."""

    motions: list[np.ndarray]
    emb: np.ndarray


def _t2m_cells(table: Table, name: str, row: _Row, text_emb: np.ndarray, reference: np.ndarray, seed: int,
               rng: np.random.Generator) -> None:
    """T2M's figures of one row in one replication: R-precision, MM-Dist, FID against the real embeddings
    ``reference``, Diversity."""
    top = M.r_precision(text_emb, row.emb, top_k=3, rng=np.random.default_rng(seed))
    for k in range(3):
        table.add(name, f"r_precision_top{k + 1}", top[k])
    table.add(name, "mm_dist", M.matching_score(text_emb, row.emb, rng=np.random.default_rng(seed)))
    table.add(name, "fid", M.fid(reference, row.emb))
    table.add(name, "diversity", M.diversity(row.emb, pairs=min(300, len(row.emb) // 2), rng=rng))


def _quality_cells(table: Table, name: str, motions: list[np.ndarray]) -> None:
    """The motion-quality figures of one row in one replication, on the joints recovered from its features."""
    from lsgan.data.features import recover_from_ric
    from lsgan.motion.quality import quality_metrics

    q = quality_metrics([recover_from_ric(m) for m in motions])
    for column in QUALITY_COLUMNS:
        table.add(name, column, q[column])


def _model_row(table: Table, name: str, generate: Callable, draw: Draw, ev, rng: np.random.Generator, *, seed: int,
               mm_captions: int, mm_samples: int) -> _Row:
    """A model's motions for the draw's captions at its lengths (``generate(requests, num=, seed=)``); its
    MultiModality cell on the way."""
    from lsgan.generate import Request

    requests = [Request(text=c, frames=len(m)) for c, m in zip(draw.captions, draw.motions)]
    motions = [m.features for m in generate(requests, num=1, seed=seed).motions]
    if mm_captions and mm_samples:
        pick = rng.choice(len(requests), size=min(mm_captions, len(requests)), replace=False)
        mm = generate([requests[i] for i in pick], num=mm_samples, seed=seed + 7919)
        emb = ev.embed_motions([m.features for m in mm.motions]).reshape(len(pick), mm_samples, -1)
        table.add(name, "multimodality", M.multimodality(emb, pairs=min(10, mm_samples), rng=rng))
    return _Row(motions, ev.embed_motions(motions))


def evaluate_text_to_motion(
    models: dict[str, str | Path],
    vae: str | Path,
    data: str | Path,
    evaluator: str | Path,
    *,
    split: str = "test",
    replications: int = 20,
    mm_captions: int = 100,
    mm_samples: int = 30,
    min_frames: int = 40,
    max_frames: int = 196,
    seed: int = 0,
    device: str = "auto",
    steps: int | None = None,
    guidance: float | None = None,
    fid_reference: str = "separate",
    progress: Callable[[str], None] | None = None,
) -> Table:
    """The text-to-motion table: a Real row and one row per model (GAN or diffusion checkpoint).

    The evaluator reads each caption's stored tokens (the official one's word vectoriser; ours reads the
    sentence). ``fid_reference`` (see :data:`FID_REFERENCES`): 'separate' compares every row with a second,
    independent real draw (T2M, MDM); 'same' compares model rows with the draw that gave their captions and
    lengths (MLD), the Real row still with the second draw.
    """
    from lsgan.data.dataset import MotionDataset
    from lsgan.generate import generate
    from lsgan.models.evaluator import load_evaluator
    from lsgan.device import pick_device

    if fid_reference not in FID_REFERENCES:
        raise ValueError(f"fid_reference must be one of {', '.join(FID_REFERENCES)}, not {fid_reference!r}")
    dev = pick_device(device)
    ev = load_evaluator(evaluator, device=dev)
    dataset = MotionDataset(data, split, min_frames=min_frames, max_frames=max_frames, normalize=False,
                            require_captions=True)
    if len(dataset) < 32:
        raise ValueError(f"{data}: split {split!r} has {len(dataset)} captioned windows; R-precision needs >= 32")
    table = Table("text-to-motion", T2M_COLUMNS, info={
        "data": str(data), "split": split, "windows": len(dataset), "evaluator": ev.id, "vae": str(vae),
        "replications": replications, "mm_captions": mm_captions, "mm_samples": mm_samples, "seed": seed,
        "fid_reference": fid_reference, "models": {k: str(v) for k, v in models.items()}},
        notes=[f"FID reference: {FID_REFERENCES[fid_reference]}."])
    gen_kwargs = {k: v for k, v in (("steps", steps), ("guidance", guidance)) if v is not None}
    for name in ("Real", *models):  # row order: Real first (MultiModality fills the model rows earlier)
        table.rows[name] = {}
    for r in range(replications):
        rng = np.random.default_rng(seed + r)
        draw = _draw(dataset, seed + 1000 * r)
        second = _draw(dataset, seed + 1000 * r + 1)
        text_emb = ev.embed_texts(draw.captions, tokens=draw.tokens)
        rows = {"Real": _Row(draw.motions, ev.embed_motions(draw.motions))}
        for name, path in models.items():
            if progress:
                progress(f"replication {r + 1}/{replications}: {name}")
            model = partial(generate, path, vae, device=str(dev), **gen_kwargs)
            rows[name] = _model_row(table, name, model, draw, ev, rng, seed=seed + r, mm_captions=mm_captions,
                                    mm_samples=mm_samples)
        second_emb = ev.embed_motions(second.motions)
        for name, row in rows.items():
            reference = second_emb if name == "Real" or fid_reference == "separate" else rows["Real"].emb
            _t2m_cells(table, name, row, text_emb, reference, seed + r, rng)
            _quality_cells(table, name, row.motions)
    if replications:
        table.note_fid_sample(len(dataset), second_emb.shape[1])
    return table


def evaluate_reconstruction(
    vae: str | Path,
    data: str | Path,
    *,
    evaluator: str | Path | None = None,
    split: str = "test",
    replications: int = 1,
    min_frames: int = 40,
    max_frames: int = 196,
    seed: int = 0,
    device: str = "auto",
    batch_size: int = 128,
) -> Table:
    """The VAE table: APE/AVE (root, trajectory, mean pose, mean joints), MPJPE (global and root-relative), the
    motion-quality figures and (with an evaluator) FID of reconstructions (encoder mean, decoder) against the real
    motions; a Real row holds the real motions' quality figures.

    APE/AVE are computed as MLD's ComputeMetrics does, in MLD's units (metres x 0.64), so the numbers sit
    beside the paper's VAE table; MPJPE is in metres on global joint positions."""
    from lsgan.data.features import recover_from_ric
    from lsgan.models.vae import load_vae
    from lsgan.device import pick_device

    dev = pick_device(device)
    model, meta = load_vae(vae, device=dev)
    mean, std = np.asarray(meta["mean"], np.float32), np.asarray(meta["std"], np.float32)
    ev = None
    if evaluator is not None:
        from lsgan.models.evaluator import load_evaluator

        ev = load_evaluator(evaluator, device=dev)
    dataset = _windows(data, split, min_frames, max_frames)
    table = Table("vae-reconstruction", VAE_COLUMNS, info={"data": str(data), "split": split, "vae": str(vae),
                                                          "windows": len(dataset), "replications": replications,
                                                          "ape_ave_units": "MLD (metres x 0.64)"})
    table.rows["Real"] = {}  # first
    for r in range(replications):
        real = _draw(dataset, seed + 1000 * r).motions
        recon: list[np.ndarray] = [None] * len(real)  # type: ignore[list-item]
        order = sorted(range(len(real)), key=lambda i: len(real[i]))
        with torch.no_grad():
            for b in range(0, len(order), batch_size):
                idx = order[b:b + batch_size]
                n = max(len(real[i]) for i in idx)
                x = np.zeros((len(idx), n, real[0].shape[1]), np.float32)
                mask = np.zeros((len(idx), n), bool)
                for j, i in enumerate(idx):
                    x[j, :len(real[i])] = (real[i] - mean) / std
                    mask[j, :len(real[i])] = True
                xt, mt = torch.from_numpy(x).to(dev), torch.from_numpy(mask).to(dev)
                mu, _ = model.encode(xt, mt)
                out = model.decode(mu, mt).float().cpu().numpy()
                for j, i in enumerate(idx):
                    recon[i] = out[j, :len(real[i])] * std + mean
        gt_joints = [recover_from_ric(m) for m in real]
        rec_joints = [recover_from_ric(m.astype(np.float32)) for m in recon]
        for k, v in M.ape_ave(rec_joints, gt_joints, unit_scale=M.MLD_UNIT_SCALE).items():
            table.add("VAE", k, v)
        table.add("VAE", "mpjpe", M.mpjpe(rec_joints, gt_joints))
        table.add("VAE", "mpjpe_rel", M.mpjpe(rec_joints, gt_joints, align_root=True))
        _quality_cells(table, "Real", real)
        _quality_cells(table, "VAE", recon)
        if ev is not None:
            real_emb = ev.embed_motions(real)
            table.add("VAE", "fid", M.fid(real_emb, ev.embed_motions(recon)))
            if r == 0:
                table.note_fid_sample(len(real), real_emb.shape[1])
    return table


def evaluate_action_to_motion(
    models: dict[str, str | Path],
    vae: str | Path,
    data: str | Path,
    classifier: str | Path,
    *,
    split: str = "test",
    replications: int = 20,
    samples: int = 1000,
    seed: int = 0,
    device: str = "auto",
    min_frames: int = 16,
    max_frames: int = 196,
    steps: int | None = None,
    guidance: float | None = None,
    progress: Callable[[str], None] | None = None,
) -> Table:
    """HumanAct12-style table: FID (classifier's 30-d features), accuracy, diversity (200 pairs) and
    multimodality (20 pairs per class), for ``samples`` motions with labels and lengths drawn from the real
    test windows; a Real row from the real windows themselves."""
    from lsgan.data.features import recover_from_ric
    from lsgan.generate import Request, generate
    from lsgan.models.evaluator import load_action_classifier
    from lsgan.device import pick_device

    dev = pick_device(device)
    clf = load_action_classifier(classifier, device=dev)
    dataset = _windows(data, split, min_frames, max_frames)
    labels_all = np.array([int(dataset.actions[w.shard][w.clip]) for w in dataset.windows])
    if (labels_all < 0).any():
        raise ValueError(f"{data}: some {split} clips have no action label; the action table needs labelled clips")
    names = dataset.action_names
    table = Table("action-to-motion", ACTION_COLUMNS, info={"data": str(data), "split": split, "samples": samples,
                                                           "replications": replications, "actions": names})
    gen_kwargs = {k: v for k, v in (("steps", steps), ("guidance", guidance)) if v is not None}
    for r in range(replications):
        rng = np.random.default_rng(seed + r)
        real = _draw(dataset, seed + 1000 * r).motions
        real_joints = [recover_from_ric(m) for m in real]
        real_feat = clf.features(real_joints)
        pick = rng.choice(len(real), size=samples, replace=samples > len(real))
        rows = {"Real": (real_feat, labels_all, clf.predict(real_joints))}
        for name, path in models.items():
            if progress:
                progress(f"replication {r + 1}/{replications}: {name}")
            requests = [Request(action=names[labels_all[i]], frames=len(real[i])) for i in pick]
            out = generate(path, vae, requests, num=1, seed=seed + r, device=str(dev), **gen_kwargs)
            joints = [m.raw_joints for m in out.motions]  # the decoded joints, as the protocol scores them
            rows[name] = (clf.features(joints), labels_all[pick], clf.predict(joints))
        for name, (feat, labels, pred) in rows.items():
            table.add(name, "fid", M.fid(real_feat, feat))
            table.add(name, "accuracy", M.accuracy(pred, labels))
            table.add(name, "diversity", M.action_diversity(feat, pairs=min(200, len(feat) // 2), rng=rng))
            table.add(name, "multimodality", M.action_multimodality(feat, labels, pairs=20, rng=rng))
    if replications:
        table.note_fid_sample(min(samples, len(real)), real_feat.shape[1])
    return table
