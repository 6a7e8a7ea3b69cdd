"""Linear layers whose weights are packed once for oneDNN, for inference on the CPU.

``nn.Linear`` on the CPU calls MKL's sgemm, which re-packs the weight matrix on every call; for a frozen encoder run
on a few rows at a time (MiniLM: 10 to 120 token rows, 42 MB of linear weights) that packing is a large share of the
work. oneDNN's inner-product with a weight packed ahead of time (the ops torch's own CPU freezing uses) took, on one
thread of this project's 2-core CPU, 125 against 201 us for 10 x 384 -> 1536 and 1,183 against 1,380 us for 112
rows; on two threads 75 against 179 and 607 against 823. Its results were bitwise the same on 1 and 2 threads for
every row count tried (1 to 2,048), so output does not depend on how many cores were free, and they differ from
MKL's by float rounding.

:class:`PackedLinear` keeps the layer's parameters (same names, same state dict) and falls back to ``F.linear``
whenever the packed product would not be the same computation: gradients wanted, another device or dtype, an
autocast region, or a graph export.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def can_pack() -> bool:
    """Whether this torch build has oneDNN and the packed inner-product ops."""
    ops = torch.ops.mkldnn
    return torch.backends.mkldnn.is_available() and hasattr(ops, "_reorder_linear_weight") \
        and hasattr(ops, "_linear_pointwise")


# Rows are padded to a multiple of this: oneDNN keeps a kernel and its buffers per input shape, and a server's
# passes come in every row count (MiniLM: +270 MB over 1,500 passes of 1 to 8 prompts unpadded, +80 MB padded to
# 16, +60 MB with MKL; the padded rows cost ~5% of the time there).
ROWS = 16


class PackedLinear(nn.Linear):
    """``linear`` with its fp32 CPU weight packed for oneDNN; the parameters are ``linear``'s own (shared)."""

    def __init__(self, linear: nn.Linear) -> None:
        nn.Module.__init__(self)
        self.in_features, self.out_features = linear.in_features, linear.out_features
        self.weight, self.bias = linear.weight, linear.bias
        self._pack()

    def _pack(self) -> None:
        with torch.no_grad():
            self.packed = torch.ops.mkldnn._reorder_linear_weight(self.weight.detach(), None)
        self.packed_version = self.weight._version  # an in-place change of the weight (load_state_dict) bumps it

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        plain = (torch.compiler.is_exporting() or (torch.is_grad_enabled() and self.weight.requires_grad)
                 or x.dtype != torch.float32 or x.device.type != "cpu" or self.weight.device.type != "cpu"
                 or self.weight.dtype != torch.float32 or torch.is_autocast_enabled("cpu"))
        if plain:
            return F.linear(x, self.weight, self.bias)
        if self.weight._version != self.packed_version:
            self._pack()
        rows = x.reshape(-1, self.in_features)  # (M, in)
        m = rows.shape[0]
        padded = -(-m // ROWS) * ROWS
        if padded != m:
            rows = torch.cat([rows, rows.new_zeros(padded - m, self.in_features)])
        out = torch.ops.mkldnn._linear_pointwise(rows, self.packed, self.bias, "none", [], "")  # (padded, out)
        return out[:m].reshape(*x.shape[:-1], self.out_features)


def pack_linears(module: nn.Module) -> int:
    """Replace every fp32 CPU ``nn.Linear`` inside ``module`` with a :class:`PackedLinear` (a frozen model's
    inference); returns how many were packed, 0 where the ops are missing."""
    if not can_pack():
        return 0
    count = 0
    for parent in list(module.modules()):
        for name, child in list(parent.named_children()):
            if type(child) is nn.Linear and child.weight.dtype == torch.float32 and child.weight.device.type == "cpu":
                setattr(parent, name, PackedLinear(child))
                count += 1
    return count
