"""ONNX runtime against torch on this CPU: the VAE decoder and the MiniLM text encoder, fp32 and int8.

The decoder is paper-sized (``lsgan.eval.bench.PAPER_VAE``, random weights) decoding 120 frames; the text encoder is
the packaged MiniLM on lsgan.deploy.int8's reference prompts, tokenised beforehand (both runtimes get the same ids).
Both are exported as ``lsgan export-model`` exports them (``lsgan.deploy.onnx_export.export_graph``); the decoder's
feed-forward and self-attention products are quantised as ``--int8`` does (lsgan.deploy.int8), and MiniLM's
feed-forward products for comparison, with both weight types (QInt8, QUInt8); also for comparison, MiniLM with
8-bit weights in every product (onnxruntime's MatMulNBits, fp32 or int8 products) and MiniLM in fp16. Each MiniLM
variant's rows say how far its embeddings turn from the fp32 graph's (mean distance at the same prompts; what that
does to the motions: ``benchmarks/models.py --quality-run``). Last, MiniLM's first 1, 2, 3 and 6 layers at batch 1
(2 tokens, ten times ``--repeats`` runs): their weights are 7 MiB per layer and this CPU's last-level cache 32 MiB,
so the time per layer says how much of batch 1 is reading weights from memory.
Each figure is the median of ``--repeats`` timed runs after one warm-up, in ms per motion (decoder) or per prompt
(text), at batch 1 and 256; onnxruntime with ``--threads`` intra-op threads, the decoder without spin-waiting and with
the runtime's (``SPIN_US``), the text encoder with the runtime's;
torch eager with the same number of threads. The 1-minute load average is
printed before and after: compare figures from quiet runs.

    python benchmarks/deploy.py
    python benchmarks/deploy.py --repeats 10 --threads 2 --json deploy.json
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch.export import Dim

from lsgan.deploy import int8 as q
from lsgan.deploy.onnx_export import DecoderGraph, TextGraph, export_graph
from lsgan.deploy.runtime import SPIN_US, open_session, session_options
from lsgan.eval.bench import PAPER_VAE
from lsgan.models.text import load_text_encoder
from lsgan.models.vae import MotionVAE

from export import timed  # benchmarks/export.py: the median of repeated calls after a warm-up

FRAMES, BATCHES = 120, (1, 256)


def export_both(folder: Path) -> tuple[MotionVAE, object]:
    """Paper-sized decoder and MiniLM in torch, their fp32 graphs and both int8 variants in ``folder``."""
    torch.manual_seed(0)
    vae = MotionVAE(PAPER_VAE).eval()
    enc = load_text_encoder("minilm")
    batch = Dim("batch", min=1)
    frames, tokens = Dim("frames", min=1, max=PAPER_VAE.max_len), Dim("tokens", min=1, max=enc.max_length)
    mask = torch.arange(64)[None] < torch.tensor([[64], [48], [32]])  # (3, 64)
    export_graph(DecoderGraph(vae), (torch.randn(3, PAPER_VAE.latent_dim), mask),
                 {"latent": {0: batch}, "mask": {0: batch, 1: frames}}, "features", folder / "decoder.onnx")
    ids, att = torch.randint(1000, 2000, (3, 9)), torch.ones(3, 9, dtype=torch.long)  # (3, 9) each
    export_graph(TextGraph(enc), (ids, att),
                 {"input_ids": {0: batch, 1: tokens}, "attention_mask": {0: batch, 1: tokens}}, "embedding",
                 folder / "text_encoder.onnx")
    products = {"decoder": q.DECODER_INT8, "text_encoder": q.MINILM_FEED_FORWARD}
    for graph, pattern in products.items():
        for weights in ("QInt8", "QUInt8"):
            q.quantise(folder / f"{graph}.onnx", folder / f"{graph}.{weights}.onnx", weights=pattern,
                       weight_type=weights)
    for level in WEIGHT_ONLY_LEVELS:
        weight_only(folder / "text_encoder.onnx", folder / f"text_encoder.w8a{level}.onnx", level)
    half(folder / "text_encoder.onnx", folder / "text_encoder.fp16.onnx")
    return vae, enc


def half(src: Path, dst: Path) -> None:
    """MiniLM in fp16 (onnxruntime's converter; inputs and outputs stay fp32), for comparison: half the bytes."""
    import onnx
    from onnxruntime.transformers.float16 import convert_float_to_float16

    onnx.save(convert_float_to_float16(onnx.load(str(src)), keep_io_types=True), str(dst))


# onnxruntime's MatMulNBits accuracy levels: 1 multiplies in fp32, 4 quantises each row's inputs to int8 per block
WEIGHT_ONLY_LEVELS = (1, 4)


def weight_only(src: Path, dst: Path, accuracy_level: int) -> None:
    """MiniLM with every product's weights in 8 bits per block of 32 (MatMulNBits, symmetric), for comparison:
    a quarter of the fp32 weights' bytes, which at batch 1 the products stream from memory."""
    import logging

    import onnx
    from onnxruntime.quantization.matmul_nbits_quantizer import DefaultWeightOnlyQuantConfig, MatMulNBitsQuantizer

    config = DefaultWeightOnlyQuantConfig(block_size=32, is_symmetric=True, accuracy_level=accuracy_level, bits=8)
    quantiser = MatMulNBitsQuantizer(onnx.load(str(src)), bits=8, block_size=32, is_symmetric=True,
                                     accuracy_level=accuracy_level, algo_config=config)
    level = logging.getLogger().level
    logging.getLogger().setLevel(logging.WARNING)  # the quantiser logs every node it skips
    try:
        quantiser.process()
    finally:
        logging.getLogger().setLevel(level)
    quantiser.model.save_model_to_file(str(dst), False)


def decoder_rows(vae: MotionVAE, folder: Path, threads: int, repeats: int) -> list[dict]:
    rows = []
    for b in BATCHES:
        z = np.random.default_rng(0).standard_normal((b, PAPER_VAE.latent_dim), dtype=np.float32)
        mask = np.ones((b, FRAMES), bool)
        with torch.inference_mode():
            t = timed(lambda: vae.decode(torch.from_numpy(z), torch.from_numpy(mask)), repeats)
        rows.append({"model": "decoder", "runtime": "torch eager fp32", "batch": b, "ms": 1e3 * t / b})
        for variant in ("", ".QInt8", ".QUInt8"):
            for spin_us in (0, SPIN_US):
                s = open_session(folder / f"decoder{variant}.onnx", session_options(threads, spin_us))
                t = timed(lambda: s.run(None, {"latent": z, "mask": mask}), repeats)
                rows.append({"model": "decoder", "runtime": f"ORT {variant[1:] or 'fp32'}", "spin_us": spin_us,
                             "batch": b, "ms": 1e3 * t / b})
    return rows


def text_rows(enc, folder: Path, threads: int, repeats: int) -> list[dict]:
    rows = []
    for b in BATCHES:
        prompts = [q.REFERENCE_PROMPTS[i % len(q.REFERENCE_PROMPTS)] + f" {i}" for i in range(b)]  # all distinct
        tokens = enc.tokenizer.encode_batch(prompts)
        length = max(len(t.ids) for t in tokens)
        ids = np.zeros((b, length), np.int64)
        att = np.zeros((b, length), np.int64)
        for i, t in enumerate(tokens):
            ids[i, :len(t.ids)], att[i, :len(t.ids)] = t.ids, 1
        graph = TextGraph(enc).eval()
        with torch.inference_mode():
            t = timed(lambda: graph(torch.from_numpy(ids), torch.from_numpy(att)), repeats)
        rows.append({"model": "text encoder", "runtime": "torch eager fp32", "batch": b, "ms": 1e3 * t / b})
        feed = {"input_ids": ids, "attention_mask": att}
        exact = None
        for variant in ("", ".fp16", ".QInt8", ".QUInt8", *(f".w8a{level}" for level in WEIGHT_ONLY_LEVELS)):
            s = open_session(folder / f"text_encoder{variant}.onnx", session_options(threads))
            t = timed(lambda: s.run(None, feed), repeats)
            emb = s.run(None, feed)[0]
            exact = emb if exact is None else exact
            rows.append({"model": "text encoder", "runtime": f"ORT {TEXT_VARIANTS[variant]}", "spin_us": SPIN_US,
                         "batch": b, "ms": 1e3 * t / b,
                         "turn": float(np.linalg.norm(emb - exact, axis=1).mean())})  # from the fp32 embedding
    return rows


TEXT_VARIANTS = {"": "fp32", ".fp16": "fp16", ".QInt8": "int8 feed-forward (QInt8)",
                 ".QUInt8": "int8 feed-forward (QUInt8)",
                 **{f".w8a{level}": f"8-bit weights, {'fp32' if level == 1 else 'int8'} products (MatMulNBits)"
                    for level in WEIGHT_ONLY_LEVELS}}


def layer_rows(threads: int, repeats: int, tokens: int = 2) -> list[dict]:
    """MiniLM's first n layers at batch 1 (``tokens`` tokens): the time per layer while their weights (7 MiB each)
    fit this CPU's caches and once they do not."""
    rows = []
    for n in LAYERS:
        enc = load_text_encoder("minilm")
        enc.model.encoder.layer = enc.model.encoder.layer[:n]
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "layers.onnx"
            ids = torch.randint(1000, 2000, (3, 9))
            export_graph(TextGraph(enc), (ids, torch.ones_like(ids)),
                         {k: {0: Dim("batch", min=1), 1: Dim("tokens", min=1, max=enc.max_length)}
                          for k in ("input_ids", "attention_mask")}, "embedding", path)
            s = open_session(path, session_options(threads))
        feed = {"input_ids": np.full((1, tokens), 2000, np.int64), "attention_mask": np.ones((1, tokens), np.int64)}
        t = timed(lambda: s.run(None, feed), repeats)
        mb = sum(p.numel() for p in enc.model.encoder.layer.parameters()) * 4 / 2**20
        rows.append({"model": f"text encoder, first {n} layers ({mb:.0f} MiB of fp32 weights)",
                     "runtime": "ORT fp32", "spin_us": SPIN_US, "batch": 1, "tokens": tokens, "ms": 1e3 * t})
    return rows


LAYERS = (1, 2, 3, 6)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2, help="torch's and onnxruntime's intra-op threads")
    parser.add_argument("--json", help="write the rows here as JSON")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        vae, enc = export_both(Path(tmp))
        rows = decoder_rows(vae, Path(tmp), args.threads, args.repeats)
        rows += text_rows(enc, Path(tmp), args.threads, args.repeats)
    rows += layer_rows(args.threads, 10 * args.repeats)  # passes of a millisecond or two: more of them
    print(f"load average (1 min): {before:.2f} before, {os.getloadavg()[0]:.2f} after; {args.threads} threads, "
          f"median of {args.repeats}")
    print("| model | runtime | spin-waiting, us | batch | ms per item | embedding turn |\n"
          "| --- | --- | ---: | ---: | ---: | ---: |")
    for r in rows:
        turn = f"{r['turn']:.1e}" if "turn" in r else ""
        print(f"| {r['model']} | {r['runtime']} | {r.get('spin_us', '')} | {r['batch']} | {r['ms']:.2f} | {turn} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"load_before": before, "threads": args.threads, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
