"""Train a latent GAN from the latent cache alone (the VAE is never loaded).

One training step = ``critic_steps`` discriminator updates, then one generator update, each on a fresh batch of
(condition, latent) pairs from the train split: text -> (caption embedding, its clip's latent), action ->
(action id, latent). Latents are standardised per dimension with the cache's train statistics; with
real_latents="sample" each step draws z ~ N(mu, exp(logvar)) instead of using mu.

Every ``eval_every`` steps the generator is scored by a latent-space FID on the validation conditions (fixed
noise, so evaluations are comparable); ``out/best/`` keeps the lowest one, ``out/last/`` (with the optimiser
state) is written every ``ckpt_every`` steps and at the end.

Randomness of step s on rank r comes from a generator seeded by (seed, r, s) alone, so a resumed run continues
exactly as an uninterrupted one. Under torchrun each rank draws its own batches (rank-seeded sampling) of
batch_size / world_size pairs; generator and critic are wrapped in DistributedDataParallel (the critic's
gradient penalty is a double backward, which DDP handles: see ``critic_loss_wgan_gp``); rank 0 evaluates and
writes checkpoints and logs.
"""
from __future__ import annotations

import math
import os
import sys
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from lsgan.eval.metrics import fid
from lsgan.models.cache import LatentCacheData, StaleCache, read_latent_cache
from lsgan.models.checkpoint import CONFIG, load_state, load_weights, save_checkpoint
from lsgan.models.gan import (
    GANConfig,
    LatentGAN,
    critic_loss_wgan_gp,
    d_loss_bce,
    g_loss_bce,
    g_loss_wgan,
    load_gan,
)
from lsgan.train.common import (
    Dist,
    RunLog,
    all_reduce_mean,
    check_finite,
    local_device,
    pick_device,
    seed_everything,
    setup_distributed,
    teardown_distributed,
)

__all__ = ["GANTrainConfig", "train_gan", "load_gan"]

EVAL_SPLITS = ("val", "test", "train")


@dataclass
class GANTrainConfig:
    lr: float = 1e-4
    betas: tuple[float, float] = (0.5, 0.9)
    weight_decay: float = 0.0
    batch_size: int = 64  # in all: each of W torchrun processes takes batch_size / W
    max_steps: int = 100_000  # generator updates
    critic_steps: int | None = None  # discriminator updates per generator update; None: 5 for WGAN-GP, 1 for BCE
    gp_weight: float = 10.0
    eval_every: int = 1000
    ckpt_every: int = 1000
    log_every: int = 50
    fid_samples: int = 2048
    real_latents: str = "sample"  # "sample": z ~ N(mu, exp(logvar)) each step; "mean": mu
    seed: int = 0

    def __post_init__(self) -> None:
        self.betas = tuple(self.betas)
        if self.real_latents not in ("sample", "mean"):
            raise ValueError(f"real_latents must be 'sample' or 'mean', not {self.real_latents!r}")
        if self.critic_steps is not None and self.critic_steps < 1:
            raise ValueError("critic_steps must be >= 1 (or None for the variant's default)")
        for name in ("batch_size", "max_steps", "eval_every", "ckpt_every", "log_every", "fid_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")

    def critic_steps_for(self, gan: GANConfig) -> int:
        return self.critic_steps or (5 if gan.wgan else 1)


# ---------------------------------------------------------------------------------------------------- data


def pairs(cache: LatentCacheData, cond: str, split: str) -> tuple[np.ndarray, np.ndarray]:
    """(conditions, clip index) of a split: text -> (caption embeddings (P, D), clips); action -> (ids (P,), clips)."""
    if cond == "text":
        keep = cache.splits[cache.caption_clip] == split
        return cache.caption_embedding[keep], cache.caption_clip[keep]
    clips = np.nonzero((cache.splits == split) & (cache.actions >= 0))[0]
    return cache.actions[clips], clips


def fit_config(gan: GANConfig, cache: LatentCacheData) -> tuple[GANConfig, list[str]]:
    """The config with latent_dim, cond_dim / num_actions taken from the cache where they differ (and why)."""
    changes, notes = {}, []
    z = cache.mu.shape[1]
    if gan.latent_dim != z:
        changes["latent_dim"] = z
        notes.append(f"latent_dim {gan.latent_dim} in the config, but the cache holds {z}-d latents: using {z}")
    if gan.cond == "text":
        if len(cache.caption_text) == 0:
            raise ValueError("cond='text' but the cache holds no captions; use cond='action' or a captioned dataset")
        width = cache.caption_embedding.shape[1]
        if gan.cond_dim != width:
            changes["cond_dim"] = width
            notes.append(
                f"cond_dim {gan.cond_dim} in the config, but the cache's text encoder "
                f"{cache.text_encoder or '(unnamed)'} gives {width}-d embeddings: using {width}"
            )
    else:
        if not (cache.actions >= 0).any():
            raise ValueError("cond='action' but no clip in the cache has an action label; use cond='text'")
        n = max(len(cache.action_names), int(cache.actions.max()) + 1)
        if gan.num_actions != n:
            changes["num_actions"] = n
        if gan.num_actions not in (0, n):  # 0: "take it from the cache"
            notes.append(f"num_actions {gan.num_actions} in the config, but the cache has {n} action classes: "
                         f"using {n}")
    return replace(gan, **changes), notes


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


def latent_fid(model: LatentGAN, ev: EvalSet, seed: int) -> float:
    """FID between latents generated for the eval conditions (fixed noise) and the real ones, standardised space."""
    if len(ev.real) < 2:
        return math.nan
    g = torch.Generator(model.device).manual_seed(seed)
    fake = torch.cat([model.sample(c, generator=g) for c in ev.cond.split(4096)]).cpu().numpy()
    return fid(fake, ev.real)


# ---------------------------------------------------------------------------------------------------- steps


def step_generator(g: torch.Generator, seed: int, rank: int, step: int) -> torch.Generator:
    """Reseed ``g`` from (seed, rank, step): the step's randomness does not depend on the run's history."""
    return g.manual_seed(int(np.random.SeedSequence([seed, rank, step]).generate_state(1)[0]))


def d_step(model: LatentGAN, d_net, opt, data: LatentPairs, b: int, gp_weight: float, g: torch.Generator) -> dict:
    """One discriminator/critic update; returns its (detached) losses."""
    real, c = data.batch(b, g)  # (b, Z), (b, ...)
    noise = torch.randn(b, model.config.noise_dim, generator=g, device=real.device)
    with torch.no_grad():
        fake = model.generator(noise, c)  # (b, Z)
    if model.config.wgan:
        out = critic_loss_wgan_gp(d_net, real, fake, c, gp_weight, generator=g)
        loss, stats = out.loss, {"wasserstein": out.wasserstein, "gp": out.gp}
    else:
        logits = d_net(torch.cat([real, fake]), torch.cat([c, c]))  # (2b,): one forward pass, as DDP expects
        loss, stats = d_loss_bce(*logits.split(b)), {}
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return {"d_loss": loss.detach(), **stats}


def g_step(model: LatentGAN, g_net, opt, data: LatentPairs, b: int, g: torch.Generator) -> torch.Tensor:
    """One generator update through the frozen, unwrapped discriminator (no weight gradients, nothing to sync)."""
    _, c = data.batch(b, g)
    noise = torch.randn(b, model.config.noise_dim, generator=g, device=data.mu.device)
    model.discriminator.requires_grad_(False)
    scores = model.discriminator(g_net(noise, c), c)  # (b,)
    loss = g_loss_wgan(scores) if model.config.wgan else g_loss_bce(scores)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    model.discriminator.requires_grad_(True)
    opt.step()
    return loss.detach()


def _wrap(module: torch.nn.Module, d: Dist, device: torch.device) -> torch.nn.Module:
    if not d.enabled:
        return module
    return DistributedDataParallel(module, device_ids=[device.index] if device.type == "cuda" else None)


# ---------------------------------------------------------------------------------------------------- loop


def _previous_run(
    out: Path, cache: LatentCacheData, gan: GANConfig, resume: bool, say
) -> tuple[GANConfig, dict | None]:
    """The run in ``out/last`` to continue: (its GAN config, {weights, state, step, fid}); never overwritten unasked."""
    if not (out / "last" / CONFIG).exists():
        if resume:
            say(f"nothing to resume in {out}: starting a new run")
        return gan, None
    if not resume:
        raise FileExistsError(f"{out} already holds a run (last/); pass resume=True to continue it, or another folder")
    weights, meta = load_weights(out / "last", kind="gan")
    if meta["extra"].get("vae_hash") != cache.vae_hash:
        raise StaleCache(f"{out} was trained on latents of another VAE than the cache's; cannot resume on this cache")
    saved = GANConfig(**meta["config"]["gan"])
    if saved != gan:
        say(f"resuming with the run's own GAN config ({saved.arch}), not the one given")
    fid_value = meta["extra"].get("val_latent_fid")
    run = {"weights": weights, "state": load_state(out / "last"), "step": int(meta["step"]),
           "fid": math.nan if fid_value is None else float(fid_value)}
    return saved, run


def train_gan(
    cache: str | os.PathLike,
    out: str | os.PathLike,
    *,
    gan: GANConfig | None = None,
    train: GANTrainConfig | None = None,
    device: str = "auto",
    resume: bool = False,
    progress: bool = True,
    expect_vae_hash: str | None = None,
    expect_text_encoder: str | None = None,
) -> dict:
    """Train a latent GAN on ``cache``, writing ``out/last``, ``out/best`` and ``out/log.csv``; returns a summary.

    expect_vae_hash / expect_text_encoder: refuse (StaleCache) a cache made with another VAE or text encoder.
    resume: continue from ``out/last`` at its step (an existing run is never overwritten without it).
    """
    gan, train = gan or GANConfig(), train or GANTrainConfig()
    device = pick_device(device)
    d = setup_distributed(device)
    device = local_device(device, d)
    try:
        with warnings.catch_warnings():
            # DDP notes that the double backward hands the critic's (1, H) output weight a gradient with other
            # (equivalent) strides than its bucket view: a performance remark about one tiny tensor.
            warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
            result = _train(Path(cache), Path(out), gan, train, device, d, resume, progress,
                            expect_vae_hash, expect_text_encoder)
    except BaseException:
        if d.enabled and dist.is_initialized():
            dist.destroy_process_group()  # no barrier: the other ranks may be gone
        raise
    teardown_distributed(d)
    return result


def _train(
    cache_path: Path,
    out: Path,
    gan: GANConfig,
    train: GANTrainConfig,
    device: torch.device,
    d: Dist,
    resume: bool,
    progress: bool,
    expect_vae_hash: str | None,
    expect_text_encoder: str | None,
) -> dict:
    def say(msg: str) -> None:
        notes.append(msg)
        if d.is_main:
            tqdm.write(f"train_gan: {msg}", file=sys.stderr)

    notes: list[str] = []
    cache = read_latent_cache(cache_path, expect_vae_hash=expect_vae_hash, expect_text_encoder=expect_text_encoder)
    gan, fitted = fit_config(gan, cache)
    for msg in fitted:
        say(msg)

    gan, run = _previous_run(out, cache, gan, resume, say)
    step, best, last_fid = 0, math.inf, math.nan
    if run is not None:
        step, best, last_fid = run["step"], run["state"]["best_fid"], run["fid"]

    if train.batch_size % d.world_size:
        raise ValueError(f"batch_size {train.batch_size} does not split over {d.world_size} processes")
    b = train.batch_size // d.world_size
    critic_steps = train.critic_steps_for(gan)

    seed_everything(train.seed)
    model = LatentGAN(gan).to(device)
    hp = dict(lr=train.lr, betas=train.betas, weight_decay=train.weight_decay)
    opt_g = torch.optim.AdamW(model.generator.parameters(), **hp)
    opt_d = torch.optim.AdamW(model.discriminator.parameters(), **hp)
    if run is not None:
        model.load_state_dict(run["weights"])
        for opt, key in ((opt_g, "opt_g"), (opt_d, "opt_d")):
            opt.load_state_dict(run["state"][key])  # the moments continue; lr, betas, weight decay: the ones given now
            for group in opt.param_groups:
                group.update(hp)
        torch.set_rng_state(run["state"]["rng"])
    g_net, d_net = _wrap(model.generator, d, device), _wrap(model.discriminator, d, device)

    data = LatentPairs(cache, gan.cond, device, sample=train.real_latents == "sample")
    ev, note = eval_set(cache, gan.cond, train.fid_samples, train.seed, device)
    if note:
        say(note)
    if len(ev.real) < 2:
        say(f"the {ev.split} split has fewer than 2 clips: no latent FID; best/ will be the last checkpoint")

    config = {"gan": asdict(gan), "train": asdict(train)}

    def save(name: str, fid_value: float, with_state: bool) -> None:
        extra = {
            "latent_mean": cache.mean.tolist(), "latent_std": cache.std.tolist(), "action_names": cache.action_names,
            "text_encoder": cache.text_encoder, "vae_hash": cache.vae_hash, "cache": str(cache_path.resolve()),
            "val_latent_fid": None if math.isnan(fid_value) else fid_value, "eval_split": ev.split,
        }
        st = None
        if with_state:
            st = {"opt_g": opt_g.state_dict(), "opt_d": opt_d.state_dict(), "best_fid": best,
                  "rng": torch.get_rng_state()}
        save_checkpoint(out / name, model=model, kind="gan", config=config, step=step, extra=extra, state=st)

    log = RunLog(out, enabled=d.is_main)
    history: list[tuple[int, float]] = []
    if step == 0 and d.is_main:
        last_fid = latent_fid(model, ev, train.seed)
        history.append((0, last_fid))
        log.write(0, latent_fid=last_fid)

    bar = tqdm(total=train.max_steps, initial=step, disable=not (progress and d.is_main), file=sys.stderr,
               desc=f"gan {gan.arch}", dynamic_ncols=True)
    g = torch.Generator(device)
    sums: dict[str, float] = {}
    window, train_time, start_step = 0, 0.0, step
    model.train()
    while step < train.max_steps:
        t0 = time.perf_counter()
        step_generator(g, train.seed, d.rank, step)
        for _ in range(critic_steps):
            d_stats = d_step(model, d_net, opt_d, data, b, train.gp_weight, g)
        g_loss = g_step(model, g_net, opt_g, data, b, g)
        losses = {k: v.item() for k, v in d_stats.items()} | {"g_loss": g_loss.item()}
        check_finite({"d_loss": losses["d_loss"], "g_loss": losses["g_loss"]}, step + 1)
        step += 1
        train_time += time.perf_counter() - t0
        bar.update(1)
        for k, v in losses.items():
            sums[k] = sums.get(k, 0.0) + v
        window += 1

        row: dict[str, float] = {}
        if step % train.log_every == 0 or step == train.max_steps:
            row = {k: all_reduce_mean(v / window, d, device) for k, v in sums.items()}
            sums, window = {}, 0
            bar.set_postfix({k: f"{v:.3g}" for k, v in row.items()}, refresh=False)
        if d.is_main and (step % train.eval_every == 0 or step == train.max_steps):
            last_fid = row["latent_fid"] = latent_fid(model, ev, train.seed)
            history.append((step, last_fid))
            if last_fid < best:
                best = last_fid
                save("best", last_fid, with_state=False)
        if d.is_main and (step % train.ckpt_every == 0 or step == train.max_steps):
            save("last", last_fid, with_state=True)
        if row:
            log.write(step, **row)
    bar.close()

    if d.is_main and not (out / "best" / CONFIG).exists():  # no finite latent FID: the last weights stand in
        save("best", last_fid, with_state=False)
    log.close()
    trained = step - start_step
    return {
        "out": str(out), "step": step, "best_val_latent_fid": best if math.isfinite(best) else None,
        "last_val_latent_fid": None if math.isnan(last_fid) else last_fid, "fid_history": history,
        "eval_split": ev.split, "critic_steps": critic_steps, "config": config, "notes": notes,
        "steps_per_s": trained / train_time if train_time > 0 else None,
    }
