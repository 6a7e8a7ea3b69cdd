"""Export every motion of an input (joints .npy, features .npy or a generate folder) to one format.

This is what ``lsgan export`` runs; notebooks can call :func:`export_motions` directly.
"""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lsgan import outputs
from lsgan.errors import reading
from lsgan.data.skeleton import FEATURE_DIM
from lsgan.export.bvh import load_motion_joints

FORMATS = ("glb", "bvh", "gif", "mp4")


@dataclass(frozen=True)
class Exported:
    """One written motion: its file, its frame count, a BVH's metres per unit, the fitted-parameter file and fit
    error (body export only)."""

    path: Path
    frames: int
    unit_m: float = 0.01
    params: Path | None = None
    fit_mean_error_mm: float | None = None
    fit_max_error_mm: float | None = None


def manifest_titles(source: Path) -> dict[str, str]:
    """Output stem -> prompt (or action) from a generate folder's manifest.json."""
    manifest = source / "manifest.json" if source.is_dir() else source.parent / "manifest.json"
    if not manifest.exists():
        return {}
    with reading(manifest, "a manifest lsgan generate wrote"):
        entries = json.loads(manifest.read_text(encoding="utf-8")).get("motions", [])
        return {e["joints"].removesuffix("_joints.npy"): str(e.get("text") or e.get("action") or "") for e in entries}


def export_motions(source: str | Path, output: str | Path, *, fmt: str, fps: float = 20.0,
                   title: str | None = None, body_model: str | Path | None = None, gender: str = "neutral",
                   model_type: str = "auto", fit_iterations: int = 100, force: bool = False,
                   rig: str | Path | None = None, joint_map: str | Path | None = None,
                   preset: str | None = None, fix_feet: bool | None = None) -> list[Exported]:
    """Write each motion of ``source`` as ``fmt`` under ``output`` (a file when ``source`` holds one motion
    and ``output`` ends in the format's extension, else a folder).

    With ``body_model`` (GLB only) the body is fitted to each motion and written as one skinned mesh, with
    the fitted parameters beside it as ``<stem>.npz``. Raises ValueError / ClipError / BodyModelError /
    EncodeError with a message naming the file and the problem. An existing output is refused unless
    ``force``, which replaces only files lsgan wrote (see :mod:`lsgan.outputs`).

    With ``rig`` (a BVH file; BVH or GLB) each motion is retargeted onto that skeleton through the joint map
    ``joint_map`` (a JSON file) or ``preset`` (:mod:`lsgan.export.retarget`).

    ``fix_feet`` (True) holds the feet still while in contact (:mod:`lsgan.motion.feet`), with the contacts of each
    motion's features (a generate folder's ``*_features.npy``, or a features .npy), else contacts estimated from
    the joints. None or False (the default) exports the motions as they are: a generate folder's already carry
    the feet ``lsgan generate`` gave them, so the export shows the motion of record.
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
    if body_model is not None and rig is not None:
        raise ValueError("a body model and a rig do not go together: --body-model fits SMPL's body, --rig retargets "
                         "onto your skeleton (use one)")
    model = read_body_model(body_model, model_type=model_type, gender=gender) if body_model is not None else None
    rigged = _load_rig(rig, joint_map, preset, fmt) if rig is not None else None
    source, out = Path(source), Path(output)
    titles = manifest_titles(source) if fmt in ("gif", "mp4") else {}
    motions = clean_feet(source, checked_motions(source, load_motion_joints(source), fps), fix_feet)
    ext = f".{fmt}"
    single = len(motions) == 1 and out.suffix.lower() == ext
    paths = [out if single else out / f"{name.removesuffix('_joints')}{ext}" for name, _ in motions]
    if not single:
        outputs.claim_folder(out, force=force, inputs=[source])
    for path in paths:
        outputs.claim_file(path, force=force or not single, inputs=[source, *([rig] if rig else [])])
        if model is not None:
            outputs.claim_file(path.with_suffix(".npz"), force=force or not single, inputs=[source])
    results = []
    for path, (name, joints) in tqdm(list(zip(paths, motions)), desc=f"export {fmt}", unit="motion",
                                     disable=len(motions) < 2):
        if model is not None:
            fit = fit_body(joints, model, iterations=fit_iterations, fps=fps)
            write_body_glb(path, fit, model)
            params = write_fit_npz(path.with_suffix(".npz"), fit)
            results.append(Exported(path, len(joints), params=params, fit_mean_error_mm=fit.mean_error_mm,
                                    fit_max_error_mm=fit.max_joint_error_mm))
        elif fmt in ("gif", "mp4"):
            label = title if title is not None else titles.get(path.stem, path.stem)
            (write_gif if fmt == "gif" else write_mp4)(path, joints, fps=fps, title=label)
            results.append(Exported(path, len(joints)))
        elif rigged is not None:
            from lsgan.export.retarget import write_rig_bvh, write_rig_glb

            (write_rig_glb if fmt == "glb" else write_rig_bvh)(path, joints, *rigged, fps=fps)
            results.append(Exported(path, len(joints), unit_m=rigged[1].scale))
        else:
            (write_glb if fmt == "glb" else write_bvh)(path, joints, fps=fps)
            results.append(Exported(path, len(joints)))
    return results


def _load_rig(rig: str | Path, joint_map: str | Path | None, preset: str | None, fmt: str):
    """(rig Bvh, JointMap) for ``--rig``, checked against each other before anything is written."""
    from lsgan.data.joint_maps import get_joint_map
    from lsgan.export.retarget import load_rig, map_warnings, plan_rig

    if fmt not in ("bvh", "glb"):
        raise ValueError(f"a rig is only used by the BVH and GLB exports (--bvh/--glb --rig), not --{fmt}")
    if (joint_map is None) == (preset is None):
        raise ValueError("a rig needs a joint map: --joint-map MAP.json or --preset NAME (one of them)")
    skeleton = load_rig(rig)
    jmap = get_joint_map(preset or "", joint_map)
    plan_rig(skeleton, jmap)
    for line in map_warnings(skeleton, jmap):
        print(f"warning: {line}", file=sys.stderr)
    return skeleton, jmap


def _features_of(source: Path, name: str) -> Path | None:
    """The features file beside a motion of ``source`` (a generate folder or .npy), if there is one."""
    folder = source if source.is_dir() else source.parent
    if not source.is_dir() and not name.endswith("_joints"):
        return source  # a features .npy is its own features (checked by shape)
    path = folder / f"{name.removesuffix('_joints')}_features.npy"
    return path if path.exists() else None


def checked_motions(source: Path, motions: list[tuple[str, np.ndarray]], fps: float) -> list:
    """``motions``, each checked as every exporter checks it (:func:`lsgan.export.bvh.checked_motion`) before
    anything is written: a ValueError names the motion's file."""
    from lsgan.export.bvh import checked_motion

    for name, joints in motions:
        try:
            checked_motion(joints, fps)
            if len(joints) < 2:
                raise ValueError("a motion needs at least 2 frames")
        except ValueError as e:
            where = source if not source.is_dir() else source / f"{name}.npy"
            raise ValueError(f"{where}: {e}") from None
    return motions


def clean_feet(source: str | Path, motions: list[tuple[str, np.ndarray]], fix: bool | None) -> list:
    """``motions`` with :func:`lsgan.motion.feet.fix_feet` applied as ``export_motions``'s ``fix_feet`` says."""
    from lsgan.data.clip import load_npy
    from lsgan.motion.feet import contacts_from_features, estimate_contacts, fix_feet

    if not fix:  # generated motions carry the feet generate gave them (lsgan.generation.decoded_motion)
        return motions
    out = []
    for name, joints in motions:
        path = _features_of(Path(source), name)
        features = load_npy(path) if path is not None else None
        if features is not None and features.shape == (len(joints), FEATURE_DIM):
            out.append((name, fix_feet(joints, contacts_from_features(features))))
        else:  # plain joints: the contacts their features would carry; the floor only if they stand on it
            floor = 0.0 if joints[..., 1].min() > -0.05 else None
            out.append((name, fix_feet(joints, estimate_contacts(joints), floor=floor)))
    return out
