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

Both train through :func:`lsgan.train.loop.fit`: ``out/last`` and ``out/best``, ``out/log.csv``, exact resume
with ``resume=True`` (weights, optimiser, step, RNG, sampler position) and a stop on a NaN loss keeping the last
good checkpoint. They run in one process (the models are small).
"""
from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch.utils.data import Dataset

from lsgan import outputs
from lsgan.data.dataset import FrameTable, LengthBucketSampler, MotionDataset
from lsgan.data.features import recover_from_ric
from lsgan.data.shards import Shard
from lsgan.eval.metrics import retrieval_metrics
from lsgan.models.evaluator import (
    ActionClassifier,
    ActionClassifierConfig,
    ActionRecognitionGRU,
    EvaluatorConfig,
    EvaluatorNet,
    LearnedEvaluator,
    load_action_classifier,
    load_learned_evaluator,
    prepare_joints,
)
from lsgan.models.t2m_modules import contrastive_loss
from lsgan.train.common import seed_everything, shard_paths
from lsgan.train.loop import EpochBatches, Env, Progress, Trainer, WindowTrainConfig, fit, launch

__all__ = [
    "ActionTrainConfig",
    "EvaluatorTrainConfig",
    "heldout_pairs",
    "retrieval_report",
    "train_action_classifier",
    "train_evaluator",
]


@dataclass
class EvaluatorTrainConfig(WindowTrainConfig):
    """T2M's text_mot_match settings by default (batch 32, lr 1e-4, margin 10, clip 0.5, unit length 4), with the
    schedule, window lengths, workers and seed of :class:`lsgan.train.loop.WindowTrainConfig`."""

    lr: float = 1e-4
    batch_size: int = 32
    margin: float = 10.0  # T2M --negative_margin
    grad_clip: float = 0.5  # max grad norm, per encoder (text head; motion side); 0 = none
    group_size: int = 32  # R-precision groups
    eval_repeats: int = 10  # held-out R-precision: mean over this many shuffles

    def against(self, model: EvaluatorConfig) -> None:
        """Refuse windows the motion encoder cannot take (recipes check it when read)."""
        if self.max_frames > model.max_motion_length:
            raise ValueError(f"train.max_frames ({self.max_frames}) exceeds model.max_motion_length "
                             f"({model.max_motion_length})")
        if self.min_frames < model.unit_length:
            raise ValueError(f"train.min_frames ({self.min_frames}) is below the unit length ({model.unit_length})")


@dataclass
class ActionTrainConfig(WindowTrainConfig):
    """The action GRU's settings; shorter clips and a denser schedule than WindowTrainConfig's defaults."""

    val_every: int = 250
    ckpt_every: int = 250
    min_frames: int = 16
    lr: float = 1e-3
    batch_size: int = 64
    grad_clip: float = 1.0


# ----------------------------------------------------------------------------------------------------------------
# Held-out pairs and the retrieval report

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
    ds = MotionDataset(shard_paths(data), split, min_frames=min_frames, max_frames=max_frames, normalize=False,
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


def _clip(params, limit: float) -> torch.Tensor:
    return torch.nn.utils.clip_grad_norm_(list(params), limit if limit > 0 else math.inf)


def _splits(paths: list[str]) -> tuple[str | None, str | None]:
    """(the split to validate on: val, else test; the held-out split: test, else val)."""
    return _split_with_data(paths, ("val", "test")), _split_with_data(paths, ("test", "val"))


def _finish(env: Env, p: Progress, metric: str, heldout: dict) -> dict:
    """Write ``heldout.json``; what both trainers return."""
    outputs.replace_by(env.out / "heldout.json", json.dumps(heldout, indent=1))
    return {"step": p.step, "train_loss": p.train_loss, "val": p.val, f"best_val_{metric}": p.best_value,
            "heldout": heldout}


# ----------------------------------------------------------------------------------------------------------------
# The text-motion evaluator

def train_evaluator(data: str | os.PathLike | Sequence[str | os.PathLike], out: str | os.PathLike, *,
                    config: EvaluatorConfig | None = None, train_config: EvaluatorTrainConfig | None = None,
                    device: str = "auto", resume: bool = False, force: bool = False, progress: bool = True,
                    text_encoder_path: str | os.PathLike | None = None) -> dict:
    """Train our text-motion evaluator on the 'train' split of the shards (captioned windows).

    Returns {"step", "train_loss", "val", "best_val_loss", "heldout": {r_precision_top1..3, mm_dist, pairs,
    group_size, chance_top1..3, split}}; ``heldout`` is also written to ``out/heldout.json``.
    Raises TrainingDiverged on a NaN/inf loss, leaving the last good checkpoint in place.
    """
    cfg, tcfg = config or EvaluatorConfig(), train_config or EvaluatorTrainConfig()
    paths = shard_paths(data)
    return launch("train_evaluator", out, device=device, resume=resume, force=force, progress=progress,
                  distributed=False, body=lambda env: _train_text(env, paths, cfg, tcfg, text_encoder_path))


def _train_text(env: Env, paths: list[str], cfg: EvaluatorConfig, tcfg: EvaluatorTrainConfig,
                text_encoder_path: str | os.PathLike | None) -> dict:
    tcfg.against(cfg)
    prev = env.previous("evaluator")
    seed_everything(tcfg.seed)
    ds = MotionDataset(paths, "train", min_frames=tcfg.min_frames, max_frames=tcfg.max_frames,
                       unit_length=cfg.unit_length, require_captions=True)
    ds.windows = [w for w in ds.windows if w.captions]
    if not len(ds):
        raise ValueError(f"no captioned training windows of {tcfg.min_frames}+ frames in {paths}: the text evaluator "
                         f"needs captions (for action labels use kind 'action')")
    val_split, test_split = _splits(paths)
    kw = {"min_frames": tcfg.min_frames, "max_frames": tcfg.max_frames, "seed": tcfg.seed}
    val = heldout_pairs(paths, val_split, **kw) if val_split else ([], [], [])
    if len(val[0]) < 3:
        env.say(f"{len(val[0])} validation pairs: no validation; best/ is the last checkpoint")
    t = _text_trainer(env, ds, val, cfg, tcfg, text_encoder_path, paths)
    p = fit(env, t, tcfg.schedule(), prev, intro=f"{len(ds)} training windows, {len(val[0])} validation pairs "
            f"({val_split}); {sum(w.numel() for w in t.model.parameters()):,} trainable parameters; "
            f"device {env.device}")

    heldout: dict = {"split": test_split}
    if test_split is not None:
        feats, caps, _ = heldout_pairs(paths, test_split, **kw)
        if len(feats) >= 3:
            final = load_learned_evaluator(env.out, env.device, text_encoder_path=text_encoder_path)
            heldout.update(retrieval_report(final.embed_texts(caps), final.embed_motions(feats),
                                            group_size=tcfg.group_size, repeats=tcfg.eval_repeats, seed=tcfg.seed))
            heldout["evaluator"] = final.id
    if "r_precision_top3" not in heldout:
        env.say("no held-out split with 3+ captioned windows: no retrieval figures")
    return _finish(env, p, "loss", heldout)


def _text_trainer(env: Env, ds: MotionDataset, val: tuple[list, list, list], cfg: EvaluatorConfig,
                  tcfg: EvaluatorTrainConfig, text_encoder_path: str | os.PathLike | None, paths: list[str]) -> Trainer:
    """T2M's contrastive step on a batch of windows; the validation loss and R-precision on fixed pairs."""
    from lsgan.models.text import load_text_encoder

    dev = env.device
    sampler = LengthBucketSampler(ds.lengths(), tcfg.batch_size, drop_last=True, seed=tcfg.seed)
    if len(sampler) == 0:
        raise ValueError(f"{', '.join(map(str, paths))}: {len(ds)} training windows make less than one batch of "
                         f"{tcfg.batch_size}; lower the recipe's evaluator.text.train.batch_size")
    enc = load_text_encoder(cfg.text_encoder, path=text_encoder_path, device=dev)
    net = EvaluatorNet(cfg, enc.dim).to(dev)
    ev = LearnedEvaluator(net, enc, ds.mean, ds.std, id="(training)", device=dev)
    captions = sorted({c.text for caps in ds.captions for clip in caps for c in clip} | set(val[1]))
    tic = time.perf_counter()
    ev.sentence_vectors(captions)
    env.say(f"{len(captions)} captions embedded with {enc.id} in {time.perf_counter() - tic:.1f} s")
    opt = torch.optim.Adam(net.parameters(), lr=tcfg.lr)
    motion_params = [*net.movement_encoder.parameters(), *net.motion_encoder.parameters()]

    def step(batch: dict) -> dict[str, torch.Tensor]:
        x, lengths = batch["motion"], batch["length"]
        if x.shape[1] < cfg.max_motion_length:  # pad as at inference (the last convolution window reaches the padding)
            x = torch.nn.functional.pad(x, (0, 0, 0, cfg.max_motion_length - x.shape[1]))
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
        grad_norms = {"grad_norm_text": _clip(net.text_head.parameters(), tcfg.grad_clip),
                      "grad_norm_motion": _clip(motion_params, tcfg.grad_clip)}
        opt.step()
        return {"loss": loss, "loss_pos": loss_pos, "loss_neg": loss_neg, **grad_norms}

    def validate() -> dict[str, float]:
        if len(val[0]) < 3:
            return {}
        net.eval()
        m, t = torch.from_numpy(ev.embed_motions(val[0])), torch.from_numpy(ev.embed_texts(val[1]))
        pos_l = contrastive_loss(t, m, False, tcfg.margin).item()
        neg_l = contrastive_loss(t, m.roll(1, 0), True, tcfg.margin).item()
        rep = retrieval_report(t.numpy(), m.numpy(), group_size=tcfg.group_size, repeats=1, seed=tcfg.seed)
        return {"loss": pos_l + neg_l, "loss_pos": pos_l, "loss_neg": neg_l,
                "r_precision_top1": rep["r_precision_top1"], "r_precision_top3": rep["r_precision_top3"],
                "mm_dist": rep["mm_dist"]}

    extra = {"mean": ds.mean.tolist(), "std": ds.std.tolist(), "text_encoder_id": enc.id,
             "text_encoder_path": None if text_encoder_path is None else os.fspath(text_encoder_path), "data": paths}
    return Trainer(
        kind="evaluator", desc="evaluator", model=net, config={"model": asdict(cfg), "train": asdict(tcfg)},
        optimizers={"optimizer": opt}, step=step, validate=validate, metric="loss",
        batches=EpochBatches(ds, sampler, seed=tcfg.seed, frames=FrameTable(ds, dev)),
        extra=lambda p: {**extra, "val": p.val, "best_loss": p.best_value},
    )


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


def train_action_classifier(data: str | os.PathLike | Sequence[str | os.PathLike], out: str | os.PathLike, *,
                            config: ActionClassifierConfig | None = None, train_config: ActionTrainConfig | None = None,
                            device: str = "auto", resume: bool = False, force: bool = False,
                            progress: bool = True) -> dict:
    """Train the action-recognition GRU on the action-labelled 'train' clips of the shards.

    Returns {"step", "train_loss", "val", "best_val_accuracy", "heldout": {accuracy, clips, chance, split}};
    ``heldout`` (test split, else val) is also written to ``out/heldout.json``.
    """
    cfg, tcfg = config or ActionClassifierConfig(), train_config or ActionTrainConfig()
    paths = shard_paths(data)
    return launch("train_action_classifier", out, device=device, resume=resume, force=force, progress=progress,
                  distributed=False, body=lambda env: _train_action(env, paths, cfg, tcfg))


def _train_action(env: Env, paths: list[str], cfg: ActionClassifierConfig, tcfg: ActionTrainConfig) -> dict:
    prev = env.previous("action-classifier")
    seed_everything(tcfg.seed)
    kw = {"min_frames": tcfg.min_frames, "max_frames": tcfg.max_frames}
    ds = ActionWindows(paths, "train", **kw)
    if not len(ds):
        raise ValueError(f"no action-labelled training clips of {tcfg.min_frames}+ frames in {paths}")
    num_classes = cfg.num_classes or len(ds.action_names)
    if num_classes < len(ds.action_names):
        raise ValueError(f"num_classes={num_classes} but {', '.join(map(str, paths))} hold(s) {len(ds.action_names)} "
                         "action labels")
    cfg = ActionClassifierConfig(**{**asdict(cfg), "num_classes": num_classes})
    val_split, test_split = _splits(paths)
    val_ds = ActionWindows(paths, val_split, **kw) if val_split else None
    t = _action_trainer(env, ds, val_ds, cfg, tcfg, paths)
    p = fit(env, t, tcfg.schedule(), prev, intro=f"{len(ds)} training clips, {len(val_ds or [])} validation clips "
            f"({val_split}), {num_classes} classes; {sum(w.numel() for w in t.model.parameters()):,} parameters; "
            f"device {env.device}")

    heldout: dict = {"split": test_split}
    test = ActionWindows(paths, test_split, **kw) if test_split is not None else []
    if len(test):
        clf, labels = load_action_classifier(env.out, env.device), np.array(test.labels)
        pred = clf.predict(test.fixed())
        heldout.update(accuracy=float((pred == labels).mean()), clips=len(test), chance=1.0 / num_classes,
                       majority=float(np.bincount(labels).max() / len(labels)), classifier=clf.id)
    return _finish(env, p, "accuracy", heldout)


def _action_trainer(env: Env, ds: ActionWindows, val_ds: ActionWindows | None, cfg: ActionClassifierConfig,
                    tcfg: ActionTrainConfig, paths: list[str]) -> Trainer:
    """Cross-entropy on a batch of crops; the accuracy on the validation clips, centre-cropped."""
    dev = env.device
    sampler = LengthBucketSampler(ds.lengths(), tcfg.batch_size, drop_last=len(ds) >= tcfg.batch_size, seed=tcfg.seed)
    val_joints = val_ds.fixed() if val_ds is not None else []
    net = ActionRecognitionGRU(cfg).to(dev)
    opt = torch.optim.Adam(net.parameters(), lr=tcfg.lr)

    def step(batch: dict) -> dict[str, torch.Tensor]:
        x, lengths, y = batch["motion"].to(dev), batch["length"], batch["action"].to(dev)
        _, logits = net(x, lengths)
        loss = torch.nn.functional.cross_entropy(logits, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = _clip(net.parameters(), tcfg.grad_clip)
        opt.step()
        return {"loss": loss, "accuracy": (logits.argmax(1) == y).float().mean(), "grad_norm": grad_norm}

    def validate() -> dict[str, float]:
        if not val_joints:
            return {}
        pred = ActionClassifier(net, ds.action_names, id="(training)", device=dev).predict(val_joints)
        return {"accuracy": float((pred == np.array(val_ds.labels)).mean())}

    return Trainer(
        kind="action-classifier", desc="action-classifier", model=net,
        config={"model": asdict(cfg), "train": asdict(tcfg)}, optimizers={"optimizer": opt}, step=step,
        validate=validate, metric="accuracy", higher_is_better=True,
        batches=EpochBatches(ds, sampler, seed=tcfg.seed, num_workers=tcfg.num_workers, pin=dev.type == "cuda"),
        extra=lambda p: {"action_names": ds.action_names, "data": paths, "val": p.val, "best_accuracy": p.best_value},
    )


def train_from_recipe(data: Sequence[str | os.PathLike], out: str | os.PathLike, recipe: dict, *,
                      kind: str | None = None, text_encoder: str | None = None, overrides: dict | None = None,
                      **options) -> dict:
    """``lsgan train-evaluator``: the recipe's ``evaluator:`` section (its ``text:`` or ``action:`` part; ``kind``
    None: the one it holds, text when both or neither) with ``overrides`` of its train values, then
    :func:`train_evaluator` or :func:`train_action_classifier` with ``options`` (device, resume, force, ...)."""
    from lsgan.recipes import configs, section

    sections = section(recipe, "evaluator", ("text", "action"))
    if kind is None:
        present = [k for k in ("text", "action") if k in sections]
        kind = present[0] if len(present) == 1 else "text"
    if kind == "action":
        options.pop("text_encoder_path", None)
        config, train_config = configs(sections, "action", ActionClassifierConfig, ActionTrainConfig, None, overrides,
                                       "evaluator.action")
        return train_action_classifier(list(data), out, config=config, train_config=train_config, **options)
    encoder = None  # the recipe's evaluator model names one; else the option, the recipe's own, MiniLM
    if text_encoder or "text_encoder" not in section(section(sections, "text"), "model"):
        encoder = text_encoder or recipe.get("text_encoder") or "minilm"
        if encoder == "none":
            raise ValueError(f"{getattr(recipe, 'source', '') or 'the recipe'}: text_encoder is none, but the text "
                             "evaluator embeds captions: name an encoder (minilm, clip-vit-l-14)")
    config, train_config = configs(sections, "text", EvaluatorConfig, EvaluatorTrainConfig,
                                   {"text_encoder": encoder}, overrides, "evaluator.text")
    return train_evaluator(list(data), out, config=config, train_config=train_config, **options)


def describe_heldout(h: dict) -> str:
    """One line for a run's held-out figures (R-precision and MM-Dist, or accuracy)."""
    if "r_precision_top3" in h:
        return (f"held-out ({h['split']}, {h['pairs']} pairs, groups of {h['group_size']}): R-precision "
                f"top-1 {h['r_precision_top1']:.3f}, top-2 {h['r_precision_top2']:.3f}, top-3 "
                f"{h['r_precision_top3']:.3f} (chance {h['chance_top1']:.3f}/{h['chance_top2']:.3f}/"
                f"{h['chance_top3']:.3f}); MM-Dist {h['mm_dist']:.3f}")
    if "accuracy" in h:
        return (f"held-out ({h['split']}, {h['clips']} clips): accuracy {h['accuracy']:.3f} "
                f"(chance {h['chance']:.3f}, majority class {h['majority']:.3f})")
    return "no held-out split (test or val) to report on"
