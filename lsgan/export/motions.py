"""Export every motion of an input (joints .npy, features .npy or a generate folder) to one format.

This is what ``lsgan export`` runs; notebooks can call :func:`export_motions` directly.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from lsgan import outputs
from lsgan.export.bvh import load_motion_joints

FORMATS = ("glb", "bvh", "gif", "mp4")


@dataclass(frozen=True)
class Exported:
    """One written motion: its file, its frame count, the fitted-parameter file and fit error (body export only)."""

    path: Path
    frames: int
    params: Path | None = None
    fit_mean_error_mm: float | None = None
    fit_max_error_mm: float | None = None


def manifest_titles(source: Path) -> dict[str, str]:
    """Output stem -> prompt (or action) from a generate folder's manifest.json."""
    manifest = source / "manifest.json" if source.is_dir() else source.parent / "manifest.json"
    if not manifest.exists():
        return {}
    entries = json.loads(manifest.read_text()).get("motions", [])
    return {e["joints"].removesuffix("_joints.npy"): e.get("text") or e.get("action") or "" for e in entries}


def export_motions(source: str | Path, output: str | Path, *, fmt: str, fps: float = 20.0,
                   title: str | None = None, body_model: str | Path | None = None, gender: str = "neutral",
                   model_type: str = "auto", fit_iterations: int = 100, force: bool = False) -> list[Exported]:
    """Write each motion of ``source`` as ``fmt`` under ``output`` (a file when ``source`` holds one motion
    and ``output`` ends in the format's extension, else a folder).

    With ``body_model`` (GLB only) the body is fitted to each motion and written as one skinned mesh, with
    the fitted parameters beside it as ``<stem>.npz``. Raises ValueError / ClipError / BodyModelError /
    EncodeError with a message naming the file and the problem. An existing output is refused unless
    ``force``, which replaces only files lsgan wrote (see :mod:`lsgan.outputs`).
    """
    from lsgan.data.body_model import read_body_model
    from lsgan.export.body import fit_body, write_fit_npz
    from lsgan.export.bvh import write_bvh
    from lsgan.export.glb import write_body_glb, write_glb
    from lsgan.export.preview import write_gif, write_mp4

    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if body_model is not None and fmt != "glb":
        raise ValueError("a body model is only used by the GLB export (--glb --body-model DIR)")
    model = read_body_model(body_model, model_type=model_type, gender=gender) if body_model is not None else None
    source, out = Path(source), Path(output)
    titles = manifest_titles(source) if fmt in ("gif", "mp4") else {}
    motions = load_motion_joints(source)
    ext = f".{fmt}"
    single = len(motions) == 1 and out.suffix.lower() == ext
    paths = [out if single else out / f"{name.removesuffix('_joints')}{ext}" for name, _ in motions]
    if not single:
        outputs.claim_folder(out, force=force, inputs=[source])
    for path in paths:
        outputs.claim_file(path, force=force or not single, inputs=[source])
        if model is not None:
            outputs.claim_file(path.with_suffix(".npz"), force=force or not single, inputs=[source])
    results = []
    for path, (name, joints) in tqdm(list(zip(paths, motions)), desc=f"export {fmt}", unit="motion",
                                     disable=len(motions) < 2):
        if model is not None:
            fit = fit_body(joints, model, iterations=fit_iterations, fps=fps)
            write_body_glb(path, fit, model)
            params = write_fit_npz(path.with_suffix(".npz"), fit)
            results.append(Exported(path, len(joints), params, fit.mean_error_mm, fit.max_joint_error_mm))
        elif fmt in ("gif", "mp4"):
            label = title if title is not None else titles.get(path.stem, path.stem)
            (write_gif if fmt == "gif" else write_mp4)(path, joints, fps=fps, title=label)
            results.append(Exported(path, len(joints)))
        else:
            (write_glb if fmt == "glb" else write_bvh)(path, joints, fps=fps)
            results.append(Exported(path, len(joints)))
    return results
