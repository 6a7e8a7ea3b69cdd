"""The VAE decoder's last step: motion that is smooth in time and on the data's skeleton by construction.

A transformer decoder predicts every frame's 263 features from its own query token, so nothing ties one frame
to the next or one frame's bones to another's: decoded joints jitter (on Bandai-Namco, jerk 3x the mocap's) and
bones stretch within a motion (5.7 mm standard deviation per bone; every mocap shard has one skeleton, 0 mm).
Two optional steps after the last linear layer remove both at the source, inside the model (training, latents,
generation, the server and the ONNX graphs all see them; nothing is fixed afterwards):

- ``smooth_output = K``: K passes of the binomial filter [1, 2, 1] / 4 over time, within each motion's frames
  (its first and last frame repeated at the ends, padding never read). One pass removes the frame-to-frame
  alternation entirely (gain 0 at 10 Hz at 20 fps) and keeps slow motion (gain 0.9 at 2 Hz).
- ``rigid_output``: the root-relative joints (the ``ric`` slice) moved onto the training data's bone lengths,
  each bone along its decoded direction, from the root outwards. Every bone then has one length in every frame;
  the angles between the bones of a branching joint (pelvis, spine3) stay learned.

Both are differentiable, so training shapes the decoder through them. The bone functions live in
:mod:`lsgan.data.bones` (numpy or torch: a timeline's seams use the same code). :class:`DecoderHead` holds the
normalisation and the skeleton the rigid step needs; they are not weights: ``train-vae`` measures them from its
data every run (a resume on changed data included) and stores them in the checkpoint's config beside the
normalisation every VAE has, and :func:`lsgan.models.vae.load_vae` checks and sets them, so the head and the code
that de-normalises its output can never hold two different normalisations.
"""
from __future__ import annotations

import torch
from torch import nn

from lsgan.data.skeleton import NUM_JOINTS
from lsgan.data.bones import on_skeleton


def smooth_time(x: torch.Tensor, mask: torch.Tensor, passes: int = 1) -> torch.Tensor:
    """``passes`` of [1, 2, 1] / 4 over the time axis of ``x`` (B,T,D), each motion's real frames ``mask`` (B,T)
    only (a motion's first and last frame stand in for their missing neighbours); padded frames come out as
    they went in."""
    inside = torch.cat([mask[:, 1:], mask.new_zeros(mask.shape[0], 1)], 1)[..., None]  # (B,T,1) frame t+1 real
    for _ in range(passes):
        before = torch.cat([x[:, :1], x[:, :-1]], 1)  # frame t-1 (frame 0 for itself)
        after = torch.where(inside, torch.cat([x[:, 1:], x[:, -1:]], 1), x)  # frame t+1, or t at a motion's end
        x = torch.where(mask[..., None], (before + 2 * x + after) / 4, x)
    return x


class DecoderHead(nn.Module):
    """Normalised decoder output (B,T,263) + mask (B,T) -> the same, smoothed and/or on the skeleton.

    The rigid step works on de-normalised features, so the head keeps the training normalisation (``mean``,
    ``std``) and the skeleton (``lengths``) as buffers that are not saved with the weights; :meth:`set_skeleton`
    fills them (they are NaN until then, so an unset head cannot pass for a working one)."""

    def __init__(self, nfeats: int, smooth: int, rigid: bool) -> None:
        super().__init__()
        self.smooth, self.rigid = smooth, rigid
        if rigid:
            self.register_buffer("mean", torch.full((nfeats,), float("nan")), persistent=False)
            self.register_buffer("std", torch.full((nfeats,), float("nan")), persistent=False)
            self.register_buffer("lengths", torch.full((NUM_JOINTS - 1,), float("nan")), persistent=False)

    def set_skeleton(self, mean: torch.Tensor, std: torch.Tensor, lengths: torch.Tensor) -> None:
        """The training data's normalisation (263,) and bone lengths (21,)."""
        for name, value in (("mean", mean), ("std", std), ("lengths", lengths)):
            getattr(self, name).copy_(torch.as_tensor(value, dtype=torch.float32))

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        x = smooth_time(x.float(), mask, self.smooth) if self.smooth else x.float()
        if self.rigid:
            x = (on_skeleton(x * self.std + self.mean, self.lengths) - self.mean) / self.std
        return x
