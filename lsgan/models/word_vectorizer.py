"""T2M's word vectoriser (utils/word_vectorizer.py of EricGuo5513/text-to-motion): the GloVe side of the official
evaluator's text input, ``'word/POS'`` tokens -> (GloVe vector, POS one-hot)."""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lsgan.pickles import load_npy, load_pickle

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
