"""The latent cache: per clip the VAE posterior (mean, log-variance), per caption a text embedding.

The GAN trains from this file alone (it never runs the VAE). Layout (format ``lsgan-latent-cache`` v1)::

    /clips/name, /clips/split (N,) str      /clips/action (N,) int32 (-1 none)   /clips/length (N,) int32
    /latents/mu, /latents/logvar (N, Z) float32
    /captions/clip (M,) int32               /captions/text (M,) str
    /captions/embedding (M, D) float32      one row per caption, from the text encoder named in the attrs
    /stats/mean, /stats/std (Z,) float32    per-dimension statistics of the train clips' mu (GAN standardisation)

Root attributes: format, format_version, lsgan_version, vae_hash (SHA-256 of the VAE weights), vae_path,
text_encoder (its id, '' when none), text_dim, latent_dim, action_names (JSON), data (the shard paths),
window (how clips longer than the VAE's window were handled).
"""
from __future__ import annotations

import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from lsgan import __version__
from lsgan.io import atomic_path

FORMAT = "lsgan-latent-cache"
FORMAT_VERSION = 1
_STR = h5py.string_dtype("utf-8")


class StaleCache(ValueError):
    """The cache was made with another VAE checkpoint or text encoder than the one in use."""


@dataclass
class LatentCacheData:
    """Everything a cache holds, in memory."""

    names: list[str]
    splits: np.ndarray  # (N,) str
    actions: np.ndarray  # (N,) int32, -1 none
    lengths: np.ndarray  # (N,) int32
    mu: np.ndarray  # (N, Z)
    logvar: np.ndarray  # (N, Z)
    caption_clip: np.ndarray  # (M,) int32
    caption_text: list[str]
    caption_embedding: np.ndarray  # (M, D)
    mean: np.ndarray  # (Z,)
    std: np.ndarray  # (Z,)
    action_names: list[str]
    vae_hash: str
    text_encoder: str
    attrs: dict


def latent_stats(mu: np.ndarray, splits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-dimension mean and std of the train clips' latent means (all clips when no train split)."""
    train = mu[splits == "train"] if (splits == "train").any() else mu
    std = train.std(0)
    return train.mean(0).astype(np.float32), np.where(std > 1e-6, std, 1.0).astype(np.float32)


def write_latent_cache(
    path: str | os.PathLike,
    *,
    names: list[str],
    splits: np.ndarray | list[str],
    actions: np.ndarray,
    lengths: np.ndarray,
    mu: np.ndarray,
    logvar: np.ndarray,
    caption_clip: np.ndarray,
    caption_text: list[str],
    caption_embedding: np.ndarray,
    action_names: list[str],
    vae_hash: str,
    vae_path: str = "",
    text_encoder: str = "",
    data: list[str] | None = None,
    window: str = "",
) -> Path:
    """Write a cache atomically (temporary file beside it, then rename)."""
    path = Path(path)
    splits = np.asarray(splits)
    mu, logvar = np.asarray(mu, np.float32), np.asarray(logvar, np.float32)
    emb = np.asarray(caption_embedding, np.float32)
    emb = emb.reshape(len(caption_text), -1) if emb.size else np.zeros((len(caption_text), 0), np.float32)
    mean, std = latent_stats(mu, splits)
    fd, tmp = atomic_path(path)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as f:
            g = f.create_group("clips")
            g.create_dataset("name", data=np.array(names, dtype=object), dtype=_STR)
            g.create_dataset("split", data=np.array(splits.tolist(), dtype=object), dtype=_STR)
            g.create_dataset("action", data=np.asarray(actions, np.int32))
            g.create_dataset("length", data=np.asarray(lengths, np.int32))
            g = f.create_group("latents")
            g.create_dataset("mu", data=mu)
            g.create_dataset("logvar", data=logvar)
            g = f.create_group("captions")
            g.create_dataset("clip", data=np.asarray(caption_clip, np.int32))
            g.create_dataset("text", data=np.array(caption_text, dtype=object), dtype=_STR)
            g.create_dataset("embedding", data=emb)
            g = f.create_group("stats")
            g.create_dataset("mean", data=mean)
            g.create_dataset("std", data=std)
            f.attrs.update(
                format=FORMAT, format_version=FORMAT_VERSION, lsgan_version=__version__, vae_hash=vae_hash,
                vae_path=vae_path, text_encoder=text_encoder, text_dim=int(emb.shape[1]),
                latent_dim=int(mu.shape[1]), action_names=json.dumps(action_names),
                data=json.dumps(data or []), window=window,
            )
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def _strings(ds) -> list[str]:
    return [s.decode("utf-8") if isinstance(s, bytes) else s for s in ds[()]]


def read_cache_attrs(path: str | os.PathLike) -> dict:
    """The root attributes of a cache (cheap: no arrays are read)."""
    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != FORMAT:
            raise ValueError(f"{path}: not an lsgan latent cache (made by `lsgan encode-latents`)")
        return dict(f.attrs)


def read_latent_cache(
    path: str | os.PathLike, *, expect_vae_hash: str | None = None, expect_text_encoder: str | None = None
) -> LatentCacheData:
    """Load a cache; refuse it (StaleCache) when it was made with another VAE or text encoder than expected."""
    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"{path}: not a readable HDF5 file ({e})") from None
    with f:
        if f.attrs.get("format") != FORMAT:
            raise ValueError(f"{path}: not an lsgan latent cache (made by `lsgan encode-latents`)")
        attrs = dict(f.attrs)
        if expect_vae_hash is not None and attrs["vae_hash"] != expect_vae_hash:
            raise StaleCache(
                f"{path} was encoded with another VAE checkpoint (weights {attrs['vae_hash'][:12]}..., "
                f"given {expect_vae_hash[:12]}...); run `lsgan encode-latents` again with this VAE"
            )
        if expect_text_encoder is not None and attrs["text_encoder"] != expect_text_encoder:
            raise StaleCache(
                f"{path} holds embeddings of text encoder {attrs['text_encoder']!r}, not {expect_text_encoder!r}; "
                "run `lsgan encode-latents` again with the encoder you want"
            )
        return LatentCacheData(
            names=_strings(f["clips/name"]),
            splits=np.array(_strings(f["clips/split"])),
            actions=f["clips/action"][()],
            lengths=f["clips/length"][()],
            mu=f["latents/mu"][()],
            logvar=f["latents/logvar"][()],
            caption_clip=f["captions/clip"][()],
            caption_text=_strings(f["captions/text"]),
            caption_embedding=f["captions/embedding"][()],
            mean=f["stats/mean"][()],
            std=f["stats/std"][()],
            action_names=json.loads(attrs["action_names"]),
            vae_hash=str(attrs["vae_hash"]),
            text_encoder=str(attrs["text_encoder"]),
            attrs=attrs,
        )


WINDOW_POLICY = (
    "one entry per training window (as MotionDataset builds them: each captioned time span is its own "
    "window, whole-clip captions share the full clip); windows longer than max_frames are centre-cropped "
    "to max_frames; lengths are rounded down to a multiple of 4; windows shorter than min_frames are left out"
)


def encode_latents(
    data: str | os.PathLike | list[str | os.PathLike],
    vae: str | os.PathLike,
    out: str | os.PathLike,
    *,
    text_encoder: str | None = "minilm",
    text_encoder_path: str | None = None,
    min_frames: int = 40,
    max_frames: int = 196,
    batch_size: int = 64,
    device: str = "auto",
    progress: bool = True,
) -> Path:
    """Encode every window of every split once with the VAE (mean, log-variance) and every caption once
    with the text encoder, into a latent cache the GAN trains from (see :data:`WINDOW_POLICY`).

    ``text_encoder=None`` stores no caption embeddings (action-conditioned data).
    """
    import torch
    from tqdm import tqdm

    from lsgan.data.dataset import MotionDataset
    from lsgan.models.checkpoint import resolve, weights_hash
    from lsgan.models.vae import load_vae
    from lsgan.train.common import pick_device

    dev = pick_device(device)
    model, meta = load_vae(vae, device=dev)
    ds = MotionDataset(data, split=None, min_frames=min_frames, max_frames=max_frames, crop_long=True,
                       mean=meta["mean"], std=meta["std"])
    if len(ds) == 0:
        raise ValueError(f"{data}: no clip of {min_frames} frames or more to encode")
    spans = []
    for w in ds.windows:
        n = min(w.stop - w.start, max_frames)
        n = max(4, n // 4 * 4) if n >= 4 else n
        start = w.start + (w.stop - w.start - n) // 2
        spans.append((start, start + n))
    order = sorted(range(len(ds.windows)), key=lambda i: spans[i][1] - spans[i][0])
    mu = np.zeros((len(ds.windows), model.config.latent_dim), np.float32)
    logvar = np.zeros_like(mu)
    bar = tqdm(total=len(order), desc="encode latents", unit="window", disable=not progress or None, file=sys.stderr)
    with torch.no_grad():
        for b in range(0, len(order), batch_size):
            idx = order[b : b + batch_size]
            xs = []
            for i in idx:
                w = ds.windows[i]
                x = ds._shard(w.shard).features(w.clip, *spans[i])
                xs.append(torch.from_numpy((x - ds.mean) / ds.std))
            lengths = torch.tensor([len(x) for x in xs])
            batch = torch.nn.utils.rnn.pad_sequence(xs, batch_first=True).to(dev)
            mask = (torch.arange(batch.shape[1])[None] < lengths[:, None]).to(dev)
            m, lv = model.encode(batch, mask)
            mu[idx], logvar[idx] = m.float().cpu().numpy(), lv.float().cpu().numpy()
            bar.update(len(idx))
    bar.close()

    names, splits, actions, lengths = [], [], [], []
    cap_clip, cap_text = [], []
    for i, w in enumerate(ds.windows):
        name = ds.names[w.shard][w.clip]
        full = w.start == 0 and w.stop == ds._shard(w.shard).lengths[w.clip]
        names.append(name if full else f"{name}#{w.start}-{w.stop}")
        splits.append(ds._shard(w.shard).splits[w.clip])
        actions.append(int(ds.actions[w.shard][w.clip]))
        lengths.append(spans[i][1] - spans[i][0])
        for k in w.captions:
            cap_clip.append(i)
            cap_text.append(ds.captions[w.shard][w.clip][k].text)
    encoder_id, emb = "", np.zeros((len(cap_text), 0), np.float32)
    if text_encoder is not None and cap_text:
        from lsgan.models.text import load_text_encoder

        enc = load_text_encoder(text_encoder, path=text_encoder_path, device=dev)
        unique = sorted(set(cap_text))
        table = enc.encode(unique).float().cpu().numpy()
        row = {t: j for j, t in enumerate(unique)}
        emb = table[[row[t] for t in cap_text]]
        encoder_id = enc.id
    return write_latent_cache(
        out, names=names, splits=np.array(splits), actions=np.array(actions), lengths=np.array(lengths),
        mu=mu, logvar=logvar, caption_clip=np.array(cap_clip, dtype=np.int64), caption_text=cap_text,
        caption_embedding=emb, action_names=ds.action_names, vae_hash=weights_hash(vae),
        vae_path=str(resolve(vae)), text_encoder=encoder_id, data=[str(p) for p in ds.paths], window=WINDOW_POLICY,
    )
