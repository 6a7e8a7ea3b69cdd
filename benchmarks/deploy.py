"""ONNX runtime against torch on this CPU: the VAE decoder and the MiniLM text encoder, fp32 and int8.

The decoder is paper-sized (``lsgan.eval.bench.PAPER_VAE``, random weights) decoding 120 frames; the text encoder is
the packaged MiniLM on lsgan.deploy.int8's reference prompts, tokenised beforehand (both runtimes get the same ids).
Both are exported as ``lsgan export-model`` exports them (``lsgan.deploy.onnx_export.export_graph``); the decoder's
feed-forward and self-attention products are quantised as ``--int8`` does (lsgan.deploy.int8), and MiniLM's
feed-forward products for comparison, with both weight types (QInt8, QUInt8).
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
    return vae, enc


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
        for variant in ("", ".QInt8", ".QUInt8"):
            s = open_session(folder / f"text_encoder{variant}.onnx", session_options(threads))
            t = timed(lambda: s.run(None, {"input_ids": ids, "attention_mask": att}), repeats)
            rows.append({"model": "text encoder", "runtime": f"ORT {variant[1:] or 'fp32'}", "spin_us": SPIN_US,
                         "batch": b, "ms": 1e3 * t / b})
    return rows


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
    print(f"load average (1 min): {before:.2f} before, {os.getloadavg()[0]:.2f} after; {args.threads} threads, "
          f"median of {args.repeats}")
    print("| model | runtime | spin-waiting, us | batch | ms per item |\n| --- | --- | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['model']} | {r['runtime']} | {r.get('spin_us', '')} | {r['batch']} | {r['ms']:.2f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"load_before": before, "threads": args.threads, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
