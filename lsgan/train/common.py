"""The pieces under the training loop (:mod:`lsgan.train.loop`): device choice, seeding, torchrun/DDP set-up,
CSV/TensorBoard logs, the NaN check and the run folder's claim."""
from __future__ import annotations

import csv
import functools
import math
import os
import random
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch
import torch.distributed as dist

from lsgan import outputs


class TrainingDiverged(RuntimeError):
    """A loss became NaN or infinite; the last good checkpoint is kept."""


def pick_device(name: str = "auto") -> torch.device:
    """'auto' -> cuda when available, else cpu; otherwise the named device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for, but torch sees no CUDA device")
    return device


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


@dataclass(frozen=True)
class Dist:
    """This process's place in a run: rank 0 of 1 unless started by torchrun."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def setup_distributed(device: torch.device) -> Dist:
    """Join the process group when started by torchrun (RANK/WORLD_SIZE set): gloo on CPU, nccl on CUDA."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", rank=rank, world_size=world)
    return Dist(rank=rank, world_size=world, local_rank=local)


def local_device(device: torch.device, d: Dist) -> torch.device:
    """One GPU per process under torchrun."""
    if device.type == "cuda" and d.enabled:
        torch.cuda.set_device(d.local_rank)
        return torch.device("cuda", d.local_rank)
    return device


def all_reduce_mean(value: float, d: Dist, device: torch.device) -> float:
    """The mean of a number over all processes (the number itself when not distributed)."""
    if not d.enabled:
        return value
    t = torch.tensor([value], dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return t.item() / d.world_size


def teardown_distributed(d: Dist) -> None:
    if d.enabled and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


R = TypeVar("R")


def run_distributed(device: str, body: Callable[[torch.device, Dist], R]) -> R:
    """``body(device, dist)`` on the picked device, inside the torchrun process group when there is one.

    The group is left with a barrier after success; after a failure it is destroyed without one (the other
    ranks may be gone).
    """
    dev = pick_device(device)
    d = setup_distributed(dev)
    dev = local_device(dev, d)
    try:
        result = body(dev, d)
    except BaseException:
        if d.enabled and dist.is_initialized():
            dist.destroy_process_group()
        raise
    teardown_distributed(d)
    return result


def closing_progress_bars(fn: Callable[..., R]) -> Callable[..., R]:
    """Decorate a training loop: when it fails, its progress bars are closed first, so that the error
    printed next starts a line of its own."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs) -> R:
        try:
            return fn(*args, **kwargs)
        except BaseException:
            from tqdm import tqdm

            for bar in list(getattr(tqdm, "_instances", ())):
                bar.close()
            raise

    return wrapper


def check_finite(losses: dict[str, float], step: int) -> None:
    """Stop a run whose loss is NaN/inf, naming the loss and the step."""
    for name, value in losses.items():
        if not math.isfinite(value):
            raise TrainingDiverged(f"{name} is {value} at step {step}; stopping (the last good checkpoint is kept)")


class RunLog:
    """Append rows of scalars to ``log.csv`` (and TensorBoard when it is installed). Rank 0 only."""

    def __init__(self, folder: str | os.PathLike, enabled: bool = True, tensorboard: bool = True) -> None:
        self.enabled = enabled
        self.path = Path(folder) / "log.csv"
        self._fields: list[str] | None = None
        self._tb = None
        if not enabled:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            with open(self.path, newline="") as f:
                self._fields = next(csv.reader(f), None)
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self._tb = SummaryWriter(str(Path(folder) / "tb"))
            except ImportError:
                self._tb = None

    def write(self, step: int, **scalars: float) -> None:
        if not self.enabled:
            return
        row = {"step": step, **{k: float(v) for k, v in scalars.items()}}
        if self._fields is None:
            self._fields = list(row)
            with open(self.path, "w", newline="") as f:
                csv.writer(f).writerow(self._fields)
        for k in row:
            if k not in self._fields:  # a new column: rewrite the header, keeping the rows
                self._fields.append(k)
                rows = list(csv.DictReader(open(self.path, newline="")))
                with open(self.path, "w", newline="") as f:
                    w = csv.DictWriter(f, self._fields)
                    w.writeheader()
                    w.writerows(rows)
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, self._fields).writerow(row)
        if self._tb is not None:
            for k, v in scalars.items():
                self._tb.add_scalar(k, float(v), step)

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()


RUN_STATE = ("last", "best", "log.csv", "train.log", "tb", "heldout.json")
"""What a training run writes in its folder; ``force`` removes these and nothing else."""
RUN_FILES = (*RUN_STATE, "demo-inputs.json", outputs.REGISTRY)
"""What a run folder may hold besides (``demo-inputs.json``: what ``lsgan demo`` started the run on)."""


def claim_run(out: str | os.PathLike, *, resume: bool, force: bool) -> None:
    """Before training into ``out``: continue (``resume``) or start over (``force``) an lsgan run there.

    A folder holding anything but a run's own files is refused for a new run, even with ``force``.
    Only rank 0 looks (and clears); the other ranks of a torchrun start after it.
    """
    out = Path(out)
    if int(os.environ.get("RANK", "0")) != 0 or not out.exists():
        return
    if not out.is_dir():
        raise outputs.OutputError(f"{out}: exists and is not a folder; give a folder for the run")
    names = sorted(p.name for p in out.iterdir())
    others = [n for n in names if n not in RUN_FILES]
    if resume:
        return
    if others:
        raise outputs.OutputError(f"{out}: holds files that are not an lsgan run's ({', '.join(others[:5])}"
                                  f"{' ...' if len(others) > 5 else ''}); choose a new or empty folder")
    if not any(n in RUN_STATE for n in names):
        return
    if not force:
        raise outputs.OutputError(f"{out}: already holds a run; pass --resume to continue it or --force to start "
                                  "over (only the run's own files are removed)")
    foreign = [n for n in ("last", "best") if (out / n).exists() and not outputs.is_ours(out / n)]
    if foreign:
        raise outputs.OutputError(f"{out / foreign[0]}: is not a checkpoint lsgan wrote (or was changed since); "
                                  "not removed, even with --force")
    for name in RUN_STATE:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        elif p.exists() or p.is_symlink():
            p.unlink()


def shard_paths(data: str | os.PathLike | Sequence[str | os.PathLike]) -> list[str]:
    """One shard or several, as a list of paths."""
    return [os.fspath(data)] if isinstance(data, (str, os.PathLike)) else [os.fspath(p) for p in data]
