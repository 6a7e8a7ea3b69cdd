"""Train the motion VAE: AdamW on a reconstruction loss + KL, validation MPJPE in metres (the loop: lsgan.train.loop).

The objective (:mod:`lsgan.train.vae_loss`) is ``VAETrainConfig.loss`` for the features: "mse", MSE on the
normalised features; or "mld", MLD's configuration (SmoothL1 on the features + SmoothL1 on the joints recovered
from them, weight 1 each), which the paper trains with (``joint_weight`` adds that joint term to "mse"); plus the
kinematic terms the config weights (velocity, acceleration, bone lengths, foot contact) and KL. The learning rate
is constant or follows a cosine to 0 after a linear warm-up (``lr_schedule``), computed from the optimiser's own
step count so a resume continues it.

One process: ``train_vae(shards, "runs/vae", model=VAEConfig(...), train=VAETrainConfig(...))``.
Several: the same call under ``torchrun --nproc_per_node=N``; every process draws its own batches of
``batch_size`` clips (the global batch is N x batch_size), gradients are averaged by DDP, rank 0 alone
writes checkpoints and logs.

Resuming reloads ``out/last/`` (weights, optimiser, step, RNG states, sampler epoch and position) and
continues at the same step: the continued run is the uninterrupted one, bit for bit on the CPU. Windows are gathered
from every frame of the shards held in memory (:class:`lsgan.data.dataset.FrameTable`; on a GPU, in its memory), in
this process: ``num_workers`` is not used here.
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np
import torch

from lsgan.data.dataset import FrameTable, LengthBucketSampler, MotionDataset
from lsgan.data.features import recover_from_ric
from lsgan.data.shards import Shard
from lsgan.data.bones import bone_lengths, skeleton_lengths
from lsgan.models.vae import MotionVAE, VAEConfig, load_vae
from lsgan.train.common import all_reduce_mean, seed_everything, shard_paths
from lsgan.train.loop import EpochBatches, Env, Trainer, WindowTrainConfig, fit, launch
from lsgan.train.vae_loss import KINEMATIC, LossWeights, vae_objective

__all__ = ["VAETrainConfig", "train_vae", "load_vae", "mld_vae_loss", "reconstruction_errors"]

LOSSES = ("mse", "mld")
SCHEDULES = ("constant", "cosine")
VALIDATION_SUMS = ("mpjpe_m", "mpjpe_rel_m", "bone_std_mm", "frames", "motions")


@dataclass
class VAETrainConfig(WindowTrainConfig):
    """With the schedule, window lengths, workers and seed of :class:`lsgan.train.loop.WindowTrainConfig`."""

    lr: float = 1e-4
    weight_decay: float = 0.0
    batch_size: int = 128  # per process
    kl_weight: float = 1e-4
    loss: str = "mse"  # "mse": MSE on the features; "mld": MLD's SmoothL1 on the features and the recovered joints
    joint_weight: float = 0.0  # with loss "mse": the joints' SmoothL1 term, metres (loss "mld" has MLD's 1)
    velocity_weight: float = 0.0  # joints' velocity error, m/s (lsgan.train.vae_loss)
    accel_weight: float = 0.0  # joints' acceleration error, m/s^2
    bone_weight: float = 0.0  # bone-length error, m
    contact_weight: float = 0.0  # speed of the feet the data says are on the ground, m/s
    kinematic_loss: str = "norm"  # "norm" (L1-type) or "squared": how velocity, acceleration, bone errors average
    lr_schedule: str = "constant"  # "constant" or "cosine" (to 0 at max_steps)
    warmup_steps: int = 0  # linear warm-up from 0 (either schedule)
    unit_length: int = 4  # window lengths rounded down to a multiple (one unit less w.p. 1/3), as HumanML3D loaders
    grad_clip: float = 1.0  # max global grad norm; 0 = no clipping
    amp: bool = True  # bf16 autocast, CUDA only
    val_batches: int = 16  # validation batches at most; 0 = the whole validation set

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {', '.join(LOSSES)}, not {self.loss!r}")
        if self.kinematic_loss not in KINEMATIC:
            raise ValueError(f"kinematic_loss must be one of {', '.join(KINEMATIC)}, not {self.kinematic_loss!r}")
        if self.lr_schedule not in SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {', '.join(SCHEDULES)}, not {self.lr_schedule!r}")
        for name in ("joint_weight", "velocity_weight", "accel_weight", "bone_weight", "contact_weight",
                     "warmup_steps"):
            if not 0 <= getattr(self, name) < math.inf:
                raise ValueError(f"{name} must be a finite number >= 0, not {getattr(self, name)!r}")
        if self.loss == "mld" and self.joint_weight:
            raise ValueError("joint_weight is for loss mse: loss mld weighs the joints 1, as MLD")

    def weights(self) -> LossWeights:
        mld = self.loss == "mld"
        return LossWeights(features="smoothl1" if mld else "mse", joints=1.0 if mld else self.joint_weight,
                           velocity=self.velocity_weight, accel=self.accel_weight, bones=self.bone_weight,
                           contact=self.contact_weight, kl=self.kl_weight, kinematic=self.kinematic_loss)

    def lr_at(self, step: int) -> float:
        """The learning rate of update ``step`` (0-based)."""
        if step < self.warmup_steps:
            return self.lr * (step + 1) / self.warmup_steps
        if self.lr_schedule == "constant":
            return self.lr
        done = (step - self.warmup_steps) / max(1, self.max_steps - self.warmup_steps)
        return self.lr * 0.5 * (1.0 + math.cos(math.pi * min(1.0, done)))

    def against(self, model: VAEConfig) -> None:
        """Refuse windows longer than the model's position code covers (recipes check it when read)."""
        if self.max_frames > model.max_len:
            raise ValueError(f"train.max_frames ({self.max_frames}) is more than model.max_len ({model.max_len}), "
                             "the longest window the VAE's position code covers")


def mld_vae_loss(x_hat: torch.Tensor, x: torch.Tensor, mu: torch.Tensor, logvar: torch.Tensor, mask: torch.Tensor,
                 kl_weight: float, mean: torch.Tensor, std: torch.Tensor) -> dict[str, torch.Tensor]:
    """MLD's VAE loss: SmoothL1 on the features + SmoothL1 on the joints ``recover_from_ric`` gives from the
    de-normalised features (``* std + mean``), weight 1 each, + kl_weight * KL(q(z|x) || N(0,I)).

    Each SmoothL1 (torch's, beta 1, as MLD's) is a mean over the real frames' elements (MLD's mean also counts the
    padded frames).
    """
    w = LossWeights(features="smoothl1", joints=1.0, kl=kl_weight)
    return vae_objective(x_hat, x, mu, logvar, mask, w, mean, std)


def reconstruction_errors(x_hat: torch.Tensor, x: torch.Tensor, mask: torch.Tensor, mean: torch.Tensor,
                          std: torch.Tensor) -> dict[str, float]:
    """Sums over a batch of normalised features (B,T,263) with real frames ``mask`` (B,T), to be divided by
    "frames" or "motions": "mpjpe_m", the per-frame mean joint error in metres (the root trajectory integrated, so
    drift counts); "mpjpe_rel_m", the same with each frame's root moved onto the real one; "bone_std_mm", each
    motion's per-bone standard deviation over its frames in mm, averaged over bones (a rigid skeleton has 0)."""
    joints_hat = recover_from_ric(x_hat.float() * std + mean)  # (B,T,22,3)
    joints = recover_from_ric(x.float() * std + mean)
    per_frame = (joints_hat - joints).norm(dim=-1).mean(-1)  # (B,T)
    rel = joints_hat - joints_hat[..., :1, :] - (joints - joints[..., :1, :])
    m = mask[..., None].to(joints.dtype)  # (B,T,1)
    n = m.sum(1).clamp_min(1.0)  # (B,1)
    bones = bone_lengths(joints_hat) * m  # (B,T,21)
    var = ((bones - bones.sum(1, keepdim=True) / n[:, None]) ** 2 * m).sum(1) / n  # (B,21)
    return {"mpjpe_m": float(per_frame[mask].sum()), "mpjpe_rel_m": float(rel.norm(dim=-1).mean(-1)[mask].sum()),
            "bone_std_mm": float(var.sqrt().mean(-1).sum() * 1000), "frames": int(mask.sum()),
            "motions": int(mask.any(1).sum())}


def _updates(opt: torch.optim.Optimizer) -> int:
    """How many updates ``opt`` has made (its per-parameter step count, saved and restored with its state)."""
    for group in opt.param_groups:
        for p in group["params"]:
            state = opt.state.get(p)
            if state and "step" in state:
                return int(state["step"])
    return 0


def _split_validation(paths: list[str], train_ds: MotionDataset, say) -> set[tuple[int, int]]:
    """(shard, clip) pairs to validate on: each shard's val clips, else its test clips, else a held-out
    10% of its train clips (removed from ``train_ds``)."""
    chosen: set[tuple[int, int]] = set()
    for s, path in enumerate(paths):
        with Shard(path) as shard:
            splits = shard.splits
        for split in ("val", "test"):
            idx = np.flatnonzero(splits == split)
            if len(idx):
                if split == "test":
                    say(f"{path}: no 'val' clips; validating on its {len(idx)} 'test' clips")
                chosen |= {(s, int(i)) for i in idx}
                break
        else:
            clips = sorted({w.clip for w in train_ds.windows if w.shard == s})
            if len(clips) > 1:
                held = clips[-max(1, len(clips) // 10):]
                train_ds.windows = [w for w in train_ds.windows if not (w.shard == s and w.clip in held)]
                say(f"{path}: no 'val' or 'test' clips; holding out {len(held)} of its {len(clips)} train clips for validation")
            else:
                held = clips
                say(f"{path}: no 'val' or 'test' clips and a single train clip; validating on that training clip")
            chosen |= {(s, i) for i in held}
    return chosen


def train_vae(data: str | os.PathLike | Sequence[str | os.PathLike], out: str | os.PathLike, *, model: VAEConfig,
              train: VAETrainConfig, device: str = "auto", resume: bool = False, force: bool = False,
              progress: bool = True) -> dict:
    """Train a MotionVAE on the 'train' split of the shards; returns the final metrics.

    Returns {"step", "train_loss", "val_mpjpe_m", "best_val_mpjpe_m"} (the same on every process).
    Raises TrainingDiverged on a NaN/inf loss or gradient, leaving the last good checkpoint in place.
    """
    train.against(model)
    paths = shard_paths(data)
    return launch("train_vae", out, device=device, resume=resume, force=force, progress=progress,
                  body=lambda env: _train(env, paths, model, train))


def _train(env: Env, paths: list[str], mcfg: VAEConfig, cfg: VAETrainConfig) -> dict:
    prev = env.previous("vae")
    if prev is not None:
        _say_changed_objective(env, prev.meta.get("config", {}).get("train", {}), cfg)
    if cfg.warmup_steps >= cfg.max_steps > 0:
        env.say(f"warmup_steps {cfg.warmup_steps} >= max_steps {cfg.max_steps}: the whole run is warm-up, the learning "
                f"rate reaches {cfg.lr_at(cfg.max_steps - 1):.3g} of {cfg.lr:.3g}")
    seed_everything(cfg.seed + env.dist.rank)
    kw = dict(min_frames=cfg.min_frames, max_frames=cfg.max_frames, unit_length=cfg.unit_length)
    train_ds = MotionDataset(paths, "train", **kw)
    val_ds = MotionDataset(paths, None, mean=train_ds.mean, std=train_ds.std, **kw)
    val_clips = _split_validation(paths, train_ds, env.say)
    val_ds.windows = [w for w in val_ds.windows if (w.shard, w.clip) in val_clips]
    if not len(train_ds):
        raise ValueError(f"no training windows of {cfg.min_frames}+ frames in {paths}")
    if not len(val_ds):
        env.say(f"no validation windows of {cfg.min_frames}+ frames: validation MPJPE will be NaN and best/ the last "
                "checkpoint")
    t = _trainer(env, train_ds, val_ds, FrameTable(train_ds, env.device), mcfg, cfg, paths)
    p = fit(env, t, cfg.schedule(), prev, intro=f"{len(train_ds)} training windows, {len(val_ds)} validation windows; "
            f"{sum(w.numel() for w in t.model.parameters()):,} parameters; device {env.device}, "
            f"{env.dist.world_size} process(es)")
    return {"step": p.step, "train_loss": p.train_loss, "val_mpjpe_m": p.val.get("mpjpe_m"),
            "best_val_mpjpe_m": p.best_value}


def _say_changed_objective(env: Env, before: dict, cfg: VAETrainConfig) -> None:
    """Tell a resume what it changes of the objective or the schedule (the run continues with the new values)."""
    keys = ("loss", "kl_weight", "joint_weight", "velocity_weight", "accel_weight", "bone_weight", "contact_weight",
            "kinematic_loss", "lr", "lr_schedule", "warmup_steps")
    defaults = VAETrainConfig()
    changed = [f"{k} {before.get(k, getattr(defaults, k))!r} -> {getattr(cfg, k)!r}" for k in keys
               if before.get(k, getattr(defaults, k)) != getattr(cfg, k)]
    if cfg.lr_schedule == "cosine" and before.get("max_steps", cfg.max_steps) != cfg.max_steps:
        changed.append(f"max_steps {before['max_steps']} -> {cfg.max_steps} (the cosine now ends there)")
    if changed:
        env.say("resuming with another objective or schedule: " + "; ".join(changed))


def _trainer(env: Env, train_ds: MotionDataset, val_ds: MotionDataset, frames: FrameTable, mcfg: VAEConfig,
             cfg: VAETrainConfig, paths: list[str]) -> Trainer:
    """The VAE's step (forward, loss, backward, clipping, AdamW) and validation, both on windows gathered from
    ``frames`` (the training and validation windows are of the same shards)."""
    dev, d = env.device, env.dist
    sampler = LengthBucketSampler(train_ds.lengths(), cfg.batch_size, seed=cfg.seed, num_replicas=d.world_size,
                                  rank=d.rank)
    if len(sampler) == 0:
        raise ValueError(f"{len(train_ds)} training windows make fewer than one batch of {cfg.batch_size} per process "
                         f"({d.world_size} processes); lower batch_size")
    mean, std = torch.as_tensor(train_ds.mean, device=dev), torch.as_tensor(train_ds.std, device=dev)
    vae = MotionVAE(mcfg).to(dev)
    skeleton = {}
    if mcfg.rigid_output:  # measured from this run's data, a resume's too: not weights, never restored from before
        lengths = training_skeleton(train_ds, frames)
        vae.head.set_skeleton(mean, std, lengths)
        skeleton = {"bone_lengths": lengths.tolist()}
    opt = torch.optim.AdamW(vae.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    net, amp = env.ddp(vae), env.autocast(cfg.amp)
    weights = cfg.weights()

    def step(batch: dict) -> dict[str, torch.Tensor]:
        x, mask = batch["motion"], batch["mask"]  # (B,T,263), (B,T): gathered on the device
        with amp:
            x_hat, mu, logvar = net(x, mask)
        losses = vae_objective(x_hat.float(), x, mu.float(), logvar.float(), mask, weights, mean, std)
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(vae.parameters(), cfg.grad_clip if cfg.grad_clip > 0 else math.inf)
        for group in opt.param_groups:
            group["lr"] = cfg.lr_at(_updates(opt))
        opt.step()
        return {"loss": losses.pop("total"), **losses, "grad_norm": grad_norm}

    extra = {"mean": train_ds.mean.tolist(), "std": train_ds.std.tolist(), "data": paths, **skeleton}
    return Trainer(
        kind="vae", desc="vae", model=vae, config={"model": asdict(mcfg), "train": asdict(cfg)},
        optimizers={"optimizer": opt}, step=step, metric="mpjpe_m",
        batches=EpochBatches(train_ds, sampler, seed=cfg.seed, frames=frames),
        validate=_validation(env, vae, val_ds, frames, cfg, mean, std),
        extra=lambda p: {**extra, "val_mpjpe_m": p.val.get("mpjpe_m"), "best_val_mpjpe_m": p.best_value},
    )


def training_skeleton(ds: MotionDataset, frames: FrameTable, most: int = 20_000) -> torch.Tensor:
    """The bone lengths (21,) of the training windows' frames (up to ``most``, evenly spaced): their median, so
    a frame or clip off the data's one skeleton cannot move it."""
    rows = np.unique(np.concatenate([frames.first_row(w.shard, w.clip) + np.arange(w.start, w.stop)
                                     for w in ds.windows]))
    rows = rows[np.linspace(0, len(rows) - 1, min(most, len(rows))).astype(np.int64)]
    return skeleton_lengths(ds.denormalize(frames.rows(rows[None])[0].cpu()))


def _validation(env: Env, vae: MotionVAE, val_ds: MotionDataset, frames: FrameTable, cfg: VAETrainConfig,
                mean: torch.Tensor, std: torch.Tensor) -> Callable[[], dict[str, float]]:
    """MPJPE (m; global and root-relative) and bone-length variation (mm) of mu-decoded validation windows, over
    all processes (a fixed subset of batches)."""
    dev, d, amp = env.device, env.dist, env.autocast(cfg.amp)
    order = list(LengthBucketSampler(val_ds.lengths(), cfg.batch_size, shuffle=False))
    mine = (order[: cfg.val_batches] if cfg.val_batches > 0 else order)[d.rank :: d.world_size]

    def validate() -> dict[str, float]:
        vae.eval()
        sums: dict[str, float] = {}
        with torch.no_grad(), torch.random.fork_rng(devices=[dev] if dev.type == "cuda" else []):
            torch.manual_seed(cfg.seed)
            for indices in mine:
                batch = val_ds.gather(indices, frames)
                x, mask = batch["motion"], batch["mask"]
                with amp:
                    x_hat = vae.decode(vae.encode(x, mask)[0], mask)
                for k, v in reconstruction_errors(x_hat, x, mask, mean, std).items():
                    sums[k] = sums.get(k, 0.0) + v
        sums = {k: all_reduce_mean(sums.get(k, 0.0), d, dev) for k in VALIDATION_SUMS}
        per = {"mpjpe_m": "frames", "mpjpe_rel_m": "frames", "bone_std_mm": "motions"}
        return {k: sums[k] / sums[n] if sums[n] else math.nan for k, n in per.items()}

    return validate
