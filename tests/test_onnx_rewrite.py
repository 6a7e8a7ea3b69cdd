"""What the exporter writes so that onnxruntime runs it fast: GELUs in the order its optimiser fuses
(lsgan.deploy.rewrite) and attention with the keys transposed in one step (lsgan.models.attention), each with the
same values as before."""
from __future__ import annotations

import numpy as np
import onnx
import onnx_ir as ir
import onnxruntime as ort
import pytest
import torch
from onnx import TensorProto, helper

from lsgan.deploy.onnx_export import export_graph
from lsgan.deploy.rewrite import gelu_in_fusable_order
from lsgan.models.attention import attend

X = np.random.default_rng(0).standard_normal((4, 37), dtype=np.float32) * 3


def torch_gelu_graph(half: float = 0.5, extra_use: bool = False) -> onnx.ModelProto:
    """``x * (half * (1 + erf(x / sqrt 2)))`` as torch's exporter writes GELU; ``extra_use`` also outputs the
    ``half * (...)`` value."""
    nodes = [helper.make_node("Div", ["x", "sqrt2"], ["d"]), helper.make_node("Erf", ["d"], ["e"]),
             helper.make_node("Add", ["e", "one"], ["a"]), helper.make_node("Mul", ["half", "a"], ["h"]),
             helper.make_node("Mul", ["x", "h"], ["y"])]
    outputs = [helper.make_tensor_value_info("y", TensorProto.FLOAT, [4, 37])]
    if extra_use:
        outputs.append(helper.make_tensor_value_info("h", TensorProto.FLOAT, [4, 37]))
    consts = [helper.make_tensor(n, TensorProto.FLOAT, [], [v]) for n, v in
              (("sqrt2", float(np.float32(np.sqrt(2)))), ("one", 1.0), ("half", half))]
    graph = helper.make_graph(nodes, "gelu", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [4, 37])],
                              outputs, consts)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])


def run(model: onnx.ModelProto, optimise: bool, tmp_path) -> tuple[np.ndarray, list[str]]:
    """The output ``y`` and the operators onnxruntime ran (after its optimiser, when ``optimise``)."""
    opts = ort.SessionOptions()
    opts.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimise
                                     else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    opts.optimized_model_filepath = str(tmp_path / "optimised.onnx")
    session = ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    y = session.run(["y"], {"x": X})[0]
    return y, [n.op_type for n in onnx.load(str(tmp_path / "optimised.onnx")).graph.node]


def rewritten(model: onnx.ModelProto) -> tuple[onnx.ModelProto, int]:
    m = ir.serde.deserialize_model(model)
    count = gelu_in_fusable_order(m.graph)
    return ir.serde.serialize_model(m), count


def test_gelu_rewrite_keeps_every_value_and_lets_onnxruntime_fuse_it(tmp_path) -> None:
    before = torch_gelu_graph()
    after, count = rewritten(before)
    assert count == 1
    y0, ops0 = run(before, optimise=False, tmp_path=tmp_path)
    y1, ops1 = run(after, optimise=False, tmp_path=tmp_path)
    assert np.array_equal(y0, y1)  # bitwise: the product with 0.5 is exact
    assert sorted(ops0) == sorted(ops1) == ["Add", "Div", "Erf", "Mul", "Mul"]  # standard ONNX still
    _, fused_before = run(before, optimise=True, tmp_path=tmp_path)
    y2, fused_after = run(after, optimise=True, tmp_path=tmp_path)
    assert "Erf" in fused_before  # onnxruntime did not recognise torch's order
    assert fused_after == ["Gelu"]
    assert np.abs(y2 - y0).max() < 1e-5


@pytest.mark.parametrize("model", [torch_gelu_graph(half=0.6), torch_gelu_graph(extra_use=True)],
                         ids=["not a gelu", "half read elsewhere"])
def test_gelu_rewrite_leaves_other_graphs_alone(model, tmp_path) -> None:
    after, count = rewritten(model)
    assert count == 0
    assert [n.input[:] for n in after.graph.node] == [n.input[:] for n in model.graph.node]


class Attention(torch.nn.Module):
    def forward(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        return attend(q, k, v, bias)


def test_exported_attention_matches_eager_and_transposes_keys_once(tmp_path) -> None:
    g = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn(3, 11, 4, 8, generator=g) for _ in range(3))
    padded = torch.arange(11)[None] >= torch.tensor([[11], [7], [2]])  # (3, 11): frames past each length
    bias = torch.zeros(3, 1, 1, 11).masked_fill(padded[:, None, None], float("-inf"))
    eager = attend(q, k, v, bias).numpy()
    path = tmp_path / "attention.onnx"
    export_graph(Attention(), (q, k, v, bias), None, "out", path)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    out = session.run(["out"], {"q": q.numpy(), "k": k.numpy(), "v": v.numpy(), "bias": bias.numpy()})[0]
    assert np.abs(out - eager).max() < 1e-5
    nodes = onnx.load(str(path)).graph.node
    perms = [list(a.ints) for n in nodes if n.op_type == "Transpose" for a in n.attribute if a.name == "perm"]
    assert [0, 2, 3, 1] in perms  # (B,T,heads,dh) -> (B,heads,dh,T): the keys in one step
    assert not any(n.op_type == "Reshape" for n in nodes[:-1])  # only the heads' merge at the end reshapes
