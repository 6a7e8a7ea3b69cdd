"""``lsgan generate``: motion from sentences or action labels: latents from a generator, then one VAE decoder pass.

The generator is a latent GAN (one generator pass) or the latent-diffusion baseline (DDIM over ``steps`` steps
with classifier-free ``guidance``); ``load_generator`` tells them apart by the checkpoint's kind. Both produce
standardised latents from the same conditions, so text encoding, de-standardising and decoding are one code path.
Timings: ``text_encoding``, ``generator`` (the GAN's generator pass, or every DDIM step of the denoiser with both
halves of guidance: the time from conditions to latents either way) and ``vae_decoding``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import time
from dataclasses import dataclass

import numpy as np
import torch

# re-exported: the structures and the writer, torch-free in lsgan.generation, shared with the ONNX runtime
from lsgan.generation import (  # noqa: F401
    CPU_DECODE_FRAMES,
    Generation,
    Motion,
    Request,
    check_prompts,
    claim_generation,
    decode_batches,
    decoded_motion,
    place_measured,
    read_prompts,
    write_generation,
)
from lsgan.generation import draw_noise as numpy_noise
from lsgan.constraints import Constraints, Placement, check_reach, meet, model_reach
from lsgan.control import ControlSettings
from lsgan.threads import LARGE_BATCH, ThreadPolicy


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


GENERATOR_KINDS = ("gan", "diffusion")


def load_generator(path: str | os.PathLike, device: str | torch.device = "cpu", prefer: str = "best"):
    """(model in eval mode, meta) of a latent generator checkpoint: a LatentGAN or a LatentDiffusion, by its kind.

    Both have ``config`` (cond, cond_dim, latent_dim, ...), ``sample(cond, num=None, generator=None, ...)`` and the
    same meta["extra"] (latent_mean/latent_std, vae_hash, text_encoder, action_names).
    """
    from lsgan.models.checkpoint import read_meta

    kind = read_meta(path, prefer).get("kind")
    if kind == "gan":
        from lsgan.models.gan import load_gan as load
    elif kind == "diffusion":
        from lsgan.models.diffusion import load_diffusion as load
    else:
        raise ValueError(f"{path}: holds a {kind!r} checkpoint, not a generator (GAN or diffusion: {GENERATOR_KINDS})")
    model, meta = load(path, device=device, prefer=prefer)
    check_generator_extra(path, prefer, model, meta)
    return model, meta


def check_generator_extra(path: str | os.PathLike, prefer: str, model, meta: dict) -> None:
    """The "extra" of a generator's config.json as generation reads it (the latent statistics, the text encoder's
    name, the action labels), or an error naming that file: a damaged one must not fail later, or decode wrongly."""
    from lsgan.errors import reading
    from lsgan.models.checkpoint import CONFIG, resolve

    with reading(resolve(path, prefer) / CONFIG, "a generator's config this lsgan version reads"):
        extra = meta.get("extra", {})
        if not isinstance(extra, dict):
            raise TypeError(f"'extra' is a {type(extra).__name__}, not an object")
        for key in ("latent_mean", "latent_std"):
            shape = np.asarray(extra[key], np.float32).shape
            if shape != (model.config.latent_dim,):
                raise ValueError(f"{key!r} holds {shape} values, not the latent size ({model.config.latent_dim},)")
        if not isinstance(extra.get("text_encoder", ""), str) or not all(
                isinstance(a, str) for a in extra.get("action_names", [])):
            raise TypeError("'text_encoder' or 'action_names' is not text")


@dataclass
class Loaded:
    """A generator with its VAE and text encoder, loaded once: what ``generate`` and ``lsgan serve`` run."""

    model: torch.nn.Module
    meta: dict  # the generator's
    decoder: torch.nn.Module
    vae_meta: dict
    device: torch.device
    encoder: object | None  # the generator's TextEncoder; None for an action-conditioned model
    gan: str
    vae: str

    @property
    def max_frames(self) -> int:
        """The longest motion the VAE decodes (its positional table)."""
        return int(self.vae_meta["config"]["model"].get("max_len", 1024))


def load_models(gan: str | os.PathLike, vae: str | os.PathLike, *, device: str | torch.device = "auto",
                text_encoder_path: str | None = None, strict_pairing: bool = True) -> Loaded:
    """The generator checkpoint ``gan``, the VAE it learned from and its text encoder, on ``device``."""
    from lsgan.models.checkpoint import weights_hash
    from lsgan.models.vae import load_vae
    from lsgan.device import pick_device

    dev = pick_device(device) if isinstance(device, str) else device
    model, gmeta = load_generator(gan, device=dev)
    decoder, vmeta = load_vae(vae, device=dev)
    extra = gmeta.get("extra", {})
    if strict_pairing and extra.get("vae_hash") and extra["vae_hash"] != weights_hash(vae):
        raise ValueError(
            f"{gan} was trained on latents of another VAE checkpoint than {vae}; "
            f"use the VAE its cache was encoded with (its path is in the {gmeta['kind']}'s config.json)"
        )
    encoder = text_encoder_for(model, extra, gan, dev, text_encoder_path)
    return Loaded(model, gmeta, decoder, vmeta, dev, encoder, str(gan), str(vae))


def text_encoder_for(model, extra: dict, name, dev: torch.device, text_encoder_path: str | None):
    """The text encoder a text-conditioned generator was trained with (checked by id); None for action models."""
    if model.config.cond != "text":
        return None
    from lsgan.models.text import load_text_encoder

    enc_id = extra.get("text_encoder", "minilm")
    enc = load_text_encoder(enc_id.split(":")[0], path=text_encoder_path, device=dev)
    if enc.id != enc_id:
        raise ValueError(f"{name} was trained with text encoder {enc_id!r}, but {enc.id!r} was loaded")
    return enc


def _conditions(model, extra: dict, name, requests: list[Request], dev: torch.device, encoder,
                timings: dict[str, float]) -> torch.Tensor:
    """The condition per request: text embeddings (R, D) from the model's own text encoder, or action ids (R,)."""
    if model.config.cond == "text":
        if any(r.text is None for r in requests):
            raise ValueError(f"{name} is conditioned on text: give prompts (--text or --prompts), not --action")
        t0 = time.perf_counter()
        cond = encoder.encode([r.text for r in requests]).to(dev)
        _sync(dev)
        timings["text_encoding"] = time.perf_counter() - t0
        return cond
    names = extra.get("action_names", [])
    unknown = sorted({r.action for r in requests if r.action not in names})
    if unknown:
        raise ValueError(f"unknown action(s) {unknown}; this model knows {names}")
    return torch.tensor([names.index(r.action) for r in requests], device=dev)


def draw_noise(seed: int, n: int, dim: int) -> tuple[torch.Tensor, torch.Generator]:
    """The starting noise (n, dim) of ``generate --seed SEED`` for n motions: the draw every runtime makes
    (:func:`lsgan.generation.draw_noise`, numpy's), as a CPU tensor; and a torch generator seeded with ``seed``, from
    which a diffusion's DDIM steps draw their own noise (eta > 0; only the torch runtime samples a diffusion)."""
    return torch.from_numpy(numpy_noise(seed, n, dim)), torch.Generator(device="cpu").manual_seed(seed)


def noise_dim(model, meta: dict) -> int:
    """The size of one motion's starting noise: the GAN's noise, or the diffusion's z_T."""
    return model.config.noise_dim if meta["kind"] == "gan" else model.config.latent_dim


def _latents(model, meta: dict, name, requests: list[Request], dev: torch.device, *, nums: list[int],
             noise: torch.Tensor, g: torch.Generator | None, encoder, batch_size: int, steps: int | None,
             guidance: float | None, eta: float | None, timings: dict[str, float]) -> tuple[torch.Tensor, dict, torch.Tensor]:
    """(latents (sum(nums), Z) in the VAE's latent space, on dev; the diffusion sampling options used, {} for a GAN;
    the condition of each motion).

    ``nums[i]`` motions for ``requests[i]``, started from the rows of ``noise`` in that order (drawn up front on the
    CPU, so latents depend neither on ``batch_size`` nor on the device's random generator).
    """
    extra = meta.get("extra", {})
    cond = _conditions(model, extra, name, requests, dev, encoder, timings)
    cond = cond.repeat_interleave(torch.tensor(nums, device=cond.device), dim=0)  # (sum(nums), ...)
    n = len(cond)
    noise = noise.to(dev)
    if meta["kind"] == "gan":
        sampling: dict = {}

        def latents(noise_b: torch.Tensor, cond_b: torch.Tensor) -> torch.Tensor:
            return model.generator(noise_b, cond_b)
    else:
        cfg = model.config
        sampling = {"steps": cfg.sample_steps if steps is None else steps,
                    "guidance": cfg.guidance_scale if guidance is None else guidance,
                    "eta": cfg.eta if eta is None else eta}
        if sampling["steps"] < 1:
            raise ValueError(f"steps must be >= 1, got {sampling['steps']}")

        def latents(noise_b: torch.Tensor, cond_b: torch.Tensor) -> torch.Tensor:
            return model.sample(cond_b, generator=g, noise=noise_b, **sampling)
    mean_z = torch.as_tensor(np.asarray(extra["latent_mean"], np.float32), device=dev)
    std_z = torch.as_tensor(np.asarray(extra["latent_std"], np.float32), device=dev)
    with torch.no_grad():
        t0 = time.perf_counter()
        z = torch.cat([latents(noise[b : b + batch_size], cond[b : b + batch_size]) for b in range(0, n, batch_size)])
        z = z * std_z + mean_z
        _sync(dev)
        timings["generator"] = time.perf_counter() - t0
    return z, sampling, cond


def run_models(loaded: Loaded, requests: list[Request], nums: list[int], noise: torch.Tensor, *,
               g: torch.Generator | None = None, batch_size: int = 256, steps: int | None = None,
               guidance: float | None = None, eta: float | None = None,
               threads: ThreadPolicy | None = None,
               constraints: list[Constraints] | None = None,
               control_settings: ControlSettings | None = None, close: bool = True) -> tuple[list[np.ndarray], dict, dict]:
    """Features (T, 263) of ``nums[i]`` motions per request, from ``noise`` (one row per motion, in order): the
    pass ``generate`` and ``lsgan serve`` share. Returns (features, timings in s, sampling options).

    ``threads``: a caller's long-lived policy (a server's: it measures the machine's load across passes), updated
    here; by default one made for this pass and undone after it. ``constraints``: one per motion
    (:mod:`lsgan.constraints`), approached by optimising the latents (:func:`steer`), then met exactly by closing
    the root onto them and warping whole poses in (docs/control.md; ``close=False``: the caller does that last part,
    :func:`lsgan.constraints.meet`).
    """
    timings = {"text_encoding": 0.0, "generator": 0.0, "vae_decoding": 0.0}
    dev = loaded.device
    own = threads is None
    policy = ThreadPolicy(large=min(batch_size, sum(nums)) >= LARGE_BATCH,
                          threads=None if dev.type == "cpu" else torch.get_num_threads()) if own else threads
    with policy if own else contextlib.nullcontext():
        if not own:
            policy.update()
        z, sampling, cond = _latents(loaded.model, loaded.meta, loaded.gan, requests, dev, nums=nums, noise=noise,
                                     g=g, encoder=loaded.encoder, batch_size=batch_size, steps=steps,
                                     guidance=guidance, eta=eta, timings=timings)
        frames = [r.frames for r, k in zip(requests, nums) for _ in range(k)]
        if constraints is not None:
            z = steer(loaded, z, noise, cond, constraints, control_settings or ControlSettings(), batch_size, timings)
        feats = _decode(loaded.decoder, loaded.vae_meta, z, frames, dev, batch_size, policy, timings)
        if constraints is not None and close:
            feats = [meet(f, c) for f, c in zip(feats, constraints)]
    return feats, timings, sampling


def check_constraints(vae_meta: dict, c: Constraints, request: Request) -> Constraints:
    """``c`` for ``request``, or an error saying why no motion of the VAE ``vae_meta`` decodes (its ``load_vae``
    meta) can meet it: another length, a root faster than its training data's, a pose of another skeleton."""
    if c.frames != request.frames:
        raise ValueError(f"the constraints are for {c.frames} frames, the motion has {request.frames}")
    check_reach(c, *model_reach(vae_meta["mean"], vae_meta["std"]))
    return c


def steer(loaded: Loaded, z: torch.Tensor, noise: torch.Tensor, cond: torch.Tensor, constraints: list[Constraints],
          settings: ControlSettings, batch_size: int, timings: dict[str, float]) -> torch.Tensor:
    """The latents (N, Z) moved to meet one constraint set per motion (:func:`lsgan.control.control`): a GAN's
    through its generator's noise (then the latent, if the settings ask); a diffusion's sampled latent directly,
    for as many steps (its DDIM chain is too long to differentiate through)."""
    from lsgan.control import control

    dev, extra, gan = loaded.device, loaded.meta["extra"], loaded.meta["kind"] == "gan"
    stats = {"latent_mean": torch.as_tensor(np.asarray(extra["latent_mean"], np.float32), device=dev),
             "latent_std": torch.as_tensor(np.asarray(extra["latent_std"], np.float32), device=dev),
             "feat_mean": torch.as_tensor(np.asarray(loaded.vae_meta["mean"], np.float32), device=dev),
             "feat_std": torch.as_tensor(np.asarray(loaded.vae_meta["std"], np.float32), device=dev)}
    if not gan:  # the noise steps become latent steps
        settings = dataclasses.replace(settings, noise_steps=0,
                                       latent_steps=settings.latent_steps or settings.noise_steps)
    t0 = time.perf_counter()
    out = []
    for b in range(0, len(z), batch_size):
        zb = (z[b : b + batch_size] - stats["latent_mean"]) / stats["latent_std"]
        cb = cond[b : b + batch_size]

        def propose(n: torch.Tensor, cb=cb, zb=zb) -> torch.Tensor:
            return loaded.model.generator(n, cb) if gan else zb

        zc, _ = control(propose, loaded.decoder, noise[b : b + batch_size].to(dev), constraints[b : b + batch_size],
                        settings=settings, frozen=(loaded.model,), **stats)
        out.append(zc)
    _sync(dev)
    timings["control"] = time.perf_counter() - t0
    return torch.cat(out)


def sample_latents(
    gen: str | os.PathLike,
    requests: list[Request],
    *,
    num: int = 1,
    seed: int = 0,
    device: str = "auto",
    text_encoder_path: str | None = None,
    batch_size: int = 256,
    steps: int | None = None,
    guidance: float | None = None,
    eta: float | None = None,
) -> np.ndarray:
    """The latents (len(requests)*num, Z), in the VAE's latent space, that ``generate`` decodes for these arguments."""
    from lsgan.device import pick_device

    dev = pick_device(device)
    model, meta = load_generator(gen, device=dev)
    encoder = text_encoder_for(model, meta.get("extra", {}), gen, dev, text_encoder_path)
    noise, g = draw_noise(seed, len(requests) * num, noise_dim(model, meta))
    z, _, _ = _latents(model, meta, gen, requests, dev, nums=[num] * len(requests), noise=noise, g=g,
                       encoder=encoder, batch_size=batch_size, steps=steps, guidance=guidance, eta=eta, timings={})
    return z.cpu().numpy()


def generate(
    gan: str | os.PathLike,
    vae: str | os.PathLike,
    requests: list[Request],
    *,
    num: int = 1,
    seed: int = 0,
    device: str = "auto",
    text_encoder_path: str | None = None,
    batch_size: int = 256,
    strict_pairing: bool = True,
    steps: int | None = None,
    guidance: float | None = None,
    eta: float | None = None,
    fix_feet: bool = False,
    constraints: Constraints | None = None,
    control_settings: ControlSettings | None = None,
    placement: Placement | None = None,
) -> Generation:
    """``num`` motions per request. Deterministic under ``seed`` (same inputs, same device -> same motions).
    ``fix_feet``: feet held still in contact, once, on the motion of record (:func:`decoded_motion`).

    ``gan``: a generator checkpoint, GAN or diffusion. ``steps`` (DDIM steps), ``guidance`` (classifier-free
    guidance scale) and ``eta`` are the diffusion's sampling options (default: its config's sample_steps,
    guidance_scale, eta); a GAN has none and ignores them, so one set of options can serve a comparison of
    both kinds (``Generation.sampling`` records what was used: {} for a GAN). With eta > 0 the noise of the
    DDIM steps is drawn batch by batch, so it depends on ``batch_size``; the starting noise never does.
    """
    loaded = load_models(gan, vae, device=device, text_encoder_path=text_encoder_path,
                         strict_pairing=strict_pairing)
    return generate_loaded(loaded, requests, num=num, seed=seed, batch_size=batch_size, steps=steps,
                           guidance=guidance, eta=eta, fix_feet=fix_feet, constraints=constraints,
                           control_settings=control_settings, placement=placement)


def generate_loaded(loaded: Loaded, requests: list[Request], *, num: int = 1, seed: int = 0, batch_size: int = 256,
                    steps: int | None = None, guidance: float | None = None, eta: float | None = None,
                    fix_feet: bool = False, constraints: Constraints | None = None,
                    control_settings: ControlSettings | None = None, placement: Placement | None = None) -> Generation:
    """:func:`generate` with the models already loaded (the same motions for the same arguments).

    ``constraints``: what every motion must do, in its own frame (:mod:`lsgan.constraints`); ``placement``: where
    the constrained motions then stand (a continuation's or in-between's: in the frame of the motions they join).
    """
    control_settings = control_settings or ControlSettings()
    check_prompts(requests)
    longest = max((r.frames for r in requests), default=0)
    if longest > loaded.max_frames:
        raise ValueError(f"{loaded.vae}: this VAE decodes at most {loaded.max_frames} frames (its max_len); "
                         f"asked for {longest}")
    if num < 1 or batch_size < 1 or not requests:
        raise ValueError(f"nothing to generate: {len(requests)} requests, num {num}, batch size {batch_size}")
    noise, g = draw_noise(seed, len(requests) * num, noise_dim(loaded.model, loaded.meta))
    each = None if constraints is None else [check_constraints(loaded.vae_meta, constraints, r) for r in requests for _ in
                                             range(num)]
    feats, timings, sampling = run_models(loaded, requests, [num] * len(requests), noise, g=g, batch_size=batch_size,
                                          steps=steps, guidance=guidance, eta=eta, constraints=each,
                                          control_settings=control_settings)
    motions = [decoded_motion(requests[k // num], k % num, f, fix_feet) for k, f in enumerate(feats)]
    if each is not None:
        place_measured(motions, each, placement)
    return Generation(motions=motions, timings_s=timings, gan=loaded.gan, vae=loaded.vae, seed=seed,
                      kind=loaded.meta["kind"], sampling=sampling, fix_feet=fix_feet,
                      control=None if constraints is None else {
                          **constraints.describe(control_settings),
                          **({"placement": placement.describe()} if placement is not None else {})})


def _decode(decoder, vmeta: dict, z: torch.Tensor, frames: list[int], dev: torch.device, batch_size: int,
            threads: ThreadPolicy, timings: dict[str, float]) -> list[np.ndarray]:
    """De-normalised features of each latent at its length, decoded in batches of similar length (on a CPU
    within :data:`~lsgan.generation.CPU_DECODE_FRAMES` padded frames a pass)."""
    feats: list[np.ndarray] = [None] * len(frames)  # type: ignore[list-item]
    budget = CPU_DECODE_FRAMES if dev.type == "cpu" else None
    with torch.no_grad():
        t0 = time.perf_counter()
        for idx in decode_batches(frames, batch_size, budget):
            threads.update()
            lengths = torch.tensor([frames[i] for i in idx], device=dev)
            mask = torch.arange(int(lengths.max()), device=dev)[None] < lengths[:, None]
            x = decoder.decode(z[idx], mask).float().cpu().numpy()
            for j, i in enumerate(idx):
                feats[i] = x[j, : frames[i]] * vmeta["std"] + vmeta["mean"]
        _sync(dev)
        timings["vae_decoding"] = time.perf_counter() - t0
    return feats
