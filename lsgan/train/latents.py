"""What the trainers on the latent cache (``train_gan``, ``train_diffusion``) share.

Training pairs (condition, standardised latent) from the cache, the config fitted to the cache's widths, the
latent-FID evaluation set (val, else test, else train) and its score, per-step reseeding, the DDP wrapper, the
run folder (what ``resume`` continues, and what is refused) and the checkpoint meta that ``generate`` reads.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel

from lsgan.eval.metrics import fid
from lsgan.models.cache import LatentCacheData, StaleCache
from lsgan.models.checkpoint import CONFIG, load_state, load_weights
from lsgan.train.common import Dist

C = TypeVar("C")

EVAL_SPLITS = ("val", "test", "train")


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


def step_generator(g: torch.Generator, seed: int, rank: int, step: int) -> torch.Generator:
    """Reseed ``g`` from (seed, rank, step): the step's randomness does not depend on the run's history."""
    return g.manual_seed(int(np.random.SeedSequence([seed, rank, step]).generate_state(1)[0]))


def wrap_ddp(module: torch.nn.Module, d: Dist, device: torch.device) -> torch.nn.Module:
    """``module`` in DistributedDataParallel under torchrun, itself otherwise."""
    if not d.enabled:
        return module
    return DistributedDataParallel(module, device_ids=[device.index] if device.type == "cuda" else None)


def previous_run(
    out: Path, cache: LatentCacheData, cfg: C, resume: bool, say: Callable[[str], None], *, kind: str
) -> tuple[C, dict | None]:
    """The run in ``out/last`` to continue: (its model config, {weights, state, step, fid}); never overwritten unasked.

    ``kind``: the checkpoint kind ("gan", "diffusion"), also the key of the model config in config.json.
    """
    if not (out / "last" / CONFIG).exists():
        if resume:
            say(f"nothing to resume in {out}: starting a new run")
        return cfg, None
    if not resume:
        raise FileExistsError(f"{out} already holds a run (last/); pass resume=True to continue it, or another folder")
    weights, meta = load_weights(out / "last", kind=kind)
    if meta["extra"].get("vae_hash") != cache.vae_hash:
        raise StaleCache(f"{out} was trained on latents of another VAE than the cache's; cannot resume on this cache")
    known = {f.name for f in fields(type(cfg))}
    saved = type(cfg)(**{k: v for k, v in meta["config"][kind].items() if k in known})
    if saved != cfg:
        label = getattr(saved, "arch", None)
        say(f"resuming with the run's own {kind.upper() if kind == 'gan' else kind} config"
            f"{f' ({label})' if label else ''}, not the one given")
    fid_value = meta["extra"].get("val_latent_fid")
    run = {"weights": weights, "state": load_state(out / "last"), "step": int(meta["step"]),
           "fid": math.nan if fid_value is None else float(fid_value)}
    return saved, run


def checkpoint_extra(cache: LatentCacheData, cache_path: Path, fid_value: float, eval_split: str) -> dict:
    """The meta["extra"] of a latent model's checkpoint: what generate needs to de-standardise and check pairings."""
    return {
        "latent_mean": cache.mean.tolist(), "latent_std": cache.std.tolist(), "action_names": cache.action_names,
        "text_encoder": cache.text_encoder, "vae_hash": cache.vae_hash, "cache": str(cache_path.resolve()),
        "val_latent_fid": None if math.isnan(fid_value) else fid_value, "eval_split": eval_split,
    }
