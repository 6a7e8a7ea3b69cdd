"""The latent cache: per clip the VAE posterior (mean, log-variance), per caption a text embedding.

The GAN trains from this file alone (it never runs the VAE). Layout (format ``lsgan-latent-cache`` v1)::

    /clips/name, /clips/split (N,) str      /clips/action (N,) int32 (-1 none)   /clips/length (N,) int32
    /latents/mu, /latents/logvar (N, Z) float32
    /captions/clip (M,) int32               /captions/text (M,) str
    /captions/embedding (M, D) float32      one row per caption, from the text encoder named in the attrs
    /stats/mean, /stats/std (Z,) float32    per-dimension statistics of the train clips' mu (GAN standardisation)

Root attributes: format, format_version, lsgan_version, vae_hash (SHA-256 of the VAE weights), vae_path
(the VAE checkpoint folder, absolute; as given on the command line in older caches), text_encoder (its id,
'' when none), text_dim, latent_dim, action_names (JSON), data (the shard paths), window (how clips longer
than the VAE's window were handled).

A cache that cannot be read or written raises DataFileError (a ValueError) starting with its path.
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
from lsgan.data.shards import (
    DataFileError,
    StringReader,
    check_layout,
    check_writable,
    hdf5_output,
    numbers,
    open_hdf5,
    reading,
)
from lsgan.faults import fault_point

FORMAT = "lsgan-latent-cache"
FORMAT_VERSION = 1
_STR = h5py.string_dtype("utf-8")
_CACHE = "an lsgan latent cache"
_HINT = "caches are made by `lsgan encode-latents`"
_DATASETS = ("clips/name", "clips/split", "clips/action", "clips/length", "latents/mu", "latents/logvar",
             "captions/clip", "captions/text", "captions/embedding", "stats/mean", "stats/std")
_ATTRS = ("format_version", "vae_hash", "text_encoder", "action_names")


class StaleCache(DataFileError):
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
    with hdf5_output(path) as f:
        g = f.create_group("clips")
        g.create_dataset("name", data=np.array(names, dtype=object), dtype=_STR)
        g.create_dataset("split", data=np.array(splits.tolist(), dtype=object), dtype=_STR)
        g.create_dataset("action", data=np.asarray(actions, np.int32))
        g.create_dataset("length", data=np.asarray(lengths, np.int32))
        g = f.create_group("latents")
        g.create_dataset("mu", data=mu)
        g.create_dataset("logvar", data=logvar)
        fault_point("cache.write")
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
    return path


def read_cache_attrs(path: str | os.PathLike) -> dict:
    """The root attributes of a cache (cheap: no arrays are read)."""
    with open_hdf5(path) as f, reading(path, _CACHE):
        check_layout(f, path, _CACHE, FORMAT, FORMAT_VERSION, _DATASETS, _ATTRS, _HINT)
        return StringReader(f, path).attributes(f)


def read_latent_cache(
    path: str | os.PathLike, *, expect_vae_hash: str | None = None, expect_text_encoder: str | None = None
) -> LatentCacheData:
    """Load a cache; refuse it (StaleCache) when it was made with another VAE or text encoder than expected."""
    path = Path(path)
    with open_hdf5(path) as f, reading(path, _CACHE):
        check_layout(f, path, _CACHE, FORMAT, FORMAT_VERSION, _DATASETS, _ATTRS, _HINT)
        strings = StringReader(f, path)
        attrs = strings.attributes(f)
        problem = _cache_problem(f, attrs)
        if problem is not None:
            raise DataFileError(f"{path}: {problem}")
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
            names=strings("clips/name"),
            splits=np.array(strings("clips/split")),
            actions=numbers(f["clips/action"]),
            lengths=numbers(f["clips/length"]),
            mu=numbers(f["latents/mu"]),
            logvar=numbers(f["latents/logvar"]),
            caption_clip=numbers(f["captions/clip"]),
            caption_text=strings("captions/text"),
            caption_embedding=numbers(f["captions/embedding"]),
            mean=numbers(f["stats/mean"]),
            std=numbers(f["stats/std"]),
            action_names=json.loads(attrs["action_names"]),
            vae_hash=str(attrs["vae_hash"]),
            text_encoder=str(attrs["text_encoder"]),
            attrs=attrs,
        )


def _cache_problem(f: h5py.File, attrs: dict) -> str | None:
    """What is wrong with a cache's tables, in words; None if nothing: one row per window in every clip column and
    latent, latent and text widths as the attributes say, positive lengths, actions and caption clips that exist."""
    n, m = f["clips/name"].shape[0], f["captions/clip"].shape[0]
    z = int(attrs.get("latent_dim", f["latents/mu"].shape[-1]))
    d = int(attrs.get("text_dim", f["captions/embedding"].shape[-1]))
    want = {"clips/split": (n,), "clips/action": (n,), "clips/length": (n,), "latents/mu": (n, z),
            "latents/logvar": (n, z), "captions/text": (m,), "captions/embedding": (m, d), "stats/mean": (z,),
            "stats/std": (z,)}
    for name, shape in want.items():
        if f[name].shape != shape:
            return f"{name} has shape {f[name].shape}, expected {shape} ({n} windows, {m} captions, latent width " \
                   f"{z}, text width {d})"
    lengths, actions, clip = (numbers(f[name]) for name in ("clips/length", "clips/action", "captions/clip"))
    num_actions = len(json.loads(attrs["action_names"]))
    if any(a.dtype.kind not in "iu" for a in (lengths, actions, clip)):
        return "clips/length, clips/action and captions/clip must hold integers"
    checks = ((lengths < 1, "window {i} has length {v}, not a positive frame count", lengths),
              ((actions < -1) | (actions >= num_actions), f"window {{i}} has action {{v}}, not an index into the "
                                                           f"{num_actions} action names", actions),
              ((clip < 0) | (clip >= n), f"caption {{i}} belongs to window {{v}}, outside the {n} windows", clip))
    for bad, text, values in checks:
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            return text.format(i=i, v=int(values[i]))
    return None


def _recorded_vae(cache: Path, recorded: str) -> Path | None:
    """The checkpoint folder at the path the cache records (a relative one, from older caches, against the
    cache's folder, then the working directory), or None."""
    from lsgan.models.checkpoint import resolve

    if not recorded:
        return None
    p = Path(recorded)
    for candidate in [p] if p.is_absolute() else [cache.resolve().parent / p, p]:
        try:
            return resolve(candidate)
        except FileNotFoundError:
            continue
    return None


def check_cache_vae(cache: str | os.PathLike, vae: str | os.PathLike | None = None,
                    allow_stale: bool = False) -> str | None:
    """Check that ``cache`` was encoded with the VAE ``vae`` (a run or checkpoint folder), else with the VAE
    at the path the cache records; returns the VAE hash to expect when reading it (None with ``allow_stale``).

    Raises StaleCache when the weights differ, DataFileError when the recorded VAE is not found.
    """
    from lsgan.models.checkpoint import resolve, weights_hash

    if allow_stale:
        return None
    cache = Path(cache)
    attrs = read_cache_attrs(cache)
    recorded, expected = str(attrs.get("vae_path", "")), str(attrs["vae_hash"])
    if vae is not None:
        folder = resolve(vae, Path(recorded).name if Path(recorded).name in ("best", "last") else "best")
    else:
        folder = _recorded_vae(cache, recorded)
        if folder is None:
            missing = f"{recorded} not found (moved?)" if recorded else "it records no VAE path"
            raise DataFileError(f"{cache}: cannot check that the cache matches its VAE: {missing}; "
                                "pass --vae RUN (or --allow-stale)")
    actual = weights_hash(folder)
    if actual != expected:
        raise StaleCache(f"{cache} was encoded with another VAE than {folder}: the cache's VAE weights have sha256 "
                         f"{expected}, these {actual}; run `lsgan encode-latents` again with this VAE "
                         "(or pass --allow-stale)")
    return expected


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
    force: bool = False,
) -> Path:
    """Encode every window of every split once with the VAE (mean, log-variance) and every caption once
    with the text encoder, into a latent cache the GAN trains from (see :data:`WINDOW_POLICY`).

    ``text_encoder=None`` stores no caption embeddings (action-conditioned data). An existing ``out`` is
    refused unless ``force`` (and then only replaced when lsgan wrote it).
    """
    from lsgan import outputs
    from lsgan.data.dataset import MotionDataset
    from lsgan.models.checkpoint import resolve, weights_hash
    from lsgan.models.vae import load_vae
    from lsgan.device import pick_device

    sources = [data] if isinstance(data, (str, os.PathLike)) else list(data)
    outputs.claim_file(out, force=force, inputs=[*sources, vae])
    check_writable(out)
    dev = pick_device(device)
    model, meta = load_vae(vae, device=dev)
    ds = MotionDataset(data, split=None, min_frames=min_frames, max_frames=max_frames, crop_long=True,
                       mean=meta["mean"], std=meta["std"])
    if len(ds) == 0:
        raise ValueError(f"{data}: no clip of {min_frames} frames or more to encode")
    spans = _window_spans(ds, max_frames)
    mu, logvar = _encode_windows(model, ds, spans, batch_size, dev, progress)
    names, splits, actions, cap_clip, cap_text = [], [], [], [], []
    for i, w in enumerate(ds.windows):
        name = ds.names[w.shard][w.clip]
        full = w.start == 0 and w.stop == ds._shard(w.shard).lengths[w.clip]
        names.append(name if full else f"{name}#{w.start}-{w.stop}")
        splits.append(ds._shard(w.shard).splits[w.clip])
        actions.append(int(ds.actions[w.shard][w.clip]))
        for k in w.captions:
            cap_clip.append(i)
            cap_text.append(ds.captions[w.shard][w.clip][k].text)
    encoder_id, emb = _embed_captions(cap_text, text_encoder, text_encoder_path, dev)
    return write_latent_cache(
        out, names=names, splits=np.array(splits), actions=np.array(actions),
        lengths=np.array([b - a for a, b in spans]), mu=mu, logvar=logvar,
        caption_clip=np.array(cap_clip, dtype=np.int64), caption_text=cap_text, caption_embedding=emb,
        action_names=ds.action_names, vae_hash=weights_hash(vae), vae_path=str(resolve(vae).resolve()),
        text_encoder=encoder_id, data=[str(p) for p in ds.paths], window=WINDOW_POLICY,
    )


def _window_spans(ds, max_frames: int) -> list[tuple[int, int]]:
    """Each window centre-cropped to ``max_frames`` and rounded down to a multiple of 4 frames."""
    spans = []
    for w in ds.windows:
        n = min(w.stop - w.start, max_frames)
        n = max(4, n // 4 * 4) if n >= 4 else n
        start = w.start + (w.stop - w.start - n) // 2
        spans.append((start, start + n))
    return spans


def _encode_windows(model, ds, spans, batch_size: int, dev, progress: bool) -> tuple[np.ndarray, np.ndarray]:
    """(mu, logvar) of every window, in batches of similar length."""
    import torch
    from tqdm import tqdm

    from lsgan.threads import ThreadPolicy

    order = sorted(range(len(spans)), key=lambda i: spans[i][1] - spans[i][0])
    mu = np.zeros((len(spans), model.config.latent_dim), np.float32)
    logvar = np.zeros_like(mu)
    bar = tqdm(total=len(order), desc="encode latents", unit="window", disable=not progress or None, file=sys.stderr)
    cpu_threads = None if torch.device(dev).type == "cpu" else torch.get_num_threads()
    with torch.no_grad(), ThreadPolicy(tune=True, threads=cpu_threads) as threads:
        for b in range(0, len(order), batch_size):
            threads.update()
            idx = order[b : b + batch_size]
            xs = [torch.from_numpy((ds._shard(ds.windows[i].shard).features(ds.windows[i].clip, *spans[i])
                                    - ds.mean) / ds.std) for i in idx]
            lengths = torch.tensor([len(x) for x in xs])
            batch = torch.nn.utils.rnn.pad_sequence(xs, batch_first=True).to(dev)
            mask = (torch.arange(batch.shape[1])[None] < lengths[:, None]).to(dev)
            m, lv = model.encode(batch, mask)
            mu[idx], logvar[idx] = m.float().cpu().numpy(), lv.float().cpu().numpy()
            bar.update(len(idx))
            fault_point("encode.batch")
    bar.close()
    return mu, logvar


def _embed_captions(texts: list[str], text_encoder: str | None, path: str | None, dev) -> tuple[str, np.ndarray]:
    """(encoder id, one embedding row per caption); each distinct text is encoded once."""
    if text_encoder is None or not texts:
        return "", np.zeros((len(texts), 0), np.float32)
    from lsgan.models.text import load_text_encoder

    enc = load_text_encoder(text_encoder, path=path, device=dev)
    unique = sorted(set(texts))
    table = enc.encode(unique).float().cpu().numpy()
    row = {t: j for j, t in enumerate(unique)}
    return enc.id, table[[row[t] for t in texts]]
