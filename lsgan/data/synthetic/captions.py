"""Templated captions: each family proposes groups of paraphrases (predicates) naming the same direction, side,
speed and repetitions as its motion; a clip's three captions come from different groups, each with a subject."""
from __future__ import annotations

import numpy as np

_SUBJECTS = (
    ("a person", "their"), ("someone", "their"), ("a man", "his"), ("the person", "their"),
    ("a woman", "her"), ("the man", "his"),
)
_TIMES = {1: "", 2: " twice", 3: " three times", 4: " four times"}
_NUMBER = {2: "two", 3: "three", 4: "four"}

Predicates = list[list[str]]  # groups of paraphrases; each caption comes from a different group


def _captions(rng: np.random.Generator, groups: Predicates, n: int = 3) -> list[str]:
    """n captions from distinct paraphrase groups, each with a subject; deterministic in ``rng``."""
    order = rng.permutation(len(groups))
    out = []
    for i in range(n):
        group = groups[order[i % len(groups)]]
        phrase = group[int(rng.integers(len(group)))]
        subject, pronoun = _SUBJECTS[int(rng.integers(len(_SUBJECTS)))]
        out.append(" ".join(f"{subject} {phrase.format(p=pronoun)}".split()))
    return out
