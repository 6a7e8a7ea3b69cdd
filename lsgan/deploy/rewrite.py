"""Exact rewrites of an exported graph, so that onnxruntime's optimiser fuses what it can fuse.

torch's exporter writes GELU as ``x * (0.5 * (1 + erf(x / sqrt 2)))``. onnxruntime's GeluFusion recognises
``(x * (1 + erf(x / sqrt 2))) * 0.5`` (or the 0.5 on x first), not this order, so every GELU ran as five
element-wise passes. :func:`gelu_in_fusable_order` swaps the two products. The values do not change: the
product with 0.5 is exact in binary floating point, so both orders round to the same number. The files stay
standard ONNX (the same five operators); onnxruntime turns each group into one Gelu kernel when it loads them,
which agrees with them to float rounding (the paper-sized int8 decoder: 7% faster at batch 1, 12% at 32 motions;
MiniLM ~4%).
"""
from __future__ import annotations

import math


def _constant(value, expected: float) -> bool:
    """Whether the graph value ``value`` is a scalar constant equal to ``expected`` (float32 rounding)."""
    tensor = value.const_value if value is not None else None
    if tensor is None:
        return False
    array = tensor.numpy()
    return array.size == 1 and math.isclose(float(array.reshape(())), expected, rel_tol=1e-6)


def _only_consumer(value):
    """The one node that reads ``value``, or None if it has none or several (or is a graph output)."""
    consumers = list(value.consumers())
    return consumers[0] if len(consumers) == 1 and not value.is_graph_output() else None


def gelu_in_fusable_order(graph) -> int:
    """Rewrite each ``Mul(x, Mul(0.5, Add(Erf(Div(x, sqrt 2)), 1)))`` of the onnx_ir ``graph`` in place as
    ``Mul(Mul(x, Add(...)), 0.5)``; returns how many were rewritten."""
    count = 0
    for erf in [n for n in graph if n.op_type == "Erf" and n.domain == ""]:
        div = erf.inputs[0].producer()
        add = _only_consumer(erf.outputs[0])
        if div is None or div.op_type != "Div" or not _constant(div.inputs[1], math.sqrt(2.0)) or add is None:
            continue
        x = div.inputs[0]
        one = [v for v in add.inputs if v is not erf.outputs[0]]
        half = _only_consumer(add.outputs[0])
        if add.op_type != "Add" or len(one) != 1 or not _constant(one[0], 1.0) or half is None or half.op_type != "Mul":
            continue
        c = [v for v in half.inputs if v is not add.outputs[0]]
        out = _only_consumer(half.outputs[0])
        if len(c) != 1 or not _constant(c[0], 0.5) or out is None or out.op_type != "Mul" \
                or [v for v in out.inputs if v is not half.outputs[0]] != [x]:
            continue
        half.replace_input_with(0, x)
        half.replace_input_with(1, add.outputs[0])  # x * (1 + erf)
        out.replace_input_with(0, half.outputs[0])
        out.replace_input_with(1, c[0])  # ... * 0.5
        count += 1
    return count
