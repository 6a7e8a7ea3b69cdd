"""The official T2M evaluator (Guo et al., CVPR 2022; the evaluator every HumanML3D paper reports with): finding
its released files, loading ``finest.tar`` into :mod:`lsgan.models.t2m_modules`, and its text side.

Its text input pipeline is reproduced: captions as HumanML3D ``word/POS`` tokens (``lsgan evaluate`` passes the
shard's: HumanML3D's own spaCy tokens, or those tagged at import; a caller that passes none gets
:mod:`lsgan.data.tokens`' tags), split on spaces as T2M's loader does, at most 20 between ``sos/OTHER`` and
``eos/OTHER``, words looked up in ``glove/our_vab_*`` (:class:`lsgan.models.word_vectorizer.WordVectorizer`).
Motions are normalised with the evaluator's own ``t2m/Comp_v6_KLD01/meta/{mean,std}.npy``
(:class:`lsgan.models.text_motion.TextMotionEvaluator`).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from lsgan.data.skeleton import FEATURE_DIM
from lsgan.data.tokens import tokenize
from lsgan.device import as_device
from lsgan.models.t2m_modules import NUM_CONTACT_DIMS, MotionEncoderBiGRUCo, MovementConvEncoder, TextEncoderBiGRUCo
from lsgan.models.text_motion import TextMotionEvaluator, check_captions
from lsgan.models.word_vectorizer import WordVectorizer
from lsgan.outputs import file_sha256
from lsgan.pickles import load_npy, load_torch

# Relative to the root of the official files (the T2M repository's checkpoints/ and glove/).
OFFICIAL_FILES: dict[str, str] = {
    "weights": "t2m/text_mot_match/model/finest.tar",
    "mean": "t2m/Comp_v6_KLD01/meta/mean.npy",
    "std": "t2m/Comp_v6_KLD01/meta/std.npy",
    "glove_data": "glove/our_vab_data.npy",
    "glove_idx": "glove/our_vab_idx.pkl",
    "glove_words": "glove/our_vab_words.pkl",
}


class T2MEvaluator(TextMotionEvaluator):
    """The released T2M text-motion matching model (``finest.tar``) with its GloVe files and Mean/Std."""

    def __init__(self, text_encoder: TextEncoderBiGRUCo, movement_encoder: MovementConvEncoder,
                 motion_encoder: MotionEncoderBiGRUCo, vectorizer: WordVectorizer, mean: np.ndarray, std: np.ndarray,
                 *, id: str = "t2m-official", device: str | torch.device = "cpu") -> None:
        self.device = as_device(device)
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
        captions = check_captions(captions, tokens)
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


def find_official(root: Path) -> tuple[dict[str, Path], list[Path]]:
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
    paths, missing = find_official(root)
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
