"""Train the motion VAE: AdamW on MSE + KL, validation MPJPE in metres, checkpoints, exact resume, DDP.

One process: ``train_vae(shards, "runs/vae", model=VAEConfig(...), train=VAETrainConfig(...))``.
Several: the same call under ``torchrun --nproc_per_node=N``; every process draws its own batches of
``batch_size`` clips (the global batch is N x batch_size), gradients are averaged by DDP, rank 0 alone
writes checkpoints and logs.

Resuming reloads ``out/last/`` (weights, optimiser, step, RNG states, sampler epoch and position) and
continues at the same step; with ``num_workers=0`` the continued run is the uninterrupted one, bit for bit.
"""
from __future__ import annotations

import csv
import math
import os
import random
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader
from tqdm import tqdm

from lsgan.data.dataset import LengthBucketSampler, MotionDataset, collate
from lsgan.data.features import recover_from_ric
from lsgan.data.shards import Shard
from lsgan.models.checkpoint import load_state, load_weights, save_checkpoint
from lsgan.models.vae import MotionVAE, VAEConfig, load_vae, vae_loss
from lsgan.train.common import (
    claim_run,
    Dist,
    RunLog,
    TrainingDiverged,
    all_reduce_mean,
    check_finite,
    closing_progress_bars,
    local_device,
    pick_device,
    seed_everything,
    setup_distributed,
    teardown_distributed,
)

__all__ = ["VAETrainConfig", "train_vae", "load_vae", "reconstruction_mpjpe"]


@dataclass
class VAETrainConfig:
    lr: float = 1e-4
    weight_decay: float = 0.0
    batch_size: int = 128  # per process
    kl_weight: float = 1e-4
    max_steps: int = 2000
    val_every: int = 500
    ckpt_every: int = 500
    log_every: int = 50
    min_frames: int = 40
    max_frames: int = 196
    unit_length: int = 4  # window lengths rounded down to a multiple (one unit less w.p. 1/3), as HumanML3D loaders
    num_workers: int = 0
    seed: int = 0
    grad_clip: float = 1.0  # max global grad norm; 0 = no clipping
    amp: bool = True  # bf16 autocast, CUDA only
    val_batches: int = 16  # validation batches at most; 0 = the whole validation set


def reconstruction_mpjpe(x_hat: torch.Tensor, x: torch.Tensor, mask: torch.Tensor, mean: torch.Tensor,
                         std: torch.Tensor) -> tuple[float, int]:
    """(sum over real frames of the per-frame mean joint error in metres, number of real frames).

    Both normalised feature tensors (B,T,263) are de-normalised and turned into joints by
    ``recover_from_ric`` (root trajectory integrated, so drift counts as error).
    """
    joints_hat = recover_from_ric(x_hat.float() * std + mean)  # (B,T,22,3)
    joints = recover_from_ric(x.float() * std + mean)
    per_frame = (joints_hat - joints).norm(dim=-1).mean(-1)  # (B,T)
    return float(per_frame[mask].sum()), int(mask.sum())


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


def _train_batches(ds: MotionDataset, sampler: LengthBucketSampler, epoch: int, skip: int, num_workers: int,
                   seed: int, pin: bool) -> Iterator[tuple[int, int, dict]]:
    """Batches forever as (epoch, batches of that epoch done, batch), starting ``skip`` batches into ``epoch``.

    The loader has its own generator so that starting a loader (e.g. on resume) leaves the global RNG alone.
    """
    while True:
        sampler.set_epoch(epoch)
        order = list(sampler)
        loader = DataLoader(ds, batch_sampler=order[skip:], collate_fn=collate, num_workers=num_workers,
                            pin_memory=pin, generator=torch.Generator().manual_seed(seed * 100_003 + epoch))
        for i, batch in enumerate(loader, start=skip + 1):
            yield epoch, i, batch
        epoch, skip = epoch + 1, 0


def _rng_state(device: torch.device) -> dict:
    state = {
        "torch": torch.get_rng_state(),
        "numpy": torch.from_numpy(np.random.get_state()[1].astype(np.int64)),
        "numpy_pos": int(np.random.get_state()[2]),
        "python": random.getstate(),
    }
    if device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def _set_rng_state(state: dict, device: torch.device) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(("MT19937", state["numpy"].numpy().astype(np.uint32), state["numpy_pos"], 0, 0.0))
    random.setstate(state["python"])
    if device.type == "cuda" and "cuda" in state:
        torch.cuda.set_rng_state(state["cuda"], device)


def _all_rng_states(d: Dist, device: torch.device) -> list[dict]:
    """Every process's RNG state (rank order), so that a resumed DDP run continues each stream."""
    mine = _rng_state(device)
    if not d.enabled:
        return [mine]
    states: list = [None] * d.world_size
    dist.all_gather_object(states, mine)
    return states


def _truncate_log(path: Path, step: int) -> None:
    """Drop log rows past ``step`` (written after the checkpoint a run resumes from)."""
    if not path.exists():
        return
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return
    keep = [rows[0]] + [r for r in rows[1:] if r and float(r[0]) <= step]
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(keep)


def train_vae(
    data: str | os.PathLike | Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    model: VAEConfig,
    train: VAETrainConfig,
    device: str = "auto",
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
) -> dict:
    """Train a MotionVAE on the 'train' split of the shards; returns the final metrics.

    Returns {"step", "train_loss", "val_mpjpe_m", "best_val_mpjpe_m"} (the same on every process).
    Raises TrainingDiverged on a NaN/inf loss or gradient, leaving the last good checkpoint in place.
    """
    paths = [os.fspath(data)] if isinstance(data, (str, os.PathLike)) else [os.fspath(p) for p in data]
    out = Path(out)
    claim_run(out, resume=resume, force=force)
    dev = pick_device(device)
    d = setup_distributed(dev)
    dev = local_device(dev, d)
    if dev.type == "cuda" and dev.index is None:
        dev = torch.device("cuda", torch.cuda.current_device())
    try:
        return _train(paths, out, model, train, dev, d, resume, progress)
    finally:
        teardown_distributed(d)


@closing_progress_bars
def _train(paths: list[str], out: Path, mcfg: VAEConfig, cfg: VAETrainConfig, dev: torch.device, d: Dist,
           resume: bool, progress: bool) -> dict:
    def say(msg: str) -> None:
        if d.is_main:
            tqdm.write(msg, file=sys.stderr)
            out.mkdir(parents=True, exist_ok=True)
            with open(out / "train.log", "a") as f:
                f.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} {msg}\n")

    state = None
    if resume and (out / "last").exists():
        state = load_state(out / "last")
        if state is None:
            raise FileNotFoundError(f"{out / 'last'}: no state.pt to resume from")
    elif resume:
        say(f"{out}: nothing to resume; starting a new run")
    elif (out / "last").exists():
        raise FileExistsError(f"{out} already holds a run; pass resume=True to continue it or choose another folder")

    seed_everything(cfg.seed + d.rank)
    kw = dict(min_frames=cfg.min_frames, max_frames=cfg.max_frames, unit_length=cfg.unit_length)
    train_ds = MotionDataset(paths, "train", **kw)
    val_ds = MotionDataset(paths, None, mean=train_ds.mean, std=train_ds.std, **kw)
    val_clips = _split_validation(paths, train_ds, say)
    val_ds.windows = [w for w in val_ds.windows if (w.shard, w.clip) in val_clips]
    if not len(train_ds):
        raise ValueError(f"no training windows of {cfg.min_frames}+ frames in {paths}")
    sampler = LengthBucketSampler(train_ds.lengths(), cfg.batch_size, seed=cfg.seed,
                                  num_replicas=d.world_size, rank=d.rank)
    if len(sampler) == 0:
        raise ValueError(f"{len(train_ds)} training windows make fewer than one batch of {cfg.batch_size} per process "
                         f"({d.world_size} processes); lower batch_size")
    val_order = list(LengthBucketSampler(val_ds.lengths(), cfg.batch_size, shuffle=False))
    val_order = val_order[: cfg.val_batches] if cfg.val_batches > 0 else val_order
    my_val = val_order[d.rank :: d.world_size]
    mean = torch.as_tensor(train_ds.mean, device=dev)
    std = torch.as_tensor(train_ds.std, device=dev)

    vae = MotionVAE(mcfg).to(dev)
    opt = torch.optim.AdamW(vae.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    step, epoch, done, best, last_val = 0, 0, 0, math.inf, None
    if state is not None:
        weights, meta = load_weights(out / "last", kind="vae")
        if meta["config"]["model"] != asdict(mcfg):
            raise ValueError(f"{out / 'last'}: its model config {meta['config']['model']} differs from {asdict(mcfg)}")
        vae.load_state_dict(weights)
        opt.load_state_dict(state["optimizer"])
        for group in opt.param_groups:  # the new config's optimiser settings win
            group.update(lr=cfg.lr, weight_decay=cfg.weight_decay)
        step, epoch, done = state["step"], state["epoch"], state["batches_done"]
        best, last_val = state["best_val_mpjpe_m"], state["val_mpjpe_m"]
        rngs = state["rng"]
        if len(rngs) == d.world_size:
            _set_rng_state(rngs[d.rank], dev)
        else:
            say(f"resuming with {d.world_size} processes from a run of {len(rngs)}: RNG streams reseeded")
        if d.is_main:
            _truncate_log(out / "log.csv", step)
        say(f"resumed from {out / 'last'} at step {step} (epoch {epoch}, batch {done})")
    ddp = DistributedDataParallel(vae, device_ids=[dev.index] if dev.type == "cuda" else None) if d.enabled else vae
    log = RunLog(out, enabled=d.is_main)
    amp = torch.autocast("cuda", dtype=torch.bfloat16) if cfg.amp and dev.type == "cuda" else nullcontext()
    train_config = {"model": asdict(mcfg), "train": asdict(cfg)}
    if not len(val_ds):
        say(f"no validation windows of {cfg.min_frames}+ frames: validation MPJPE will be NaN and best/ never written")
    if d.is_main and state is None:
        say(f"{len(train_ds)} training windows, {len(val_ds)} validation windows; {sum(p.numel() for p in vae.parameters()):,} "
            f"parameters; device {dev}, {d.world_size} process(es)")

    def validate() -> float:
        """Mean per-frame MPJPE (m) of mu-decoded validation windows, over all processes."""
        vae.eval()
        total, frames = 0.0, 0
        with torch.no_grad(), torch.random.fork_rng(devices=[dev] if dev.type == "cuda" else []):
            torch.manual_seed(cfg.seed)
            loader = DataLoader(val_ds, batch_sampler=my_val, collate_fn=collate, num_workers=cfg.num_workers,
                                generator=torch.Generator().manual_seed(cfg.seed))
            for batch in loader:
                x, mask = batch["motion"].to(dev), batch["mask"].to(dev)
                with amp:
                    x_hat = vae.decode(vae.encode(x, mask)[0], mask)
                s, n = reconstruction_mpjpe(x_hat, x, mask, mean, std)
                total, frames = total + s, frames + n
        vae.train()
        total, frames = all_reduce_mean(total, d, dev), all_reduce_mean(float(frames), d, dev)
        return total / frames if frames else math.nan

    def checkpoint(folder: str, with_state: bool) -> None:
        if not all(torch.isfinite(p).all() for p in vae.parameters()):  # never replace a good checkpoint with NaNs
            raise TrainingDiverged(f"non-finite weights at step {step}; stopping (the last good checkpoint is kept)")
        rngs = _all_rng_states(d, dev) if with_state else None
        if not d.is_main:
            return
        extra = {"mean": train_ds.mean.tolist(), "std": train_ds.std.tolist(), "val_mpjpe_m": last_val,
                 "best_val_mpjpe_m": None if math.isinf(best) else best, "data": paths}
        train_state = None
        if with_state:
            train_state = {"optimizer": opt.state_dict(), "step": step, "epoch": epoch, "batches_done": done,
                           "best_val_mpjpe_m": best, "val_mpjpe_m": last_val, "rng": rngs}
        save_checkpoint(out / folder, model=vae, kind="vae", config=train_config, step=step, extra=extra, state=train_state)

    batches = _train_batches(train_ds, sampler, epoch, done, cfg.num_workers, cfg.seed, dev.type == "cuda")
    bar = tqdm(total=cfg.max_steps, initial=step, disable=not (progress and d.is_main), file=sys.stderr,
               dynamic_ncols=True, desc="vae")
    sums, count, tic = np.zeros(4), 0, time.perf_counter()
    train_loss = math.nan
    vae.train()
    while step < cfg.max_steps:
        epoch, done, batch = next(batches)
        x, mask = batch["motion"].to(dev, non_blocking=True), batch["mask"].to(dev, non_blocking=True)
        with amp:
            x_hat, mu, logvar = ddp(x, mask)
        losses = vae_loss(x_hat.float(), x, mu.float(), logvar.float(), mask, cfg.kl_weight)
        opt.zero_grad(set_to_none=True)
        losses["total"].backward()
        gnorm = torch.nn.utils.clip_grad_norm_(vae.parameters(), cfg.grad_clip if cfg.grad_clip > 0 else math.inf)
        values = [losses["total"].item(), losses["recon"].item(), losses["kl"].item(), gnorm.item()]
        if d.enabled:  # every process sees the same numbers, so all of them stop together on a NaN
            t = torch.tensor(values, dtype=torch.float64, device=dev)
            dist.all_reduce(t)
            values = (t / d.world_size).tolist()
        check_finite({"loss": values[0], "grad_norm": values[3]}, step + 1)
        opt.step()
        step += 1
        sums, count = sums + values, count + 1
        bar.update(1)
        bar.set_postfix(loss=f"{values[0]:.4f}", best=f"{best:.4f}" if math.isfinite(best) else "-")

        row: dict[str, float] = {}
        if step % cfg.log_every == 0 or step == cfg.max_steps:
            mean_vals = sums / count
            train_loss = float(mean_vals[0])
            row.update(loss=mean_vals[0], recon=mean_vals[1], kl=mean_vals[2], grad_norm=mean_vals[3],
                       lr=opt.param_groups[0]["lr"], sec_per_step=(time.perf_counter() - tic) / count, epoch=epoch)
            sums, count = np.zeros(4), 0
        if step % cfg.val_every == 0 or step == cfg.max_steps:
            last_val = validate()
            row.update(val_mpjpe_m=last_val)
            if last_val < best:
                best = last_val
                checkpoint("best", with_state=False)
            row.update(best_val_mpjpe_m=best)
        if row:
            log.write(step, **row)
        if step % cfg.ckpt_every == 0 or step == cfg.max_steps:
            checkpoint("last", with_state=True)
        if "loss" in row:
            tic = time.perf_counter()  # sec_per_step counts training steps, not validation or checkpoints
    bar.close()
    log.close()
    if math.isnan(train_loss) and count:
        train_loss = float(sums[0] / count)
    return {"step": step, "train_loss": train_loss, "val_mpjpe_m": last_val,
            "best_val_mpjpe_m": best if math.isfinite(best) else None}
