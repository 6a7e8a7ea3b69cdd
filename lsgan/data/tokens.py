"""Word/POS tokens for captions in HumanML3D's ``word/POS`` form, without a language model.

The original dataset tagged its captions with spaCy; its loaders (and the T2M evaluator's word
vectoriser) need the tokens, so captions we make ourselves get them from this small rule-based
tagger. It knows the closed word classes and the motion vocabulary; other words default to NOUN,
or VERB/ADV by their endings. Good enough for templated captions; bring spaCy tags for free text.
"""
from __future__ import annotations

import re

_DET = {"a", "an", "the", "this", "that", "these", "those", "each", "every", "some", "another", "both", "all"}
_PRON = {"he", "she", "it", "they", "his", "her", "its", "their", "them", "him", "himself", "herself", "themselves",
         "someone", "somebody", "one", "who"}
_ADP = {"in", "on", "at", "to", "into", "onto", "from", "with", "over", "under", "above", "below", "across", "around",
        "through", "towards", "toward", "by", "of", "for", "along", "behind", "about", "after", "before", "up", "down",
        "out", "off", "while", "like", "than", "as"}
_AUX = {"is", "are", "was", "were", "be", "been", "being", "has", "have", "had", "does", "do", "did", "can", "will"}
_CCONJ = {"and", "or", "but", "then"}
_ADV = {"forward", "forwards", "backward", "backwards", "back", "slowly", "quickly", "fast", "again", "twice",
        "sideways", "away", "high", "low", "briefly", "repeatedly", "together", "once",
        "upward", "upwards", "downward", "downwards", "energetically", "calmly", "clockwise"}
_ADJ = {"left", "right", "both", "slow", "quick", "big", "small", "elderly", "old", "young", "active", "tired",
        "exhausted", "feminine", "masculine", "normal", "youthful", "energetic", "high", "low", "short", "long",
        "full", "large", "wide", "little", "few", "several", "other", "same"}
_VERB = {"walk", "run", "jog", "jump", "hop", "turn", "wave", "raise", "lift", "lower", "squat", "kick", "step",
         "move", "go", "stand", "sit", "bend", "stretch", "swing", "throw", "catch", "dance", "spin", "crouch", "rotate",
         "shuffle", "stride", "sprint", "reach", "put", "bring", "hold", "make", "take", "keep", "start", "stop",
         "stroll", "march", "leap", "bounce", "pivot", "greet", "signal", "wander", "strut", "trudge", "hurry", "dash"}
_BODY = {"hand", "hands", "arm", "arms", "leg", "legs", "foot", "feet", "head", "knee", "knees", "body", "shoulder",
         "shoulders", "hip", "hips", "elbow", "elbows", "wrist", "wrists", "waist", "torso"}
_WORD = re.compile(r"[A-Za-z]+(?:'[a-z]+)?|\d+(?:\.\d+)?")


def _verb_stem(word: str) -> str | None:
    for suffix, repl in (("ing", ""), ("ing", "e"), ("es", ""), ("s", ""), ("ed", ""), ("ed", "e"), ("ped", ""),
                         ("ning", ""), ("ping", ""), ("ps", "p")):
        if word.endswith(suffix):
            stem = word[: -len(suffix)] + repl
            if stem in _VERB:
                return stem
            if len(stem) > 2 and stem[-1] == stem[-2] and stem[:-1] in _VERB:
                return stem[:-1]
    return word if word in _VERB else None


def tag(word: str, previous: str | None = None) -> str:
    """The POS tag of one lower-case word (previous tag decides left/right as ADJ before a noun)."""
    if word.replace(".", "", 1).isdigit():
        return "NUM"
    for table, pos in ((_DET, "DET"), (_PRON, "PRON"), (_AUX, "AUX"), (_CCONJ, "CCONJ")):
        if word in table:
            return pos
    if word in _BODY:
        return "NOUN"
    if word in ("left", "right"):
        return "ADV" if previous in ("VERB", "ADP") else "ADJ"
    if word in _ADP:
        return "ADP"
    if _verb_stem(word) is not None:
        return "VERB"
    if word in _ADJ:
        return "ADJ"
    if word in _ADV or word.endswith("ly"):
        return "ADV"
    return "NOUN"


def tokenize(text: str) -> str:
    """``'a man waves his left hand'`` -> ``'a/DET man/NOUN wave/VERB his/PRON left/ADJ hand/NOUN'``.

    Verbs are lemmatised to their stem (as spaCy's lemmas in HumanML3D are); other words are lower-cased.
    """
    out: list[str] = []
    previous: str | None = None
    for m in _WORD.finditer(text.lower()):
        word = m.group(0)
        pos = tag(word, previous)
        lemma = _verb_stem(word) if pos == "VERB" else word
        out.append(f"{lemma or word}/{pos}")
        previous = pos
    return " ".join(out)
