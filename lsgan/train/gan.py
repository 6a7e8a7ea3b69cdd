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
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from lsgan.models.cache import read_latent_cache
from lsgan.models.checkpoint import CONFIG, save_checkpoint
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
    claim_run,
    Dist,
    RunLog,
    all_reduce_mean,
    check_finite,
    run_distributed,
    seed_everything,
)
from lsgan.train.latents import (  # noqa: F401  (pairs, EvalSet, EVAL_SPLITS: importable from here as before)
    EVAL_SPLITS,
    EvalSet,
    LatentPairs,
    checkpoint_extra,
    eval_set,
    fit_config,
    latent_fid,
    pairs,
    previous_run,
    step_generator,
    wrap_ddp,
)

__all__ = ["GANTrainConfig", "train_gan", "load_gan"]


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


# ---------------------------------------------------------------------------------------------------- steps


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


# ---------------------------------------------------------------------------------------------------- loop


def train_gan(
    cache: str | os.PathLike,
    out: str | os.PathLike,
    *,
    gan: GANConfig | None = None,
    train: GANTrainConfig | None = None,
    device: str = "auto",
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
    expect_vae_hash: str | None = None,
    expect_text_encoder: str | None = None,
) -> dict:
    """Train a latent GAN on ``cache``, writing ``out/last``, ``out/best`` and ``out/log.csv``; returns a summary.

    expect_vae_hash / expect_text_encoder: refuse (StaleCache) a cache made with another VAE or text encoder.
    resume: continue from ``out/last`` at its step (an existing run is never overwritten without it).
    """
    gan, train = gan or GANConfig(), train or GANTrainConfig()
    claim_run(out, resume=resume, force=force)

    def body(device: torch.device, d: Dist) -> dict:
        with warnings.catch_warnings():
            # DDP notes that the double backward hands the critic's (1, H) output weight a gradient with other
            # (equivalent) strides than its bucket view: a performance remark about one tiny tensor.
            warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
            return _train(Path(cache), Path(out), gan, train, device, d, resume, progress,
                          expect_vae_hash, expect_text_encoder)

    return run_distributed(device, body)


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

    gan, run = previous_run(out, cache, gan, resume, say, kind="gan")
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
    g_net, d_net = wrap_ddp(model.generator, d, device), wrap_ddp(model.discriminator, d, device)

    data = LatentPairs(cache, gan.cond, device, sample=train.real_latents == "sample")
    ev, note = eval_set(cache, gan.cond, train.fid_samples, train.seed, device)
    if note:
        say(note)
    if len(ev.real) < 2:
        say(f"the {ev.split} split has fewer than 2 clips: no latent FID; best/ will be the last checkpoint")

    config = {"gan": asdict(gan), "train": asdict(train)}

    def save(name: str, fid_value: float, with_state: bool) -> None:
        extra = checkpoint_extra(cache, cache_path, fid_value, ev.split)
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
