"""What the trainers on the latent cache (``train_gan``, ``train_diffusion``) share.

Training pairs (condition, standardised latent) from the cache, the config fitted to the cache's widths (or the
continued run's own, on latents of the same VAE), the latent-FID evaluation set (val, else test, else train) and its
score, their Trainer for :func:`lsgan.train.loop.fit` (a generator reseeded per step, the latent FID from step 0),
the checkpoint meta that ``generate`` reads and the summary they return.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch

from lsgan.eval.metrics import fid
from lsgan.models.cache import LatentCacheData, StaleCache, read_latent_cache
from lsgan.train.graphs import GraphedStep, use_cuda_graph
from lsgan.train.loop import Env, Previous, Progress, Schedule, SeededSteps, Trainer

C = TypeVar("C")

EVAL_SPLITS = ("val", "test", "train")


@dataclass
class LatentTrainConfig:
    """Settings that mean the same for both latent trainers; GANTrainConfig and DiffusionTrainConfig add their own
    (and their optimiser defaults)."""

    lr: float = 1e-4
    betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = 0.0
    batch_size: int = 64  # in all: each of W torchrun processes takes batch_size / W
    max_steps: int = 100_000
    eval_every: int = 1000
    ckpt_every: int = 1000
    log_every: int = 50
    fid_samples: int = 2048
    real_latents: str = "sample"  # "sample": z ~ N(mu, exp(logvar)) each step; "mean": mu
    seed: int = 0
    cuda_graph: bool = True  # on one CUDA device, replay each step as one CUDA graph (lsgan.train.graphs)

    def __post_init__(self) -> None:
        self.betas = tuple(self.betas)
        if self.real_latents not in ("sample", "mean"):
            raise ValueError(f"real_latents must be 'sample' or 'mean', not {self.real_latents!r}")
        for name in ("batch_size", "max_steps", "eval_every", "ckpt_every", "log_every", "fid_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")

    def schedule(self) -> Schedule:
        return Schedule(self.max_steps, self.log_every, self.eval_every, self.ckpt_every)


def pairs(cache: LatentCacheData, cond: str, split: str) -> tuple[np.ndarray, np.ndarray]:
    """(conditions, clip index) of a split: text -> (caption embeddings (P, D), clips); action -> (ids (P,), clips)."""
    if cond == "text":
        keep = cache.splits[cache.caption_clip] == split
        return cache.caption_embedding[keep], cache.caption_clip[keep]
    clips = np.nonzero((cache.splits == split) & (cache.actions >= 0))[0]
    return cache.actions[clips], clips


def fit_config(cfg: C, cache: LatentCacheData) -> tuple[C, list[str]]:
    """The model config (any dataclass with latent_dim, cond, cond_dim, num_actions) with the widths taken from
    the cache where they differ, and why."""
    changes, notes = {}, []
    z = cache.mu.shape[1]
    if cfg.latent_dim != z:
        changes["latent_dim"] = z
        notes.append(f"latent_dim {cfg.latent_dim} in the config, but the cache holds {z}-d latents: using {z}")
    if cfg.cond == "text":
        if len(cache.caption_text) == 0:
            raise ValueError("cond='text' but the cache holds no captions; use cond='action' or a captioned dataset")
        if not cache.text_encoder or cache.caption_embedding.shape[1] == 0:
            raise ValueError("cond='text' but the cache was encoded without a text encoder (--text-encoder none): "
                             "encode it with one, or use cond='action'")
        width = cache.caption_embedding.shape[1]
        if cfg.cond_dim != width:
            changes["cond_dim"] = width
            notes.append(
                f"cond_dim {cfg.cond_dim} in the config, but the cache's text encoder "
                f"{cache.text_encoder or '(unnamed)'} gives {width}-d embeddings: using {width}"
            )
    else:
        if not (cache.actions >= 0).any():
            raise ValueError("cond='action' but no clip in the cache has an action label; use cond='text'")
        n = max(len(cache.action_names), int(cache.actions.max()) + 1)
        if cfg.num_actions != n:
            changes["num_actions"] = n
        if cfg.num_actions not in (0, n):  # 0: "take it from the cache"
            notes.append(f"num_actions {cfg.num_actions} in the config, but the cache has {n} action classes: "
                         f"using {n}")
    return replace(cfg, **changes), notes


class LatentPairs:
    """The train pairs on the device, latents standardised; ``batch`` draws a random batch of them."""

    def __init__(self, cache: LatentCacheData, cond: str, device: torch.device, sample: bool) -> None:
        c, clip = pairs(cache, cond, "train")
        if len(clip) == 0:
            raise ValueError(f"no training examples: the cache has no train-split clips with a {cond} condition")
        self.cond = torch.as_tensor(c, device=device)  # (P, D) float or (P,) long
        self.clip = torch.as_tensor(clip, dtype=torch.long, device=device)  # (P,)
        self.mu = torch.as_tensor((cache.mu - cache.mean) / cache.std, device=device)  # (N, Z)
        self.sigma = torch.as_tensor(np.exp(0.5 * cache.logvar) / cache.std, device=device)  # (N, Z)
        self.sample = sample

    def batch(self, b: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(standardised latents (b, Z), conditions (b, ...)) of b random pairs."""
        i = torch.randint(len(self.clip), (b,), generator=g, device=self.clip.device)
        clip = self.clip[i]
        z = self.mu[clip]
        if self.sample:
            z = z + self.sigma[clip] * torch.randn(z.shape, generator=g, device=z.device)
        return z, self.cond[i]


@dataclass
class EvalSet:
    """Conditions to generate from (fid_samples of them) and the real standardised latents they are compared with."""

    split: str
    cond: torch.Tensor
    real: np.ndarray  # (R, Z)


def eval_set(
    cache: LatentCacheData, cond: str, num: int, seed: int, device: torch.device
) -> tuple[EvalSet, str | None]:
    """The first of val / test / train with examples, and a note when it is not val."""
    for split in EVAL_SPLITS:
        c, clip = pairs(cache, cond, split)
        if len(clip):
            break
    order = np.random.default_rng(seed).permutation(len(clip))
    pick = order[np.arange(num) % len(clip)]  # every condition, cycled, or a fixed random subset
    real = ((cache.mu[clip] - cache.mean) / cache.std).astype(np.float32)
    note = None if split == "val" else f"no validation {cond} conditions in the cache: latent FID on the {split} split"
    return EvalSet(split, torch.as_tensor(c[pick], device=device), real), note


def latent_fid(model: torch.nn.Module, ev: EvalSet, seed: int, chunk: int = 4096, **sample_options) -> float:
    """FID between latents generated for the eval conditions (fixed noise) and the real ones, standardised space.

    ``model.sample(cond, generator=g, **sample_options)``: a LatentGAN, or a LatentDiffusion with its DDIM options.
    """
    if len(ev.real) < 2:
        return math.nan
    was_training = model.training
    model.eval()
    g = torch.Generator(model.device).manual_seed(seed)
    fake = torch.cat([model.sample(c, generator=g, **sample_options) for c in ev.cond.split(chunk)]).cpu().numpy()
    model.train(was_training)
    return fid(fake, ev.real)


@dataclass
class LatentData:
    """What a latent trainer reads from the cache: the train pairs, the latent-FID set and its per-process batch."""

    cache: LatentCacheData
    path: Path
    pairs: LatentPairs
    ev: EvalSet
    batch: int


def open_cache(env: Env, cache_path: Path, cfg: C, train: LatentTrainConfig, kind: str, expect_vae_hash: str | None,
               expect_text_encoder: str | None) -> tuple[C, Previous | None, LatentData]:
    """(model config fitted to the cache, or the continued run's own; the run to continue; the data).

    ``kind``: the checkpoint kind ("gan", "diffusion"), also the key of the model config in config.json.
    """
    cache = read_latent_cache(cache_path, expect_vae_hash=expect_vae_hash, expect_text_encoder=expect_text_encoder)
    cfg, fitted = fit_config(cfg, cache)
    for msg in fitted:
        env.say(msg)
    prev = env.previous(kind)
    if prev is not None:
        cfg = _adopt(prev, cache, cfg, kind, env.say)
    if train.batch_size % env.dist.world_size:
        raise ValueError(f"batch_size {train.batch_size} does not split over {env.dist.world_size} processes")
    data = LatentPairs(cache, cfg.cond, env.device, sample=train.real_latents == "sample")
    ev, note = eval_set(cache, cfg.cond, train.fid_samples, train.seed, env.device)
    if note:
        env.say(note)
    if len(ev.real) < 2:
        env.say(f"the {ev.split} split has fewer than 2 clips: no latent FID; best/ will be the last checkpoint")
    return cfg, prev, LatentData(cache, cache_path, data, ev, train.batch_size // env.dist.world_size)


def _adopt(prev: Previous, cache: LatentCacheData, cfg: C, kind: str, say: Callable[[str], None]) -> C:
    """The continued run's own model config; its latents must come from the cache's VAE."""
    if prev.meta["extra"].get("vae_hash") != cache.vae_hash:
        raise StaleCache(f"{prev.folder.parent} was trained on latents of another VAE than the cache's; cannot resume "
                         "on this cache")
    known = {f.name for f in fields(type(cfg))}
    saved = type(cfg)(**{k: v for k, v in prev.meta["config"][kind].items() if k in known})
    if saved != cfg:
        label = getattr(saved, "arch", None)
        say(f"resuming with the run's own {kind.upper() if kind == 'gan' else kind} config"
            f"{f' ({label})' if label else ''}, not the one given")
    return saved


def latent_trainer(env: Env, kind: str, desc: str, model: torch.nn.Module, config: dict,
                   optimizers: dict[str, torch.optim.Optimizer], step: Callable, data: LatentData, seed: int,
                   cuda_graph: bool, **sample_options) -> Trainer:
    """A latent model's Trainer: one seeded generator per step, scored (from step 0) by the latent FID; on one
    CUDA device with ``cuda_graph``, its steps replayed as one CUDA graph (the optimisers built with
    :func:`lsgan.train.graphs.optimizer_options`)."""
    if use_cuda_graph(cuda_graph, env.device, env.dist.enabled):
        step = GraphedStep(step)
        env.say(f"each training step is replayed as one CUDA graph after {step.warmup} eager steps (--no-cuda-graph, "
                "or cuda_graph: false in the recipe, runs every step eagerly: the same updates, more slowly)")
    return Trainer(
        kind=kind, desc=desc, model=model, config=config, optimizers=optimizers, step=step,
        batches=SeededSteps(seed, env.dist.rank, env.device), metric="latent_fid", val_prefix="", log_details=False,
        same_config=None,
        validate=lambda: {"latent_fid": latent_fid(model, data.ev, seed, **sample_options)}, val_at_start=True,
        extra=lambda p: checkpoint_extra(data.cache, data.path, p.val.get("latent_fid", math.nan), data.ev.split),
    )


def latent_summary(env: Env, p: Progress, data: LatentData, config: dict) -> dict:
    """What train_gan and train_diffusion return (each adds its own settings)."""
    last = p.val.get("latent_fid", math.nan)
    return {
        "out": str(env.out), "step": p.step, "best_val_latent_fid": p.best_value,
        "last_val_latent_fid": None if math.isnan(last) else last,
        "fid_history": [(step, val["latent_fid"]) for step, val in p.history], "eval_split": data.ev.split,
        "config": config, "notes": env.notes, "steps_per_s": p.steps_per_s,
    }


def checkpoint_extra(cache: LatentCacheData, cache_path: Path, fid_value: float, eval_split: str) -> dict:
    """The meta["extra"] of a latent model's checkpoint: what generate needs to de-standardise and check pairings."""
    return {
        "latent_mean": cache.mean.tolist(), "latent_std": cache.std.tolist(), "action_names": cache.action_names,
        "text_encoder": cache.text_encoder, "vae_hash": cache.vae_hash, "cache": str(cache_path.resolve()),
        "val_latent_fid": None if math.isnan(fid_value) else fid_value, "eval_split": eval_split,
    }
