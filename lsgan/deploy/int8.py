"""int8 graphs: onnxruntime's dynamic quantisation of the decoder's feed-forward products, and what it costs.

Which products: the feed-forward layers of every decoder block (d -> ff and ff -> d, 8 of the ~13 d x d products
per frame and layer at ff = 4d). Their weights become int8 per output channel (symmetric ``QInt8``); their inputs
are quantised to uint8 on the fly. Measured on the trained Bandai GAN's decoder (100 fixed motions, joint
error against fp32): every product per tensor, 16.7 mm mean (120 max); every product per channel, 12.9 mm; the
feed-forward products alone per channel, 1.4 mm (15 max). The final feature layer is the worst to quantise
(7.8 mm once it alone stays fp32), then the skip projections and the attention input projections, so they stay
fp32. u8 activations x s8 weights is the fast path of x86 CPUs with AVX-512 VNNI; on x86 CPUs without VNNI that
pair can saturate (onnxruntime's quantisation docs): re-export there with ``weight_type="QUInt8"``.

Only the decoder is quantised. The generator stays fp32: it is tiny, and its error would pass through the
decoder. The text encoder stays fp32 too: on the trained Bandai GAN an int8 MiniLM turned embeddings by up to 20
degrees (cosine 0.94), the generator answered with other motions, and the joints moved by 322 mm on average.

The price is measured at export time and stored in the manifest: the same 100 fixed requests and seed through
the fp32 and the int8 graphs, the distance between their 22 joints (``recover_from_ric`` of the de-normalised
features), mean and max over every joint of every frame, in millimetres.
"""
from __future__ import annotations

import ast
import logging
import os
import re
from pathlib import Path

import numpy as np

from lsgan.generation import Request
from lsgan.io import atomic_path, publish

QUANTISED = ("decoder",)
WEIGHT_TYPE = "QInt8"
DECODER_FEED_FORWARD = r"\.(linear1|linear2)$"  # the feed-forward Linears of torch's transformer layers
MINILM_FEED_FORWARD = r"\.layer\.\d+\.(intermediate|output)\.dense$"  # BERT's, for comparisons
REFERENCE_SEED = 0
_SUBJECTS = ("a person", "someone", "a man", "a woman", "the figure")
_ACTIONS = ("walks forward", "runs forward", "jumps up", "waves the right hand", "waves the left hand", "squats down",
            "kicks with the right leg", "kicks with the left leg", "turns around", "sits down", "raises both arms",
            "walks backwards", "climbs up stairs", "dances happily", "throws a ball", "picks something up",
            "stretches the arms", "bows politely", "walks in a circle", "spins around")
REFERENCE_PROMPTS = tuple(f"{s} {a}" for a in _ACTIONS for s in _SUBJECTS)  # 100 fixed prompts


def products_in(graph, modules: str) -> list[str]:
    """Names of the MatMul/Gemm nodes with a constant weight that the exporter traced inside a module whose name
    matches the regular expression ``modules`` (torch's dynamo exporter records each node's module scopes)."""
    constant = {init.name for init in graph.initializer}
    pattern = re.compile(modules)

    def scopes(node) -> list[str]:
        meta = {p.key: p.value for p in node.metadata_props}
        return ast.literal_eval(meta.get("pkg.torch.onnx.name_scopes", "[]"))  # a list of str literals

    return [n.name for n in graph.node
            if n.op_type in ("MatMul", "Gemm") and len(n.input) > 1 and n.input[1] in constant
            and any(pattern.search(scope) for scope in scopes(n))]


def quantise(src: Path, dst: Path, *, modules: str = DECODER_FEED_FORWARD, weight_type: str = WEIGHT_TYPE) -> list[str]:
    """Write ``dst``: the graph ``src`` with per-channel int8 weights in the products of ``modules`` (dynamic
    quantisation), atomically; returns the quantised nodes' names."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    model = onnx.load(str(src))
    nodes = products_in(model.graph, modules)
    if not nodes:
        raise ValueError(f"{src}: no matrix products inside modules matching {modules!r} to quantise")
    fd, tmp = atomic_path(dst)
    os.close(fd)
    quiet = logging.getLogger().level
    logging.getLogger().setLevel(logging.ERROR)  # its advice to pre-process first goes to the root logger
    try:
        # a ModelProto, not the path: from a path it writes a scratch copy beside the source, in the output folder
        quantize_dynamic(model, tmp, weight_type=getattr(QuantType, weight_type), per_channel=True,
                         nodes_to_quantize=nodes)
        publish(tmp, dst)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    finally:
        logging.getLogger().setLevel(quiet)
    return nodes


def reference_requests(manifest: dict, count: int = 100) -> list[Request]:
    """The fixed requests of the int8 error: the 100 prompts (or the action labels in turn), 40 to 196 frames."""
    top = min(196, int(manifest["max_frames"]))
    frames = [max(1, min(top, 40 + (37 * i) % 157)) for i in range(count)]
    if manifest["condition"] == "text":
        return [Request(text=REFERENCE_PROMPTS[i % len(REFERENCE_PROMPTS)], frames=f) for i, f in enumerate(frames)]
    names = manifest["action_names"]
    return [Request(action=names[i % len(names)], frames=f) for i, f in enumerate(frames)]


def joint_error_mm(fp32, int8) -> dict:
    """Mean and max joint distance (mm) between two loaded variants (OnnxMotionModel) on the reference requests."""
    requests = reference_requests(fp32.manifest)
    a = fp32.generate(requests, seed=REFERENCE_SEED).motions
    b = int8.generate(requests, seed=REFERENCE_SEED).motions
    d = np.concatenate([np.linalg.norm(x.joints - y.joints, axis=-1).ravel() for x, y in zip(a, b)]) * 1000.0
    return {"mean": float(d.mean()), "max": float(d.max()), "motions": len(requests), "seed": REFERENCE_SEED,
            "requests": "lsgan.deploy.int8.reference_requests"}
