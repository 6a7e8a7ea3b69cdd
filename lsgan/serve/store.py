"""Generated motions kept for download: a bounded, thread-safe LRU in memory, keyed by unguessable ids."""
from __future__ import annotations

import re
import secrets
import threading
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

ID_PATTERN = re.compile(r"[0-9a-f]{32}")  # secrets.token_hex(16): 128 random bits


@dataclass
class Stored:
    joints: np.ndarray  # (T, 22, 3) float32, metres
    fps: float
    title: str  # the prompt or action, for file names
    files: dict[str, bytes] = field(default_factory=dict)  # exports made so far, by extension


class MotionStore:
    """At most ``size`` motions; adding one past that drops the least recently used."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._items: OrderedDict[str, Stored] = OrderedDict()
        self._lock = threading.Lock()

    def add(self, motion: Stored) -> str:
        key = secrets.token_hex(16)
        with self._lock:
            self._items[key] = motion
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return key

    def get(self, key: str) -> Stored | None:
        """The motion, marked as recently used; None for an id that is malformed, unknown or dropped."""
        if not ID_PATTERN.fullmatch(key):
            return None
        with self._lock:
            motion = self._items.get(key)
            if motion is not None:
                self._items.move_to_end(key)
            return motion

    def joints(self, key: str) -> np.ndarray | None:
        """A stored motion's joints (T, 22, 3), or None (:meth:`get`)."""
        motion = self.get(key)
        return None if motion is None else motion.joints

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)
