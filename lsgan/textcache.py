"""Prompt embeddings kept across calls: a server meets the same prompts again and again (a page's user tries seeds
and lengths for one sentence), and the text encoder is the largest part of a pass after the decoder.

One cache serves both runtimes: :class:`PromptCache` holds rows of any kind (torch tensors, numpy arrays) and asks
its caller to embed only what it lacks; :class:`CachedTextEncoder` wraps a torch text encoder with it.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any


class PromptCache:
    """The embeddings of the last ``size`` distinct prompts, least recently used dropped first; thread-safe.

    A row equals a fresh embedding up to the padding of the batch its prompt was first embedded in (the encoders
    mask padded tokens: rows agree within ~1e-6).
    """

    def __init__(self, size: int = 1024) -> None:
        if size < 1:
            raise ValueError(f"a prompt cache holds at least 1 prompt, not {size}")
        self.size = size
        self._rows: OrderedDict[str, Any] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def rows(self, texts: Sequence[str], embed: Callable[[list[str]], Sequence[Any]]) -> list[Any]:
        """One row per text, in order; ``embed(missing)`` (rows in the order given) runs once, on the distinct
        texts not held, outside the lock."""
        texts = list(texts)
        with self._lock:  # the rows held are taken now: another thread may drop them while ``embed`` runs
            found = {t: self._rows[t] for t in texts if t in self._rows}
            for t in found:
                self._rows.move_to_end(t)
            missing = list(dict.fromkeys(t for t in texts if t not in found))
            self.hits += sum(t in found for t in texts)
            self.misses += len(missing)
        fresh = list(embed(missing)) if missing else []
        if len(fresh) != len(missing):
            raise ValueError(f"the encoder gave {len(fresh)} rows for {len(missing)} prompts")
        found.update(zip(missing, fresh))
        with self._lock:
            for t in missing:
                self._rows[t] = found[t]
            while len(self._rows) > self.size:
                self._rows.popitem(last=False)
        return [found[t] for t in texts]


class CachedTextEncoder:
    """A torch text encoder whose ``encode(texts)`` embeds only the texts it has not seen among the last ``size``."""

    def __init__(self, encoder, size: int = 1024) -> None:
        self.encoder, self.cache = encoder, PromptCache(size)
        self.id, self.dim = encoder.id, encoder.dim

    def encode(self, texts, **kwargs):
        import torch

        rows = self.cache.rows(texts, lambda missing: self.encoder.encode(missing, **kwargs))
        return torch.stack(rows) if rows else torch.empty(0, self.dim)
