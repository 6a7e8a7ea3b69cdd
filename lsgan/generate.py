"""``lsgan generate``: motion from sentences or action labels, one generator pass plus one decoder pass."""
from __future__ import annotations

import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from lsgan.data.features import recover_from_ric
from lsgan.data.skeleton import FPS


@dataclass
class Request:
    """One condition to generate for: a prompt or an action label, and a length in frames (20 fps)."""

    text: str | None = None
    action: str | None = None
    frames: int = 120


@dataclass
class Motion:
    request: Request
    sample: int
    features: np.ndarray  # (T, 263), de-normalised
    joints: np.ndarray  # (T, 22, 3)


@dataclass
class Generation:
    motions: list[Motion]
    timings_s: dict[str, float] = field(default_factory=dict)
    gan: str = ""
    vae: str = ""
    seed: int = 0

    @property
    def ms_per_motion(self) -> float:
        return 1000.0 * sum(self.timings_s.values()) / max(len(self.motions), 1)


def read_prompts(path: str | os.PathLike, default_frames: int) -> list[Request]:
    """One prompt per line, optionally ``prompt#frames``; blank lines and lines starting with '//' are skipped."""
    out = []
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if not line or line.startswith("//"):
            continue
        m = re.fullmatch(r"(.*)#\s*(\d+)\s*", line)
        out.append(Request(text=m.group(1).strip(), frames=int(m.group(2))) if m else Request(text=line, frames=default_frames))
    return out


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


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
) -> Generation:
    """``num`` motions per request. Deterministic under ``seed`` (same inputs, same device -> same motions)."""
    from lsgan.models.checkpoint import weights_hash
    from lsgan.models.gan import load_gan
    from lsgan.models.vae import load_vae
    from lsgan.train.common import pick_device

    dev = pick_device(device)
    model, gmeta = load_gan(gan, device=dev)
    decoder, vmeta = load_vae(vae, device=dev)
    extra = gmeta.get("extra", {})
    if strict_pairing and extra.get("vae_hash") and extra["vae_hash"] != weights_hash(vae):
        raise ValueError(
            f"{gan} was trained on latents of another VAE checkpoint than {vae}; "
            "use the VAE its cache was encoded with (its path is in the GAN's config.json)"
        )
    cond_kind = model.config.cond
    timings = {"text_encoding": 0.0, "generator": 0.0, "vae_decoding": 0.0}
    if cond_kind == "text":
        if any(r.text is None for r in requests):
            raise ValueError(f"{gan} is conditioned on text: give prompts (--text or --prompts), not --action")
        from lsgan.models.text import load_text_encoder

        enc_id = extra.get("text_encoder", "minilm")
        enc = load_text_encoder(enc_id.split(":")[0], path=text_encoder_path, device=dev)
        if enc.id != enc_id:
            raise ValueError(f"{gan} was trained with text encoder {enc_id!r}, but {enc.id!r} was loaded")
        t0 = time.perf_counter()
        cond = enc.encode([r.text for r in requests]).to(dev)
        _sync(dev)
        timings["text_encoding"] = time.perf_counter() - t0
    else:
        names = extra.get("action_names", [])
        unknown = sorted({r.action for r in requests if r.action not in names})
        if unknown:
            raise ValueError(f"unknown action(s) {unknown}; this model knows {names}")
        cond = torch.tensor([names.index(r.action) for r in requests], device=dev)

    mean_z = torch.as_tensor(np.asarray(extra["latent_mean"], np.float32), device=dev)
    std_z = torch.as_tensor(np.asarray(extra["latent_std"], np.float32), device=dev)
    cond = cond.repeat_interleave(num, dim=0)  # (R*num, ...)
    frames = [r.frames for r in requests for _ in range(num)]
    g = torch.Generator(device="cpu").manual_seed(seed)
    noise = torch.randn(len(frames), model.config.noise_dim, generator=g).to(dev)
    feats: list[np.ndarray] = [None] * len(frames)  # type: ignore[list-item]
    with torch.no_grad():
        t0 = time.perf_counter()
        z = torch.cat([model.generator(noise[b : b + batch_size], cond[b : b + batch_size])
                       for b in range(0, len(frames), batch_size)])
        z = z * std_z + mean_z
        _sync(dev)
        timings["generator"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        order = sorted(range(len(frames)), key=lambda i: frames[i])
        for b in range(0, len(order), batch_size):
            idx = order[b : b + batch_size]
            lengths = torch.tensor([frames[i] for i in idx], device=dev)
            mask = torch.arange(int(lengths.max()), device=dev)[None] < lengths[:, None]
            x = decoder.decode(z[idx], mask).float().cpu().numpy()
            for j, i in enumerate(idx):
                feats[i] = x[j, : frames[i]] * vmeta["std"] + vmeta["mean"]
        _sync(dev)
        timings["vae_decoding"] = time.perf_counter() - t0
    motions = [
        Motion(request=requests[k // num], sample=k % num, features=f.astype(np.float32),
               joints=recover_from_ric(f.astype(np.float32)))
        for k, f in enumerate(feats)
    ]
    return Generation(motions=motions, timings_s=timings, gan=str(gan), vae=str(vae), seed=seed)


def _slug(text: str, limit: int = 40) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:limit] or "motion"


def write_generation(result: Generation, out: str | os.PathLike) -> Path:
    """features ``.npy``, joints ``.npy`` (T,22,3) per motion and ``manifest.json``; returns the manifest path."""
    from lsgan.models.checkpoint import resolve, weights_hash

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for i, m in enumerate(result.motions):
        stem = f"{i:03d}_{_slug(m.request.text or m.request.action or 'motion')}"
        np.save(out / f"{stem}_features.npy", m.features)
        np.save(out / f"{stem}_joints.npy", m.joints)
        entries.append({
            "index": i, "text": m.request.text, "action": m.request.action, "frames": int(len(m.features)),
            "seconds": len(m.features) / FPS, "sample": m.sample, "features": f"{stem}_features.npy",
            "joints": f"{stem}_joints.npy",
        })
    manifest = {
        "seed": result.seed,
        "fps": FPS,
        "gan": {"path": str(resolve(result.gan)), "sha256": weights_hash(result.gan)},
        "vae": {"path": str(resolve(result.vae)), "sha256": weights_hash(result.vae)},
        "timings_s": result.timings_s,
        "ms_per_motion": result.ms_per_motion,
        "motions": entries,
    }
    path = out / "manifest.json"
    path.write_text(json.dumps(manifest, indent=1))
    return path
