"""The one training loop. A model contributes its step, not a copy of the loop.

A trainer (``train_vae``, ``train_gan``, ``train_diffusion``, ``train_evaluator``, ``train_action_classifier``) calls
:func:`launch`, which claims the run folder, picks the device and, under torchrun, joins the process group. Inside,
it builds its model, optimisers and data and hands :func:`fit` a :class:`Trainer`: the checkpoint kind and config,
the optimisers, a batch source, ``step`` (one update from one batch, returning its scalars), ``validate`` and the
metric that picks ``best/``. The loop owns the rest:

- the schedule: window means of the step scalars every ``log_every`` steps (the same on every process),
  validation every ``val_every`` (``best/`` keeps the best score), ``last/`` every ``ckpt_every`` steps and at the
  end; ``best/`` is the last weights when no validation ever scored;
- exact resume: ``last/state.pt`` holds the step, the optimisers, every process's RNG states, the batch source's
  position and the validation record, so a resumed run repeats the uninterrupted one bit for bit (on the CPU, with
  its batches gathered from a FrameTable or read without loader workers); log rows written after that checkpoint
  are dropped;
- the NaN stop: a non-finite step scalar (every process sees the same ones) or non-finite weights at a checkpoint
  raise TrainingDiverged, and the last good checkpoint stays; the step scalars are read back in one transfer at
  each log, validation and checkpoint step (so a GPU is never kept waiting for a loss to be read), which is also
  where a NaN is found, always before anything is written;
- DDP (rank 0 alone writes), bf16 autocast on CUDA, log.csv and TensorBoard (RunLog), train.log, the progress bar;
- the CPU threads: decided when the run starts (:func:`lsgan.threads.run_threads`: fewer when other processes keep
  cores busy) and kept, resumes included, so that its numbers never depend on the load.
"""
from __future__ import annotations

import dataclasses
import math
import os
import random
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset
from tqdm import tqdm

from lsgan import outputs
from lsgan.data.dataset import FrameTable, LengthBucketSampler, collate
from lsgan.device import pick_device
from lsgan.faults import fault_point
from lsgan.models.checkpoint import CONFIG, load_state, load_weights, save_checkpoint
from lsgan.threads import ThreadPolicy, run_threads, threads_said
from lsgan.train.common import (
    Dist,
    RunLog,
    TrainingDiverged,
    check_finite,
    claim_run,
    closing_progress_bars,
    run_distributed,
)

R = TypeVar("R")


# ---------------------------------------------------------------------------------------------------- the run


@dataclass
class Previous:
    """The run in ``out/last`` that is continued: its weights, config.json and training state."""

    folder: Path
    weights: dict[str, torch.Tensor]
    meta: dict
    state: dict


@dataclass
class Env:
    """Where a run trains: its folder, device and place in the torchrun group, and what it reported."""

    name: str
    out: Path
    device: torch.device
    dist: Dist
    resume: bool
    progress: bool
    notes: list[str] = field(default_factory=list)
    journal: str | None = field(default=None, repr=False)  # train.log's text, read once, then kept here

    @property
    def is_main(self) -> bool:
        return self.dist.is_main

    def say(self, msg: str) -> None:
        """A note for the user: kept in ``notes``; on stderr and in ``train.log`` from rank 0."""
        self.notes.append(msg)
        if not self.is_main:
            return
        tqdm.write(f"{self.name}: {msg}", file=sys.stderr)
        path = self.out / "train.log"
        if self.journal is None:
            self.journal = path.read_text(encoding="utf-8", errors="replace") if path.exists() else ""
        self.journal += f"{time.strftime('%Y-%m-%d %H:%M:%S')} {msg}\n"
        outputs.replace_by(path, self.journal)  # rewritten whole, never appended in place (see RunLog)

    def ddp(self, module: torch.nn.Module) -> torch.nn.Module:
        """``module`` in DistributedDataParallel under torchrun, itself otherwise."""
        if not self.dist.enabled:
            return module
        return DistributedDataParallel(module, device_ids=[self.device.index] if self.device.type == "cuda" else None)

    def autocast(self, enabled: bool) -> AbstractContextManager:
        """bf16 autocast on CUDA when ``enabled``; nothing otherwise."""
        if enabled and self.device.type == "cuda":
            return torch.autocast("cuda", dtype=torch.bfloat16)
        return nullcontext()

    def previous(self, kind: str) -> Previous | None:
        """The run to continue (``resume``), or None; a run is never overwritten unasked."""
        last = self.out / "last"
        if not (last / CONFIG).exists():
            if self.resume:
                self.say(f"nothing to resume in {self.out}: starting a new run")
            return None
        if not self.resume:
            raise FileExistsError(f"{self.out} already holds a run; pass resume=True to continue it or choose "
                                  "another folder")
        state = load_state(last)
        if state is None:
            raise FileNotFoundError(f"{last}: no state.pt to resume from")
        weights, meta = load_weights(last, kind=kind)
        return Previous(last, weights, meta, _upgrade(state, meta))


def launch(name: str, out: str | os.PathLike, *, device: str, resume: bool, force: bool, progress: bool, body: Callable[[Env], R],
           distributed: bool = True) -> R:
    """Claim ``out`` (:func:`claim_run`), then ``body(env)`` on the picked device: under torchrun inside its process
    group when ``distributed``, else in this process alone. Progress bars are closed before an error propagates."""
    out = Path(out)
    claim_run(out, resume=resume, force=force)

    def run(dev: torch.device, d: Dist) -> R:
        if dev.type == "cuda" and dev.index is None:
            dev = torch.device("cuda", torch.cuda.current_device())
        return closing_progress_bars(body)(Env(name, out, dev, d, resume, progress))

    return run_distributed(device, run) if distributed else run(pick_device(device), Dist())


# ---------------------------------------------------------------------------------------------------- batches


class Batches(Protocol):
    """Where a step's input comes from: ``source(step)``, and what a resumed run needs to continue it."""

    def __call__(self, step: int) -> Any: ...

    def state(self) -> dict: ...

    def load(self, state: dict) -> None: ...


class EpochBatches:
    """The sampler's batches of ``ds``, epoch after epoch; resumes at the saved (epoch, batches done).

    With ``frames`` (a :class:`~lsgan.data.dataset.FrameTable` of ``ds``) each batch is gathered from the table in
    this process: the batches a loader without workers makes, bit for bit, at the cost of an index (no loader
    processes restarted every epoch, nothing read from disk). Otherwise a DataLoader with ``num_workers`` reads
    them; each epoch's loader has its own generator, so starting one (e.g. on resume) leaves the global RNG alone.
    """

    def __init__(self, ds: Dataset, sampler: LengthBucketSampler, *, seed: int, frames: FrameTable | None = None,
                 num_workers: int = 0, pin: bool = False) -> None:
        self.ds, self.sampler, self.seed, self.frames = ds, sampler, seed, frames
        self.num_workers, self.pin = num_workers, pin
        self.epoch, self.done = 0, 0
        self._batches: Iterator[tuple[int, int, dict]] | None = None

    def __call__(self, step: int) -> dict:
        if self._batches is None:
            self._batches = self._from(self.epoch, self.done)
        self.epoch, self.done, batch = next(self._batches)
        return batch

    def state(self) -> dict:
        return {"epoch": self.epoch, "batches_done": self.done}

    def load(self, state: dict) -> None:
        self.epoch, self.done = state["epoch"], state["batches_done"]

    def _from(self, epoch: int, skip: int) -> Iterator[tuple[int, int, dict]]:
        """(epoch, batches of that epoch done, batch) forever, starting ``skip`` batches into ``epoch``."""
        while True:
            self.sampler.set_epoch(epoch)
            order = list(self.sampler)[skip:]
            if self.frames is not None:
                batches: Iterator[dict] = (self.ds.gather(b, self.frames) for b in order)
            else:
                g = torch.Generator().manual_seed(self.seed * 100_003 + epoch)
                batches = iter(DataLoader(self.ds, batch_sampler=order, collate_fn=collate,
                                          num_workers=self.num_workers, pin_memory=self.pin, generator=g))
            for i, batch in enumerate(batches, start=skip + 1):
                yield epoch, i, batch
            epoch, skip = epoch + 1, 0


class SeededSteps:
    """A torch generator reseeded from (seed, rank, step) for every step: a step's draws do not depend on the run's
    history, so a resumed run needs no saved position."""

    def __init__(self, seed: int, rank: int, device: torch.device) -> None:
        self.seed, self.rank, self.generator = seed, rank, torch.Generator(device)

    def __call__(self, step: int) -> torch.Generator:
        seed = np.random.SeedSequence([self.seed, self.rank, step]).generate_state(1)[0]
        return self.generator.manual_seed(int(seed))

    def state(self) -> dict:
        return {}

    def load(self, state: dict) -> None:
        """Nothing to restore: every step reseeds."""


# ---------------------------------------------------------------------------------------------------- the loop


@dataclass
class Schedule:
    max_steps: int
    log_every: int
    val_every: int
    ckpt_every: int

    def due(self, step: int, every: int) -> bool:
        return step % every == 0 or step == self.max_steps


@dataclass
class WindowTrainConfig:
    """Settings that mean the same for every trainer on shard windows (VAE, evaluators): the schedule, the window
    lengths, the loader's worker processes and the seed. Each trainer's config adds its own (and may change a
    default)."""

    max_steps: int = 2000
    val_every: int = 500
    ckpt_every: int = 500
    log_every: int = 50
    min_frames: int = 40
    max_frames: int = 196
    num_workers: int = 0  # loader processes where a trainer reads through a DataLoader (windows of shards are gathered)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.min_frames > self.max_frames:
            raise ValueError(f"min_frames ({self.min_frames}) is more than max_frames ({self.max_frames})")

    def schedule(self) -> Schedule:
        return Schedule(self.max_steps, self.log_every, self.val_every, self.ckpt_every)


@dataclass
class Trainer:
    """What a model contributes to :func:`fit`."""

    kind: str  # the checkpoint kind ("vae", "gan", ...)
    desc: str  # the progress bar's label
    model: torch.nn.Module  # what checkpoints hold (unwrapped)
    config: dict  # config.json's "config"
    optimizers: dict[str, torch.optim.Optimizer]  # by their key in state.pt
    batches: Batches
    step: Callable[[Any], dict[str, Any]]  # one update from batches(step); its scalars (floats, 0-d tensors)
    validate: Callable[[], dict[str, float]]  # metrics of the current weights ({} when there is nothing to score)
    metric: str  # the validate() key that picks best/
    extra: Callable[[Progress], dict]  # config.json's "extra"
    higher_is_better: bool = False
    val_prefix: str = "val_"  # a validation metric's column in log.csv: prefix + key
    log_details: bool = True  # also log lr, the epoch (EpochBatches) and the best score (sec_per_step: always)
    val_at_start: bool = False  # validate the untrained model too (logged at step 0, never best/)
    same_config: str | None = "model"  # the config section a resumed run must match (None: the run's own is used)


@dataclass
class Progress:
    """Where a run stands (saved in last/ for resuming) and what this call did."""

    sign: float = 1.0  # -1.0 when higher scores are better: ``best`` is sign * score, lower is better
    step: int = 0
    best: float = math.inf
    val: dict[str, float] = field(default_factory=dict)  # the latest validation
    history: list[tuple[int, dict[str, float]]] = field(default_factory=list)  # this call's validations
    train_loss: float = math.nan  # the latest logged window mean of "loss"
    steps: int = 0  # steps taken in this call
    seconds: float = 0.0  # spent in them (not in validation or checkpoints)
    threads: int = 0  # the run's CPU threads, kept for its resumes (0: not decided yet, or a GPU run)

    @property
    def best_value(self) -> float | None:
        return None if math.isinf(self.best) else self.sign * self.best

    @property
    def steps_per_s(self) -> float | None:
        return self.steps / self.seconds if self.seconds > 0 else None


def fit(env: Env, t: Trainer, s: Schedule, previous: Previous | None = None, intro: str = "") -> Progress:
    """Train ``t`` to ``s.max_steps``, continuing ``previous`` (else saying ``intro``); validate, log and checkpoint
    on schedule."""
    p = Progress(sign=-1.0 if t.higher_is_better else 1.0)
    log = RunLog(env.out, enabled=env.is_main)
    if previous is not None:
        _restore(env, t, previous, p, log)
    elif intro:
        env.say(intro)
    if t.val_at_start and p.step == 0:
        log.write(0, **_validate(env, t, p, track_best=False))
    bar = tqdm(total=s.max_steps, initial=p.step, disable=not (env.progress and env.is_main), file=sys.stderr,
               dynamic_ncols=True, desc=t.desc)
    sums: dict[str, float] = {}
    pending: list[dict[str, Any]] = []  # step scalars not read back yet (on a GPU: tensors still being computed)
    count, seconds = 0, 0.0
    t.model.train()
    with ThreadPolicy(threads=_run_threads(env, p)):
        tic = time.perf_counter()
        while p.step < s.max_steps:
            pending.append(t.step(t.batches(p.step)))
            fault_point("train.step")
            p.step, p.steps = p.step + 1, p.steps + 1
            bar.update(1)
            if not any(s.due(p.step, every) for every in (s.log_every, s.val_every, s.ckpt_every)):
                continue
            for scalars in _read_back(env, pending, first=p.step - len(pending) + 1):
                sums = {k: sums.get(k, 0.0) + v for k, v in scalars.items()}
            took = time.perf_counter() - tic  # the steps since the last read-back, up to their results
            count, seconds, p.seconds, pending = count + len(pending), seconds + took, p.seconds + took, []
            row: dict[str, float] = {}
            if s.due(p.step, s.log_every):
                means = {k: v / count for k, v in sums.items()}
                bar.set_postfix({k: f"{v:.3g}" for k, v in means.items()}, refresh=False)
                row = _train_row(t, p, means, seconds / count)
                sums, count, seconds = {}, 0, 0.0
            if s.due(p.step, s.val_every):
                row.update(_validate(env, t, p, track_best=True))
            if row:
                log.write(p.step, **row)
            if s.due(p.step, s.ckpt_every):
                _checkpoint(env, t, p, "last", with_state=True)
            tic = time.perf_counter()
    bar.close()
    log.close()
    if env.is_main and not (env.out / "best" / CONFIG).exists():  # nothing scored: the last weights stand in
        _checkpoint(env, t, p, "best", with_state=False)
    return p


def _run_threads(env: Env, p: Progress) -> int:
    """The run's CPU threads (:func:`lsgan.threads.run_threads`), recorded in ``p`` for its checkpoints; on a GPU
    the CPU only feeds it and torch's count stays."""
    if env.device.type != "cpu":
        return torch.get_num_threads()
    count = run_threads(p.threads)
    if p.threads and count != p.threads:
        env.say(f"this run trained on {p.threads} CPU threads and continues on {count} (fixed now): the steps "
                "from here differ from an uninterrupted run in rounding")
    elif not p.threads:
        env.say(f"{count} CPU threads for this run ({threads_said()}; kept for its resumes)")
    p.threads = count
    return count


def _read_back(env: Env, pending: list[dict[str, Any]], first: int) -> list[dict[str, float]]:
    """The scalars of the steps ``first``, ``first + 1``, ... as floats, each averaged over the processes, so that
    all of them stop together on a NaN (TrainingDiverged names the first non-finite step).

    Steps hand back tensors and the loop reads them here, every few steps, in one transfer: a GPU is never left
    idle waiting for the host to read one step's loss before it queues the next step's work.
    """
    keys = list(pending[0])
    cells = [step[k] for step in pending for k in keys]
    tensors = [v.detach().to(env.device, torch.float64).reshape(()) for v in cells if torch.is_tensor(v)]
    read = iter(torch.stack(tensors).cpu().tolist() if tensors else [])
    values = [next(read) if torch.is_tensor(v) else float(v) for v in cells]
    if env.dist.enabled:
        summed = torch.tensor(values, dtype=torch.float64, device=env.device)
        dist.all_reduce(summed)
        values = (summed / env.dist.world_size).tolist()
    rows = [dict(zip(keys, values[i * len(keys) : (i + 1) * len(keys)])) for i in range(len(pending))]
    for i, scalars in enumerate(rows):
        check_finite(scalars, first + i)
    return rows


def _train_row(t: Trainer, p: Progress, means: dict[str, float], sec_per_step: float) -> dict[str, float]:
    p.train_loss = means.get("loss", p.train_loss)
    if not t.log_details:
        return {**means, "sec_per_step": sec_per_step}
    lr = next(iter(t.optimizers.values())).param_groups[0]["lr"]
    return {**means, "lr": lr, "sec_per_step": sec_per_step, "epoch": t.batches.state()["epoch"]}


def _validate(env: Env, t: Trainer, p: Progress, *, track_best: bool) -> dict[str, float]:
    """Score the weights, keep a new best in best/; the log columns."""
    p.val = t.validate()
    t.model.train()
    p.history.append((p.step, p.val))
    row = {t.val_prefix + k: v for k, v in p.val.items()}
    if not track_best:
        return row
    if t.metric in p.val and p.sign * p.val[t.metric] < p.best:
        p.best = p.sign * p.val[t.metric]
        _checkpoint(env, t, p, "best", with_state=False)
    if t.log_details and not math.isinf(p.best):
        row[f"best_{t.val_prefix}{t.metric}"] = p.best_value
    return row


def _checkpoint(env: Env, t: Trainer, p: Progress, folder: str, with_state: bool) -> None:
    """Write ``out/folder`` from rank 0 (every rank calls: the RNG states are gathered)."""
    if not all(torch.isfinite(w).all() for w in t.model.parameters()):  # never replace a good checkpoint with NaNs
        raise TrainingDiverged(f"non-finite weights at step {p.step}; stopping (the last good checkpoint is kept)")
    rngs = _all_rng_states(env) if with_state else None
    if not env.is_main:
        return
    state = None
    if with_state:
        state = {**{k: opt.state_dict() for k, opt in t.optimizers.items()}, **t.batches.state(), "step": p.step,
                 "best": p.best, "val": p.val, "rng": rngs, "threads": p.threads}
    save_checkpoint(env.out / folder, model=t.model, kind=t.kind, config=t.config, step=p.step, extra=t.extra(p),
                    state=state)


# ---------------------------------------------------------------------------------------------------- resuming


def _with_defaults(saved, model) -> object:
    """A saved model config with the fields it lacks at their defaults: a field added since it was saved defaults to
    what the model did before it existed, so such a run still resumes."""
    config = getattr(getattr(model, "module", model), "config", None)
    if not (isinstance(saved, dict) and dataclasses.is_dataclass(config)):
        return saved
    defaults = {f.name: f.default for f in dataclasses.fields(config) if f.default is not dataclasses.MISSING}
    return {**defaults, **saved}


def _restore(env: Env, t: Trainer, prev: Previous, p: Progress, log: RunLog) -> None:
    """Weights, optimiser moments (with the hyperparameters given now), batch position, record and RNG of ``prev``."""
    saved = prev.meta["config"].get(t.same_config)
    if t.same_config is not None and _with_defaults(saved, t.model) != t.config[t.same_config]:
        raise ValueError(f"{prev.folder}: its {t.same_config} config {saved} differs from {t.config[t.same_config]}")
    t.model.load_state_dict(prev.weights)
    for key, opt in t.optimizers.items():
        given = [{k: v for k, v in group.items() if k != "params"} for group in opt.param_groups]
        opt.load_state_dict(prev.state[key])
        for group, settings in zip(opt.param_groups, given):
            group.update(settings)
    t.batches.load(prev.state)
    p.step, p.best, p.val = int(prev.state["step"]), float(prev.state["best"]), dict(prev.state["val"])
    p.threads = int(prev.state.get("threads", 0))
    log.truncate(p.step)
    rngs = prev.state["rng"]
    if len(rngs) == env.dist.world_size:
        _set_rng_state(rngs[env.dist.rank], env.device)
    else:
        env.say(f"resuming with {env.dist.world_size} processes from a run of {len(rngs)}: RNG streams reseeded")
    env.say(f"resumed from {prev.folder} at step {p.step}")


def _upgrade(state: dict, meta: dict) -> dict:
    """A state.pt written before the trainers shared this loop, in today's layout (runs started then resume)."""
    if "best_val_mpjpe_m" in state:  # train_vae's
        val = state.pop("val_mpjpe_m")
        state.update(best=state.pop("best_val_mpjpe_m"), val={} if val is None else {"mpjpe_m": val})
    if "best_fid" in state:  # train_gan's and train_diffusion's: rank 0's torch RNG; the step and FID in config.json
        fid = meta["extra"].get("val_latent_fid")
        state.update(best=state.pop("best_fid"), step=meta["step"], val={} if fid is None else {"latent_fid": fid},
                     rng=[{"torch": state.pop("rng"), "cuda": state.pop("cuda_rng", None)}])
    return state


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
    if "numpy" in state:  # absent from an upgraded state (its trainer drew from torch alone)
        np.random.set_state(("MT19937", state["numpy"].numpy().astype(np.uint32), state["numpy_pos"], 0, 0.0))
        random.setstate(state["python"])
    if device.type == "cuda" and state.get("cuda") is not None:
        torch.cuda.set_rng_state(state["cuda"], device)


def _all_rng_states(env: Env) -> list[dict]:
    """Every process's RNG state (rank order), so that a resumed DDP run continues each stream."""
    mine = _rng_state(env.device)
    if not env.dist.enabled:
        return [mine]
    states: list = [None] * env.dist.world_size
    dist.all_gather_object(states, mine)
    return states
