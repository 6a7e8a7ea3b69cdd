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

from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch

from lsgan.data.features import recover_from_ric
from lsgan.data.skeleton import NUM_JOINTS


@dataclass
class Constraints:
    """What one motion of ``frames`` frames must do. ``path``: (frames, 2) ground positions (x, z) of the root, NaN
    rows free; ``keyframes``: {frame: (22, 3) joint positions, NaN entries free}."""

    frames: int
    path: np.ndarray | None = None
    keyframes: dict[int, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.path is not None:
            self.path = np.asarray(self.path, np.float32)
            if self.path.shape != (self.frames, 2):
                raise ValueError(f"a path for {self.frames} frames is ({self.frames}, 2) ground points, "
                                 f"not {self.path.shape}")
            if np.isinf(self.path).any():
                raise ValueError("a path holds an infinite coordinate")
        for f, pose in list(self.keyframes.items()):
            pose = np.asarray(pose, np.float32)
            if not 0 <= f < self.frames:
                raise ValueError(f"keyframe {f} is beyond the motion's {self.frames} frames (0..{self.frames - 1})")
            if pose.shape != (NUM_JOINTS, 3) or np.isinf(pose).any():
                raise ValueError(f"keyframe {f}: a pose is {NUM_JOINTS} joints x 3 finite coordinates (NaN = free), "
                                 f"not {pose.shape}")
            self.keyframes[f] = pose

    @property
    def empty(self) -> bool:
        return (self.path is None or np.isnan(self.path).all()) and not self.keyframes


@dataclass
class ControlSettings:
    noise_steps: int = 30
    latent_steps: int = 30
    lr: float = 0.05
    noise_prior: float = 0.1  # weight of ((|n|^2 / d) - 1)^2
    latent_prior: float = 0.01  # weight of the mean squared standardised distance from the generator's latent


def path_points(waypoints: np.ndarray, frames: int, fps: float = 20.0) -> np.ndarray:
    """(frames, 2) ground positions from waypoints (K, 3) of (time s, x, z), linearly between them; frames before
    the first and after the last waypoint are free (NaN)."""
    w = np.asarray(waypoints, np.float64)
    if w.ndim != 2 or w.shape[1] != 3 or len(w) == 0 or not np.isfinite(w).all():
        raise ValueError(f"waypoints are rows of finite (time, x, z), not an array of shape {w.shape}")
    if (np.diff(w[:, 0]) <= 0).any():
        raise ValueError("waypoint times must increase")
    t = np.arange(frames) / fps
    out = np.stack([np.interp(t, w[:, 0], w[:, 1]), np.interp(t, w[:, 0], w[:, 2])], -1)
    out[(t < w[0, 0]) | (t > w[-1, 0])] = np.nan
    return out.astype(np.float32)


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


def _joint_errors(joints: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """(B,) mean distance (m) of the constrained coordinates' joints: a joint counts where any coordinate is set."""
    d = ((joints - target) * weight).norm(dim=-1)  # (B,T,22)
    on = weight.amax(-1)
    return (d * on).sum((1, 2)) / on.sum((1, 2)).clamp_min(1)


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


def control(generator, decoder, cond: torch.Tensor, noise: torch.Tensor, constraints: list[Constraints], *,
            latent_mean: torch.Tensor, latent_std: torch.Tensor, feat_mean: torch.Tensor, feat_std: torch.Tensor,
            settings: ControlSettings = ControlSettings()) -> tuple[torch.Tensor, dict]:
    """Latents (B, Z) in the VAE's space for ``cond`` (B, ...) and starting ``noise`` (B, d) that meet
    ``constraints`` (one per row) as closely as the priors allow, and a report: per row, the mean and largest
    error (m) of the constrained joints before and after."""
    with _frozen(generator, decoder):
        return _control(generator, decoder, cond, noise, constraints, latent_mean, latent_std, feat_mean, feat_std,
                        settings)


def _control(generator, decoder, cond, noise, constraints, latent_mean, latent_std, feat_mean, feat_std,
             settings: ControlSettings) -> tuple[torch.Tensor, dict]:
    dev = noise.device
    target, weight = _targets(constraints, dev)
    lengths = torch.tensor([c.frames for c in constraints], device=dev)
    mask = torch.arange(target.shape[1], device=dev)[None] < lengths[:, None]

    def joints(z: torch.Tensor) -> torch.Tensor:
        x = decoder.decode(z * latent_std + latent_mean, mask)  # (B,T,263) normalised
        return recover_from_ric(x * feat_std + feat_mean)  # (B,T,22,3)

    with torch.no_grad():
        z0 = generator(noise, cond)  # standardised latents
        before = _joint_errors(joints(z0), target, weight)
    n = noise.clone().requires_grad_(True)
    opt = torch.optim.Adam([n], lr=settings.lr)
    for _ in range(settings.noise_steps):
        prior = (((n**2).mean(-1) - 1) ** 2).sum() * settings.noise_prior
        loss = _joint_errors(joints(generator(n, cond)), target, weight).sum() + prior
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        z_gen = generator(n, cond)
    z = z_gen.clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=settings.lr)
    for _ in range(settings.latent_steps):
        prior = ((z - z_gen) ** 2).mean(-1).sum() * settings.latent_prior
        loss = _joint_errors(joints(z), target, weight).sum() + prior
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        j = joints(z)
        after = _joint_errors(j, target, weight)
        worst = (((j - target) * weight).norm(dim=-1) * weight.amax(-1)).amax((1, 2))
    report = {"mean_error_m_before": before.tolist(), "mean_error_m": after.tolist(), "max_error_m": worst.tolist()}
    return (z.detach() * latent_std + latent_mean), report
