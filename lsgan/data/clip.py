"""What every importer yields: a clip of 22 joints at 20 fps (or ready-made features), its captions and label."""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field, replace

import numpy as np

from lsgan.pickles import PickleReadError
from lsgan.pickles import load_npy as checked_npy


class ClipError(Exception):
    """A clip (or input file) that cannot be imported; the message says why. The pipeline skips and reports it."""


@dataclass(frozen=True)
class Caption:
    """One description of a clip. ``start``/``end`` are seconds; 0.0/0.0 means the whole clip."""

    text: str
    tokens: str = ""
    start: float = 0.0
    end: float = 0.0


@dataclass
class RawClip:
    """An imported clip before featurisation.

    ``joints`` is (T,22,3) in metres, Y up, SMPL joint order, 20 fps. ``features`` is set instead (T,263)
    when the source already holds HumanML3D features (a processed HumanML3D folder).
    ``mirror`` asks the pipeline to add the mirrored copy 'M'+name.
    """

    name: str
    source_file: str
    joints: np.ndarray | None = None
    features: np.ndarray | None = None
    captions: list[Caption] = field(default_factory=list)
    action: str | None = None
    split: str | None = None
    mirror: bool = False
    mirror_of: str | None = None


_SWAP = {"left": "right", "right": "left", "Left": "Right", "Right": "Left", "LEFT": "RIGHT", "RIGHT": "LEFT"}
_SIDE_WORD = re.compile(r"(?<![A-Za-z])(left|right|Left|Right|LEFT|RIGHT)(?![a-z])")


def swap_left_right(text: str) -> str:
    """Swap the words left and right (also inside 'walk-turn-left', 'left_hand'), keeping their case."""
    return _SIDE_WORD.sub(lambda m: _SWAP[m.group(1)], text)


def mirror_caption(caption: Caption) -> Caption:
    """The caption of the mirrored clip: left and right swapped in the text and in the tokens."""
    return replace(caption, text=swap_left_right(caption.text), tokens=swap_left_right(caption.tokens))


def load_npy(path: str | os.PathLike) -> np.ndarray:
    """A numeric ``.npy`` array, never unpickled; a clear ClipError for anything else or a truncated file."""
    try:
        with open(path, "rb") as f:
            if f.read(6) != b"\x93NUMPY":
                raise ClipError(f"{path}: not a .npy array file")
        array = checked_npy(path)  # its header checked against the file's size before numpy allocates
    except ClipError:
        raise
    except PickleReadError as e:
        raise ClipError(str(e)) from None
    except ValueError as e:
        raise ClipError(f"{path}: truncated or corrupt .npy file ({e})") from None
    except OSError as e:
        raise ClipError(f"{path}: cannot read ({e})") from None
    if array.dtype.kind not in "fiu":
        raise ClipError(f"{path}: holds {array.dtype} data, expected numbers")
    return array
