"""Word/POS tokens for captions in HumanML3D's ``word/POS`` form, without a language model.

HumanML3D tagged its captions with spaCy (``process_text`` in legacy/text_process.py of EricGuo5513/HumanML3D:
hyphens removed, only alphabetic words kept, NOUN and VERB words replaced by their lemma except 'left');
its loaders and the T2M evaluator's word vectoriser read those tokens, and lsgan keeps them. Captions we
make ourselves (templates, synthetic data) are tagged once, at import, by this small rule-based tagger,
which follows the same rules and the dataset's tag choices (possessives as DET, 'something' as PRON). It
knows the closed word classes and the motion vocabulary; other words default to NOUN, or VERB/ADV by their
endings. Good enough for templated captions; bring spaCy tags for free text.
"""
from __future__ import annotations

import re

_DET = {"a", "an", "the", "this", "that", "these", "those", "each", "every", "some", "another", "both", "all",
        "his", "her", "its", "their", "my", "your", "our"}
_PRON = {"he", "she", "it", "they", "them", "him", "himself", "herself", "itself", "themselves", "i", "you", "we",
         "me", "us", "someone", "somebody", "something", "anyone", "anybody", "anything", "everyone", "everybody",
         "everything", "nobody", "nothing", "one", "who"}
_ADP = {"in", "on", "at", "to", "into", "onto", "from", "with", "over", "under", "above", "below", "across", "around",
        "through", "towards", "toward", "by", "of", "for", "along", "behind", "about", "after", "before", "up", "down",
        "out", "off", "while", "like", "than", "as"}
_AUX = {"is", "are", "was", "were", "be", "been", "being", "has", "have", "had", "does", "do", "did", "can", "will"}
_CCONJ = {"and", "or", "but", "then"}
_NUM = {"two", "three", "four", "five", "six", "seven", "eight", "nine", "ten"}
_ADV = {"forward", "forwards", "backward", "backwards", "back", "slowly", "quickly", "fast", "again", "twice",
        "sideways", "away", "high", "low", "briefly", "repeatedly", "together", "once", "always",
        "upward", "upwards", "downward", "downwards", "energetically", "calmly", "clockwise"}
_ADJ = {"left", "right", "both", "slow", "quick", "big", "small", "elderly", "old", "young", "active", "tired",
        "exhausted", "feminine", "masculine", "normal", "youthful", "energetic", "high", "low", "short", "long",
        "full", "large", "wide", "little", "few", "several", "other", "same", "original", "ordinary"}
_VERB = {"walk", "run", "jog", "jump", "hop", "turn", "wave", "raise", "lift", "lower", "squat", "kick", "step",
         "move", "go", "stand", "sit", "bend", "stretch", "swing", "throw", "catch", "dance", "spin", "crouch", "rotate",
         "shuffle", "stride", "sprint", "reach", "put", "bring", "hold", "make", "take", "keep", "start", "stop",
         "stroll", "march", "leap", "bounce", "pivot", "greet", "signal", "wander", "strut", "trudge", "hurry", "dash",
         "pick", "kneel", "wash", "rub", "balance", "flap", "lean", "spread", "climb", "stumble", "fly", "crawl",
         "clap", "punch", "push", "pull", "roll", "slide", "skip", "drink", "eat", "touch", "grab", "shake", "wipe",
         "place", "play", "look", "swim", "fall"}
_NOUN_LEMMA = {"feet": "foot", "teeth": "tooth", "men": "man", "women": "woman", "children": "child"}
_BODY = {"hand", "hands", "arm", "arms", "leg", "legs", "foot", "feet", "head", "knee", "knees", "body", "shoulder",
         "shoulders", "hip", "hips", "elbow", "elbows", "wrist", "wrists", "waist", "torso"}
_WORD = re.compile(r"[a-z]+(?:'[a-z]+)?")


def _verb_stem(word: str) -> str | None:
    for suffix, repl in (("ing", ""), ("ing", "e"), ("ies", "y"), ("es", ""), ("s", ""), ("ed", ""), ("ed", "e"),
                         ("ped", ""), ("ning", ""), ("ping", ""), ("ps", "p")):
        if word.endswith(suffix):
            stem = word[: -len(suffix)] + repl
            if stem in _VERB:
                return stem
            if len(stem) > 2 and stem[-1] == stem[-2] and stem[:-1] in _VERB:
                return stem[:-1]
    return word if word in _VERB else None


def tag(word: str, previous: str | None = None) -> str:
    """The POS tag of one lower-case word (previous tag decides left/right as ADJ before a noun)."""
    for table, pos in ((_DET, "DET"), (_PRON, "PRON"), (_AUX, "AUX"), (_CCONJ, "CCONJ"), (_NUM, "NUM")):
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
    if word in _ADV or word.endswith(("ly", "wards")):
        return "ADV"
    return "NOUN"


def _noun_lemma(word: str) -> str:
    """The singular of a plural noun (spaCy's lemma for the regular and the body-part plurals)."""
    if word in _NOUN_LEMMA:
        return _NOUN_LEMMA[word]
    if len(word) > 4 and word.endswith("ies"):
        return word[:-3] + "y"
    if word.endswith(("ches", "shes", "sses", "xes")):
        return word[:-2]
    if len(word) > 3 and word.endswith("s") and not word.endswith(("ss", "us", "is")):
        return word[:-1]
    return word


def tokenize(text: str) -> str:
    """``'a man waves his left hand'`` -> ``'a/DET man/NOUN wave/VERB his/DET left/ADJ hand/NOUN'``.

    As HumanML3D's tagging: lower-cased, hyphens removed ('full-body' is one word), words that are not
    alphabetic dropped (numbers; the clitic of "person's", "don't"), verbs and nouns lemmatised.
    """
    out: list[str] = []
    previous: str | None = None
    for m in _WORD.finditer(text.lower().replace("-", "")):
        word = m.group(0)
        word = word[:-3] if word.endswith("n't") else word.split("'")[0]
        if not word:
            continue
        pos = tag(word, previous)
        lemma = _verb_stem(word) if pos == "VERB" else _noun_lemma(word) if pos == "NOUN" else word
        out.append(f"{lemma or word}/{pos}")
        previous = pos
    return " ".join(out)
