"""``lsgan preprocess``: any source -> validated, featurised clips -> an HDF5 shard or a HumanML3D folder.

Work is split into fixed chunks of input items. Each finished chunk is saved atomically in a staging
folder beside the output (``OUTPUT.parts/``), so an interrupted run continues with ``resume=True`` and
gives the same result; bad clips are reported with their reason and skipped (``strict`` makes them fatal).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from lsgan import __version__
from lsgan.data.clip import Caption, ClipError, RawClip, mirror_caption, swap_left_right
from lsgan.data.features import joints_to_features
from lsgan.data.shards import FORMAT_VERSION, ClipRecord, write_shard
from lsgan.io import atomic_file
from lsgan.data.skeleton import FEATURE_DIM, FPS, NUM_JOINTS, mirror_joints

FORMATS = ("hdf5", "humanml3d")


class PreprocessError(Exception):
    """A run that cannot go on (strict mode and a bad clip, a resume with other options, no clips at all)."""


@dataclass
class Skip:
    """A clip or input that was not imported, and why."""

    item: str
    reason: str
    clip: str | None = None


@dataclass
class PreprocessResult:
    output: Path
    clips: int
    frames: int
    captions: int
    mirrored: int
    skipped: list[Skip] = field(default_factory=list)
    report: Path | None = None

    @property
    def hours(self) -> float:
        return self.frames / FPS / 3600

    def summary(self) -> str:
        skipped = f"; skipped {len(self.skipped)}" + (f" (see {self.report})" if self.report else "")
        return (
            f"{self.output}: {self.clips} clips ({self.mirrored} mirrored), {self.frames:,} frames, "
            f"{self.hours:.2f} h, {self.captions} captions{skipped if self.skipped else ''}"
        )


def hash_split(name: str) -> str:
    """Deterministic 80/10/10 train/val/test split from a hash of the clip name."""
    u = int.from_bytes(hashlib.sha256(name.encode("utf-8")).digest()[:8], "big") / 2.0**64
    return "train" if u < 0.8 else ("val" if u < 0.9 else "test")


def _sha256(path: str) -> str | None:
    if not os.path.isfile(path):
        return None
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _check_joints(clip: RawClip, min_frames: int) -> np.ndarray:
    j = np.asarray(clip.joints)
    if j.ndim != 3 or j.shape[1:] != (NUM_JOINTS, 3):
        raise ClipError(f"joints of shape {j.shape}, expected (T, {NUM_JOINTS}, 3)")
    if not np.isfinite(j).all():
        bad = np.flatnonzero(~np.isfinite(j).all(axis=(1, 2)))
        raise ClipError(f"NaN or infinite joint positions in {len(bad)} of {len(j)} frames (first: frame {bad[0]})")
    if len(j) < max(min_frames, 2):
        raise ClipError(f"too short: {len(j)} frames at {FPS} fps (minimum {max(min_frames, 2)})")
    return j.astype(np.float32, copy=False)


def _check_features(clip: RawClip, min_frames: int) -> np.ndarray:
    x = np.asarray(clip.features)
    if x.ndim != 2 or x.shape[1] != FEATURE_DIM:
        raise ClipError(f"features of shape {x.shape}, expected (T, {FEATURE_DIM})")
    if not np.isfinite(x).all():
        raise ClipError("NaN or infinite feature values")
    if len(x) + 1 < max(min_frames, 2):
        raise ClipError(f"too short: {len(x)} feature frames (minimum {max(min_frames, 2) - 1})")
    return x.astype(np.float32, copy=False)


def _mirrored(clip: RawClip) -> RawClip:
    return RawClip(
        name="M" + clip.name,
        source_file=clip.source_file,
        joints=mirror_joints(clip.joints),
        captions=[mirror_caption(c) for c in clip.captions],
        action=swap_left_right(clip.action) if clip.action is not None else None,
        split=clip.split,
        mirror_of=clip.name,
    )


def _record(clip: RawClip, feats: np.ndarray) -> dict:
    base = clip.mirror_of or clip.name
    return {
        "name": clip.name,
        "features": feats,
        "captions": [dataclasses.astuple(c) for c in clip.captions],
        "action": clip.action,
        "split": clip.split or hash_split(base),
        "source_file": clip.source_file,
        "mirror_of": clip.mirror_of,
    }


def process_chunk(source, items: list[str], mirror: bool | None, min_frames: int) -> dict:
    """Load, validate and featurise the clips of some items (runs in a worker). Never raises for bad input."""
    records: list[dict] = []
    skips: list[dict] = []
    inputs: dict[str, str | None] = {}
    pending: list[RawClip] = []  # clips with joints, featurised together below
    for item in items:
        try:
            clips = source.load(item)
        except ClipError as e:
            skips.append({"item": item, "clip": None, "reason": str(e)})
            continue
        except Exception as e:  # an importer bug or an unforeseen format problem: report, do not crash the run
            skips.append({"item": item, "clip": None, "reason": f"{type(e).__name__}: {e}"})
            continue
        inputs[item] = _sha256(item)
        for clip in clips:
            try:
                if clip.features is not None:
                    records.append(_record(clip, _check_features(clip, min_frames)))
                    continue
                clip.joints = _check_joints(clip, min_frames)
            except ClipError as e:
                skips.append({"item": item, "clip": clip.name, "reason": str(e)})
                continue
            pending.append(clip)
            if clip.mirror if mirror is None else mirror:
                pending.append(_mirrored(clip))
    if pending:
        try:
            with np.errstate(all="ignore"):  # a degenerate clip yields NaN features, reported below
                feats = joints_to_features([c.joints for c in pending])
        except Exception:  # find the culprit(s) one by one
            feats = []
            for c in pending:
                try:
                    with np.errstate(all="ignore"):
                        feats.append(joints_to_features(c.joints))
                except Exception as e:
                    feats.append(e)
        for clip, x in zip(pending, feats):
            if isinstance(x, Exception) or not np.isfinite(x).all():
                why = f"feature computation failed: {x}" if isinstance(x, Exception) else (
                    "features are not finite (degenerate skeleton: coincident joints or zero-length bones?)")
                skips.append({"item": clip.source_file, "clip": clip.name, "reason": why})
                continue
            records.append(_record(clip, x))
    return {"records": records, "skips": skips, "inputs": inputs}


def _save_chunk(path: Path, result: dict) -> None:
    arrays = {f"f{i}": r["features"] for i, r in enumerate(result["records"])}
    meta = {
        "records": [{k: v for k, v in r.items() if k != "features"} for r in result["records"]],
        "skips": result["skips"],
        "inputs": result["inputs"],
    }
    with atomic_file(path) as f:
        np.savez(f, meta=np.array(json.dumps(meta)), **arrays)


def _load_chunk_meta(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z["meta"]))


def _iter_records(paths: list[Path]) -> Iterator[ClipRecord]:
    for path in paths:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            for i, r in enumerate(meta["records"]):
                yield ClipRecord(
                    name=r["name"], features=z[f"f{i}"], split=r["split"], source_file=r["source_file"],
                    captions=[Caption(*c) for c in r["captions"]], action=r["action"], mirror_of=r["mirror_of"],
                )


def _source_config(source) -> dict:
    return {"name": source.name, **dataclasses.asdict(source)}


def preprocess(
    source,
    output: str | os.PathLike,
    *,
    format: str = "hdf5",
    mirror: bool | None = None,
    min_frames: int = 10,
    workers: int = 1,
    chunk_size: int = 16,
    resume: bool = False,
    strict: bool = False,
    report: str | os.PathLike | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> PreprocessResult:
    """Import everything ``source`` lists and write ``output`` (an .h5 shard, or a folder for 'humanml3d').

    mirror: add mirrored copies ('M' + name); None follows the source's default.
    min_frames: clips with fewer joint frames are skipped as too short (training length bounds are
    applied later, when reading). on_progress(done_items, total_items) is called after each chunk.
    """
    if format not in FORMATS:
        raise ValueError(f"unknown output format {format!r}; choose one of {', '.join(FORMATS)}")
    output = Path(output)
    items = source.scan()
    if not items:
        raise PreprocessError(f"{source.name}: no input files found under {getattr(source, 'root', '')!s}")
    staging = output.with_name(output.name + ".parts")
    options = {"mirror": mirror, "min_frames": min_frames, "chunk_size": chunk_size}
    manifest = {"lsgan_version": __version__, "source": _source_config(source), "options": options, "items": len(items)}
    if staging.exists() and resume:
        old = json.loads((staging / "manifest.json").read_text()) if (staging / "manifest.json").exists() else None
        if old != json.loads(json.dumps(manifest)):
            raise PreprocessError(
                f"{staging}: the interrupted run used other inputs or options; run without --resume to start over"
            )
    elif staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True, exist_ok=True)
    (staging / "manifest.json").write_text(json.dumps(manifest, indent=1))

    chunks = [items[i : i + chunk_size] for i in range(0, len(items), chunk_size)]
    paths = [staging / f"chunk_{k:06d}.npz" for k in range(len(chunks))]
    todo = [k for k, p in enumerate(paths) if not p.exists()]
    done_items = len(items) - sum(len(chunks[k]) for k in todo)

    def finished(k: int, result: dict) -> None:
        nonlocal done_items
        if strict and result["skips"]:
            s = result["skips"][0]
            raise PreprocessError(f"{s['item']}{' [' + s['clip'] + ']' if s['clip'] else ''}: {s['reason']}")
        _save_chunk(paths[k], result)
        done_items += len(chunks[k])
        if on_progress is not None:
            on_progress(done_items, len(items))

    if on_progress is not None:
        on_progress(done_items, len(items))
    if workers <= 1:
        for k in todo:
            finished(k, process_chunk(source, chunks[k], mirror, min_frames))
    else:
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"), initializer=_init_worker) as pool:
            futures = {k: pool.submit(process_chunk, source, chunks[k], mirror, min_frames) for k in todo}
            try:
                for k in todo:
                    finished(k, futures[k].result())
            except BaseException:
                pool.shutdown(wait=False, cancel_futures=True)
                raise

    metas = [_load_chunk_meta(p) for p in paths]
    skipped = [Skip(**s) for m in metas for s in m["skips"]]
    names = [r["name"] for m in metas for r in m["records"]]
    if not names:
        raise PreprocessError(f"{source.name}: no clip could be imported ({len(skipped)} skipped)")
    dup = sorted(n for n, c in Counter(names).items() if c > 1)
    if dup:
        raise PreprocessError(f"clip names are not unique: {', '.join(dup[:5])}")
    action_names = getattr(source, "action_names", None)
    action_names = list(action_names()) if callable(action_names) else sorted(
        {r["action"] for m in metas for r in m["records"] if r["action"] is not None}
    )
    inputs = {k: v for m in metas for k, v in m["inputs"].items()}
    provenance = {
        "source": _source_config(source),
        "options": {**options, "format": format},
        "inputs": [{"path": p, "sha256": inputs[p]} for p in sorted(inputs)]
        + [{"path": p, "sha256": _sha256(p)} for p in source.inputs()],
        "lsgan_version": __version__,
        "format_version": FORMAT_VERSION,
    }
    stats_fn = getattr(source, "stats", None)
    stats = stats_fn() if callable(stats_fn) else None

    if format == "hdf5":
        summary = write_shard(
            output, _iter_records(paths), source=source.name, action_names=action_names,
            provenance=provenance, stats=stats,
        )
    else:
        from lsgan.data.humanml3d_format import write_humanml3d_folder

        summary = write_humanml3d_folder(output, _iter_records(paths), stats=stats, provenance=provenance)

    result = PreprocessResult(
        output=output, clips=summary["clips"], frames=summary["frames"], captions=summary["captions"],
        mirrored=sum(1 for m in metas for r in m["records"] if r["mirror_of"]), skipped=skipped,
    )
    report_path = Path(report) if report is not None else output.with_name(output.name + ".report.json")
    _write_report(report_path, result, source)
    result.report = report_path
    shutil.rmtree(staging)
    return result


def _init_worker() -> None:
    """One thread per worker process: the workers already use the cores (torch reads this at import)."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = "1"


def _write_report(path: Path, result: PreprocessResult, source) -> None:
    body = {
        "output": str(result.output),
        "source": _source_config(source),
        "clips": result.clips,
        "mirrored": result.mirrored,
        "frames": result.frames,
        "hours": round(result.hours, 4),
        "captions": result.captions,
        "skipped": [dataclasses.asdict(s) for s in result.skipped],
    }
    with atomic_file(path, "w") as f:
        json.dump(body, f, indent=1)


def print_skips(result: PreprocessResult, limit: int = 10, stream=sys.stderr) -> None:
    """A few skipped clips with their reasons, for the terminal."""
    for s in result.skipped[:limit]:
        print(f"  skipped {s.item}{' [' + s.clip + ']' if s.clip else ''}: {s.reason}", file=stream)
    if len(result.skipped) > limit:
        print(f"  ... and {len(result.skipped) - limit} more (see {result.report})", file=stream)
