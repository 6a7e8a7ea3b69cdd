"""Write clips in the original HumanML3D folder layout, so MLD, MDM, T2M-GPT and MoMask read them unchanged.

::

    OUT/new_joint_vecs/ID.npy   (T,263) float32     OUT/new_joints/ID.npy  (T,22,3) from recover_from_ric
    OUT/texts/ID.txt            caption#tokens#start#end per line
    OUT/Mean.npy, OUT/Std.npy   (263,)              OUT/{train,val,test,train_val,all}.txt
"""
from __future__ import annotations

import json
import os
from collections.abc import Iterable

import numpy as np

from lsgan.data.features import recover_from_ric
from lsgan.data.shards import ClipRecord, _Accumulator
from lsgan.data.tokens import tokenize
from lsgan import outputs
from lsgan.io import atomic_folder


def _fmt_time(t: float) -> str:
    """The shortest text whose ``float`` is ``t`` (NaN as 'nan'), so T2M's loaders read the tag back exactly."""
    return repr(float(t)) if t else "0.0"


def caption_line(text: str, tokens: str, start: float, end: float) -> str:
    """``caption#tokens#start#end``; captions without tokens are tagged here."""
    return f"{text}#{tokens or tokenize(text)}#{_fmt_time(start)}#{_fmt_time(end)}"


def write_humanml3d_folder(
    output: str | os.PathLike,
    clips: Iterable[ClipRecord],
    *,
    stats: tuple[np.ndarray, np.ndarray] | None = None,
    provenance: dict | None = None,
) -> dict:
    """Write the folder atomically: built beside ``output`` and renamed into place when complete."""
    with atomic_folder(output) as tmp:
        for sub in ("new_joint_vecs", "new_joints", "texts"):
            (tmp / sub).mkdir()
        acc = _Accumulator()
        splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
        n_clips = n_frames = n_caps = 0
        for clip in clips:
            x = np.asarray(clip.features, dtype=np.float32)
            np.save(tmp / "new_joint_vecs" / f"{clip.name}.npy", x)
            np.save(tmp / "new_joints" / f"{clip.name}.npy", recover_from_ric(x).astype(np.float32))
            lines = [caption_line(c.text, c.tokens, c.start, c.end) for c in clip.captions]
            (tmp / "texts" / f"{clip.name}.txt").write_text("\n".join(lines) + ("\n" if lines else ""), encoding="utf-8")
            splits.setdefault(clip.split, []).append(clip.name)
            if clip.split == "train" and stats is None:
                acc.add(x)
            n_clips += 1
            n_frames += len(x)
            n_caps += len(lines)
        mean, std = stats if stats is not None else acc.result()
        np.save(tmp / "Mean.npy", np.asarray(mean, np.float32))
        np.save(tmp / "Std.npy", np.asarray(std, np.float32))
        for split, names in splits.items():
            (tmp / f"{split}.txt").write_text("".join(f"{n}\n" for n in names))
        (tmp / "train_val.txt").write_text("".join(f"{n}\n" for n in splits["train"] + splits["val"]))
        (tmp / "all.txt").write_text("".join(f"{n}\n" for s in splits.values() for n in s))
        if provenance is not None:
            (tmp / "lsgan_provenance.json").write_text(json.dumps(provenance, indent=1, sort_keys=True))
        outputs.record_tree(tmp)  # each file is known as lsgan's, so a later --force can tell edits apart
    return {"clips": n_clips, "frames": n_frames, "captions": n_caps}
