"""int8 graphs: onnxruntime's dynamic quantisation, and what it costs in joint positions.

Weights become int8 once (per tensor, symmetric: ``QInt8``); activations are quantised to uint8 on the fly
at each matrix product. u8 activations x s8 weights is the fast path of x86 CPUs with AVX-512 VNNI (measured
on the paper-sized decoder: QInt8 faster than QUInt8 weights at batch 1 and 256, docs/deploy.md). On x86
CPUs without VNNI that pair can saturate (onnxruntime's quantisation docs): re-export there with
``weight_type="QUInt8"``. Only the decoder is quantised. The generator stays fp32: it is tiny, and its error
would pass through the decoder. The text encoder stays fp32 too: on the trained Bandai GAN an int8 MiniLM turned
embeddings by up to 20 degrees (cosine 0.94), the generator answered with other motions, and the joints moved by
322 mm on average (6.3 m at most), against 17 mm for the int8 decoder alone.

The price is measured at export time and stored in the manifest: the same 100 fixed requests and seed through
the fp32 and the int8 graphs, the distance between their 22 joints (``recover_from_ric`` of the de-normalised
features), mean and max over every joint of every frame, in millimetres.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from lsgan.generation import Request
from lsgan.io import atomic_path, publish

QUANTISED = ("decoder",)
WEIGHT_TYPE = "QInt8"
REFERENCE_SEED = 0
_SUBJECTS = ("a person", "someone", "a man", "a woman", "the figure")
_ACTIONS = ("walks forward", "runs forward", "jumps up", "waves the right hand", "waves the left hand", "squats down",
            "kicks with the right leg", "kicks with the left leg", "turns around", "sits down", "raises both arms",
            "walks backwards", "climbs up stairs", "dances happily", "throws a ball", "picks something up",
            "stretches the arms", "bows politely", "walks in a circle", "spins around")
REFERENCE_PROMPTS = tuple(f"{s} {a}" for a in _ACTIONS for s in _SUBJECTS)  # 100 fixed prompts


def quantise(src: Path, dst: Path, weight_type: str = WEIGHT_TYPE) -> None:
    """Write ``dst``: the graph ``src`` with int8 weights in its matrix products (dynamic quantisation), atomically."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic

    fd, tmp = atomic_path(dst)
    os.close(fd)
    quiet = logging.getLogger().level
    logging.getLogger().setLevel(logging.ERROR)  # its advice to pre-process first goes to the root logger
    try:
        # a ModelProto, not the path: from a path it writes a scratch copy beside the source, in the output folder
        quantize_dynamic(onnx.load(str(src)), tmp, weight_type=getattr(QuantType, weight_type))
        publish(tmp, dst)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    finally:
        logging.getLogger().setLevel(quiet)


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
