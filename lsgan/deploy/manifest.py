"""``manifest.json`` of an ONNX export: what the graphs are, how to feed them, and where they came from.

The manifest is written last, so a folder without one is an unfinished (or foreign) export. Every file the
export wrote is listed with its SHA-256; readers check the files they use, so a damaged or replaced graph is
named instead of producing wrong motions. ``format_version`` changes whenever a reader of an older version
would misread a newer folder.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from lsgan.outputs import file_sha256

FORMAT = "lsgan-onnx"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
GRAPHS = ("text_encoder", "generator", "decoder")  # in the order they run
VARIANTS = ("fp32", "int8")
CONDITIONS = ("text", "action")
REQUIRED = ("condition", "noise_dim", "latent_dim", "latent_mean", "latent_std", "feature_mean", "feature_std",
            "fps", "max_frames", "graphs", "variants", "files", "sources")
HOW_TO_EXPORT = "make one with `lsgan export-model RUN -o DIR --onnx`"


def file_entry(path: Path) -> dict:
    """A file's manifest entry: size and SHA-256."""
    return {"bytes": path.stat().st_size, "sha256": file_sha256(path)}


def read_manifest(folder: str | os.PathLike) -> dict:
    """The manifest of an exported folder, checked for format and version (not yet the files: :func:`verify`)."""
    folder = Path(folder)
    path = folder / MANIFEST
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder; an ONNX export is a folder ({HOW_TO_EXPORT})")
    if not path.is_file():
        raise ValueError(f"{folder}: no {MANIFEST}, so not a (finished) ONNX export of lsgan; {HOW_TO_EXPORT}")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, OSError) as e:
        raise ValueError(f"{path}: truncated or corrupt ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise ValueError(f"{path}: not the manifest of an lsgan ONNX export (no format {FORMAT!r})")
    version = manifest.get("format_version")
    if version != FORMAT_VERSION:
        raise ValueError(f"{path}: format version {version!r}; this lsgan reads version {FORMAT_VERSION}: "
                         "export the model again with this lsgan")
    missing = [k for k in REQUIRED if k not in manifest]
    if missing or manifest["condition"] not in CONDITIONS:
        raise ValueError(f"{path}: incomplete manifest (missing {', '.join(missing) or 'a known condition'})")
    return manifest


def verify(folder: str | os.PathLike, manifest: dict, names: list[str]) -> None:
    """Check that the files ``names`` are as the export wrote them (present, same SHA-256)."""
    folder = Path(folder)
    for name in names:
        path = folder / name
        entry = manifest["files"].get(name)
        if entry is None:
            raise ValueError(f"{folder / MANIFEST}: does not list {name}")
        if not path.is_file():
            raise ValueError(f"{path}: missing from the export; export the model again")
        if file_sha256(path) != entry["sha256"]:
            raise ValueError(f"{path}: changed since it was exported (SHA-256 differs from {MANIFEST}): damaged or "
                             "replaced; export the model again")


def variant_files(folder: str | os.PathLike, manifest: dict, variant: str) -> dict[str, str]:
    """{graph: file name} of a variant ("fp32", "int8"), with a clear error when the export lacks it."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; choose one of {VARIANTS}")
    graphs = manifest["variants"].get(variant, {}).get("graphs")
    if not graphs:
        hint = " (export with --int8)" if variant == "int8" else ""
        raise ValueError(f"{folder}: has no {variant} graphs{hint}")
    return graphs
