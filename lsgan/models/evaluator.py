"""Evaluators: the networks that turn motions (and captions) into the embeddings the metrics are computed on.

Text-to-motion (R-precision, MM-Dist, FID, diversity, multimodality) needs a text-motion co-embedding;
action-to-motion (accuracy, FID, diversity, multimodality) needs an action-recognition network. Both
are loaded with one call and used through one small interface each:

>>> ev = load_evaluator("runs/evaluator")          # or the root of the official T2M files
>>> ev.embed_motions([features])                   # list of (T,263) de-normalised -> (N, 512)
>>> ev.embed_texts(["a person walks forward"])     # -> (N, 512)
>>> clf = load_action_classifier("runs/act-clf")
>>> clf.features([joints]), clf.predict([joints])  # list of (T,22,3) -> (N, 30), (N,)

**The official T2M evaluator** (Guo et al., CVPR 2022; the evaluator every HumanML3D paper reports
with). The modules below carry the parameter names of ``networks/modules.py`` of
EricGuo5513/text-to-motion, so the state dicts of its ``finest.tar`` load unchanged:

- ``MovementConvEncoder(259, 512, 512)``: ``main`` = Conv1d(k4, s2, p1) -> Dropout(0.2) -> LeakyReLU(0.2),
  twice (the time axis shrinks 4x), then ``out_net`` Linear. The input drops the 4 foot-contact dims.
- ``MotionEncoderBiGRUCo(512, 1024, 512)``: ``input_emb`` Linear -> bidirectional GRU (learned initial
  state ``hidden`` (2,1,H)) over ``length // 4`` steps, both final states -> ``output_net``
  (Linear -> LayerNorm -> LeakyReLU(0.2) -> Linear).
- ``TextEncoderBiGRUCo(300, 15, 512, 512)``: GloVe word vector + ``pos_emb``(one-hot of 15 POS
  categories) -> ``input_emb`` -> bidirectional GRU -> ``output_net``.

Its input pipeline is reproduced as well: captions as HumanML3D ``word/POS`` tokens (``lsgan evaluate``
passes the shard's: HumanML3D's own spaCy tokens, or those tagged at import; a caller that passes none gets
:mod:`lsgan.data.tokens`' tags), split on spaces as T2M's loader does, at most 20 between ``sos/OTHER`` and
``eos/OTHER``, words looked up in ``glove/our_vab_*`` (unknown words -> ``unk`` with POS OTHER; words of
the VIP lists get their VIP category); motions de-normalised by the caller and re-normalised here with
the evaluator's own ``t2m/Comp_v6_KLD01/meta/{mean,std}.npy``, padded with zeros to 196 frames (as the
T2M loaders pad; the padding reaches the last convolution window), sorted by length for packing.
Lengths are floored to a multiple of 4 (the trailing frames dropped), as the T2M loaders crop them.

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
from torch.nn.utils.rnn import pack_padded_sequence

from lsgan.data.skeleton import FEATURE_DIM, NUM_JOINTS
from lsgan.data.tokens import tokenize
from lsgan.outputs import file_sha256
from lsgan.pickles import load_npy, load_pickle, load_torch

__all__ = [
    "MAX_TEXT_LEN",
    "OFFICIAL_FILES",
    "POS_ENUMERATOR",
    "VIP_WORDS",
    "ActionClassifier",
    "ActionClassifierConfig",
    "ActionRecognitionGRU",
    "EvaluatorConfig",
    "EvaluatorNet",
    "LearnedEvaluator",
    "MotionEncoderBiGRUCo",
    "MovementConvEncoder",
    "T2MEvaluator",
    "TextEncoderBiGRUCo",
    "TextMotionEvaluator",
    "WordVectorizer",
    "contrastive_loss",
    "load_action_classifier",
    "load_evaluator",
    "load_learned_evaluator",
    "load_t2m_evaluator",
    "prepare_joints",
]

# ----------------------------------------------------------------------------------------------------------------
# T2M's word vectoriser tables (utils/word_vectorizer.py of EricGuo5513/text-to-motion)

POS_ENUMERATOR: dict[str, int] = {
    "VERB": 0, "NOUN": 1, "DET": 2, "ADP": 3, "NUM": 4, "AUX": 5, "PRON": 6, "ADJ": 7, "ADV": 8,
    "Loc_VIP": 9, "Body_VIP": 10, "Obj_VIP": 11, "Act_VIP": 12, "Desc_VIP": 13, "OTHER": 14,
}
# Checked in this order (a word in two lists takes the first), as the original iterates its dict.
VIP_WORDS: dict[str, tuple[str, ...]] = {
    "Loc_VIP": ("left", "right", "clockwise", "counterclockwise", "anticlockwise", "forward", "back", "backward",
                "up", "down", "straight", "curve"),
    "Body_VIP": ("arm", "chin", "foot", "feet", "face", "hand", "mouth", "leg", "waist", "eye", "knee", "shoulder",
                 "thigh"),
    "Obj_VIP": ("stair", "dumbbell", "chair", "window", "floor", "car", "ball", "handrail", "baseball", "basketball"),
    "Act_VIP": ("walk", "run", "swing", "pick", "bring", "kick", "put", "squat", "throw", "hop", "dance", "jump",
                "turn", "stumble", "dance", "stop", "sit", "lift", "lower", "raise", "wash", "stand", "kneel",
                "stroll", "rub", "bend", "balance", "flap", "jog", "shuffle", "lean", "rotate", "spin", "spread",
                "climb"),
    "Desc_VIP": ("slowly", "carefully", "fast", "careful", "slow", "quickly", "happy", "angry", "sad", "happily",
                 "angrily", "sadly"),
}
MAX_TEXT_LEN = 20  # tokens, before sos/eos
WORD_DIM = 300
UNIT_LENGTH = 4
MAX_MOTION_LENGTH = 196  # the T2M loaders pad every motion to this many frames
NUM_CONTACT_DIMS = 4  # foot contacts: the last 4 feature dims, not read by the evaluator

# Relative to the root of the official files (the T2M repository's checkpoints/ and glove/).
OFFICIAL_FILES: dict[str, str] = {
    "weights": "t2m/text_mot_match/model/finest.tar",
    "mean": "t2m/Comp_v6_KLD01/meta/mean.npy",
    "std": "t2m/Comp_v6_KLD01/meta/std.npy",
    "glove_data": "glove/our_vab_data.npy",
    "glove_idx": "glove/our_vab_idx.pkl",
    "glove_words": "glove/our_vab_words.pkl",
}


def _init_weight(m: nn.Module) -> None:
    if isinstance(m, (nn.Conv1d, nn.Linear)):
        nn.init.xavier_normal_(m.weight)
        if m.bias is not None:
            nn.init.constant_(m.bias, 0)


# ----------------------------------------------------------------------------------------------------------------
# The T2M modules (parameter names as the official checkpoint)

class MovementConvEncoder(nn.Module):
    """(B, T, input) -> (B, T // 4, output): two strided convolutions, then a per-step Linear."""

    def __init__(self, input_size: int = FEATURE_DIM - NUM_CONTACT_DIMS, hidden_size: int = 512,
                 output_size: int = 512) -> None:
        super().__init__()
        self.main = nn.Sequential(
            nn.Conv1d(input_size, hidden_size, 4, 2, 1),
            nn.Dropout(0.2),
            nn.LeakyReLU(0.2),
            nn.Conv1d(hidden_size, output_size, 4, 2, 1),
            nn.Dropout(0.2),
            nn.LeakyReLU(0.2),
        )
        self.out_net = nn.Linear(output_size, output_size)
        self.main.apply(_init_weight)
        self.out_net.apply(_init_weight)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        return self.out_net(self.main(inputs.permute(0, 2, 1)).permute(0, 2, 1))


class _BiGRUCo(nn.Module):
    """Bidirectional GRU over packed sequences from a learned initial state, both last states -> output_net."""

    def __init__(self, hidden_size: int, output_size: int) -> None:
        super().__init__()
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = nn.Sequential(
            nn.Linear(hidden_size * 2, hidden_size),
            nn.LayerNorm(hidden_size),
            nn.LeakyReLU(0.2),
            nn.Linear(hidden_size, output_size),
        )
        self.output_net.apply(_init_weight)
        self.hidden_size = hidden_size
        self.hidden = nn.Parameter(torch.randn((2, 1, hidden_size)))

    def _run(self, input_embs: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        hidden = self.hidden.repeat(1, input_embs.shape[0], 1)
        packed = pack_padded_sequence(input_embs, lengths.detach().cpu().long(), batch_first=True,
                                      enforce_sorted=False)
        _, last = self.gru(packed, hidden)  # (2, B, H), rows back in the input order
        return self.output_net(torch.cat([last[0], last[1]], dim=-1))


class MotionEncoderBiGRUCo(_BiGRUCo):
    """(B, T', input) movement codes and lengths in units (T // 4) -> (B, output)."""

    def __init__(self, input_size: int = 512, hidden_size: int = 1024, output_size: int = 512) -> None:
        super().__init__(hidden_size, output_size)
        self.input_emb = nn.Linear(input_size, hidden_size)
        self.input_emb.apply(_init_weight)

    def forward(self, inputs: torch.Tensor, m_lens: torch.Tensor) -> torch.Tensor:
        return self._run(self.input_emb(inputs), m_lens)


class TextEncoderBiGRUCo(_BiGRUCo):
    """(B, L, 300) word vectors, (B, L, 15) POS one-hots and lengths -> (B, output)."""

    def __init__(self, word_size: int = WORD_DIM, pos_size: int = len(POS_ENUMERATOR), hidden_size: int = 512,
                 output_size: int = 512) -> None:
        super().__init__(hidden_size, output_size)
        self.pos_emb = nn.Linear(pos_size, word_size)
        self.input_emb = nn.Linear(word_size, hidden_size)
        self.input_emb.apply(_init_weight)
        self.pos_emb.apply(_init_weight)

    def forward(self, word_embs: torch.Tensor, pos_onehot: torch.Tensor, cap_lens: torch.Tensor) -> torch.Tensor:
        return self._run(self.input_emb(word_embs + self.pos_emb(pos_onehot)), cap_lens)


def contrastive_loss(a: torch.Tensor, b: torch.Tensor, negative: bool, margin: float) -> torch.Tensor:
    """T2M's ContrastiveLoss (Hadsell et al.): mean d^2 for matched pairs, mean max(0, margin - d)^2 otherwise.

    ``d`` is the Euclidean distance between rows (``F.pairwise_distance``, eps 1e-6 as there).
    """
    d = nn.functional.pairwise_distance(a, b, keepdim=True)
    if negative:
        return torch.clamp(margin - d, min=0.0).pow(2).mean()
    return d.pow(2).mean()


# ----------------------------------------------------------------------------------------------------------------
# GloVe side of the official evaluator

class WordVectorizer:
    """T2M's word vectoriser: ``'word/POS'`` -> (300-d GloVe vector, 15-d POS one-hot).

    Reads ``{prefix}_data.npy`` (V,300), ``{prefix}_idx.pkl`` (dict word -> row) and ``{prefix}_words.pkl``
    (list of words) from ``folder``; the pickles are read by :mod:`lsgan.pickles` (an exact allowlist:
    plain values, numpy arrays and scalars), so they cannot run code.
    """

    def __init__(self, folder: str | os.PathLike, prefix: str = "our_vab") -> None:
        folder = Path(folder)
        data_path = folder / f"{prefix}_data.npy"
        vectors = load_npy(data_path)
        words = load_pickle(folder / f"{prefix}_words.pkl")
        word2idx = load_pickle(folder / f"{prefix}_idx.pkl")
        if vectors.ndim != 2:
            raise ValueError(f"{data_path}: expected (V, {WORD_DIM}) word vectors, got shape {vectors.shape}")
        if not isinstance(words, (list, tuple)) or not all(isinstance(w, str) for w in words):
            raise ValueError(f"{folder / f'{prefix}_words.pkl'}: expected a list of words")
        if not isinstance(word2idx, dict):
            raise ValueError(f"{folder / f'{prefix}_idx.pkl'}: expected a dict word -> index")
        try:
            self.word2vec = {w: np.asarray(vectors[int(word2idx[w])], dtype=np.float32) for w in words}
        except (KeyError, IndexError, TypeError, ValueError) as e:
            raise ValueError(f"{folder}: {prefix}_words.pkl, {prefix}_idx.pkl and {prefix}_data.npy disagree ({e!r})") from e
        if "unk" not in self.word2vec:
            raise ValueError(f"{folder}: the vocabulary has no 'unk' entry (T2M maps unknown words to it)")
        self.dim = vectors.shape[1]
        self._vip = {}
        for key, values in VIP_WORDS.items():
            for w in values:
                self._vip.setdefault(w, key)

    def __len__(self) -> int:
        return len(self.word2vec)

    @staticmethod
    def pos_onehot(pos: str) -> np.ndarray:
        v = np.zeros(len(POS_ENUMERATOR), dtype=np.float32)
        v[POS_ENUMERATOR.get(pos, POS_ENUMERATOR["OTHER"])] = 1.0
        return v

    def __getitem__(self, token: str) -> tuple[np.ndarray, np.ndarray]:
        word, _, pos = token.rpartition("/") if "/" in token else (token, "", "OTHER")
        if word in self.word2vec:
            return self.word2vec[word], self.pos_onehot(self._vip.get(word, pos))
        return self.word2vec["unk"], self.pos_onehot("OTHER")

    def encode(self, tokens: Sequence[str], max_text_len: int = MAX_TEXT_LEN) -> tuple[np.ndarray, np.ndarray, int]:
        """(word vectors (max_text_len+2, 300), POS one-hots (max_text_len+2, 15), sentence length with sos/eos)."""
        tokens = list(tokens)[:max_text_len]
        tokens = ["sos/OTHER", *tokens, "eos/OTHER"]
        sent_len = len(tokens)
        tokens += ["unk/OTHER"] * (max_text_len + 2 - sent_len)
        pairs = [self[t] for t in tokens]
        return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]), sent_len


# ----------------------------------------------------------------------------------------------------------------
# Shared motion side

def _as_device(device) -> torch.device:
    return device if isinstance(device, torch.device) else torch.device(device)


def _check_features(features: Sequence[np.ndarray], unit: int) -> list[np.ndarray]:
    if isinstance(features, np.ndarray) and features.ndim == 2:
        raise TypeError("embed_motions() takes a list of (T, 263) arrays, not a single array: wrap it as [x]")
    out = []
    for i, x in enumerate(features):
        x = np.asarray(x.detach().cpu() if isinstance(x, torch.Tensor) else x, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != FEATURE_DIM:
            raise ValueError(f"motion {i}: features of shape {x.shape}, expected (T, {FEATURE_DIM})")
        if len(x) < unit:
            raise ValueError(f"motion {i}: {len(x)} frames; the evaluator needs at least {unit}")
        if not np.isfinite(x).all():
            raise ValueError(f"motion {i}: features hold NaN or inf")
        out.append(x[: len(x) // unit * unit])
    return out


def motion_forward(movement: MovementConvEncoder, motion: MotionEncoderBiGRUCo, x: torch.Tensor,
                   lengths: torch.Tensor, unit: int = UNIT_LENGTH) -> torch.Tensor:
    """Normalised, zero-padded features (B, P, 263) and frame lengths (B,) -> embeddings (B, D).

    The foot contacts are dropped, the movement encoder runs over the padded batch, the motion GRU over
    ``lengths // unit`` steps. Pad to the same length at training and inference (the padding reaches the
    last convolution window): see :func:`embed_motion_batches`.
    """
    movements = movement(x[..., :-NUM_CONTACT_DIMS])
    return motion(movements, torch.div(lengths, unit, rounding_mode="floor"))


def embed_motion_batches(movement: MovementConvEncoder, motion: MotionEncoderBiGRUCo, normed: list[np.ndarray],
                         device: torch.device, *, unit: int = UNIT_LENGTH, pad_to: int = MAX_MOTION_LENGTH,
                         batch_size: int = 256) -> np.ndarray:
    """Embed normalised motions (lengths multiples of ``unit``), in input order.

    As the T2M loaders do, a motion shorter than ``pad_to`` frames is zero-padded to ``pad_to``, and a
    motion of ``pad_to`` frames or more is not padded at all. Motions are sorted by length (longest
    first) and batched with others padded alike, so a motion's embedding never depends on the others.
    """
    n = len(normed)
    lengths = np.array([len(x) for x in normed])
    order = sorted(range(n), key=lambda i: (-lengths[i], i))
    keys = [max(pad_to, int(lengths[i])) for i in order]
    out: np.ndarray | None = None
    start = 0
    while start < n:
        stop = start
        while stop < n and stop - start < batch_size and keys[stop] == keys[start]:
            stop += 1
        idx = order[start:stop]
        width = keys[start]
        x = np.zeros((len(idx), width, FEATURE_DIM), dtype=np.float32)
        for row, i in enumerate(idx):
            x[row, : lengths[i]] = normed[i]
        emb = motion_forward(movement, motion, torch.from_numpy(x).to(device),
                             torch.as_tensor(lengths[idx]), unit)
        emb = emb.float().cpu().numpy()
        if out is None:
            out = np.empty((n, emb.shape[1]), dtype=np.float32)
        out[idx] = emb
        start = stop
    return out if out is not None else np.zeros((0, motion.output_net[-1].out_features), dtype=np.float32)


class TextMotionEvaluator:
    """What ``lsgan evaluate`` uses: ``id``, ``dim``, ``embed_motions(features)``, ``embed_texts(captions)``.

    Subclasses set ``movement_encoder``, ``motion_encoder``, ``mean``, ``std``, ``unit_length``, ``pad_to``
    and implement :meth:`embed_texts`. Everything runs in eval mode without gradients and is deterministic.
    """

    id: str
    dim: int
    device: torch.device
    movement_encoder: MovementConvEncoder
    motion_encoder: MotionEncoderBiGRUCo
    mean: np.ndarray
    std: np.ndarray
    unit_length: int = UNIT_LENGTH
    pad_to: int = MAX_MOTION_LENGTH

    def normalize(self, features: np.ndarray) -> np.ndarray:
        return (features - self.mean) / self.std

    @torch.no_grad()
    def embed_motions(self, features: Sequence[np.ndarray], *, batch_size: int = 256) -> np.ndarray:
        """De-normalised (T_i, 263) features -> (N, dim) float32 embeddings, rows in input order.

        Lengths are floored to a multiple of ``unit_length`` (trailing frames dropped); at least one unit.
        """
        feats = _check_features(features, self.unit_length)
        normed = [self.normalize(x).astype(np.float32) for x in feats]
        was = self.movement_encoder.training, self.motion_encoder.training
        self.movement_encoder.eval()
        self.motion_encoder.eval()
        try:
            out = embed_motion_batches(self.movement_encoder, self.motion_encoder, normed, self.device,
                                       unit=self.unit_length, pad_to=self.pad_to, batch_size=batch_size)
        finally:
            self.movement_encoder.train(was[0])
            self.motion_encoder.train(was[1])
        return out if len(feats) else np.zeros((0, self.dim), np.float32)

    def embed_texts(self, captions: Sequence[str], *, tokens: Sequence[str] | None = None,
                    batch_size: int = 256) -> np.ndarray:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(id={self.id!r}, dim={self.dim}, device={str(self.device)!r})"


def _check_captions(captions: Sequence[str], tokens: Sequence[str] | None) -> list[str]:
    if isinstance(captions, str):
        raise TypeError("embed_texts() takes a list of strings, not a single string: wrap it as [caption]")
    captions = list(captions)
    if not all(isinstance(c, str) for c in captions):
        raise TypeError("embed_texts() takes strings only")
    if tokens is not None and len(tokens) != len(captions):
        raise ValueError(f"{len(tokens)} token strings for {len(captions)} captions")
    return captions


# ----------------------------------------------------------------------------------------------------------------
# The official T2M evaluator

class T2MEvaluator(TextMotionEvaluator):
    """The released T2M text-motion matching model (``finest.tar``) with its GloVe files and Mean/Std."""

    def __init__(self, text_encoder: TextEncoderBiGRUCo, movement_encoder: MovementConvEncoder,
                 motion_encoder: MotionEncoderBiGRUCo, vectorizer: WordVectorizer, mean: np.ndarray, std: np.ndarray,
                 *, id: str = "t2m-official", device: str | torch.device = "cpu") -> None:
        self.device = _as_device(device)
        self.text_encoder = text_encoder.to(self.device).eval()
        self.movement_encoder = movement_encoder.to(self.device).eval()
        self.motion_encoder = motion_encoder.to(self.device).eval()
        for m in (self.text_encoder, self.movement_encoder, self.motion_encoder):
            m.requires_grad_(False)
        self.vectorizer = vectorizer
        self.mean = np.asarray(mean, np.float32)
        self.std = np.asarray(std, np.float32)
        self.id = id
        self.dim = motion_encoder.output_net[-1].out_features

    @torch.no_grad()
    def embed_texts(self, captions: Sequence[str], *, tokens: Sequence[str] | None = None,
                    batch_size: int = 256) -> np.ndarray:
        """Captions -> (N, 512) from their tokens: ``tokens`` (one ``'word/POS ...'`` string per caption, as the
        shard stores them) where given, else the caption tagged by lsgan.data.tokens. The text is not read."""
        captions = _check_captions(captions, tokens)
        n = len(captions)
        words, poses, lens = [], [], []
        for i, c in enumerate(captions):
            tok = tokens[i] if tokens is not None and tokens[i] else tokenize(c)
            w, p, s = self.vectorizer.encode(tok.split())
            words.append(w)
            poses.append(p)
            lens.append(s)
        out = np.empty((n, self.dim), dtype=np.float32)
        order = sorted(range(n), key=lambda i: (-lens[i], i))
        for start in range(0, n, batch_size):
            idx = order[start:start + batch_size]
            w = torch.from_numpy(np.stack([words[i] for i in idx])).to(self.device)
            p = torch.from_numpy(np.stack([poses[i] for i in idx])).to(self.device)
            emb = self.text_encoder(w, p, torch.as_tensor([lens[i] for i in idx]))
            out[idx] = emb.float().cpu().numpy()
        return out


def _find_official(root: Path) -> tuple[dict[str, Path], list[Path]]:
    """(paths of the official files, missing ones) for the first layout under ``root`` that has finest.tar.

    Layouts: ``root/t2m/...`` + ``root/glove`` (files put side by side), the T2M repository
    (``root/checkpoints/t2m/...`` + ``root/glove``), MLD's ``deps`` (``root/t2m/t2m/...`` + ``root/glove``).
    """
    bases = [root, root / "checkpoints", root / "t2m"]
    base = next((b for b in bases if (b / OFFICIAL_FILES["weights"]).is_file()), root)
    glove_dirs = [root / "glove", base / "glove", root.parent / "glove"]
    glove = next((g for g in glove_dirs if (g / "our_vab_data.npy").is_file()), root / "glove")
    paths = {}
    for key, rel in OFFICIAL_FILES.items():
        paths[key] = glove / Path(rel).name if key.startswith("glove") else base / rel
    missing = [p for p in paths.values() if not p.is_file()]
    return paths, missing


def _infer_t2m_modules(ckpt: dict, where: Path) -> tuple[TextEncoderBiGRUCo, MovementConvEncoder, MotionEncoderBiGRUCo]:
    missing = [k for k in ("text_encoder", "movement_encoder", "motion_encoder") if k not in ckpt]
    if missing:
        raise ValueError(f"{where}: not a T2M text_mot_match checkpoint (no {', '.join(missing)}; "
                         f"it holds {sorted(map(str, ckpt))})")
    te, me, mo = ckpt["text_encoder"], ckpt["movement_encoder"], ckpt["motion_encoder"]
    try:
        text = TextEncoderBiGRUCo(word_size=te["pos_emb.weight"].shape[0], pos_size=te["pos_emb.weight"].shape[1],
                                  hidden_size=te["input_emb.weight"].shape[0], output_size=te["output_net.3.weight"].shape[0])
        movement = MovementConvEncoder(me["main.0.weight"].shape[1], me["main.0.weight"].shape[0],
                                       me["main.3.weight"].shape[0])
        motion = MotionEncoderBiGRUCo(mo["input_emb.weight"].shape[1], mo["input_emb.weight"].shape[0],
                                      mo["output_net.3.weight"].shape[0])
        text.load_state_dict(te)
        movement.load_state_dict(me)
        motion.load_state_dict(mo)
    except (KeyError, RuntimeError, AttributeError, IndexError) as e:
        raise ValueError(f"{where}: its state dicts do not fit the T2M evaluator modules ({e})") from e
    if movement.main[0].in_channels != FEATURE_DIM - NUM_CONTACT_DIMS:
        raise ValueError(f"{where}: an evaluator for {movement.main[0].in_channels + NUM_CONTACT_DIMS}-d features "
                         f"(KIT-ML?); lsgan uses HumanML3D's {FEATURE_DIM}")
    return text, movement, motion


def load_t2m_evaluator(root: str | os.PathLike, device: str | torch.device = "cpu") -> T2MEvaluator:
    """The official evaluator from the folder holding ``t2m/`` and ``glove/`` (see :data:`OFFICIAL_FILES`)."""
    root = Path(root).expanduser()
    paths, missing = _find_official(root)
    if missing:
        raise FileNotFoundError(f"{root}: the official T2M evaluator needs these files, missing: "
                                + ", ".join(str(p) for p in missing))
    ckpt = load_torch(paths["weights"])
    if not isinstance(ckpt, dict):
        raise ValueError(f"{paths['weights']}: expected a dict of state dicts, got {type(ckpt).__name__}")
    text, movement, motion = _infer_t2m_modules(ckpt, paths["weights"])
    mean, std = (load_npy(paths[k]).astype(np.float32) for k in ("mean", "std"))
    for k, v in (("mean", mean), ("std", std)):
        if v.shape != (FEATURE_DIM,):
            raise ValueError(f"{paths[k]}: shape {v.shape}, expected ({FEATURE_DIM},)")
    if (std <= 0).any():
        raise ValueError(f"{paths['std']}: non-positive entries")
    vectorizer = WordVectorizer(paths["glove_data"].parent)
    if vectorizer.dim != text.pos_emb.out_features:
        raise ValueError(f"{paths['glove_data']}: {vectorizer.dim}-d word vectors; the text encoder reads "
                         f"{text.pos_emb.out_features}")
    ev_id = f"t2m-official:{file_sha256(paths['weights'])[:16]}"
    return T2MEvaluator(text, movement, motion, vectorizer, mean, std, id=ev_id, device=device)


# ----------------------------------------------------------------------------------------------------------------
# Our own text-motion evaluator

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
        self.text_head.apply(_init_weight)

    def embed_motion(self, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        return motion_forward(self.movement_encoder, self.motion_encoder, x, lengths, self.cfg.unit_length)

    def embed_sentence(self, s: torch.Tensor) -> torch.Tensor:
        return self.text_head(s)


class LearnedEvaluator(TextMotionEvaluator):
    """Our evaluator: :class:`EvaluatorNet` + a frozen sentence encoder + the training shard's Mean/Std."""

    def __init__(self, net: EvaluatorNet, text_encoder, mean: np.ndarray, std: np.ndarray, *, id: str,
                 device: str | torch.device = "cpu", cache_sentences: bool = True) -> None:
        self.device = _as_device(device)
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
        captions = _check_captions(captions, tokens)
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
    dev = _as_device(device)
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
    paths, missing = _find_official(p)
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
        self.device = _as_device(device)
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
