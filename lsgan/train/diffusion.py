"""Train the latent-diffusion baseline (MLD's denoiser) from the latent cache alone, like ``train_gan``.

One step: a batch of (condition, latent) train pairs (latents standardised with the cache's statistics; with
real_latents="sample", z ~ N(mu, exp(logvar)) as MLD's diffusion stage draws it from the frozen VAE), uniform
timesteps, noise, the condition replaced by the null token with probability ``cond_mask_prob`` (for
classifier-free guidance), and the MSE between the denoiser's prediction and the noise. AdamW (MLD: lr 1e-4 and
torch's other defaults, weight decay 0.01).

Every ``eval_every`` steps the model is scored by the same latent-space FID on the validation conditions as the
GANs, from DDIM samples with ``eval_steps`` steps and guidance ``eval_guidance`` (default: the model's) and fixed
noise; ``out/best/`` keeps the lowest, ``out/last/`` (with the optimiser state) is written every ``ckpt_every``
steps and at the end. The randomness of step s on rank r comes from (seed, r, s) alone, so ``resume`` continues
exactly; under torchrun the denoiser runs in DistributedDataParallel and rank 0 evaluates and writes.
"""
from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tqdm import tqdm

from lsgan.models.cache import read_latent_cache
from lsgan.models.checkpoint import CONFIG, save_checkpoint
from lsgan.models.diffusion import (
    DiffusionConfig,
    LatentDiffusion,
    diffusion_loss,
    load_diffusion,
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
from lsgan.train.latents import (
    LatentPairs,
    checkpoint_extra,
    eval_set,
    fit_config,
    latent_fid,
    previous_run,
    step_generator,
    wrap_ddp,
)

__all__ = ["DiffusionTrainConfig", "load_diffusion", "train_diffusion"]


@dataclass
class DiffusionTrainConfig:
    lr: float = 1e-4
    betas: tuple[float, float] = (0.9, 0.999)
    weight_decay: float = 0.01  # torch's AdamW default, which MLD keeps
    batch_size: int = 64  # in all: each of W torchrun processes takes batch_size / W
    max_steps: int = 100_000
    eval_every: int = 1000
    ckpt_every: int = 1000
    log_every: int = 50
    fid_samples: int = 2048
    eval_steps: int = 10  # DDIM steps of the samples scored by the latent FID (fewer than sampling's, for speed)
    eval_guidance: float | None = None  # None: the model's guidance_scale
    real_latents: str = "sample"  # "sample": z ~ N(mu, exp(logvar)) each step; "mean": mu
    seed: int = 0

    def __post_init__(self) -> None:
        self.betas = tuple(self.betas)
        if self.real_latents not in ("sample", "mean"):
            raise ValueError(f"real_latents must be 'sample' or 'mean', not {self.real_latents!r}")
        for name in ("batch_size", "max_steps", "eval_every", "ckpt_every", "log_every", "fid_samples", "eval_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")


def train_diffusion(
    cache: str | os.PathLike,
    out: str | os.PathLike,
    *,
    diffusion: DiffusionConfig | None = None,
    train: DiffusionTrainConfig | None = None,
    device: str = "auto",
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
    expect_vae_hash: str | None = None,
    expect_text_encoder: str | None = None,
) -> dict:
    """Train the denoiser on ``cache``, writing ``out/last``, ``out/best`` and ``out/log.csv``; returns a summary.

    expect_vae_hash / expect_text_encoder: refuse (StaleCache) a cache made with another VAE or text encoder.
    resume: continue from ``out/last`` at its step (an existing run is never overwritten without it).
    """
    diffusion, train = diffusion or DiffusionConfig(), train or DiffusionTrainConfig()
    claim_run(out, resume=resume, force=force)
    return run_distributed(device, lambda dev, d: _train(
        Path(cache), Path(out), diffusion, train, dev, d, resume, progress, expect_vae_hash, expect_text_encoder))


def _train(
    cache_path: Path,
    out: Path,
    cfg: DiffusionConfig,
    train: DiffusionTrainConfig,
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
            tqdm.write(f"train_diffusion: {msg}", file=sys.stderr)

    notes: list[str] = []
    cache = read_latent_cache(cache_path, expect_vae_hash=expect_vae_hash, expect_text_encoder=expect_text_encoder)
    cfg, fitted = fit_config(cfg, cache)
    for msg in fitted:
        say(msg)
    cfg, run = previous_run(out, cache, cfg, resume, say, kind="diffusion")
    step, best, last_fid = 0, math.inf, math.nan
    if run is not None:
        step, best, last_fid = run["step"], run["state"]["best_fid"], run["fid"]
    if train.batch_size % d.world_size:
        raise ValueError(f"batch_size {train.batch_size} does not split over {d.world_size} processes")
    b = train.batch_size // d.world_size

    seed_everything(train.seed)
    model = LatentDiffusion(cfg).to(device)
    hp = {"lr": train.lr, "betas": train.betas, "weight_decay": train.weight_decay}
    opt = torch.optim.AdamW(model.parameters(), **hp)
    if run is not None:
        model.load_state_dict(run["weights"])
        opt.load_state_dict(run["state"]["opt"])  # the moments continue; the hyperparameters are the ones given now
        for group in opt.param_groups:
            group.update(hp)
        torch.set_rng_state(run["state"]["rng"])  # dropout draws from the global generator
        if device.type == "cuda" and run["state"].get("cuda_rng") is not None:
            torch.cuda.set_rng_state(run["state"]["cuda_rng"], device)
    net = wrap_ddp(model.denoiser, d, device)

    data = LatentPairs(cache, cfg.cond, device, sample=train.real_latents == "sample")
    ev, note = eval_set(cache, cfg.cond, train.fid_samples, train.seed, device)
    if note:
        say(note)
    if len(ev.real) < 2:
        say(f"the {ev.split} split has fewer than 2 clips: no latent FID; best/ will be the last checkpoint")
    sampling = {"steps": train.eval_steps, "guidance": train.eval_guidance, "eta": 0.0}
    config = {"diffusion": asdict(cfg), "train": asdict(train)}

    def save(name: str, fid_value: float, with_state: bool) -> None:
        st = None
        if with_state:
            st = {"opt": opt.state_dict(), "best_fid": best, "rng": torch.get_rng_state(),
                  "cuda_rng": torch.cuda.get_rng_state(device) if device.type == "cuda" else None}
        save_checkpoint(out / name, model=model, kind="diffusion", config=config, step=step,
                        extra=checkpoint_extra(cache, cache_path, fid_value, ev.split), state=st)

    log = RunLog(out, enabled=d.is_main)
    history: list[tuple[int, float]] = []
    if step == 0 and d.is_main:
        last_fid = latent_fid(model, ev, train.seed, **sampling)
        history.append((0, last_fid))
        log.write(0, latent_fid=last_fid)

    bar = tqdm(total=train.max_steps, initial=step, disable=not (progress and d.is_main), file=sys.stderr,
               desc="diffusion", dynamic_ncols=True)
    g = torch.Generator(device)
    loss_sum, window, train_time, start_step = 0.0, 0, 0.0, step
    model.train()
    while step < train.max_steps:
        t0 = time.perf_counter()
        step_generator(g, train.seed, d.rank, step)
        z0, c = data.batch(b, g)
        loss = diffusion_loss(model, z0, c, g, net=net)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        value = loss.item()
        check_finite({"loss": value}, step + 1)
        step += 1
        train_time += time.perf_counter() - t0
        bar.update(1)
        loss_sum, window = loss_sum + value, window + 1

        row: dict[str, float] = {}
        if step % train.log_every == 0 or step == train.max_steps:
            row = {"loss": all_reduce_mean(loss_sum / window, d, device)}
            loss_sum, window = 0.0, 0
            bar.set_postfix({"loss": f"{row['loss']:.3g}"}, refresh=False)
        if d.is_main and (step % train.eval_every == 0 or step == train.max_steps):
            last_fid = row["latent_fid"] = latent_fid(model, ev, train.seed, **sampling)
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
        "eval_split": ev.split, "eval_sampling": sampling, "config": config, "notes": notes,
        "steps_per_s": trained / train_time if train_time > 0 else None,
    }
