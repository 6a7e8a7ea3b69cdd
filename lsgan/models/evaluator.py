"""Evaluators: the networks that turn motions (and captions) into the embeddings the metrics are computed on.

Text-to-motion (R-precision, MM-Dist, FID, diversity, multimodality) needs a text-motion co-embedding;
action-to-motion (accuracy, FID, diversity, multimodality) needs an action-recognition network. Both
are loaded with one call and used through one small interface each:

>>> ev = load_evaluator("runs/evaluator")          # or the root of the official T2M files
>>> ev.embed_motions([features])                   # list of (T,263) de-normalised -> (N, 512)
>>> ev.embed_texts(["a person walks forward"])     # -> (N, 512)
>>> clf = load_action_classifier("runs/act-clf")
>>> clf.features([joints]), clf.predict([joints])  # list of (T,22,3) -> (N, 30), (N,)

``load_evaluator`` reads either evaluator of text-to-motion: **the official T2M one**
(:mod:`lsgan.models.t2m_checkpoint`, on the modules of :mod:`lsgan.models.t2m_modules`) or **our own**, defined
here with the action recogniser, the two kinds ``lsgan train-evaluator`` trains (:mod:`lsgan.train.evaluator`).

**Our own evaluator** (``lsgan train-evaluator``, for data the official one was not trained on, or when
its files are absent): the same motion side (the same modules, sizes configurable), and a text side
that needs no GloVe: the configured frozen sentence encoder (MiniLM by default) followed by a small head
shaped like T2M's ``output_net``. Normalisation uses the training shard's Mean/Std (kept in the
checkpoint).

**Action recognition** (Action2Motion / ACTOR's HumanAct12 recogniser): joints x 3 -> 2-layer GRU
(hidden 128) -> the output at the last real frame -> ``linear1`` (30) -> tanh -> ``linear2`` (classes);
FID is computed on the 30-d tanh layer. Parameter names as ACTOR's ``MotionDiscriminator``
(``recurrent``, ``linear1``, ``linear2``). Two deliberate differences: the initial GRU state is zero (the
original draws it with ``torch.randn`` at every call, so its features are random), and the input is our
22 joints (the original reads SMPL's 24), translated so that the root starts at the origin (as
Action2Motion's loader offsets each clip by its first root position).
"""
from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch import nn

from lsgan.data.skeleton import FEATURE_DIM, NUM_JOINTS
from lsgan.device import as_device
from lsgan.models.t2m_checkpoint import find_official, load_t2m_evaluator
from lsgan.models.t2m_modules import NUM_CONTACT_DIMS, MotionEncoderBiGRUCo, MovementConvEncoder, init_weight
from lsgan.models.text_motion import MAX_MOTION_LENGTH, UNIT_LENGTH, TextMotionEvaluator, check_captions, motion_forward

__all__ = [
    "ActionClassifier",
    "ActionClassifierConfig",
    "ActionRecognitionGRU",
    "EvaluatorConfig",
    "EvaluatorNet",
    "LearnedEvaluator",
    "load_action_classifier",
    "load_evaluator",
    "load_learned_evaluator",
    "prepare_joints",
]


@dataclass
class EvaluatorConfig:
    """Sizes of our evaluator. Defaults are T2M's (movement 512/512, motion GRU 1024, co-embedding 512)."""

    movement_hidden: int = 512  # T2M dim_movement_enc_hidden
    movement_latent: int = 512  # T2M dim_movement_latent
    motion_hidden: int = 1024  # T2M dim_motion_hidden
    embed_dim: int = 512  # T2M dim_coemb_hidden
    text_encoder: str = "minilm"  # frozen sentence encoder (lsgan.models.text)
    text_hidden: int = 512  # width of the text head
    unit_length: int = UNIT_LENGTH
    max_motion_length: int = MAX_MOTION_LENGTH  # motions shorter than this are zero-padded to it


class EvaluatorNet(nn.Module):
    """The trainable part of our evaluator: the T2M motion side and a head on frozen sentence embeddings."""

    def __init__(self, cfg: EvaluatorConfig, text_dim: int) -> None:
        super().__init__()
        self.cfg = cfg
        self.movement_encoder = MovementConvEncoder(FEATURE_DIM - NUM_CONTACT_DIMS, cfg.movement_hidden,
                                                    cfg.movement_latent)
        self.motion_encoder = MotionEncoderBiGRUCo(cfg.movement_latent, cfg.motion_hidden, cfg.embed_dim)
        self.text_head = nn.Sequential(
            nn.Linear(text_dim, cfg.text_hidden),
            nn.LayerNorm(cfg.text_hidden),
            nn.LeakyReLU(0.2),
            nn.Linear(cfg.text_hidden, cfg.embed_dim),
        )
        self.text_head.apply(init_weight)

    def embed_motion(self, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        return motion_forward(self.movement_encoder, self.motion_encoder, x, lengths, self.cfg.unit_length)

    def embed_sentence(self, s: torch.Tensor) -> torch.Tensor:
        return self.text_head(s)


class LearnedEvaluator(TextMotionEvaluator):
    """Our evaluator: :class:`EvaluatorNet` + a frozen sentence encoder + the training shard's Mean/Std."""

    def __init__(self, net: EvaluatorNet, text_encoder, mean: np.ndarray, std: np.ndarray, *, id: str,
                 device: str | torch.device = "cpu", cache_sentences: bool = True) -> None:
        self.device = as_device(device)
        self.net = net.to(self.device)
        self.text_encoder = text_encoder
        self.movement_encoder = net.movement_encoder
        self.motion_encoder = net.motion_encoder
        self.mean = np.asarray(mean, np.float32)
        self.std = np.asarray(std, np.float32)
        self.unit_length = net.cfg.unit_length
        self.pad_to = net.cfg.max_motion_length
        self.dim = net.cfg.embed_dim
        self.id = id
        self._cache: dict[str, torch.Tensor] | None = {} if cache_sentences else None

    def sentence_vectors(self, captions: Sequence[str]) -> torch.Tensor:
        """Frozen sentence-encoder embeddings (N, text_dim) on the CPU (cached: they never change)."""
        captions = list(captions)
        if self._cache is None:
            return self.text_encoder.encode(captions)
        todo = sorted({c for c in captions if c not in self._cache})
        if todo:
            if len(self._cache) + len(todo) > 200_000:
                self._cache.clear()
            for c, v in zip(todo, self.text_encoder.encode(todo)):
                self._cache[c] = v
        if not captions:
            return torch.zeros(0, self.text_encoder.dim)
        return torch.stack([self._cache[c] for c in captions])

    @torch.no_grad()
    def embed_texts(self, captions: Sequence[str], *, tokens: Sequence[str] | None = None,
                    batch_size: int = 256) -> np.ndarray:
        """Captions -> (N, embed_dim). ``tokens`` are accepted for interface parity and not used."""
        captions = check_captions(captions, tokens)
        vecs = self.sentence_vectors(captions)
        head = self.net.text_head
        was = head.training
        head.eval()
        try:
            out = [head(vecs[s:s + batch_size].to(self.device)).float().cpu() for s in range(0, len(captions), batch_size)]
        finally:
            head.train(was)
        return torch.cat(out).numpy() if out else np.zeros((0, self.dim), np.float32)


def load_learned_evaluator(path: str | os.PathLike, device: str | torch.device = "cpu", *,
                           text_encoder_path: str | os.PathLike | None = None, prefer: str = "best") -> LearnedEvaluator:
    """Our evaluator from a ``train-evaluator`` run (its ``best/`` by default) or checkpoint folder."""
    from lsgan.models.checkpoint import load_weights, resolve, weights_hash
    from lsgan.models.text import load_text_encoder

    weights, meta = load_weights(path, prefer=prefer, kind="evaluator")
    cfg = _build(EvaluatorConfig, meta["config"]["model"])
    extra = meta.get("extra", {})
    dev = as_device(device)
    enc = load_text_encoder(cfg.text_encoder, path=text_encoder_path or extra.get("text_encoder_path"), device=dev)
    if extra.get("text_encoder_id") and enc.id != extra["text_encoder_id"]:
        warnings.warn(f"{path}: trained with text encoder {extra['text_encoder_id']}, loaded {enc.id}", stacklevel=2)
    net = EvaluatorNet(cfg, enc.dim)
    net.load_state_dict(weights)
    net.eval().requires_grad_(False)
    folder = resolve(path, prefer)
    return LearnedEvaluator(net, enc, np.asarray(extra["mean"], np.float32), np.asarray(extra["std"], np.float32),
                            id=f"lsgan-evaluator:{weights_hash(folder)[:16]}", device=dev)


def _build(cls, values: dict):
    names = {f.name for f in fields(cls)}
    return cls(**{k: v for k, v in values.items() if k in names})


def _is_run(path: Path) -> bool:
    from lsgan.models.checkpoint import CONFIG

    return any((p / CONFIG).is_file() for p in (path, path / "best", path / "last"))


def load_evaluator(path: str | os.PathLike, device: str | torch.device = "cpu", *,
                   text_encoder_path: str | os.PathLike | None = None) -> TextMotionEvaluator:
    """A text-motion evaluator: our own ``train-evaluator`` run folder, or the official T2M files.

    ``path``: a run (or checkpoint) folder of ``lsgan train-evaluator``; or the root of the official files
    (``t2m/text_mot_match/model/finest.tar``, ``t2m/Comp_v6_KLD01/meta/{mean,std}.npy`` and
    ``glove/our_vab_{data.npy,idx.pkl,words.pkl}``; also under ``checkpoints/`` as in the T2M repository,
    or MLD's ``deps/``). A missing file is named in the error.
    """
    p = Path(path).expanduser()
    if not p.exists():
        raise FileNotFoundError(f"evaluator {p} does not exist")
    if _is_run(p):
        from lsgan.models.checkpoint import read_meta

        kind = read_meta(p).get("kind")
        if kind != "evaluator":
            raise ValueError(f"{p}: holds a {kind!r} checkpoint, not a text-motion evaluator "
                             f"(train one with `lsgan train-evaluator`)")
        return load_learned_evaluator(p, device, text_encoder_path=text_encoder_path)
    paths, missing = find_official(p)
    if paths["weights"].is_file():
        return load_t2m_evaluator(p, device)  # names any other missing file
    raise FileNotFoundError(
        f"{p}: no evaluator here. Expected a run folder of `lsgan train-evaluator` (best/ or last/ with config.json) "
        f"or the official T2M files, missing: " + ", ".join(str(m) for m in missing))


# ----------------------------------------------------------------------------------------------------------------
# Action recognition

@dataclass
class ActionClassifierConfig:
    """Action2Motion's recogniser: joints x 3 -> GRU(hidden_size, num_layers) -> feature_dim (tanh) -> classes."""

    num_joints: int = NUM_JOINTS
    hidden_size: int = 128
    num_layers: int = 2
    feature_dim: int = 30
    num_classes: int = 0  # 0: the number of action labels of the training shard


class ActionRecognitionGRU(nn.Module):
    """Parameter names as ACTOR's/Action2Motion's ``MotionDiscriminator`` (``recurrent``, ``linear1``, ``linear2``)."""

    def __init__(self, cfg: ActionClassifierConfig) -> None:
        super().__init__()
        if cfg.num_classes < 1:
            raise ValueError("ActionClassifierConfig.num_classes must be set (>= 1)")
        self.cfg = cfg
        self.recurrent = nn.GRU(cfg.num_joints * 3, cfg.hidden_size, cfg.num_layers)
        self.linear1 = nn.Linear(cfg.hidden_size, cfg.feature_dim)
        self.linear2 = nn.Linear(cfg.feature_dim, cfg.num_classes)

    def forward(self, x: torch.Tensor, lengths: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x (B, T, J*3) zero-padded, lengths (B,) -> (30-d tanh features, class logits).

        The GRU is one-directional, so its output at the last real frame does not see the padding.
        """
        b = x.shape[0]
        h0 = torch.zeros(self.cfg.num_layers, b, self.cfg.hidden_size, device=x.device, dtype=x.dtype)
        out, _ = self.recurrent(x.permute(1, 0, 2), h0)  # (T, B, H)
        last = out[lengths.to(x.device).long() - 1, torch.arange(b, device=x.device)]
        feat = torch.tanh(self.linear1(last))
        return feat, self.linear2(feat)


def prepare_joints(joints: np.ndarray) -> np.ndarray:
    """(T, J, 3) joints -> (T, J*3) float32, translated so that the root of the first frame is at the origin."""
    j = np.asarray(joints, dtype=np.float32)
    if j.ndim != 3 or j.shape[-1] != 3:
        raise ValueError(f"joints of shape {j.shape}, expected (T, J, 3)")
    return (j - j[:1, :1]).reshape(len(j), -1)


class ActionClassifier:
    """A trained action recogniser: ``features(joints)`` (N, 30), ``predict(joints)`` (N,), ``action_names``."""

    def __init__(self, net: ActionRecognitionGRU, action_names: Sequence[str], *, id: str,
                 device: str | torch.device = "cpu") -> None:
        self.device = as_device(device)
        self.net = net.to(self.device)
        self.action_names = list(action_names)
        self.id = id
        self.dim = net.cfg.feature_dim

    @torch.no_grad()
    def _run(self, joints: Sequence[np.ndarray], batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        if isinstance(joints, np.ndarray) and joints.ndim == 3:
            raise TypeError("takes a list of (T, 22, 3) joint arrays, not a single array: wrap it as [joints]")
        xs = [prepare_joints(j) for j in joints]
        for i, x in enumerate(xs):
            if x.shape[1] != self.net.cfg.num_joints * 3 or len(x) < 1:
                raise ValueError(f"motion {i}: {x.shape}, expected (T>=1, {self.net.cfg.num_joints * 3}) after flattening")
        was = self.net.training
        self.net.eval()
        try:
            return self._batches(xs, batch_size)
        finally:
            self.net.train(was)

    def _batches(self, xs: list[np.ndarray], batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        n = len(xs)
        feats = np.zeros((n, self.dim), np.float32)
        logits = np.zeros((n, self.net.cfg.num_classes), np.float32)
        order = sorted(range(n), key=lambda i: (-len(xs[i]), i))
        for s in range(0, n, batch_size):
            idx = order[s:s + batch_size]
            width = len(xs[idx[0]])
            x = np.zeros((len(idx), width, xs[idx[0]].shape[1]), np.float32)
            for r, i in enumerate(idx):
                x[r, : len(xs[i])] = xs[i]
            f, lg = self.net(torch.from_numpy(x).to(self.device), torch.as_tensor([len(xs[i]) for i in idx]))
            feats[idx], logits[idx] = f.float().cpu().numpy(), lg.float().cpu().numpy()
        return feats, logits

    def features(self, joints: Sequence[np.ndarray], *, batch_size: int = 256) -> np.ndarray:
        """(N, 30) features of the tanh layer (FID, diversity and multimodality are computed on them)."""
        return self._run(joints, batch_size)[0]

    def logits(self, joints: Sequence[np.ndarray], *, batch_size: int = 256) -> np.ndarray:
        return self._run(joints, batch_size)[1]

    def predict(self, joints: Sequence[np.ndarray], *, batch_size: int = 256) -> np.ndarray:
        """(N,) predicted class indices (into ``action_names``)."""
        return self.logits(joints, batch_size=batch_size).argmax(1)

    def __repr__(self) -> str:
        return f"ActionClassifier(id={self.id!r}, classes={len(self.action_names)}, device={str(self.device)!r})"


def load_action_classifier(path: str | os.PathLike, device: str | torch.device = "cpu", *,
                           prefer: str = "best") -> ActionClassifier:
    """An action classifier trained by ``lsgan train-evaluator --kind action`` (run or checkpoint folder)."""
    from lsgan.models.checkpoint import load_weights, resolve, weights_hash

    p = Path(path).expanduser()
    if not p.exists():
        raise FileNotFoundError(f"action classifier {p} does not exist")
    weights, meta = load_weights(p, prefer=prefer, kind="action-classifier")
    cfg = _build(ActionClassifierConfig, meta["config"]["model"])
    net = ActionRecognitionGRU(cfg)
    net.load_state_dict(weights)
    net.eval().requires_grad_(False)
    names = meta.get("extra", {}).get("action_names") or [str(i) for i in range(cfg.num_classes)]
    return ActionClassifier(net, names, id=f"lsgan-action-classifier:{weights_hash(resolve(p, prefer))[:16]}",
                            device=device)
