"""A latent GAN, its VAE's decoder and its MiniLM text encoder as ONNX graphs (``lsgan export-model --onnx``).

The torch side of :mod:`lsgan.deploy`. Graphs come from torch.onnx's dynamo exporter with dynamic batch, token
and frame axes. The older TorchScript exporter is not used: it bakes the traced batch and frame counts into
nn.MultiheadAttention's reshapes, so a decoder traced at 60 frames fails at 40. The transformer fast path is
switched off while exporting (its fused kernel has no ONNX form).

What is written, in order (the manifest last, so a folder without one is an unfinished export)::

    text_encoder.onnx   input_ids (B, L) int64, attention_mask (B, L) int64 -> embedding (B, 384) float32
    tokenizer.json      the text encoder's tokenizer, truncation and padding set as MiniLMEncoder uses them
    vocab.txt           its WordPiece vocabulary (for BERT tokenizers that read one, e.g. C#'s)
    generator.onnx      noise (B, noise_dim) float32, condition -> latent (B, Z) float32, standardised
    decoder.onnx        latent (B, Z) float32 (de-standardised), mask (B, T) bool -> features (B, T, 263)
    decoder.int8.onnx   with --int8: the decoder with int8 weights (lsgan.deploy.int8)
    manifest.json       lsgan.deploy.manifest

The condition is the text embedding (B, 384) float32, or for an action GAN the action's index (B,) int64 into
the manifest's ``action_names`` (the generator's own embedding table is inside the graph).
"""
from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn
from torch.export import Dim

from lsgan import __version__, outputs
from lsgan.data.skeleton import FPS
from lsgan.deploy import int8 as q
from lsgan.deploy.manifest import FORMAT, FORMAT_VERSION, MANIFEST, file_entry
from lsgan.deploy.rewrite import gelu_in_fusable_order
from lsgan.io import atomic_file, atomic_path, discard, publish

OPSET = 18  # the dynamo exporter's lowest
_EXAMPLE_BATCH, _EXAMPLE_TOKENS, _EXAMPLE_FRAMES = 3, 9, 64  # traced sizes; every axis is dynamic


class TextGraph(nn.Module):
    """MiniLM as MiniLMEncoder.encode runs it: masked mean of the last hidden states, L2-normalised."""

    def __init__(self, encoder) -> None:
        super().__init__()
        self.bert = encoder.model

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        hidden = self.bert(input_ids, attention_mask.bool())  # (B, L, D)
        m = attention_mask.unsqueeze(-1).to(hidden.dtype)  # (B, L, 1)
        mean = (hidden * m).sum(1) / m.sum(1).clamp(min=1e-9)  # (B, D)
        return nn.functional.normalize(mean, p=2, dim=1)


class GeneratorGraph(nn.Module):
    def __init__(self, generator: nn.Module) -> None:
        super().__init__()
        self.generator = generator

    def forward(self, noise: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        return self.generator(noise, condition)  # (B, Z), standardised


class DecoderGraph(nn.Module):
    def __init__(self, vae: nn.Module) -> None:
        super().__init__()
        self.vae = vae

    def forward(self, latent: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return self.vae.decode(latent, mask)  # (B, T, 263), zero on padded frames


@dataclass
class Sources:
    """What an export reads: the GAN, the VAE and the text encoder, loaded and checked to belong together."""

    run: Path
    vae_path: Path
    gan: nn.Module
    gan_meta: dict
    vae: nn.Module
    vae_meta: dict
    encoder: object | None  # a MiniLMEncoder, or None for an action GAN


@dataclass
class ExportResult:
    folder: Path
    manifest: dict
    seconds: float


def gan_meta(run: str | os.PathLike) -> dict:
    """The checkpoint meta of ``run``, refused unless it is a latent GAN."""
    from lsgan.models.checkpoint import read_meta

    meta = read_meta(run)
    kind = meta.get("kind")
    if kind == "diffusion":
        raise ValueError(f"{run}: a latent-diffusion model; only GANs export to ONNX (one generator pass; "
                         "diffusion samples in a loop of denoiser steps)")
    if kind != "gan":
        raise ValueError(f"{run}: holds a {kind!r} checkpoint, not a GAN; export-model exports latent GANs "
                         "(`lsgan train-gan`)")
    return meta


def recorded_vae(run: str | os.PathLike, meta: dict) -> Path:
    """The VAE a GAN learned the latents of: the one its latent cache (named in its config.json) was encoded with."""
    from lsgan.models.cache import read_cache_attrs
    from lsgan.models.checkpoint import resolve

    cache = meta.get("extra", {}).get("cache")
    if not cache or not Path(cache).is_file():
        raise ValueError(f"{run}: cannot find its VAE: the latent cache its config.json names ({cache or 'none'}) "
                         "is not there; pass --vae RUN")
    recorded = str(read_cache_attrs(cache).get("vae_path", ""))
    try:
        if recorded:
            return resolve(recorded)
    except FileNotFoundError:
        pass
    raise ValueError(f"{run}: cannot find its VAE: {recorded or 'no path'} (recorded in {cache}) is not there; "
                     "pass --vae RUN")


def load_sources(run: str | os.PathLike, vae: str | os.PathLike,
                 text_encoder_path: str | os.PathLike | None = None) -> Sources:
    """Load a GAN run, its VAE and its text encoder, refusing any other pairing than the one it was trained on."""
    from lsgan.models.checkpoint import weights_hash
    from lsgan.models.gan import load_gan
    from lsgan.models.text import load_text_encoder
    from lsgan.models.vae import load_vae

    gan, gmeta = load_gan(run)
    decoder, vmeta = load_vae(vae)
    extra = gmeta.get("extra", {})
    if extra.get("vae_hash") and extra["vae_hash"] != weights_hash(vae):
        raise ValueError(f"{run} was trained on latents of another VAE checkpoint than {vae}; pass the VAE its "
                         "cache was encoded with (--vae)")
    encoder = None
    if gan.config.cond == "text":
        enc_id = extra.get("text_encoder", "minilm")
        if not enc_id.startswith("minilm"):
            raise ValueError(f"{run}: conditioned on {enc_id.split(':')[0]} embeddings; only the MiniLM text encoder "
                             "exports to ONNX")
        encoder = load_text_encoder("minilm", path=text_encoder_path)
        if encoder.id != enc_id:
            raise ValueError(f"{run} was trained with text encoder {enc_id!r}, but {encoder.id!r} was loaded "
                             "(--text-encoder-path)")
    return Sources(Path(run), Path(vae), gan, gmeta, decoder, vmeta, encoder)


@contextlib.contextmanager
def _exporting() -> Iterator[None]:
    """The transformer fast path off, and the exporter's warnings and log lines (notes to torch developers) quiet."""
    fast = torch.backends.mha.get_fastpath_enabled()
    loggers = [logging.getLogger(name) for name in ("torch.onnx", "torch.export", "onnxscript", "onnx_ir")]
    levels = [lg.level for lg in loggers]
    torch.backends.mha.set_fastpath_enabled(False)
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            yield
    finally:
        torch.backends.mha.set_fastpath_enabled(fast)
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def _signature(values) -> list[dict]:
    """Names, numpy dtypes and shapes (named axes as strings) of a graph's inputs or outputs."""
    return [{"name": v.name, "dtype": str(v.dtype.numpy()),
             "shape": [d if isinstance(d, int) else str(d) for d in v.shape]} for v in values]


def export_graph(module: nn.Module, args: tuple, dynamic: dict, output: str, path: Path, opset: int = OPSET) -> dict:
    """Export ``module`` to ``path`` (atomically), its one output named ``output``; returns the graph's signature.

    Inputs are named after ``module.forward``'s arguments. The exporter names inner values after torch ops
    (e.g. ``embedding``), so one that holds the output's name is renamed first. GELUs are written in the order
    onnxruntime fuses (:mod:`lsgan.deploy.rewrite`: the same values).
    """
    with _exporting():
        program = torch.onnx.export(module.eval(), args, dynamo=True, dynamic_shapes=dynamic, opset_version=opset,
                                    optimize=True, verbose=False)
    graph = program.model.graph
    gelu_in_fusable_order(graph)
    for node in graph:
        for value in node.outputs:
            if value.name == output and value is not graph.outputs[0]:
                value.name = f"{output}_inner"
    graph.outputs[0].name = output
    fd, tmp = atomic_path(path)
    os.close(fd)
    try:
        program.save(tmp, external_data=False)
        publish(tmp, path)
    except BaseException:
        discard(tmp)
        raise
    return {"inputs": _signature(graph.inputs), "outputs": _signature(graph.outputs)}


def export_graphs(src: Sources, folder: Path, opset: int = OPSET, say: Callable[[str], None] = lambda m: None) -> dict:
    """Write text_encoder.onnx (text GANs), generator.onnx and decoder.onnx; returns {graph: signature}."""
    cfg, batch = src.gan.config, Dim("batch", min=1)
    g = torch.Generator().manual_seed(0)  # example inputs: any values serve; the caller's random state is left alone
    out = {}
    if src.encoder is not None:
        say("exporting the text encoder (MiniLM)")
        tokens = Dim("tokens", min=1, max=src.encoder.max_length)
        ids = torch.randint(1000, 2000, (_EXAMPLE_BATCH, _EXAMPLE_TOKENS), generator=g)
        mask = (torch.arange(_EXAMPLE_TOKENS)[None] < torch.tensor([[9], [6], [4]])).long()
        dynamic = {"input_ids": {0: batch, 1: tokens}, "attention_mask": {0: batch, 1: tokens}}
        out["text_encoder"] = export_graph(TextGraph(src.encoder), (ids, mask), dynamic, "embedding",
                                           folder / "text_encoder.onnx", opset)
    say("exporting the generator")
    noise = torch.randn(_EXAMPLE_BATCH, cfg.noise_dim, generator=g)
    if cfg.cond == "text":
        cond = torch.randn(_EXAMPLE_BATCH, cfg.cond_dim, generator=g)  # (B, D) embeddings
    else:
        cond = torch.arange(_EXAMPLE_BATCH) % cfg.num_actions  # (B,) action indices
    out["generator"] = export_graph(GeneratorGraph(src.gan.generator), (noise, cond),
                                    {"noise": {0: batch}, "condition": {0: batch}}, "latent", folder / "generator.onnx",
                                    opset)
    say("exporting the VAE decoder")
    max_frames = src.vae.config.max_len
    t = min(_EXAMPLE_FRAMES, max_frames)
    mask = torch.arange(t)[None] < torch.tensor([[t], [max(1, t * 3 // 4)], [max(1, t // 2)]])  # (3, T)
    frames = Dim("frames", min=1, max=max_frames)
    latent = torch.randn(_EXAMPLE_BATCH, src.vae.config.latent_dim, generator=g)
    dynamic = {"latent": {0: batch}, "mask": {0: batch, 1: frames}}
    out["decoder"] = export_graph(DecoderGraph(src.vae), (latent, mask), dynamic, "features", folder / "decoder.onnx",
                                  opset)
    return out


def write_tokenizer(encoder, folder: Path) -> dict:
    """tokenizer.json (truncation and padding as MiniLMEncoder uses them) and vocab.txt; returns the settings."""
    from tokenizers import Tokenizer

    tok = Tokenizer.from_str(encoder.tokenizer.to_str())
    pad_token = tok.id_to_token(encoder.pad_id)
    tok.enable_truncation(max_length=encoder.max_length)
    tok.enable_padding(pad_id=encoder.pad_id, pad_token=pad_token)
    text = tok.to_str()
    with atomic_file(folder / "tokenizer.json", "w", encoding="utf-8") as fh:
        fh.write(text)
    vocab = Path(encoder.folder) / "vocab.txt"
    if vocab.is_file():
        with atomic_file(folder / "vocab.txt") as fh:
            fh.write(vocab.read_bytes())
    spec = json.loads(text)
    return {"file": "tokenizer.json", "vocab": "vocab.txt" if vocab.is_file() else None,
            "model": spec["model"]["type"], "lowercase": bool((spec.get("normalizer") or {}).get("lowercase")),
            "special_tokens": "[CLS] prompt [SEP]", "max_length": encoder.max_length,
            "truncation": "longest_first (right)", "padding": "to the longest prompt of a batch (right)",
            "pad_id": encoder.pad_id, "pad_token": pad_token}


def planned_files(src: Sources, int8: bool) -> list[str]:
    text = src.encoder is not None
    names = (["text_encoder.onnx", "tokenizer.json", "vocab.txt"] if text else []) + ["generator.onnx", "decoder.onnx"]
    quantised = [f"{g}.int8.onnx" for g in q.QUANTISED if text or g != "text_encoder"]
    return names + (quantised if int8 else []) + [MANIFEST]


def build_manifest(src: Sources, folder: Path, graphs: dict, tokenizer: dict | None, quantised: list[str] | None,
                   opset: int) -> dict:
    """The manifest (lsgan.deploy.manifest) of what was written (``quantised``: the decoder's int8 nodes, None
    without --int8); the int8 error is added by :func:`export_onnx`."""
    from lsgan.models.checkpoint import resolve, weights_hash

    cfg, extra = src.gan.config, src.gan_meta.get("extra", {})
    fp32 = {g: f"{g}.onnx" for g in graphs}
    variants = {"fp32": {"graphs": fp32}}
    if quantised is not None:
        quantisation = {"method": "onnxruntime.quantization.quantize_dynamic", "weight_type": q.WEIGHT_TYPE,
                        "weights": "per output channel", "activations": "QUInt8, scaled per tensor at run time",
                        "graphs": [g for g in q.QUANTISED if g in graphs],
                        "nodes": q.DECODER_INT8_NODES, "quantised_nodes": quantised}
        variants["int8"] = {"graphs": {g: f"{g}.int8.onnx" if g in q.QUANTISED else f for g, f in fp32.items()},
                            "quantisation": quantisation}
    files = {f for v in variants.values() for f in v["graphs"].values()}
    if tokenizer is not None:
        files |= {tokenizer["file"], *([tokenizer["vocab"]] if tokenizer["vocab"] else [])}
    return {
        "format": FORMAT, "format_version": FORMAT_VERSION, "lsgan_version": __version__,
        "condition": cfg.cond, "action_names": extra.get("action_names", []) if cfg.cond == "action" else [],
        "noise_dim": cfg.noise_dim, "latent_dim": cfg.latent_dim,
        "cond_dim": cfg.cond_dim if cfg.cond == "text" else None,
        "latent_mean": list(map(float, extra["latent_mean"])), "latent_std": list(map(float, extra["latent_std"])),
        "feature_mean": src.vae_meta["mean"].tolist(), "feature_std": src.vae_meta["std"].tolist(),
        "fps": FPS, "max_frames": int(src.vae.config.max_len),
        "text_encoder": src.encoder.id if src.encoder is not None else None, "tokenizer": tokenizer,
        "graphs": graphs, "variants": variants,
        "files": {name: file_entry(folder / name) for name in sorted(files)},
        "sources": {"generator": {"kind": "gan", "arch": cfg.arch, "path": str(resolve(src.run).resolve()),
                                  "weights_hash": weights_hash(src.run), "step": src.gan_meta.get("step")},
                    "vae": {"path": str(resolve(src.vae_path).resolve()), "weights_hash": weights_hash(src.vae_path)}},
        "exporter": {"torch": torch.__version__, "method": "torch.onnx.export(dynamo=True)", "opset": opset},
    }


def export_onnx(run: str | os.PathLike, out: str | os.PathLike, *, vae: str | os.PathLike | None = None,
                int8: bool = False, force: bool = False, text_encoder_path: str | os.PathLike | None = None,
                opset: int = OPSET, threads: int | None = None,
                progress: Callable[[str], None] = lambda m: None) -> ExportResult:
    """Export the GAN ``run`` (with its VAE and text encoder) into the folder ``out``; see the module docstring.

    ``out`` is claimed before anything is written (lsgan.outputs: an existing folder needs ``force``, which
    replaces only lsgan's files, and it may not lie inside an input). ``int8`` also writes the quantised graphs and measures their
    joint error against the fp32 ones (``threads``: onnxruntime's, for that measurement).
    """
    from lsgan.deploy.runtime import OnnxMotionModel

    missing = [m for m in ("onnx", "onnxscript", "onnxruntime") if importlib.util.find_spec(m) is None]
    if missing:
        raise ValueError(f"export-model --onnx needs {', '.join(missing)}: pip install 'lsgan[onnx]'")
    t0 = time.perf_counter()
    meta = gan_meta(run)
    vae = Path(vae) if vae is not None else recorded_vae(run, meta)
    inputs = [run, vae, *([text_encoder_path] if text_encoder_path else [])]
    outputs.check_inputs(Path(out), inputs)
    src = load_sources(run, vae, text_encoder_path)  # before --force clears an earlier export: this one can be made
    folder = outputs.claim_folder(out, force=force, inputs=inputs)
    for name in planned_files(src, int8):
        outputs.claim_file(folder / name, force=True)
    folder.mkdir(parents=True, exist_ok=True)
    graphs = export_graphs(src, folder, opset, progress)
    tokenizer = write_tokenizer(src.encoder, folder) if src.encoder is not None else None
    quantised = None
    if int8:
        progress(f"quantising {q.DECODER_INT8_NODES} to int8")
        quantised = q.quantise(folder / "decoder.onnx", folder / "decoder.int8.onnx")
    manifest = build_manifest(src, folder, graphs, tokenizer, quantised, opset)
    if int8:
        progress("measuring the int8 graphs' joint error against fp32 (100 motions)")
        fp32, int8_ = (OnnxMotionModel(folder, manifest, variant=v, threads=threads, check_files=False)
                       for v in ("fp32", "int8"))
        manifest["variants"]["int8"]["joint_error_mm"] = q.joint_error_mm(fp32, int8_)
    with atomic_file(folder / MANIFEST, "w", encoding="utf-8") as fh:
        json.dump(manifest, fh, indent=1)
    return ExportResult(folder, manifest, time.perf_counter() - t0)
