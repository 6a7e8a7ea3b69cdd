"""The server's joints-to-JSON writer (lsgan.serve.jsonfmt): valid JSON with every coordinate rounded, and the same
bytes from the lookup table as from the digit-by-digit writer."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from lsgan.serve import jsonfmt


def awkward(n: int, scale: float, seed: int = 0) -> np.ndarray:
    """``n`` float32 values around ``scale`` with the cases that trip a number writer mixed in."""
    rng = np.random.default_rng(seed)
    v = (rng.standard_normal(n) * scale).astype(np.float32)
    v[:12] = [0.0, -0.0, 4e-5, -4e-5, 5e-5, -6e-5, 9.99994, -9.99994, 9.99996, -9.99996, 1.0, -1.0]
    return v


@pytest.mark.parametrize("scale", [0.7, 3.0, 40.0], ids=["near the start", "up to 10 m", "past 10 m"])
@pytest.mark.parametrize("decimals", [2, 4])
def test_joints_json_is_json_of_the_rounded_coordinates(scale: float, decimals: int) -> None:
    joints = awkward(120 * 22 * 3, scale).reshape(120, 22, 3)
    text = jsonfmt.joints_json(joints, decimals)
    parsed = np.array(json.loads(text))
    assert parsed.shape == (120, 22, 3)
    expected = np.rint(joints.astype(np.float64) * 10**decimals) / 10**decimals
    assert np.abs(parsed - expected).max() < 1e-9
    assert not re.search(rb"-0\.0{%d}[,\]]" % decimals, text)  # a value that rounds to zero has no sign


@pytest.mark.parametrize("decimals", [1, 2, 4])
def test_table_gives_the_digit_writers_bytes(decimals: int) -> None:
    values = awkward(5000, 3.0, seed=decimals)
    values = values[np.abs(values) < 9.99]  # all of them under 10 m: the table's case
    assert np.array_equal(jsonfmt._numbers_fast(values, decimals), jsonfmt._numbers(values, decimals))


def test_one_value_past_the_table_sends_all_to_the_digit_writer() -> None:
    values = awkward(300, 1.0)
    values[7] = -123.45678
    fast = jsonfmt._numbers_fast(values, 4)
    assert fast.shape[1] == 1 + 3 + 1 + 4  # three integer digits for every number
    assert np.array_equal(fast, jsonfmt._numbers(values, 4))


def test_empty_and_non_finite_joints() -> None:
    assert jsonfmt.joints_json(np.zeros((0, 22, 3), np.float32)) == b"[]"
    bad = np.zeros((2, 22, 3), np.float32)
    bad[1, 3, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        jsonfmt.joints_json(bad)
