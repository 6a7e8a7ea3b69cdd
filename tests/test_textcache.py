"""lsgan.textcache.PromptCache, the prompt-embedding cache of both serving engines, with a real embedding
function (character counts, so every row can be checked) and real threads."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from lsgan.textcache import PromptCache


def expected(texts: list[str]) -> np.ndarray:
    """A deterministic embedding: the counts of 'a'..'e' in each text."""
    return np.array([[t.count(c) for c in "abcde"] for t in texts], np.float32)


class Counts:
    """:func:`expected`, recording what it was asked to embed."""

    def __init__(self) -> None:
        self.calls: list[list[str]] = []

    def __call__(self, texts: list[str]) -> np.ndarray:
        self.calls.append(list(texts))
        return expected(texts)


def test_rows_come_in_order_and_only_missing_prompts_are_embedded() -> None:
    cache, embed = PromptCache(4), Counts()
    texts = ["aa", "bb", "aa", "cc"]
    np.testing.assert_array_equal(np.stack(cache.rows(texts, embed)), expected(texts))
    assert embed.calls == [["aa", "bb", "cc"]] and (cache.hits, cache.misses) == (0, 3)
    texts = ["cc", "dd", "aa"]
    np.testing.assert_array_equal(np.stack(cache.rows(texts, embed)), expected(texts))
    assert embed.calls[-1] == ["dd"] and (cache.hits, cache.misses) == (2, 4)
    assert cache.rows([], embed) == [] and len(embed.calls) == 2


def test_the_least_recently_used_prompt_goes_first() -> None:
    cache, embed = PromptCache(2), Counts()
    cache.rows(["a", "b"], embed)
    cache.rows(["a"], embed)  # "b" is now the least recently used
    cache.rows(["c"], embed)  # drops "b"
    cache.rows(["a", "b"], embed)
    assert embed.calls == [["a", "b"], ["c"], ["b"]]


def test_a_wrong_number_of_rows_and_an_empty_cache_are_refused() -> None:
    with pytest.raises(ValueError, match="2 rows for 1 prompts"):
        PromptCache(2).rows(["a"], lambda missing: [np.zeros(5), np.zeros(5)])
    with pytest.raises(ValueError, match="at least 1 prompt"):
        PromptCache(0)


def test_threads_sharing_a_small_cache_get_their_own_rows() -> None:
    """Eight threads, 40 prompts, a cache of 5: prompts are dropped while others are being embedded."""
    cache, errors = PromptCache(5), []
    prompts = ["a" * i + "b" * (i % 7) + "e" * (i % 3) for i in range(40)]

    def work(k: int) -> None:
        rng = np.random.default_rng(k)
        for _ in range(200):
            texts = [prompts[i] for i in rng.integers(0, len(prompts), 3)]
            rows = np.stack(cache.rows(texts, expected))
            if not np.array_equal(rows, expected(texts)):
                errors.append(texts)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and cache.hits > 0 and len(cache._rows) <= 5
