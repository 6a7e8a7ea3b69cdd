"""Checkpoints as a folder: weights in safetensors, a JSON config, and (for resuming) the training state.

::

    run/last/model.safetensors   weights (never pickled)
    run/last/config.json         {"kind", "config", "step", "lsgan_version", "extra"}
    run/last/state.pt            optimiser/scheduler/RNG state, read with torch.load(weights_only=True)
                                 after lsgan.pickles has scanned its pickle for bounds
    run/best/...                 the same for the best checkpoint so far (by the run's validation metric)

Each folder is written beside its final place and renamed, so a crash never leaves half a checkpoint.
A file that holds anything but tensors and plain values, or is truncated or corrupt, raises a ValueError
naming it (never torch's suggestion to load it with ``weights_only=False``).
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from lsgan import __version__
from lsgan.errors import reading
from lsgan.faults import fault_point
from lsgan.io import atomic_folder
from lsgan.pickles import load_torch

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
        # one metadata entry: safetensors writes a mapping of several in a random order, so identical runs would
        # differ byte for byte
        tag = json.dumps({"kind": kind, "lsgan_version": __version__}, sort_keys=True)
        save_file(weights, tmp / WEIGHTS, metadata={"lsgan": tag})
        meta = {"kind": kind, "config": config, "step": int(step), "lsgan_version": __version__, "extra": extra or {}}
        (tmp / CONFIG).write_text(json.dumps(meta, indent=1, sort_keys=True))
        if state is not None:
            torch.save(state, tmp / STATE)
        fault_point("checkpoint.write")
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


def checkpoint_reader(load: Callable) -> Callable:
    """A ``load(path, ..., prefer=...)`` that builds a model from a checkpoint, its errors naming the checkpoint's
    config.json (a damaged one, or one of another lsgan version)."""

    @functools.wraps(load)
    def wrapper(path, *args, **kwargs):
        folder = resolve(path, kwargs.get("prefer", args[1] if len(args) > 1 else "best"))
        with reading(folder / CONFIG, "a checkpoint config this lsgan version reads"):
            return load(path, *args, **kwargs)

    return wrapper


def _read_config(folder: Path) -> dict:
    path = folder / CONFIG
    try:
        meta = json.loads(path.read_text())
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError
        raise ValueError(f"{path}: truncated or corrupt ({exc})") from exc
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: truncated or corrupt (a JSON {type(meta).__name__}, not an object)")
    return meta


def _read_weights(folder: Path) -> dict[str, torch.Tensor]:
    path = folder / WEIGHTS
    try:
        return load_file(path)
    except SafetensorError as exc:
        raise ValueError(f"{path}: truncated or corrupt ({exc})") from exc


def read_meta(path: str | os.PathLike, prefer: str = "best") -> dict:
    return _read_config(resolve(path, prefer))


def load_weights(path: str | os.PathLike, prefer: str = "best", kind: str | None = None) -> tuple[dict, dict]:
    """(state_dict, meta) of a checkpoint; ``kind`` checks what it holds (e.g. 'vae')."""
    folder = resolve(path, prefer)
    meta = _read_config(folder)
    if kind is not None and meta.get("kind") != kind:
        raise ValueError(f"{folder}: holds a {meta.get('kind')!r} checkpoint, not a {kind!r} one")
    return _read_weights(folder), meta


def load_torch_file(path: str | os.PathLike) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU, through :func:`lsgan.pickles.load_torch` (its pickles
    scanned for bounds first); a ValueError naming the file when it is refused or damaged."""
    return load_torch(path)


def load_state(path: str | os.PathLike, prefer: str = "last") -> dict | None:
    """The training state saved with a checkpoint (weights_only: no arbitrary code runs), or None."""
    folder = resolve(path, prefer)
    if not (folder / STATE).exists():
        return None
    return check_state(load_torch_file(folder / STATE), folder / STATE, _read_config(folder).get("kind"))


# The optimisers (by their key in state.pt) and batch position each trainer saves, beside step, best, val and rng.
STATE_KEYS = {"vae": ("optimizer", "epoch", "batches_done"), "evaluator": ("optimizer", "epoch", "batches_done"),
              "action-classifier": ("optimizer", "epoch", "batches_done"), "gan": ("opt_g", "opt_d"),
              "diffusion": ("opt",)}
_STATE_TYPES = {"step": int, "epoch": int, "batches_done": int, "threads": int, "best": (int, float), "val": dict,
                "rng": (list, torch.Tensor)}


def check_state(state: Any, path: str | os.PathLike, kind: str | None = None) -> dict:
    """``state`` if it is the training state lsgan saves for a ``kind`` checkpoint (today's layout or the one
    before the trainers shared a loop), else a ValueError naming ``path`` and what is missing or wrong, so that
    resuming never fails inside the trainer on a damaged or foreign state.pt."""
    def bad(problem: str) -> ValueError:
        return ValueError(f"{path}: not a training state lsgan wrote ({problem}): the run cannot be resumed from it")

    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        raise bad(f"it holds a {type(state).__name__}, not a dictionary of named entries")
    best = next((k for k in ("best", "best_val_mpjpe_m", "best_fid") if k in state), "best")
    wanted = [*STATE_KEYS[kind], "rng", best, *(() if best == "best_fid" else ("step",))] if kind in STATE_KEYS else []
    missing = [k for k in wanted if k not in state]
    if missing:
        raise bad(f"no {', '.join(repr(k) for k in missing)}")
    for key, value in state.items():
        expected = _STATE_TYPES.get(key)
        if expected is not None and (not isinstance(value, expected) or isinstance(value, bool)):
            raise bad(f"{key!r} is a {type(value).__name__}")
    for key in STATE_KEYS.get(kind, ()):
        opt = state[key]
        if key.startswith("opt") and not (isinstance(opt, dict) and isinstance(opt.get("state"), dict)
                                          and isinstance(opt.get("param_groups"), list)):
            raise bad(f"{key!r} is not an optimiser's state")
    rngs = state.get("rng")
    if isinstance(rngs, list) and not all(isinstance(r, dict) and isinstance(r.get("torch"), torch.Tensor)
                                          for r in rngs):
        raise bad("'rng' is not a list of random-generator states")
    return state


def weights_hash(path: str | os.PathLike, prefer: str = "best") -> str:
    """SHA-256 of the weights (names, dtypes, shapes, values): identifies a checkpoint in caches.

    Hashed from the tensors, not the file bytes: safetensors may order its JSON header differently
    from one save to the next.
    """
    h = hashlib.sha256()
    weights = _read_weights(resolve(path, prefer))
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
