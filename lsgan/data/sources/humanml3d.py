"""A processed HumanML3D folder: features as they are, captions with time spans, official splits, own Mean/Std."""
from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from lsgan.data.clip import Caption, ClipError, RawClip, load_npy
from lsgan.data.skeleton import FEATURE_DIM
from lsgan.data.tokens import tokenize

SPLITS = ("train", "val", "test")


def parse_caption_line(line: str) -> Caption | None:
    """One line of a HumanML3D text file, ``caption#tokens#start#end``; plain text is a whole-clip caption.

    The tokens are kept as the line gives them (tagged by lsgan.data.tokens only when it has none); each
    time tag is ``float`` of its text, NaN included, as T2M's loaders read it (a missing or non-numeric
    tag counts as 0.0 here; T2M would skip the clip). :func:`lsgan.data.captions.span_frames` makes frames.
    """
    line = line.strip()
    if not line:
        return None
    parts = line.split("#")
    text = parts[0].strip()
    tokens = parts[1].strip() if len(parts) > 1 else ""
    try:
        start = float(parts[2]) if len(parts) > 2 and parts[2].strip() else 0.0
        end = float(parts[3]) if len(parts) > 3 and parts[3].strip() else 0.0
    except ValueError:
        start = end = 0.0
    return Caption(text=text, tokens=tokens or tokenize(text), start=start, end=end)


def read_captions(path: Path) -> list[Caption]:
    """All captions of a text file (missing file -> no captions)."""
    if not path.exists():
        return []
    with open(path, encoding="utf-8") as f:
        return [c for c in map(parse_caption_line, f) if c is not None and c.text]


def read_split_files(folder: Path) -> dict[str, str]:
    """Clip id -> split from ``train.txt``, ``val.txt``, ``test.txt`` in ``folder`` (those present).

    Cached per folder (a worker reads the files once); treat the returned dict as read-only.
    """
    return _split_table(os.fspath(folder))


@lru_cache(maxsize=8)
def _split_table(folder_name: str) -> dict[str, str]:
    folder = Path(folder_name)
    split_of: dict[str, str] = {}
    for split in SPLITS:
        path = folder / f"{split}.txt"
        if path.exists():
            for line in path.read_text(encoding="utf-8").split():
                split_of.setdefault(line.strip(), split)
    return split_of


@dataclass
class HumanML3DSource:
    """``root`` holds new_joint_vecs/, texts/, Mean.npy, Std.npy and the split files."""

    root: str
    name = "humanml3d"

    def _ids(self) -> list[str]:
        root = Path(self.root)
        if not (root / "new_joint_vecs").is_dir():
            raise ClipError(f"{root}: not a processed HumanML3D folder (no new_joint_vecs/ inside)")
        split_of = read_split_files(root)
        if split_of:
            return sorted(split_of)  # ids missing on disk are reported by load()
        all_txt = root / "all.txt"
        if all_txt.exists():
            return sorted(set(all_txt.read_text(encoding="utf-8").split()))
        return sorted(p.stem for p in (root / "new_joint_vecs").glob("*.npy"))

    def scan(self) -> list[str]:
        return self._ids()

    def inputs(self) -> list[str]:
        root = Path(self.root)
        names = [f"{s}.txt" for s in SPLITS] + ["all.txt", "Mean.npy", "Std.npy"]
        return [str(root / n) for n in names if (root / n).exists()]

    def stats(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The folder's own Mean/Std (kept as they are), or None when absent."""
        root = Path(self.root)
        if not ((root / "Mean.npy").exists() and (root / "Std.npy").exists()):
            return None
        return load_npy(str(root / "Mean.npy")).astype(np.float32), load_npy(str(root / "Std.npy")).astype(np.float32)

    def item_files(self, item: str) -> list[str]:
        """The clip's features and caption files (those that exist): what a resume compares."""
        root = Path(self.root)
        return [os.fspath(p) for p in (root / "new_joint_vecs" / f"{item}.npy", root / "texts" / f"{item}.txt")
                if p.is_file()]

    def load(self, item: str) -> list[RawClip]:
        root = Path(self.root)
        path = root / "new_joint_vecs" / f"{item}.npy"
        if not path.exists():
            raise ClipError(f"{path}: listed in the split files but missing on disk")
        feats = load_npy(path)
        if feats.ndim != 2 or feats.shape[1] != FEATURE_DIM:
            raise ClipError(f"{path}: expected features of shape (T, {FEATURE_DIM}), got {feats.shape}")
        split = read_split_files(root).get(item)
        return [
            RawClip(
                name=item,
                source_file=os.fspath(path),
                features=feats.astype(np.float32, copy=False),
                captions=read_captions(root / "texts" / f"{item}.txt"),
                split=split,
                mirror_of=item[1:] if item.startswith("M") else None,
            )
        ]
