"""Control: a motion that follows a root path on the ground and hits keyframed joints, from the same generator.

A constraint is met by optimising what the generator starts from, through the frozen generator, the VAE decoder
and ``recover_from_ric``, all differentiable torch (docs/control.md):

1. the generator's input noise ``n`` (starting at the seed's draw, so a seed still names one motion), for
   ``noise_steps`` Adam steps, with a prior keeping ``n`` on the shell N(0, I) samples live on;
2. then the latent ``z`` itself, for ``latent_steps`` steps, with a prior keeping it within a few standard
   deviations (of the training latents) of where the generator put it: the decoder reaches poses and paths the
   generator's range does not.

The losses are means over the constrained frames, in metres: the root's ground position against the path, each
keyframed joint against its target. What is left of each is measured after the last step and returned, so an
unreachable constraint is met as closely as the prior allows and the caller can say by how much.
"""
from __future__ import annotations

from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch

from lsgan.constraints import Constraints, facing_frame
from lsgan.data.features import recover_from_ric
from lsgan.data.skeleton import FPS, NUM_JOINTS


@dataclass
class ControlSettings:
    noise_steps: int = 30
    latent_steps: int = 0  # latent steps after the noise: on by choice (with closing and warping they gained nothing)
    lr: float = 0.05
    noise_prior: float = 0.1  # weight of ((|n|^2 / d) - 1)^2
    latent_prior: float = 0.01  # weight of the mean squared standardised distance from the generator's latent
    speed_weight: float = 0.1  # weight of the root's velocity miss (m/s) along the path, against its position (m)
    pose_weight: float = 1.0  # weight of whole-pose keyframes' miss in their facing frame (what root closing leaves)


def _targets(c: list[Constraints], dev: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,T,22,3) target joints with (B,T,22,3) weights: the root's x, z from the path, the keyframes' joints."""
    T = max(x.frames for x in c)
    target = torch.zeros(len(c), T, NUM_JOINTS, 3)
    weight = torch.zeros_like(target)
    for b, x in enumerate(c):
        if x.path is not None:
            p = torch.from_numpy(x.path)
            ok = ~p.isnan().any(-1)
            target[b, : x.frames, 0, 0], target[b, : x.frames, 0, 2] = p[:, 0].nan_to_num(), p[:, 1].nan_to_num()
            weight[b, : x.frames, 0, 0] = weight[b, : x.frames, 0, 2] = ok.float()
        for f, pose in x.keyframes.items():
            q = torch.from_numpy(pose)
            target[b, f] = torch.where(q.isnan(), target[b, f], q)
            weight[b, f] = torch.maximum(weight[b, f], (~q.isnan()).float())
    return target.to(dev), weight.to(dev)


def _speed_errors(joints: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """(B,) mean miss (m/s) of the root's ground velocity against the path's, over pairs of set frames: what
    closing the root onto the path afterwards would add to the motion's own velocity (feet sliding)."""
    on = weight[:, :, 0, 0] * weight[:, :, 0, 2]  # (B,T)
    pair = on[:, 1:] * on[:, :-1]
    step = joints[:, 1:, 0][..., [0, 2]] - joints[:, :-1, 0][..., [0, 2]]
    want = target[:, 1:, 0][..., [0, 2]] - target[:, :-1, 0][..., [0, 2]]
    return ((step - want).norm(dim=-1) * pair).sum(1) / pair.sum(1).clamp_min(1) * FPS


def _joint_errors(joints: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """(B,) mean distance (m) of the constrained coordinates' joints: a joint counts where any coordinate is set."""
    d = ((joints - target) * weight).norm(dim=-1)  # (B,T,22)
    on = weight.amax(-1)
    return (d * on).sum((1, 2)) / on.sum((1, 2)).clamp_min(1)


def _whole_poses(constraints: list[Constraints], dev) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(rows (K,), frames (K,), poses in their facing frame (K, 22, 3)) of the keyframes that set every joint and
    of the poses (already in their facing frame)."""
    rows, frames, poses = [], [], []
    for b, c in enumerate(constraints):
        for f, pose in c.keyframes.items():
            if not np.isnan(pose).any():
                rows.append(b), frames.append(f), poses.append(facing_frame(np.asarray(pose, np.float64)))
        for f, pose in c.poses.items():
            rows.append(b), frames.append(f), poses.append(np.asarray(pose, np.float64))
    if not rows:
        return torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long), torch.zeros(0, NUM_JOINTS, 3)
    local = torch.from_numpy(np.stack(poses).astype(np.float32))
    return torch.tensor(rows, device=dev), torch.tensor(frames, device=dev), local.to(dev)


def _pose_errors(joints: torch.Tensor, whole: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """(B,) mean joint distance (m) of whole-pose keyframes in their facing frames (0 for rows with none)."""
    rows, frames, local = whole
    out = joints.new_zeros(joints.shape[0])
    if not len(rows):
        return out
    d = (facing_frame(joints[rows, frames]) - local).norm(dim=-1).mean(-1)  # (K,): what closing the root leaves
    count = torch.zeros_like(out).index_add_(0, rows, torch.ones_like(d))
    return out.index_add(0, rows, d) / count.clamp_min(1)


def _loss(joints: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, whole, settings: ControlSettings) -> torch.Tensor:
    return (_joint_errors(joints, target, weight) + settings.speed_weight * _speed_errors(joints, target, weight)
            + settings.pose_weight * _pose_errors(joints, whole)).sum()


@contextmanager
def _frozen(*modules: torch.nn.Module):
    """The modules' parameters out of autograd for the block (only the inputs are optimised), then as they were."""
    params = [p for m in modules for p in m.parameters()]
    was = [p.requires_grad for p in params]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p, w in zip(params, was):
            p.requires_grad_(w)


def control(propose: Callable[[torch.Tensor], torch.Tensor], decoder, noise: torch.Tensor,
            constraints: list[Constraints], *, latent_mean: torch.Tensor, latent_std: torch.Tensor,
            feat_mean: torch.Tensor, feat_std: torch.Tensor, settings: ControlSettings = ControlSettings(),
            frozen: tuple[torch.nn.Module, ...] = ()) -> tuple[torch.Tensor, dict]:
    """Latents (B, Z) in the VAE's space that meet ``constraints`` (one per row) as closely as the priors allow,
    starting from ``propose(noise)``: the generator with its condition bound, giving standardised latents (B, Z)
    for noise (B, d). A proposal that does not depend on the noise (a diffusion's sampled latent) gets no noise
    steps. ``frozen``: the modules behind ``propose`` (their weights stay out of autograd). The report gives, per
    row, the mean and largest error (m) of the constrained joints before and after."""
    with _frozen(decoder, *frozen):
        return _control(propose, decoder, noise, constraints, latent_mean, latent_std, feat_mean, feat_std, settings)


def _control(propose, decoder, noise, constraints, latent_mean, latent_std, feat_mean, feat_std,
             settings: ControlSettings) -> tuple[torch.Tensor, dict]:
    dev = noise.device
    target, weight = _targets(constraints, dev)
    whole = _whole_poses(constraints, dev)
    lengths = torch.tensor([c.frames for c in constraints], device=dev)
    mask = torch.arange(target.shape[1], device=dev)[None] < lengths[:, None]

    def joints(z: torch.Tensor) -> torch.Tensor:
        x = decoder.decode(z * latent_std + latent_mean, mask)  # (B,T,263) normalised
        return recover_from_ric(x * feat_std + feat_mean)  # (B,T,22,3)

    with torch.no_grad():
        z0 = propose(noise)  # standardised latents
        before = _joint_errors(joints(z0), target, weight)
    n = noise.clone().requires_grad_(True)
    opt = torch.optim.Adam([n], lr=settings.lr)
    for _ in range(settings.noise_steps):
        prior = (((n**2).mean(-1) - 1) ** 2).sum() * settings.noise_prior
        loss = _loss(joints(propose(n)), target, weight, whole, settings) + prior
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        z_gen = propose(n)
    z = z_gen.clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=settings.lr)
    for _ in range(settings.latent_steps):
        prior = ((z - z_gen) ** 2).mean(-1).sum() * settings.latent_prior
        loss = _loss(joints(z), target, weight, whole, settings) + prior
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = _joint_errors(joints(z), target, weight)
    report = {"mean_error_m_before": before.tolist(), "mean_error_m": after.tolist()}
    return (z.detach() * latent_std + latent_mean), report
