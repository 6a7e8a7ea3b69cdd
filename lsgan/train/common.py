"""The pieces under the training loop (:mod:`lsgan.train.loop`): device choice, seeding, torchrun/DDP set-up,
CSV/TensorBoard logs, the NaN check and the run folder's claim."""
from __future__ import annotations

import contextlib
import csv
import functools
import io
import math
import os
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch
import torch.distributed as dist

from lsgan import outputs
from lsgan.device import pick_device


class TrainingDiverged(RuntimeError):
    """A loss became NaN or infinite; the last good checkpoint is kept."""


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
    """Stop a run whose loss is NaN/inf, naming the loss, the step and the step's other values (a term that
    blew up points at its weight or learning rate)."""
    for name, value in losses.items():
        if not math.isfinite(value):
            rest = ", ".join(f"{k} {v:.3g}" for k, v in losses.items() if k != name)
            raise TrainingDiverged(f"{name} is {value} at step {step} ({rest or 'nothing else logged'}); stopping "
                                   "(the last good checkpoint, if one was written, is kept; a very large loss weight or "
                                   "learning rate in the recipe does this)")


class RunLog:
    """Rows of scalars in ``log.csv`` (and TensorBoard when it is installed). Rank 0 only.

    The whole file is rewritten atomically at each row (a run's log is small), never appended in place: a
    hard-linked snapshot of the run keeps its bytes, and a kill leaves the last complete file.
    """

    def __init__(self, folder: str | os.PathLike, enabled: bool = True, tensorboard: bool = True) -> None:
        self.enabled = enabled
        self.path = Path(folder) / "log.csv"
        self._fields: list[str] = []
        self._rows: list[dict] = []
        self._tb = self._tb_dir = None
        if not enabled:
            return
        if self.path.exists():
            self._fields, self._rows = read_log(self.path)
        if tensorboard:
            self._open_tensorboard(Path(folder) / "tb")

    def _open_tensorboard(self, tb: Path) -> None:
        """A SummaryWriter in a folder of its own under ``tb/`` for this process (recorded at each flush)."""
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            return
        self._tb_dir = outputs.make_folder(tb / f"run-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}")
        self._tb = SummaryWriter(str(self._tb_dir))

    def truncate(self, step: int) -> None:
        """Drop the rows past ``step`` (written after the checkpoint a run resumes from)."""
        if self.enabled and self.path.exists():
            self._rows = [r for r in self._rows if float(r["step"]) <= step]
            self._save()

    def write(self, step: int, **scalars: float) -> None:
        if not self.enabled:
            return
        row = {"step": step, **{k: float(v) for k, v in scalars.items()}}
        self._fields += [k for k in row if k not in self._fields]
        self._rows.append(row)
        self._save()
        if self._tb is not None:
            for k, v in scalars.items():
                self._tb.add_scalar(k, float(v), step)
            self._tb.flush()
            outputs.record(self._tb_dir)

    def _save(self) -> None:
        text = io.StringIO()
        w = csv.DictWriter(text, self._fields, lineterminator="\n")
        w.writeheader()
        w.writerows(self._rows)
        outputs.replace_by(self.path, text.getvalue())

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
            outputs.record(self._tb_dir)


def read_log(path: Path) -> tuple[list[str], list[dict]]:
    """``log.csv``'s columns and rows; a file lsgan cannot have written is refused naming the line."""
    with open(path, newline="", encoding="utf-8", errors="replace") as f:
        rows = list(csv.reader(f))
    if not rows:
        return [], []
    fields = rows[0]
    if not fields or fields[0] != "step":
        raise outputs.OutputError(f"{path}: not a training log (its first column is not 'step'); move it away")
    out = []
    for line, r in enumerate(rows[1:], 2):
        try:
            float(r[0])
        except (IndexError, ValueError):
            raise outputs.OutputError(f"{path}: line {line} is not a log row (no step number); lsgan keeps this "
                                      "file as it wrote it: move the notes to another file") from None
        out.append(dict(zip(fields, r)))
    return fields, out


RUN_STATE = ("last", "best", "log.csv", "train.log", "tb", "heldout.json")
"""What a training run writes in its folder; ``force`` removes these (when lsgan's) and nothing else."""
RUN_FILES = (*RUN_STATE, "demo-inputs.json", outputs.REGISTRY)
"""What a run folder may hold besides (``demo-inputs.json``: what ``lsgan demo`` started the run on)."""


def claim_run(out: str | os.PathLike, *, resume: bool, force: bool) -> None:
    """Before training into ``out``: continue (``resume``) or start over (``force``) an lsgan run there.

    A run's own file that is not lsgan's (edited, or put there by the user) is refused either way. A folder
    holding other files is refused for a new run, even with ``force``, and for ``resume`` unless it holds a
    run's ``last/`` checkpoint. Only rank 0 looks (and clears); the other ranks of a torchrun start after it.
    """
    out = Path(out)
    if int(os.environ.get("RANK", "0")) != 0:
        return
    outputs.check_writer(out)  # a second lsgan process training into the same folder is refused
    if not out.exists():
        outputs.reserve(out)
        return
    if not out.is_dir():
        raise outputs.OutputError(f"{out}: exists and is not a folder; give a folder for the run")
    outputs.sweep_temps(out)  # a killed run's temporaries (recorded, their process gone)
    names = sorted(p.name for p in out.iterdir() if p.name != outputs.REGISTRY)
    for n in names:
        if n in RUN_STATE and not _run_entry_ours(out / n):
            raise outputs.OutputError(f"{out / n}: is not what lsgan wrote there ({outputs.why_not_ours(out / n)}); "
                                      "lsgan will not replace it, even with --force or --resume: move it away")
    others = [n for n in names if n not in RUN_FILES]
    listed = f"{', '.join(others[:5])}{' ...' if len(others) > 5 else ''}"
    if resume and (out / "last").exists():
        outputs.reserve(out)
        return
    if others:
        what = "no lsgan run to resume (no last/ checkpoint) but files that are not an lsgan run's" if resume else \
            "files that are not an lsgan run's"
        raise outputs.OutputError(f"{out}: holds {what} ({listed}); choose a new or empty folder")
    state = [n for n in names if n in RUN_STATE]
    if state and not (force or resume):
        raise outputs.OutputError(f"{out}: already holds a run; pass --resume to continue it or --force to start "
                                  "over (only the run's own files are removed)")
    outputs.reserve(out)
    for n in state:  # a new run: lsgan's own files of the previous one go (a resume without last/ starts anew)
        if n == "tb" and outputs.made_folder(out / n):
            outputs.clear_ours(out / n)  # the folder goes when empty; an event folder never recorded stays
            with contextlib.suppress(outputs.OutputError):
                outputs.remove(out / n)
        else:
            outputs.remove(out / n)


def _run_entry_ours(p: Path) -> bool:
    """A run file or folder lsgan wrote; ``tb/`` also when it is a folder lsgan made (TensorBoard writes in it)."""
    return outputs.is_ours(p) or (p.name == "tb" and p.is_dir() and not p.is_symlink() and outputs.made_folder(p))


def shard_paths(data: str | os.PathLike | Sequence[str | os.PathLike]) -> list[str]:
    """One shard or several, as a list of paths."""
    return [os.fspath(data)] if isinstance(data, (str, os.PathLike)) else [os.fspath(p) for p in data]
