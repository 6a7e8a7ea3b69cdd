"""int8 graphs: onnxruntime's dynamic quantisation of the decoder's feed-forward and self-attention products.

Which products: in every decoder block the feed-forward layers (d -> ff, ff -> d) and the self-attention
projections (in_proj d -> 3d, out_proj d -> d), 12 of the ~13 d x d products per frame and layer at ff = 4d. Their
weights become int8 per output channel (symmetric ``QInt8``); their inputs are quantised to uint8 on the fly.
Measured on the trained Bandai GAN's decoder (100 fixed motions, joint error against fp32, mean / max): every
product per tensor, 16.7 / 120 mm; every product per channel, 12.9 mm; every product but the final feature layer,
7.8 mm; the feed-forward and self-attention products, 2.3 / 23 mm (the feed-forward ones alone: 1.4 / 15); adding
the cross-attention's output projection, 5.3 mm. So the cross-attention (computed once per motion), the skip
projections and the final feature layer stay fp32. u8 activations x s8 weights is the fast path of x86 CPUs with
AVX-512 VNNI; on x86 CPUs without VNNI that pair can saturate (onnxruntime's quantisation docs): re-export there
with ``weight_type="QUInt8"``.

Only the decoder is quantised. The generator stays fp32: it is tiny, and its error would pass through the
decoder. The text encoder stays fp32 too: on the trained Bandai GAN an int8 MiniLM turned embeddings by up to 20
degrees (cosine 0.94), the generator answered with other motions, and the joints moved by 322 mm on average.

The price is measured at export time and stored in the manifest: the same 100 fixed requests and seed through
the fp32 and the int8 graphs, the distance between their 22 joints (``recover_from_ric`` of the de-normalised
features, made rigid as every output is), mean and max over every joint of every frame, in millimetres.
"""
from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from lsgan.generation import Request
from lsgan.io import atomic_path, discard, publish

QUANTISED = ("decoder",)
WEIGHT_TYPE = "QInt8"
# the products to quantise, by the name of the weight they multiply (the exporter's name: dots become underscores)
DECODER_INT8 = r"_(linear1|linear2|self_attn_in_proj|self_attn_out_proj)_weight$"  # feed-forward, self-attention
DECODER_INT8_NODES = "the decoder's feed-forward and self-attention products"
MINILM_FEED_FORWARD = r"_layer_\d+_(intermediate|output)_dense_weight$"  # BERT's, for comparisons
REFERENCE_SEED = 0
_SUBJECTS = ("a person", "someone", "a man", "a woman", "the figure")
_ACTIONS = ("walks forward", "runs forward", "jumps up", "waves the right hand", "waves the left hand", "squats down",
            "kicks with the right leg", "kicks with the left leg", "turns around", "sits down", "raises both arms",
            "walks backwards", "climbs up stairs", "dances happily", "throws a ball", "picks something up",
            "stretches the arms", "bows politely", "walks in a circle", "spins around")
REFERENCE_PROMPTS = tuple(f"{s} {a}" for a in _ACTIONS for s in _SUBJECTS)  # 100 fixed prompts


def products_in(graph, weights: str) -> list[str]:
    """Names of the MatMul nodes with a constant weight whose traced torch op multiplies a parameter whose name
    matches the regular expression ``weights`` (torch's dynamo exporter records each node's op with its arguments,
    parameters as ``%p_<dotted name with underscores>``). MatMul only: dynamic quantisation leaves Gemm alone."""
    constant = {init.name for init in graph.initializer}
    pattern = re.compile(weights)

    def parameters(node) -> list[str]:
        meta = {p.key: p.value for p in node.metadata_props}
        return re.findall(r"%p_(\w+)", meta.get("pkg.torch.onnx.fx_node", ""))

    return [n.name for n in graph.node
            if n.op_type == "MatMul" and len(n.input) > 1 and n.input[1] in constant
            and any(pattern.search(name) for name in parameters(n))]


def quantise(src: Path, dst: Path, *, weights: str = DECODER_INT8, weight_type: str = WEIGHT_TYPE) -> list[str]:
    """Write ``dst``: the graph ``src`` with per-channel int8 weights in the products of the parameters matching
    ``weights`` (dynamic quantisation), atomically; returns the quantised nodes' names."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    model = onnx.load(str(src))
    nodes = products_in(model.graph, weights)
    if not nodes:
        raise ValueError(f"{src}: no matrix products of weights matching {weights!r} to quantise")
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
        discard(tmp)
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
