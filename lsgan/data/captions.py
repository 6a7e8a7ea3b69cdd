"""Captions: T2M's rule for the frames a time-tagged caption covers, and template captions for labelled mocap.

**Time spans.** A HumanML3D caption line ends in two time tags, ``#start#end`` in seconds. T2M's loaders
(``data/dataset.py`` of EricGuo5513/text-to-motion, ``Text2MotionDataset`` and ``Text2MotionDatasetV2``; MLD
and MDM copy them) read each tag as ``float(text)``, count a NaN tag as 0.0, take ``0.0#0.0`` as the whole
clip and otherwise cut ``motion[int(start * 20):int(end * 20)]``. :func:`span_frames` is that rule; lsgan
keeps every tag as the float64 of its text (shards v2), so the frames are T2M's to the frame.

**Templates** (Bandai-Namco: content x style). Text-to-motion training wants varied sentences, so every
(content, style) pair gets several fixed paraphrases. They are deterministic (no sampling) so a rerun of
preprocessing gives the same shards. Sides are written as the words "left"/"right" so the mirrored copy
only needs a word swap.
"""
from __future__ import annotations

import math

from lsgan.data.skeleton import FPS


def span_frames(start: float, end: float, length: int) -> tuple[int, int] | None:
    """Frames ``(a, b)`` of a ``length``-frame clip that a caption tagged ``start``/``end`` covers; None: whole clip.

    T2M's rule (see the module docstring): ``start``/``end`` must be ``float`` of the tag's text (a float32
    rounding moves 38% of one-decimal tags by a frame). NaN counts as 0.0; ``(a, b)`` are the bounds of the
    Python slice ``[int(start * 20):int(end * 20)]`` of the clip (``b == a`` when it is empty). A tag ``int``
    cannot convert (infinite) gives an empty span: T2M skips such a caption.
    """
    s = 0.0 if math.isnan(start) else float(start)
    e = 0.0 if math.isnan(end) else float(end)
    if s == 0.0 and e == 0.0:
        return None
    if not (math.isfinite(s) and math.isfinite(e)):
        return 0, 0
    a, b, _ = slice(int(s * FPS), int(e * FPS)).indices(length)
    return a, max(a, b)

# content -> (present tense, present participle, main verb, trailing participle clause)
_CONTENT: dict[str, tuple[str, str, str, str]] = {
    "walk": ("walks forward", "walking forward", "walks", "moving straight ahead"),
    "walk-turn-left": (
        "walks forward and turns left", "walking and turning to the left", "walks", "turning to the left",
    ),
    "walk-turn-right": (
        "walks forward and turns right", "walking and turning to the right", "walks", "turning to the right",
    ),
    "run": ("runs forward", "running forward", "runs", "moving straight ahead"),
    "wave-both-hands": ("waves both hands", "waving both hands", "waves", "using both hands"),
    "wave-left-hand": ("waves the left hand", "waving the left hand", "waves", "using the left hand"),
    "wave-right-hand": ("waves the right hand", "waving the right hand", "waves", "using the right hand"),
    "raise-up-both-hands": (
        "raises both hands up", "raising both hands up", "lifts both arms", "raising the hands high",
    ),
    "raise-up-left-hand": (
        "raises the left hand up", "raising the left hand up", "lifts the left arm", "raising the left hand high",
    ),
    "raise-up-right-hand": (
        "raises the right hand up", "raising the right hand up", "lifts the right arm", "raising the right hand high",
    ),
}

# style -> (subject, manner, second manner)
_STYLE: dict[str, tuple[str, str, str]] = {
    "active": ("an energetic person", "in an active way", "full of energy"),
    "elderly": ("an elderly person", "in an elderly way", "like an old person"),
    "exhausted": ("an exhausted person", "in an exhausted way", "as if very tired"),
    "feminine": ("a feminine person", "in a feminine way", "with feminine mannerisms"),
    "masculine": ("a masculine person", "in a masculine way", "with masculine mannerisms"),
    "normal": ("a person", "in a normal way", "in an ordinary manner"),
    "youthful": ("a young person", "in a youthful way", "like a young person"),
}


def _content_phrases(content: str) -> tuple[str, str, str, str]:
    if content in _CONTENT:
        return _CONTENT[content]
    words = content.replace("-", " ").replace("_", " ").strip()
    return (f"performs {words}", f"performing {words}", "moves", f"performing {words}")


def _style_phrases(style: str) -> tuple[str, str, str]:
    if style in _STYLE:
        return _STYLE[style]
    words = style.replace("-", " ").replace("_", " ").strip()
    return ("a person", f"in a {words} way", f"in a {words} manner")


def bandai_captions(content: str, style: str) -> list[str]:
    """Four paraphrases describing ``content`` (e.g. 'walk-turn-left') done in ``style`` (e.g. 'elderly').

    Unknown labels fall back to their words ("performs x y in a z way") rather than failing.
    """
    present, participle, verb, clause = _content_phrases(content)
    subject, manner, manner2 = _style_phrases(style)
    return [
        f"{subject} {present}",
        f"someone {present} {manner}",
        f"a person is {participle} {manner2}",
        f"someone {verb} {manner}, {clause}",
    ]
