"""BVH importer: any mocap in BVH (optionally gzip-compressed) through a joint-map preset or a user map.

Positions come from forward kinematics of the file's channels, are mapped to the 22 SMPL joints, scaled to
metres, turned Y-up and resampled to 20 fps. With the ``bandai`` preset each clip also gets its action label
(the content) and template captions from the dataset's labels; other presets leave captions empty.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar

import numpy as np

from lsgan.data.bvh import forward_kinematics, read_bvh
from lsgan.data.captions import bandai_captions
from lsgan.data.clip import Caption, ClipError, RawClip
from lsgan.data.joint_maps import JointMap, apply_joint_map, get_joint_map
from lsgan.data.resample import resample
from lsgan.data.skeleton import FPS
from lsgan.data.tokens import tokenize

_SUFFIXES = (".bvh.gz", ".bvh")
_BANDAI_PREFIX = re.compile(r"^dataset-\d+_")
_BANDAI_NAME = re.compile(r"^dataset-\d+_(?P<content>.+)_(?P<style>[^_]+)_(?P<take>\d+)$")
_LABEL_FILES = ("cfg/content_label.txt", "cfg/style_label.txt")


def clip_name(path: str | Path) -> str:
    """The file name without ``.bvh`` / ``.bvh.gz`` (any case)."""
    name = Path(path).name
    for suffix in _SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return Path(path).stem


def find_label_dir(start: str | Path) -> Path | None:
    """The nearest folder at or above ``start`` holding ``cfg/content_label.txt`` and ``cfg/style_label.txt``."""
    here = Path(start).resolve()
    for folder in (here, *here.parents):
        if all((folder / f).is_file() for f in _LABEL_FILES):
            return folder
    return None


def _read_labels(path: Path) -> list[str]:
    """Label names in id order, the 'dataset-2_' prefix stripped ('dataset-2_walk' -> 'walk')."""
    lines = [line.strip() for line in path.read_text().splitlines()]
    return [_BANDAI_PREFIX.sub("", line) for line in lines if line]


def bandai_labels(path: str | Path) -> tuple[str, str] | None:
    """(content, style) of a Bandai clip: from the ``.json`` beside it and ``cfg/*_label.txt`` above it,
    else parsed from the name ``dataset-2_{content}_{style}_{take}``; None when neither works."""
    path = Path(path)
    name = clip_name(path)
    label_file = path.with_name(name + ".json")
    label_dir = find_label_dir(path.parent)
    if label_file.is_file() and label_dir is not None:
        try:
            ids = json.loads(label_file.read_text())
            contents = _read_labels(label_dir / _LABEL_FILES[0])
            styles = _read_labels(label_dir / _LABEL_FILES[1])
            return contents[int(ids["content"])], styles[int(ids["style"])]
        except (OSError, ValueError, KeyError, IndexError, TypeError):
            pass
    match = _BANDAI_NAME.match(name)
    if match:
        return match["content"], match["style"]
    return None


@dataclass
class BvhSource:
    """BVH files under ``root`` (searched recursively for ``*.bvh`` and ``*.bvh.gz``), or one file.

    ``preset`` picks a joint map (``bandai``, ``cmu``); ``joint_map`` (a JSON file, see
    :mod:`lsgan.data.joint_maps`) overrides the map (the ``bandai`` preset still reads the labels).
    ``scale`` (metres per file unit) and ``fps`` override the map's and the file's values.
    ``mirror`` asks the pipeline for mirrored copies.
    """

    root: str
    preset: str = "bandai"
    joint_map: str | None = None
    scale: float | None = None
    fps: float | None = None
    mirror: bool = True
    name: ClassVar[str] = "bvh"

    def _map(self) -> JointMap:
        jmap = get_joint_map(self.preset, self.joint_map)
        return jmap if self.scale is None else replace(jmap, scale=float(self.scale))

    def scan(self) -> list[str]:
        self._map()  # a broken joint map stops the run here, once, instead of failing every clip
        root = Path(self.root)
        if root.is_file():
            return [str(root)]
        if not root.is_dir():
            raise ClipError(f"{root}: no such BVH file or folder")
        return sorted(str(p) for p in root.rglob("*") if p.name.lower().endswith(_SUFFIXES) and p.is_file())

    def inputs(self) -> list[str]:
        files = [str(self.joint_map)] if self.joint_map is not None else []
        if self.preset == "bandai":
            root = Path(self.root)
            label_dir = find_label_dir(root if root.is_dir() else root.parent)
            if label_dir is not None:
                files += [str(label_dir / f) for f in _LABEL_FILES]
        return files

    def load(self, item: str) -> list[RawClip]:
        jmap = self._map()
        bvh = read_bvh(item)
        joints = apply_joint_map(forward_kinematics(bvh), bvh.names, jmap, item)
        src_fps = self.fps or jmap.fps or bvh.fps
        try:
            joints = resample(joints, float(src_fps), float(FPS)).astype(np.float32)
        except ValueError as exc:
            raise ClipError(f"{item}: {exc}") from None
        captions: list[Caption] = []
        action = None
        if self.preset == "bandai":
            labels = bandai_labels(item)
            if labels is not None:
                action = labels[0]
                captions = [Caption(text=t, tokens=tokenize(t)) for t in bandai_captions(*labels)]
        return [
            RawClip(
                name=clip_name(item),
                source_file=item,
                joints=joints,
                captions=captions,
                action=action,
                mirror=self.mirror,
            )
        ]
