"""Importers: each turns one kind of input into :class:`~lsgan.data.clip.RawClip` objects.

A source is a small picklable dataclass built from the command-line options. ``scan()`` lists its
work items (one input file each, in a deterministic order); ``load(item)`` does the heavy work for one
item in a worker process and returns its clips, raising :class:`~lsgan.data.clip.ClipError` for bad input.
"""
from __future__ import annotations

from typing import Protocol

from lsgan.data.clip import RawClip


class Source(Protocol):
    name: str

    def scan(self) -> list[str]:
        """Work items (usually input file paths), in a stable order."""

    def load(self, item: str) -> list[RawClip]:
        """The clips of one work item."""

    def inputs(self) -> list[str]:
        """Input files besides the items (split files, Mean/Std, index.csv) for provenance."""
