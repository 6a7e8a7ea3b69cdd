"""The text-motion evaluator interface (what ``lsgan evaluate`` calls) and the motion side both text-motion
evaluators share.

Motions come de-normalised from the caller and are re-normalised with the evaluator's own Mean/Std, floored to a
multiple of 4 frames (the trailing frames dropped, as the T2M loaders crop them), padded with zeros to 196 frames
(as the T2M loaders pad; the padding reaches the last convolution window) and sorted by length for packing.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from lsgan.data.skeleton import FEATURE_DIM
from lsgan.models.t2m_modules import NUM_CONTACT_DIMS, MotionEncoderBiGRUCo, MovementConvEncoder

UNIT_LENGTH = 4
MAX_MOTION_LENGTH = 196  # the T2M loaders pad every motion to this many frames


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


def check_captions(captions: Sequence[str], tokens: Sequence[str] | None) -> list[str]:
    if isinstance(captions, str):
        raise TypeError("embed_texts() takes a list of strings, not a single string: wrap it as [caption]")
    captions = list(captions)
    if not all(isinstance(c, str) for c in captions):
        raise TypeError("embed_texts() takes strings only")
    if tokens is not None and len(tokens) != len(captions):
        raise ValueError(f"{len(tokens)} token strings for {len(captions)} captions")
    return captions
