"""Linear layers packed for oneDNN (lsgan.models.packed): the values of nn.Linear to float rounding, the same bits
on one thread and two, the plain product wherever the packed one would compute something else, and MiniLM packed."""
from __future__ import annotations

import pytest
import torch
from torch import nn

from lsgan.models.packed import PackedLinear, can_pack, pack_linears

pytestmark = pytest.mark.skipif(not can_pack(), reason="this torch build has no oneDNN packed linear ops")


def layer(k: int = 384, n: int = 1536) -> nn.Linear:
    torch.manual_seed(0)
    return nn.Linear(k, n).requires_grad_(False)


@pytest.fixture
def threads():
    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)


@pytest.mark.parametrize("rows", [1, 5, 10, 33, 112, 700])
def test_packed_gives_linears_values_and_the_same_bits_on_any_thread_count(rows: int, threads) -> None:
    plain = layer()
    packed = PackedLinear(plain)
    x = torch.randn(2, rows, 384, generator=torch.Generator().manual_seed(rows))
    with torch.no_grad():
        threads(1)
        one = packed(x)
        threads(2)
        two = packed(x)
        torch.testing.assert_close(one, plain(x), rtol=1e-5, atol=1e-5)
    assert torch.equal(one, two)


def test_plain_product_where_packing_would_change_the_computation() -> None:
    packed = PackedLinear(layer().requires_grad_(True))
    x = torch.randn(4, 384)
    assert packed(x).grad_fn is not None  # gradients wanted: the plain product, differentiable
    with torch.autocast("cpu", dtype=torch.bfloat16), torch.no_grad():
        assert packed(x).dtype == torch.bfloat16  # autocast still decides the precision


def test_weights_changed_in_place_are_packed_again() -> None:
    packed = PackedLinear(layer())
    x = torch.randn(3, 384)
    with torch.no_grad():
        before = packed(x)
        other = layer()
        other.weight.mul_(-2.0)
        packed.load_state_dict(other.state_dict())
        after = packed(x)
    torch.testing.assert_close(after, nn.functional.linear(x, other.weight, other.bias), rtol=1e-5, atol=1e-5)
    assert not torch.allclose(before, after)


def test_pack_linears_keeps_the_state_dict_and_the_outputs() -> None:
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(8, 16), nn.GELU(), nn.Sequential(nn.Linear(16, 4))).eval()
    keys = list(model.state_dict())
    x = torch.randn(5, 8)
    with torch.no_grad():
        expected = model(x)
        assert pack_linears(model) == 2
        got = model(x)
    assert list(model.state_dict()) == keys
    assert all(isinstance(m, PackedLinear) for m in (model[0], model[2][0]))
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)


def test_minilm_runs_packed() -> None:
    from lsgan.models.text import load_text_encoder

    enc = load_text_encoder("minilm")
    linears = [m for m in enc.model.modules() if isinstance(m, nn.Linear)]
    assert linears and all(isinstance(m, PackedLinear) for m in linears)
