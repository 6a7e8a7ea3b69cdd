"""Checkpoints as a folder: weights in safetensors, a JSON config, and (for resuming) the training state.

::

    run/last/model.safetensors   weights (never pickled)
    run/last/config.json         {"kind", "config", "step", "lsgan_version", "extra"}
    run/last/state.pt            optimiser/scheduler/RNG state, read with torch.load(weights_only=True)
    run/best/...                 the same for the best checkpoint so far (by the run's validation metric)

Each folder is written beside its final place and renamed, so a crash never leaves half a checkpoint.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from lsgan import __version__
from lsgan.io import atomic_folder

WEIGHTS, CONFIG, STATE = "model.safetensors", "config.json", "state.pt"


def save_checkpoint(
    folder: str | os.PathLike,
    *,
    model: torch.nn.Module,
    kind: str,
    config: dict,
    step: int,
    extra: dict | None = None,
    state: dict | None = None,
) -> Path:
    """Write ``folder`` atomically. ``state`` (optional) holds tensors/plain values for resuming."""
    with atomic_folder(folder) as tmp:
        weights = {k: v.detach().contiguous().cpu() for k, v in unwrap(model).state_dict().items()}
        save_file(weights, tmp / WEIGHTS, metadata={"kind": kind, "lsgan_version": __version__})
        meta = {"kind": kind, "config": config, "step": int(step), "lsgan_version": __version__, "extra": extra or {}}
        (tmp / CONFIG).write_text(json.dumps(meta, indent=1, sort_keys=True))
        if state is not None:
            torch.save(state, tmp / STATE)
    return Path(folder)


def resolve(path: str | os.PathLike, prefer: str = "best") -> Path:
    """A checkpoint folder from a run folder (its ``best/`` or ``last/``) or a checkpoint folder itself."""
    path = Path(path)
    if (path / CONFIG).exists():
        return path
    order = (prefer, "last" if prefer == "best" else "best")
    for sub in order:
        if (path / sub / CONFIG).exists():
            return path / sub
    raise FileNotFoundError(f"{path}: no checkpoint here (expected {CONFIG} and {WEIGHTS}, or best/ or last/ holding them)")


def read_meta(path: str | os.PathLike, prefer: str = "best") -> dict:
    folder = resolve(path, prefer)
    return json.loads((folder / CONFIG).read_text())


def load_weights(path: str | os.PathLike, prefer: str = "best", kind: str | None = None) -> tuple[dict, dict]:
    """(state_dict, meta) of a checkpoint; ``kind`` checks what it holds (e.g. 'vae')."""
    folder = resolve(path, prefer)
    meta = json.loads((folder / CONFIG).read_text())
    if kind is not None and meta.get("kind") != kind:
        raise ValueError(f"{folder}: holds a {meta.get('kind')!r} checkpoint, not a {kind!r} one")
    return load_file(folder / WEIGHTS), meta


def load_state(path: str | os.PathLike, prefer: str = "last") -> dict | None:
    """The training state saved with a checkpoint (weights_only: no arbitrary code runs), or None."""
    folder = resolve(path, prefer)
    if not (folder / STATE).exists():
        return None
    return torch.load(folder / STATE, map_location="cpu", weights_only=True)


def weights_hash(path: str | os.PathLike, prefer: str = "best") -> str:
    """SHA-256 of the weights (names, dtypes, shapes, values): identifies a checkpoint in caches.

    Hashed from the tensors, not the file bytes: safetensors may order its JSON header differently
    from one save to the next.
    """
    h = hashlib.sha256()
    weights = load_file(resolve(path, prefer) / WEIGHTS)
    for name in sorted(weights):
        t = weights[name].contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def unwrap(model: torch.nn.Module) -> torch.nn.Module:
    """The module inside DistributedDataParallel / torch.compile wrappers."""
    while hasattr(model, "module") or hasattr(model, "_orig_mod"):
        model = getattr(model, "module", None) or getattr(model, "_orig_mod")
    return model
