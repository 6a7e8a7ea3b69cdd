"""Folders of a user's things for the hostile-tree tests: a working folder beside an 'outside' one holding the
targets of links and hard links, and snapshots that compare both byte for byte."""
from __future__ import annotations

import os
from pathlib import Path

from lsgan.outputs import REGISTRY


def work_and_outside(base: Path, work: str = "work") -> tuple[Path, Path]:
    """``base/work`` (empty) and ``base/outside`` with secret.txt (a link target) and linked.txt (hard-linked)."""
    inside, outside = base / work, base / "outside"
    inside.mkdir()
    outside.mkdir()
    (outside / "secret.txt").write_bytes(b"secret")
    (outside / "linked.txt").write_bytes(b"hard-linked")
    return inside, outside


def snapshot(root: Path) -> dict[str, tuple]:
    """Everything under ``root`` but lsgan's registries: its kind and bytes (a link by its target)."""
    snap = {}
    for p in sorted(root.rglob("*")):
        if p.name != REGISTRY:
            snap[str(p.relative_to(root))] = (("link", os.readlink(p)) if p.is_symlink() else ("dir",) if p.is_dir()
                                              else ("file", p.read_bytes()))
    return snap
