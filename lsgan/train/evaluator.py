"""Train the evaluators: our own text-motion evaluator (T2M's recipe) and an action-recognition GRU.

``train_evaluator(shards, "runs/evaluator", config=EvaluatorConfig(...), train_config=EvaluatorTrainConfig(...))``
trains the co-embedding as T2M's ``train_tex_mot_match.py`` does: windows of the 'train' split drawn
as T2M's loader draws them (one caption picked at random per draw, the length floored to a multiple of
4 and one unit shorter with probability 1/3, a random crop of that length, normalised with the shard's
Mean/Std), batches of 32, and T2M's contrastive loss with margin 10 on the Euclidean distance
between caption and motion embeddings: matched pairs are pulled together (d^2), and each caption is pushed
away from the motion of another item of its batch (the batch shifted by a random offset;
max(0, 10 - d)^2). Adam (lr 1e-4), gradients clipped to norm 0.5 per encoder, as there.

Differences from T2M, on purpose: the text side is a frozen sentence encoder with a trained head (no GloVe
here); the movement encoder is trained jointly with the rest (T2M pre-trains it in a motion autoencoder
and freezes it); the negative shift is drawn from 1..B-1 (T2M's ``randint(0, B-1)`` can draw 0, making the
"negatives" the positives).

Validation (every ``val_every`` steps, on the 'val' split, else 'test'): the contrastive loss with a
fixed shift and R-precision, on fixed windows; ``best/`` keeps the lowest validation loss (T2M keeps
``finest.tar`` the same way). At the end the best checkpoint is loaded as users load it and scored on
held-out pairs ('test', else 'val'): R-precision top-1/2/3 in groups of 32 and MM-Dist
(:func:`lsgan.eval.metrics.retrieval_metrics`), averaged over ``eval_repeats`` shuffles; written to
``out/heldout.json``.

``train_action_classifier(shards, "runs/act-clf", ...)`` trains the recogniser of
:class:`lsgan.models.evaluator.ActionRecognitionGRU` with cross-entropy on joints recovered from the
features (``recover_from_ric``), random crops of whole clips, and reports held-out accuracy.

Both write ``out/last`` and ``out/best`` with :mod:`lsgan.models.checkpoint`, ``out/log.csv``, resume
exactly with ``resume=True`` (weights, optimiser, step, RNG, sampler position) and stop on a NaN loss
keeping the last good checkpoint. They run in one process (the models are small).
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from lsgan.data.dataset import LengthBucketSampler, MotionDataset
from lsgan.data.features import recover_from_ric
from lsgan.data.shards import Shard
from lsgan.eval.metrics import retrieval_metrics
from lsgan.models.checkpoint import load_state, load_weights, save_checkpoint
from lsgan.models.evaluator import (
    ActionClassifierConfig,
    ActionRecognitionGRU,
    EvaluatorConfig,
    EvaluatorNet,
    LearnedEvaluator,
    contrastive_loss,
    load_action_classifier,
    load_learned_evaluator,
    prepare_joints,
)
from lsgan.train.common import (
    claim_run,
    RunLog,
    TrainingDiverged,
    check_finite,
    closing_progress_bars,
    pick_device,
    seed_everything,
)
from lsgan.train.vae import _rng_state, _set_rng_state, _train_batches, _truncate_log

__all__ = [
    "ActionTrainConfig",
    "EvaluatorTrainConfig",
    "heldout_pairs",
    "retrieval_report",
    "train_action_classifier",
    "train_evaluator",
]


@dataclass
class EvaluatorTrainConfig:
    """T2M's text_mot_match settings by default (batch 32, lr 1e-4, margin 10, clip 0.5, unit length 4)."""

    lr: float = 1e-4
    batch_size: int = 32
    margin: float = 10.0  # T2M --negative_margin
    max_steps: int = 2000
    val_every: int = 500
    ckpt_every: int = 500
    log_every: int = 50
    min_frames: int = 40
    max_frames: int = 196
    grad_clip: float = 0.5  # max grad norm, per encoder (text head; motion side); 0 = none
    num_workers: int = 0
    seed: int = 0
    group_size: int = 32  # R-precision groups
    eval_repeats: int = 10  # held-out R-precision: mean over this many shuffles


@dataclass
class ActionTrainConfig:
    lr: float = 1e-3
    batch_size: int = 64
    max_steps: int = 2000
    val_every: int = 250
    ckpt_every: int = 250
    log_every: int = 50
    min_frames: int = 16
    max_frames: int = 196
    grad_clip: float = 1.0
    num_workers: int = 0
    seed: int = 0


# ----------------------------------------------------------------------------------------------------------------
# Held-out pairs and the retrieval report

def _paths(data) -> list[str]:
    return [os.fspath(data)] if isinstance(data, (str, os.PathLike)) else [os.fspath(p) for p in data]


def _split_with_data(paths: list[str], order: Sequence[str]) -> str | None:
    for split in order:
        for p in paths:
            with Shard(p) as s:
                if len(s.indices(split)):
                    return split
    return None


def heldout_pairs(data, split: str, *, min_frames: int = 40, max_frames: int = 196, seed: int = 0
                  ) -> tuple[list[np.ndarray], list[str], list[str]]:
    """Fixed (features, caption, tokens) pairs of a split: every captioned window once (longer ones centre-cropped
    to ``max_frames``), one of its captions picked with ``seed``. Features are de-normalised (as stored)."""
    ds = MotionDataset(_paths(data), split, min_frames=min_frames, max_frames=max_frames, normalize=False,
                       require_captions=True)
    rng = np.random.default_rng(seed)
    feats, caps, toks = [], [], []
    shards: dict[int, Shard] = {}
    try:
        for w in ds.windows:
            if not w.captions:
                continue
            if w.shard not in shards:
                shards[w.shard] = Shard(ds.paths[w.shard])
            n = min(w.stop - w.start, max_frames)
            a = w.start + (w.stop - w.start - n) // 2
            feats.append(shards[w.shard].features(w.clip, a, a + n))
            c = ds.captions[w.shard][w.clip][w.captions[int(rng.integers(len(w.captions)))]]
            caps.append(c.text)
            toks.append(c.tokens)
    finally:
        for s in shards.values():
            s.close()
    return feats, caps, toks


def retrieval_report(text_emb: np.ndarray, motion_emb: np.ndarray, *, group_size: int = 32, repeats: int = 10,
                     seed: int = 0) -> dict:
    """R-precision top-1/2/3 and MM-Dist (mean over ``repeats`` shuffles), the group size used and chance levels.

    With fewer pairs than ``group_size`` the groups hold all pairs (and chance rises accordingly).
    """
    n = len(text_emb)
    g = min(group_size, n)
    if g < 3:
        raise ValueError(f"{n} held-out pairs: too few for R-precision")
    tops, mms = [], []
    for r in range(max(1, repeats)):
        top, mm = retrieval_metrics(text_emb, motion_emb, top_k=3, group_size=g, rng=np.random.default_rng(seed + r))
        tops.append(top)
        mms.append(mm)
    top = np.mean(tops, 0)
    return {"r_precision_top1": float(top[0]), "r_precision_top2": float(top[1]), "r_precision_top3": float(top[2]),
            "mm_dist": float(np.mean(mms)), "pairs": n, "group_size": g,
            "chance_top1": 1 / g, "chance_top2": 2 / g, "chance_top3": 3 / g}


# ----------------------------------------------------------------------------------------------------------------
# The loop both trainers share

def _say_to(out: Path, enabled: bool = True) -> Callable[[str], None]:
    def say(msg: str) -> None:
        if not enabled:
            return
        tqdm.write(msg, file=sys.stderr)
        out.mkdir(parents=True, exist_ok=True)
        with open(out / "train.log", "a") as f:
            f.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {msg}\n")
    return say


def _start(out: Path, resume: bool, say) -> dict | None:
    if resume and (out / "last").exists():
        state = load_state(out / "last")
        if state is None:
            raise FileNotFoundError(f"{out / 'last'}: no state.pt to resume from")
        return state
    if resume:
        say(f"{out}: nothing to resume; starting a new run")
    elif (out / "last").exists():
        raise FileExistsError(f"{out} already holds a run; pass resume=True to continue it or choose another folder")
    return None


@closing_progress_bars
def _loop(*, out: Path, kind: str, desc: str, net: torch.nn.Module, opt: torch.optim.Optimizer, ds: Dataset,
          sampler: LengthBucketSampler, cfg, dev: torch.device, state: dict | None, config: dict,
          step_fn: Callable[[dict], dict[str, float]], validate: Callable[[], dict[str, float]], best_key: str,
          higher_is_better: bool, extra: Callable[[], dict], progress: bool, say) -> dict:
    """Train ``net`` for ``cfg.max_steps`` steps of ``step_fn``; validate, log and checkpoint on schedule."""
    step, epoch, done = 0, 0, 0
    sign = -1.0 if higher_is_better else 1.0
    best, last_val = math.inf, {}
    if state is not None:
        weights, meta = load_weights(out / "last", kind=kind)
        if meta["config"]["model"] != config["model"]:
            raise ValueError(f"{out / 'last'}: its model config {meta['config']['model']} differs from {config['model']}")
        net.load_state_dict(weights)
        opt.load_state_dict(state["optimizer"])
        for group in opt.param_groups:
            group.update(lr=cfg.lr)
        step, epoch, done = state["step"], state["epoch"], state["batches_done"]
        best, last_val = state["best"], dict(state["val"])
        _set_rng_state(state["rng"][0], dev)
        _truncate_log(out / "log.csv", step)
        say(f"resumed from {out / 'last'} at step {step} (epoch {epoch}, batch {done})")

    def checkpoint(folder: str, with_state: bool) -> None:
        if not all(torch.isfinite(p).all() for p in net.parameters()):
            raise TrainingDiverged(f"non-finite weights at step {step}; stopping (the last good checkpoint is kept)")
        train_state = None
        if with_state:
            train_state = {"optimizer": opt.state_dict(), "step": step, "epoch": epoch, "batches_done": done,
                           "best": best, "val": last_val, "rng": [_rng_state(dev)]}
        save_checkpoint(out / folder, model=net, kind=kind, config=config, step=step,
                        extra={**extra(), "val": last_val, "best_" + best_key: None if math.isinf(best) else sign * best},
                        state=train_state)

    log = RunLog(out)
    batches = _train_batches(ds, sampler, epoch, done, cfg.num_workers, cfg.seed, dev.type == "cuda")
    bar = tqdm(total=cfg.max_steps, initial=step, disable=not progress, file=sys.stderr, dynamic_ncols=True, desc=desc)
    sums: dict[str, float] = {}
    count, tic, train_loss = 0, time.perf_counter(), math.nan
    net.train()
    while step < cfg.max_steps:
        epoch, done, batch = next(batches)
        losses = step_fn(batch)  # forward, backward and clipping; the update waits for the check
        check_finite(losses, step + 1)
        opt.step()
        step += 1
        for k, v in losses.items():
            sums[k] = sums.get(k, 0.0) + v
        count += 1
        bar.update(1)
        bar.set_postfix(loss=f"{losses['loss']:.3f}")
        row: dict[str, float] = {}
        if step % cfg.log_every == 0 or step == cfg.max_steps:
            row.update({k: v / count for k, v in sums.items()}, lr=opt.param_groups[0]["lr"],
                       sec_per_step=(time.perf_counter() - tic) / count, epoch=epoch)
            train_loss = row["loss"]
            sums, count = {}, 0
        if step % cfg.val_every == 0 or step == cfg.max_steps:
            last_val = validate()
            net.train()
            row.update({f"val_{k}": v for k, v in last_val.items()})
            if best_key in last_val and sign * last_val[best_key] < best:
                best = sign * last_val[best_key]
                checkpoint("best", with_state=False)
            if not math.isinf(best):
                row[f"best_val_{best_key}"] = sign * best
        if row:
            log.write(step, **row)
        if step % cfg.ckpt_every == 0 or step == cfg.max_steps:
            checkpoint("last", with_state=True)
        if "loss" in row:
            tic = time.perf_counter()
    bar.close()
    log.close()
    if math.isnan(train_loss) and count:
        train_loss = sums["loss"] / count
    return {"step": step, "train_loss": train_loss, "val": last_val,
            f"best_val_{best_key}": None if math.isinf(best) else sign * best}


def _clip(params, limit: float) -> torch.Tensor:
    return torch.nn.utils.clip_grad_norm_(list(params), limit if limit > 0 else math.inf)


# ----------------------------------------------------------------------------------------------------------------
# The text-motion evaluator

def train_evaluator(
    data: str | os.PathLike | Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    config: EvaluatorConfig | None = None,
    train_config: EvaluatorTrainConfig | None = None,
    device: str = "auto",
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
    text_encoder_path: str | os.PathLike | None = None,
) -> dict:
    """Train our text-motion evaluator on the 'train' split of the shards (captioned windows).

    Returns {"step", "train_loss", "val", "best_val_loss", "heldout": {r_precision_top1..3, mm_dist, pairs,
    group_size, chance_top1..3, split}}; ``heldout`` is also written to ``out/heldout.json``.
    Raises TrainingDiverged on a NaN/inf loss, leaving the last good checkpoint in place.
    """
    from lsgan.models.text import load_text_encoder

    cfg, tcfg = config or EvaluatorConfig(), train_config or EvaluatorTrainConfig()
    paths, out, dev = _paths(data), Path(out), pick_device(device)
    claim_run(out, resume=resume, force=force)
    if tcfg.max_frames > cfg.max_motion_length:
        raise ValueError(f"train.max_frames ({tcfg.max_frames}) exceeds model.max_motion_length ({cfg.max_motion_length})")
    if tcfg.min_frames < cfg.unit_length:
        raise ValueError(f"train.min_frames ({tcfg.min_frames}) is below the unit length ({cfg.unit_length})")
    say = _say_to(out)
    state = _start(out, resume, say)
    seed_everything(tcfg.seed)

    ds = MotionDataset(paths, "train", min_frames=tcfg.min_frames, max_frames=tcfg.max_frames,
                       unit_length=cfg.unit_length, require_captions=True)
    ds.windows = [w for w in ds.windows if w.captions]
    if not len(ds):
        raise ValueError(f"no captioned training windows of {tcfg.min_frames}+ frames in {paths}: the text evaluator "
                         f"needs captions (for action labels use kind 'action')")
    sampler = LengthBucketSampler(ds.lengths(), tcfg.batch_size, drop_last=True, seed=tcfg.seed)
    if len(sampler) == 0:
        raise ValueError(f"{len(ds)} training windows make less than one batch of {tcfg.batch_size}; lower batch_size")
    val_split = _split_with_data(paths, ("val", "test"))
    test_split = _split_with_data(paths, ("test", "val"))
    kw = {"min_frames": tcfg.min_frames, "max_frames": tcfg.max_frames, "seed": tcfg.seed}
    val = heldout_pairs(paths, val_split, **kw) if val_split else ([], [], [])
    if len(val[0]) < 3:
        say(f"{len(val[0])} validation pairs: no validation; best/ is the last checkpoint")

    enc = load_text_encoder(cfg.text_encoder, path=text_encoder_path, device=dev)
    net = EvaluatorNet(cfg, enc.dim).to(dev)
    ev = LearnedEvaluator(net, enc, ds.mean, ds.std, id="(training)", device=dev)
    captions = sorted({c.text for caps in ds.captions for clip in caps for c in clip} | set(val[1]))
    t0 = time.perf_counter()
    ev.sentence_vectors(captions)
    opt = torch.optim.Adam(net.parameters(), lr=tcfg.lr)
    config_dict = {"model": asdict(cfg), "train": asdict(tcfg)}
    if state is None:
        say(f"{len(ds)} training windows ({len(captions)} captions embedded with {enc.id} in "
            f"{time.perf_counter() - t0:.1f} s), {len(val[0])} validation pairs ({val_split}); "
            f"{sum(p.numel() for p in net.parameters()):,} trainable parameters; device {dev}")
    motion_params = [*net.movement_encoder.parameters(), *net.motion_encoder.parameters()]
    pad_to = cfg.max_motion_length

    def step_fn(batch: dict) -> dict[str, float]:
        x, lengths = batch["motion"], batch["length"]
        if x.shape[1] < pad_to:  # pad as at inference (the last convolution window reaches the padding)
            x = torch.nn.functional.pad(x, (0, 0, 0, pad_to - x.shape[1]))
        mot = net.embed_motion(x.to(dev, non_blocking=True), lengths)
        txt = net.embed_sentence(ev.sentence_vectors(batch["caption"]).to(dev))
        b = len(lengths)
        shift = int(torch.randint(1, b, ()).item())
        neg = mot[(torch.arange(b, device=dev) + shift) % b]
        loss_pos = contrastive_loss(txt, mot, False, tcfg.margin)
        loss_neg = contrastive_loss(txt, neg, True, tcfg.margin)
        loss = loss_pos + loss_neg
        opt.zero_grad(set_to_none=True)
        loss.backward()
        g_text = _clip(net.text_head.parameters(), tcfg.grad_clip)
        g_motion = _clip(motion_params, tcfg.grad_clip)
        values = {"loss": loss.item(), "loss_pos": loss_pos.item(), "loss_neg": loss_neg.item(),
                  "grad_norm_text": g_text.item(), "grad_norm_motion": g_motion.item()}
        return values

    def validate() -> dict[str, float]:
        if len(val[0]) < 3:
            return {}
        net.eval()
        m = torch.from_numpy(ev.embed_motions(val[0]))
        t = torch.from_numpy(ev.embed_texts(val[1]))
        neg = m.roll(1, 0)
        pos_l = contrastive_loss(t, m, False, tcfg.margin).item()
        neg_l = contrastive_loss(t, neg, True, tcfg.margin).item()
        rep = retrieval_report(t.numpy(), m.numpy(), group_size=tcfg.group_size, repeats=1, seed=tcfg.seed)
        return {"loss": pos_l + neg_l, "loss_pos": pos_l, "loss_neg": neg_l,
                "r_precision_top1": rep["r_precision_top1"], "r_precision_top3": rep["r_precision_top3"],
                "mm_dist": rep["mm_dist"]}

    def extra() -> dict:
        return {"mean": ds.mean.tolist(), "std": ds.std.tolist(), "text_encoder_id": enc.id,
                "text_encoder_path": None if text_encoder_path is None else os.fspath(text_encoder_path),
                "data": paths}

    result = _loop(out=out, kind="evaluator", desc="evaluator", net=net, opt=opt, ds=ds, sampler=sampler, cfg=tcfg,
                   dev=dev, state=state, config=config_dict, step_fn=step_fn, validate=validate, best_key="loss",
                   higher_is_better=False, extra=extra, progress=progress, say=say)
    if not (out / "best").exists():  # no validation: the last checkpoint is the one to use
        import shutil

        shutil.copytree(out / "last", out / "best", ignore=shutil.ignore_patterns("state.pt"))

    heldout: dict = {"split": test_split}
    if test_split is not None:
        feats, caps, _ = heldout_pairs(paths, test_split, **kw)
        if len(feats) >= 3:
            final = load_learned_evaluator(out, dev, text_encoder_path=text_encoder_path)
            heldout.update(retrieval_report(final.embed_texts(caps), final.embed_motions(feats),
                                            group_size=tcfg.group_size, repeats=tcfg.eval_repeats, seed=tcfg.seed))
            heldout["evaluator"] = final.id
    if "r_precision_top3" not in heldout:
        say("no held-out split with 3+ captioned windows: no retrieval figures")
    (out / "heldout.json").write_text(json.dumps(heldout, indent=1))
    result["heldout"] = heldout
    return result


# ----------------------------------------------------------------------------------------------------------------
# The action classifier

class ActionWindows(Dataset):
    """Whole action-labelled clips of a split as joints: random crops of up to ``max_frames`` frames.

    Items (for :func:`lsgan.data.dataset.collate`): ``motion`` (L, 66) joints with the crop's first root at
    the origin, ``length``, ``action``. Joints are recovered from the features once, when the set is built.
    """

    def __init__(self, paths: list[str], split: str | None, *, min_frames: int, max_frames: int) -> None:
        self.joints: list[np.ndarray] = []
        self.labels: list[int] = []
        self.names: list[str] = []
        self.max_frames = max_frames
        self.action_names: list[str] = []
        for s, p in enumerate(paths):
            with Shard(p) as shard:
                if s == 0:
                    self.action_names = shard.action_names
                elif shard.action_names != self.action_names:
                    raise ValueError(f"{p}: its action labels differ from those of {paths[0]}")
                for i in shard.indices(split):
                    a = int(shard.actions[i])
                    if a < 0 or shard.lengths[i] < min_frames:
                        continue
                    self.joints.append(recover_from_ric(shard.features(int(i))).astype(np.float32))
                    self.labels.append(a)
                    self.names.append(shard.names[i])

    def __len__(self) -> int:
        return len(self.joints)

    def lengths(self) -> np.ndarray:
        return np.array([min(len(j), self.max_frames) for j in self.joints])

    def __getitem__(self, index: int) -> dict:
        j = self.joints[index]
        n = min(len(j), self.max_frames)
        start = int(torch.randint(len(j) - n + 1, ()).item())
        x = prepare_joints(j[start:start + n])
        return {"motion": torch.from_numpy(x), "length": n, "caption": "", "tokens": "",
                "action": self.labels[index], "name": self.names[index]}

    def fixed(self) -> list[np.ndarray]:
        """Every clip once, centre-cropped to ``max_frames`` (joints (T,22,3), as a caller would pass them)."""
        out = []
        for j in self.joints:
            n = min(len(j), self.max_frames)
            a = (len(j) - n) // 2
            out.append(j[a:a + n])
        return out


def train_action_classifier(
    data: str | os.PathLike | Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    config: ActionClassifierConfig | None = None,
    train_config: ActionTrainConfig | None = None,
    device: str = "auto",
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
) -> dict:
    """Train the action-recognition GRU on the action-labelled 'train' clips of the shards.

    Returns {"step", "train_loss", "val", "best_val_accuracy", "heldout": {accuracy, clips, chance, split}};
    ``heldout`` (test split, else val) is also written to ``out/heldout.json``.
    """
    cfg, tcfg = config or ActionClassifierConfig(), train_config or ActionTrainConfig()
    paths, out, dev = _paths(data), Path(out), pick_device(device)
    claim_run(out, resume=resume, force=force)
    say = _say_to(out)
    state = _start(out, resume, say)
    seed_everything(tcfg.seed)
    kw = {"min_frames": tcfg.min_frames, "max_frames": tcfg.max_frames}
    ds = ActionWindows(paths, "train", **kw)
    if not len(ds):
        raise ValueError(f"no action-labelled training clips of {tcfg.min_frames}+ frames in {paths}")
    num_classes = cfg.num_classes or len(ds.action_names)
    if num_classes < len(ds.action_names):
        raise ValueError(f"num_classes={num_classes} but the data has {len(ds.action_names)} action labels")
    cfg = ActionClassifierConfig(**{**asdict(cfg), "num_classes": num_classes})
    sampler = LengthBucketSampler(ds.lengths(), tcfg.batch_size, drop_last=len(ds) >= tcfg.batch_size, seed=tcfg.seed)
    val_split = _split_with_data(paths, ("val", "test"))
    test_split = _split_with_data(paths, ("test", "val"))
    val_ds = ActionWindows(paths, val_split, **kw) if val_split else None
    val_joints = val_ds.fixed() if val_ds is not None else []
    net = ActionRecognitionGRU(cfg).to(dev)
    opt = torch.optim.Adam(net.parameters(), lr=tcfg.lr)
    config_dict = {"model": asdict(cfg), "train": asdict(tcfg)}
    if state is None:
        say(f"{len(ds)} training clips, {len(val_joints)} validation clips ({val_split}), {num_classes} classes; "
            f"{sum(p.numel() for p in net.parameters()):,} parameters; device {dev}")

    def step_fn(batch: dict) -> dict[str, float]:
        x, lengths, y = batch["motion"].to(dev), batch["length"], batch["action"].to(dev)
        _, logits = net(x, lengths)
        loss = torch.nn.functional.cross_entropy(logits, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        g = _clip(net.parameters(), tcfg.grad_clip)
        values = {"loss": loss.item(), "accuracy": (logits.argmax(1) == y).float().mean().item(), "grad_norm": g.item()}
        return values

    def classifier() -> object:
        from lsgan.models.evaluator import ActionClassifier

        return ActionClassifier(net, ds.action_names, id="(training)", device=dev)

    def validate() -> dict[str, float]:
        if not val_joints:
            return {}
        pred = classifier().predict(val_joints)
        return {"accuracy": float((pred == np.array(val_ds.labels)).mean())}

    def extra() -> dict:
        return {"action_names": ds.action_names, "data": paths}

    result = _loop(out=out, kind="action-classifier", desc="action-classifier", net=net, opt=opt, ds=ds,
                   sampler=sampler, cfg=tcfg, dev=dev, state=state, config=config_dict, step_fn=step_fn,
                   validate=validate, best_key="accuracy", higher_is_better=True, extra=extra, progress=progress,
                   say=say)
    if not (out / "best").exists():
        import shutil

        shutil.copytree(out / "last", out / "best", ignore=shutil.ignore_patterns("state.pt"))
    heldout: dict = {"split": test_split}
    if test_split is not None:
        test = ActionWindows(paths, test_split, **kw)
        if len(test):
            clf = load_action_classifier(out, dev)
            labels = np.array(test.labels)
            pred = clf.predict(test.fixed())
            heldout.update(accuracy=float((pred == labels).mean()), clips=len(test),
                           chance=1.0 / num_classes,
                           majority=float(np.bincount(labels).max() / len(labels)), classifier=clf.id)
    (out / "heldout.json").write_text(json.dumps(heldout, indent=1))
    result["heldout"] = heldout
    return result
