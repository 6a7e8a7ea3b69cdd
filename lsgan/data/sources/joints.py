"""A folder of (T,22,3) joint files at 20 fps: the original pipeline's intermediate ``joints/`` folder."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path


from lsgan.data.clip import ClipError, RawClip, load_npy
from lsgan.data.skeleton import NUM_JOINTS
from lsgan.data.sources.humanml3d import read_captions, read_split_files


@dataclass
class JointsSource:
    """``root`` holds ``*.npy`` joints (extra joints beyond 22 are dropped, as the original does).

    Captions come from ``texts/ID.txt`` (in ``root`` or ``texts``); splits from train/val/test.txt in
    ``root`` when present. The folder normally holds the mirrored 'M' files already, so ``mirror`` is off.
    """

    root: str
    texts: str | None = None
    mirror: bool = False
    name = "joints"

    def scan(self) -> list[str]:
        root = Path(self.root)
        if not root.is_dir():
            raise ClipError(f"{root}: not a folder of joint .npy files")
        return sorted(os.fspath(p) for p in root.glob("*.npy"))

    def inputs(self) -> list[str]:
        root = Path(self.root)
        return [os.fspath(root / f"{s}.txt") for s in ("train", "val", "test") if (root / f"{s}.txt").exists()]

    def item_files(self, item: str) -> list[str]:
        """The joints file and its caption file (when there is one): what a resume compares."""
        path = Path(item)
        text = (Path(self.texts) if self.texts else path.parent / "texts") / f"{path.stem}.txt"
        return [item] + ([os.fspath(text)] if text.is_file() else [])

    def load(self, item: str) -> list[RawClip]:
        path = Path(item)
        joints = load_npy(path)
        if joints.ndim == 2 and joints.shape[1] % 3 == 0:
            joints = joints.reshape(len(joints), -1, 3)
        if joints.ndim != 3 or joints.shape[2] != 3 or joints.shape[1] < NUM_JOINTS:
            raise ClipError(f"{path}: expected joints of shape (T, 22, 3), got {joints.shape}")
        texts = Path(self.texts) if self.texts else path.parent / "texts"
        name = path.stem
        return [
            RawClip(
                name=name,
                source_file=os.fspath(path),
                joints=joints[:, :NUM_JOINTS],
                captions=read_captions(texts / f"{name}.txt"),
                split=read_split_files(path.parent).get(name),
                mirror=self.mirror,
                mirror_of=name[1:] if name.startswith("M") and (path.parent / f"{name[1:]}.npy").exists() else None,
            )
        ]
