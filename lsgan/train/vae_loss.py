"""The VAE's training objective: a term on the features, terms on the joints recovered from them, and KL.

What users see is joints, so a VAE trained only on its 263 features can score well there and still show motions
whose bones stretch, whose feet slide and which jitter: ``recover_from_ric`` reads the root-relative positions and
integrates the root's velocities, and nothing in a feature loss asks the positions to agree with the velocities,
with one another from frame to frame, or with one skeleton. The kinematic terms below ask it of the joints
directly, in SI units, each averaged over the real frames only:

- ``joints`` (MLD): SmoothL1 (beta 1) between the recovered global joints, metres; the root trajectory included.
- ``velocity``: the joints' velocity error, m/s (T2M-GPT's and MoMask's VQ-VAEs call their second term a velocity
  loss but apply it to the root-relative positions; this one differences the recovered joints).
- ``accel``: the same for accelerations, m/s^2: jitter is an acceleration error that positions barely see.

- ``bones``: mean absolute error of the 21 bone lengths, metres. The data's skeleton is one rigid skeleton
  (``preprocess`` retargets every clip onto it), so this asks each frame for that skeleton.
- ``contact``: MDM's foot-contact loss: the speed (m/s) of the ankles and toes between frames t and t+1 where the
  data's contact label of frame t (features 259:263, computed from that pair's velocity) says the foot is down.

``kinematic`` says how the velocity, acceleration and bone errors are averaged: "norm", the mean of each error
vector's norm (an L1-type penalty: its gradient does not shrink with the error, and where the decoder is unsure it
pulls towards no change at all, which measured as a collapse onto one fixed pose); or "squared", the mean squared
norm (an L2 penalty, whose minimiser is the conditional mean, as for the features).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from lsgan.data.features import recover_from_ric
from lsgan.data.skeleton import FPS
from lsgan.data.bones import bone_lengths

KINEMATIC = ("norm", "squared")
CONTACT_JOINTS = (7, 10, 8, 11)  # left ankle, left toe, right ankle, right toe: the order of features 259:263


@dataclass(frozen=True)
class LossWeights:
    """The objective's terms and their weights (0 leaves a term out)."""

    features: str = "mse"  # "mse" or "smoothl1" (MLD's), on the normalised features
    joints: float = 0.0
    velocity: float = 0.0
    accel: float = 0.0
    bones: float = 0.0
    contact: float = 0.0
    kl: float = 1e-4
    kinematic: str = "norm"  # "norm" or "squared": how velocity, acceleration and bone errors are averaged

    @property
    def uses_joints(self) -> bool:
        return any((self.joints, self.velocity, self.accel, self.bones, self.contact))


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` (B,T,...) over the frames where ``mask`` (B,T) holds (every trailing element counts)."""
    m = mask.to(values.dtype).reshape(mask.shape + (1,) * (values.dim() - 2))
    per = math.prod(values.shape[2:])  # from the shape: a window of 1 or 2 frames has no velocity or acceleration
    return (values * m).sum() / (m.sum() * per).clamp_min(1.0)


def _feature_term(x_hat: torch.Tensor, x: torch.Tensor, mask: torch.Tensor, kind: str) -> torch.Tensor:
    err = (x_hat - x) ** 2 if kind == "mse" else F.smooth_l1_loss(x_hat, x, reduction="none")
    return _masked_mean(err, mask)


def kinematic_terms(j_hat: torch.Tensor, j: torch.Tensor, mask: torch.Tensor, contacts: torch.Tensor,
                    fps: float = FPS, kinematic: str = "norm") -> dict[str, torch.Tensor]:
    """The kinematic terms of recovered joints ``j_hat`` against ``j`` (B,T,22,3), with the real frames ``mask``
    (B,T) and the data's foot contacts (B,T,4) in [0, 1]; ``kinematic`` as :class:`LossWeights`."""
    err = (lambda d: d.norm(dim=-1)) if kinematic == "norm" else (lambda d: (d**2).sum(-1))
    pairs, triples = mask[:, 1:] & mask[:, :-1], mask[:, 2:] & mask[:, 1:-1] & mask[:, :-2]
    v_hat, v = j_hat.diff(dim=1) * fps, j.diff(dim=1) * fps  # (B,T-1,22,3) m/s
    a_hat, a = v_hat.diff(dim=1) * fps, v.diff(dim=1) * fps  # (B,T-2,22,3) m/s^2
    on = (contacts[:, :-1] > 0.5) & pairs[..., None]  # (B,T-1,4): frame t's label is the pair (t, t+1)'s
    feet = v_hat[:, :, list(CONTACT_JOINTS)].norm(dim=-1)  # (B,T-1,4)
    return {
        "joints": _masked_mean(F.smooth_l1_loss(j_hat, j, reduction="none"), mask),
        "velocity": _masked_mean(err(v_hat - v), pairs),
        "accel": _masked_mean(err(a_hat - a), triples),
        "bones": _masked_mean(err((bone_lengths(j_hat) - bone_lengths(j))[..., None]), mask),
        "contact": (feet * on).sum() / on.sum().clamp_min(1),
    }


def vae_objective(x_hat: torch.Tensor, x: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor, mask: torch.Tensor,
                  w: LossWeights, mean: torch.Tensor, std: torch.Tensor) -> dict[str, torch.Tensor]:
    """{"total", "recon", each weighted kinematic term, "kl"} for normalised features ``x_hat``, ``x`` (B,T,263),
    the posterior ``mu``, ``logvar`` and the real frames ``mask`` (B,T); ``mean``, ``std`` de-normalise.

    KL is averaged over the batch and latent dimensions (MLD's KLLoss), so MLD's weight 1e-4 means the same here.
    """
    out = {"recon": _feature_term(x_hat, x, mask, w.features)}
    total = out["recon"]
    if w.uses_joints:
        raw_hat, raw = x_hat * std + mean, x * std + mean
        terms = kinematic_terms(recover_from_ric(raw_hat), recover_from_ric(raw), mask, raw[..., -4:],
                                kinematic=w.kinematic)
        for name, value in terms.items():
            weight = getattr(w, name)
            if weight:
                out[f"recon_{name}"] = value
                total = total + weight * value
    out["kl"] = (-0.5 * (1 + logvar - mu**2 - logvar.exp())).mean()
    return {"total": total + w.kl * out["kl"], **out}
