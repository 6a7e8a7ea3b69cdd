"""The built-in synthetic motions (:mod:`lsgan.data.synthetic`) as a source: no input files needed."""
from __future__ import annotations

from dataclasses import dataclass

from lsgan.data.clip import Caption, ClipError, RawClip
from lsgan.data.synthetic import clip_family, synthetic_clip
from lsgan.data.tokens import tokenize


@dataclass
class SyntheticSource:
    """``num_clips`` procedural clips; clip i depends only on (seed, i), so items load in any worker and order.

    Families are assigned round-robin (all of them by default). ``mirror`` is off by default because
    every sided family already comes in both sides.
    """

    num_clips: int = 400
    seed: int = 0
    families: tuple[str, ...] | None = None
    mirror: bool = False
    name = "synthetic"

    def __post_init__(self) -> None:
        if self.num_clips < 0 or self.seed < 0:
            raise ValueError(f"num_clips and seed must be non-negative, got {self.num_clips}, {self.seed}")
        if self.families is not None:
            self.families = tuple(self.families)
        clip_family(0, self.families)  # fails early on an unknown family

    def scan(self) -> list[str]:
        return [f"{i:06d}" for i in range(self.num_clips)]

    def inputs(self) -> list[str]:
        return []

    def load(self, item: str) -> list[RawClip]:
        if not (item.isdigit() and int(item) < self.num_clips):
            raise ClipError(f"{item!r}: not a synthetic clip index below {self.num_clips}")
        clip = synthetic_clip(int(item), self.seed, self.families)
        return [
            RawClip(
                name=clip.name,
                source_file="synthetic",
                joints=clip.joints,
                captions=[Caption(text=text, tokens=tokenize(text)) for text in clip.captions],
                action=clip.action,
                mirror=self.mirror,
            )
        ]
