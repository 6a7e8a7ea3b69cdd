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
import re
import signal
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from lsgan import __version__, outputs
from lsgan.data.clip import Caption, ClipError, RawClip, mirror_caption, swap_left_right
from lsgan.data.features import joints_to_features
from lsgan.data.plausibility import clip_checks, summarise
from lsgan.data.plausibility import format_summary as format_plausibility
from lsgan.data.shards import FEATURE_LIMIT, FORMAT_VERSION, ClipRecord, unusable_rows, write_shard
from lsgan.data.skeleton import FEATURE_DIM, FPS, NUM_JOINTS, mirror_joints
from lsgan.faults import fault_point
from lsgan.interrupts import sigint_held
from lsgan.io import atomic_file
from lsgan.pickles import load_npz

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
    plausibility: dict | None = None  # lsgan.data.plausibility.summarise() of the clips imported from joints

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
    return outputs.file_sha256(path) if os.path.isfile(path) else None


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
    if len(bad := unusable_rows(x)):
        raise ClipError(f"feature values that are NaN, infinite or beyond ±{FEATURE_LIMIT:g} in {len(bad)} of "
                        f"{len(x)} frames (first: frame {bad[0]})")
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


def item_files(source, item: str) -> list[str]:
    """The files one work item reads, which address its chunk: the source's own list, else the item's file."""
    own = getattr(source, "item_files", None)
    if callable(own):
        return [os.fspath(f) for f in own(item)]
    for candidate in (item, item.partition("#")[0]):
        if os.path.isfile(candidate):
            return [candidate]
    return []


def process_chunk(source, items: list[str], mirror: bool | None, min_frames: int) -> dict:
    """Load, validate and featurise the clips of some items (runs in a worker). Never raises for bad input.

    ``inputs`` maps every file read to its SHA-256, hashed just before it was read.
    """
    fault_point("preprocess.worker")  # tests/test_faults.py: a worker that dies (each counts its own visits)
    records: list[dict] = []
    skips: list[dict] = []
    inputs: dict[str, str | None] = {}
    checks: dict[str, dict] = {}  # plausibility figures of each clip imported from joints
    pending: list[RawClip] = []  # clips with joints, featurised together below
    for item in items:
        for f in item_files(source, item):
            inputs.setdefault(f, _sha256(f))
        try:
            clips = source.load(item)
        except ClipError as e:
            skips.append({"item": item, "clip": None, "reason": str(e)})
            continue
        except Exception as e:  # an importer bug or an unforeseen format problem: report, do not crash the run
            skips.append({"item": item, "clip": None, "reason": f"{type(e).__name__}: {e}"})
            continue
        for clip in clips:
            try:
                if clip.features is not None:
                    records.append(_record(clip, _check_features(clip, min_frames)))
                    continue
                clip.joints = _check_joints(clip, min_frames)
            except ClipError as e:
                skips.append({"item": item, "clip": clip.name, "reason": str(e)})
                continue
            checks[clip.name] = clip_checks(clip.joints)  # mirrored copies give the same figures
            pending.append(clip)
            if clip.mirror if mirror is None else mirror:
                pending.append(_mirrored(clip))
    _featurise(pending, records, skips)
    imported = {r["name"] for r in records}
    checks = {name: c for name, c in checks.items() if name in imported}
    return {"records": records, "skips": skips, "inputs": inputs, "plausibility": checks}


def _featurise(pending: list[RawClip], records: list[dict], skips: list[dict]) -> None:
    """Features of all pending clips in one batch; a clip that fails is found and skipped with its reason."""
    if not pending:
        return
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
        if isinstance(x, Exception) or len(unusable_rows(x)):
            why = f"feature computation failed: {x}" if isinstance(x, Exception) else (
                f"features are not finite or beyond ±{FEATURE_LIMIT:g} (degenerate skeleton: coincident joints or "
                "zero-length bones? positions in other units than metres?)")
            skips.append({"item": clip.source_file, "clip": clip.name, "reason": why})
            continue
        records.append(_record(clip, x))


def _save_chunk(path: Path, key: str, result: dict) -> None:
    arrays = {f"f{i}": r["features"] for i, r in enumerate(result["records"])}
    meta = {
        "key": key,
        "records": [{k: v for k, v in r.items() if k != "features"} for r in result["records"]],
        "skips": result["skips"],
        "inputs": result["inputs"],
        "plausibility": result["plausibility"],
    }
    with atomic_file(path) as f:
        np.savez(f, meta=np.array(json.dumps(meta)), **arrays)


def _load_chunk_meta(path: Path) -> dict:
    return json.loads(str(load_npz(path, keys=("meta",))["meta"]))


def _iter_records(paths: list[Path]) -> Iterator[ClipRecord]:
    for path in paths:
        z = load_npz(path)  # headers checked against the file before numpy allocates
        meta = json.loads(str(z["meta"]))
        for i, r in enumerate(meta["records"]):
            yield ClipRecord(
                name=r["name"], features=z[f"f{i}"], split=r["split"], source_file=r["source_file"],
                captions=[Caption(*c) for c in r["captions"]], action=r["action"], mirror_of=r["mirror_of"],
            )
        fault_point("preprocess.write")


def _source_config(source) -> dict:
    return {"name": source.name, **dataclasses.asdict(source)}


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:32]


@dataclass
class _Plan:
    """The work: chunks of items, each addressed by the content of what it reads and the options."""

    chunks: list[list[str]]
    keys: list[str]
    hashes: dict[str, str | None]  # every item file -> SHA-256 when planned
    extra: dict[str, str | None]  # the source's other inputs (split files, labels, maps) -> SHA-256


def _plan(source, items: list[str], chunk_size: int, options: dict) -> _Plan:
    files = {it: item_files(source, it) for it in items}
    hashes = {f: _sha256(f) for fs in files.values() for f in fs}
    extra = {p: _sha256(p) for p in source.inputs()}
    base = _digest({"lsgan": __version__, "format": FORMAT_VERSION, "source": _source_config(source),
                    "options": options, "inputs": extra})
    chunks = [items[i : i + chunk_size] for i in range(0, len(items), chunk_size)]
    keys = [_digest({"base": base, "items": [[it, [hashes[f] for f in files[it]]] for it in c]}) for c in chunks]
    return _Plan(chunks, keys, hashes, extra)


def _open_staging(staging: Path, manifest: dict, keep: set[str]) -> None:
    """Make the staging folder, keeping only the finished chunks named in ``keep``."""
    if staging.exists():
        if not outputs.made_folder(staging) or not outputs.is_ours(staging / "manifest.json"):
            raise PreprocessError(f"{staging}: exists and is not a staging folder lsgan made (or its manifest.json "
                                  "was changed); move it away")
        outputs.sweep_temps(staging)
        for p in staging.glob("chunk_*.npz"):
            if p.name not in keep and outputs.is_ours(p):
                outputs.remove(p)
    outputs.make_folder(staging)
    with atomic_file(staging / "manifest.json", "w", encoding="utf-8") as f:
        json.dump(manifest, f, indent=1)


def _close_staging(staging: Path, paths: list[Path]) -> None:
    """Remove the staging folder's own files, and the folder when lsgan made it and nothing else is left."""
    for p in [*paths, staging / "manifest.json"]:
        if outputs.is_ours(p):
            outputs.remove(p)
    outputs.sweep_temps(staging)
    try:
        outputs.remove(staging)
    except outputs.OutputError:
        pass  # someone else's files are in it, or lsgan did not make it: leave it


def _claim(source, items: list[str], output: Path, format: str, report: Path, force: bool) -> None:
    """Refuse outputs that exist (without ``force``), are not lsgan's, or hold the inputs."""
    roots = [getattr(source, a) for a in ("root", "path") if isinstance(getattr(source, a, None), str)]
    inputs = [*roots, *items[:1], *source.inputs()]
    outputs.check_apart(output, report, output.with_name(output.name + ".parts"))
    if format == "hdf5":
        outputs.claim_file(output, force=force, inputs=[*inputs, *(i for i in items if os.path.isfile(i))])
    else:
        outputs.claim_folder(output, force=force, inputs=inputs, whole=True)
    outputs.claim_file(report, force=force, inputs=inputs)


def _run_chunks(source, plan: _Plan, paths: list[Path], todo: list[int], *, mirror, min_frames: int,
                workers: int, strict: bool, progress: Callable[[int], None]) -> None:
    """Process the chunks not yet done (in worker processes when ``workers`` > 1), saving each when done."""

    def finished(k: int, result: dict) -> None:
        if strict and result["skips"]:
            s = result["skips"][0]
            reason = s["reason"].removeprefix(f"{s['item']}: ")  # a reader's reason may name the file already
            raise PreprocessError(f"{s['item']}{' [' + s['clip'] + ']' if s['clip'] else ''}: {reason}")
        _save_chunk(paths[k], plan.keys[k], result)
        progress(len(plan.chunks[k]))
        fault_point("preprocess.chunk")

    if workers <= 1:
        for k in todo:
            finished(k, process_chunk(source, plan.chunks[k], mirror, min_frames))
        return
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"), initializer=_init_worker) as pool:
        try:
            with sigint_held():  # the workers start here (one per submit): Ctrl-C is the main process's alone
                futures = {k: pool.submit(process_chunk, source, plan.chunks[k], mirror, min_frames) for k in todo}
            for k in todo:
                finished(k, futures[k].result())
        except BaseException as e:  # the workers end their current chunk and exit; the rest are never started
            pool.shutdown(wait=False, cancel_futures=True)
            if isinstance(e, BrokenProcessPool):  # says neither which run nor what to do
                raise PreprocessError(f"{paths[0].parent}: a worker process died (killed, or out of memory?); the "
                                      "finished chunks are kept there: run the same command with --resume") from None
            raise


def _check_unchanged(source, plan: _Plan, metas: list[dict]) -> dict[str, str | None]:
    """The hashes of what was read; an input edited while the run read it stops the run."""
    read: dict[str, str | None] = {}
    for m in metas:
        read.update(m["inputs"])
    now = {**{f: read.get(f) for f in plan.hashes}, **{p: _sha256(p) for p in plan.extra}}
    changed = sorted(f for f, h in {**plan.hashes, **plan.extra}.items() if now.get(f) != h)
    if changed:
        raise PreprocessError(f"{changed[0]}: changed while it was being preprocessed"
                              f"{f' (and {len(changed) - 1} more)' if len(changed) > 1 else ''}; run again")
    return {**read, **plan.extra}


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
    force: bool = False,
    report: str | os.PathLike | None = None,
    on_progress: Callable[[int, int], None] | None = None,
) -> PreprocessResult:
    """Import everything ``source`` lists and write ``output`` (an .h5 shard, or a folder for 'humanml3d').

    mirror: add mirrored copies ('M' + name); None follows the source's default.
    min_frames: clips with fewer joint frames are skipped as too short (training length bounds are
    applied later, when reading). resume: reuse the finished chunks in ``OUTPUT.parts/`` whose inputs
    (by SHA-256) and options are unchanged. force: replace an output lsgan wrote before (never another file).
    on_progress(done_items, total_items) is called after each chunk.
    """
    if format not in FORMATS:
        raise ValueError(f"unknown output format {format!r}; choose one of {', '.join(FORMATS)}")
    output = Path(output)
    report_path = Path(report) if report is not None else output.with_name(output.name + ".report.json")
    items = source.scan()
    if not items:
        raise PreprocessError(f"{getattr(source, 'root', source.name)!s}: no input files found")
    staging = output.with_name(output.name + ".parts")
    # a resumed run that was stopped after writing its output may replace that output (when it is lsgan's)
    _claim(source, items, output, format, report_path, force or (resume and (staging / "manifest.json").is_file()))
    options = {"mirror": mirror, "min_frames": min_frames, "chunk_size": chunk_size}
    plan = _plan(source, items, chunk_size, options)
    paths = [staging / f"chunk_{k}.npz" for k in plan.keys]
    _open_staging(staging, {"lsgan_version": __version__, "source": _source_config(source), "options": options,
                            "items": len(items)}, {p.name for p in paths} if resume else set())
    todo = [k for k, p in enumerate(paths) if not p.exists()]
    done = len(items) - sum(len(plan.chunks[k]) for k in todo)

    def progress(n: int) -> None:
        nonlocal done
        done += n
        if on_progress is not None:
            on_progress(done, len(items))

    progress(0)
    _run_chunks(source, plan, paths, todo, mirror=mirror, min_frames=min_frames, workers=workers, strict=strict,
                progress=progress)
    metas = [_load_chunk_meta(p) for p in paths]
    inputs = _check_unchanged(source, plan, metas)
    result = _write_output(source, output, format, paths, metas, inputs, options)
    _write_report(report_path, result, source)
    result.report = report_path
    fault_point("preprocess.report")
    _close_staging(staging, paths)
    if not result.clips:
        why = "; ".join(line.strip() for line in format_skips(result.skipped, report_path, groups=3).splitlines())
        raise PreprocessError(f"{getattr(source, 'root', source.name)!s}: no clip could be imported "
                              f"({len(result.skipped)} skipped): {why}")
    return result


def _write_output(source, output: Path, format: str, paths: list[Path], metas: list[dict], inputs: dict,
                  options: dict) -> PreprocessResult:
    """The shard or folder from the finished chunks (nothing is written when no clip was imported)."""
    skipped = [Skip(**s) for m in metas for s in m["skips"]]
    names = [r["name"] for m in metas for r in m["records"]]
    if not names:
        return PreprocessResult(output=output, clips=0, frames=0, captions=0, mirrored=0, skipped=skipped)
    dup = sorted(n for n, c in Counter(names).items() if c > 1)
    if dup:
        raise PreprocessError(f"{getattr(source, 'root', source.name)!s}: clip names are not unique: "
                              f"{', '.join(dup[:5])}")
    action_names = getattr(source, "action_names", None)
    action_names = list(action_names()) if callable(action_names) else sorted(
        {r["action"] for m in metas for r in m["records"] if r["action"] is not None}
    )
    provenance = {
        "source": _source_config(source),
        "options": {**options, "format": format},
        "inputs": [{"path": p, "sha256": inputs[p]} for p in sorted(inputs)],
        "lsgan_version": __version__,
        "format_version": FORMAT_VERSION,
    }
    stats_fn = getattr(source, "stats", None)
    stats = stats_fn() if callable(stats_fn) else None
    if format == "hdf5":
        need = sum(p.stat().st_size for p in paths) + (1 << 20)  # the chunks hold the features uncompressed
        summary = write_shard(output, _iter_records(paths), need_bytes=need, source=source.name,
                              action_names=action_names, provenance=provenance, stats=stats)
    else:
        from lsgan.data.humanml3d_format import write_humanml3d_folder

        summary = write_humanml3d_folder(output, _iter_records(paths), stats=stats, provenance=provenance)
    checks = {name: c for m in metas for name, c in m["plausibility"].items()}
    return PreprocessResult(
        output=output, clips=summary["clips"], frames=summary["frames"], captions=summary["captions"],
        mirrored=sum(1 for m in metas for r in m["records"] if r["mirror_of"]), skipped=skipped,
        plausibility=summarise(checks) if checks else None,
    )


def _init_worker() -> None:
    """One thread per worker process (the workers already use the cores; torch reads this at import), and
    Ctrl-C is left to the main process, which stops the run and reports once."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _die_with_parent()
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = "1"


def _die_with_parent() -> None:
    """On Linux, have the kernel kill this worker when the main process dies (even by SIGKILL), so a killed
    run leaves no orphans behind; elsewhere the pool's own shutdown is all there is."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() == 1:  # the main process died before this line
        os._exit(1)


def _write_report(path: Path, result: PreprocessResult, source) -> None:
    body = {
        "output": str(result.output),
        "source": _source_config(source),
        "clips": result.clips,
        "mirrored": result.mirrored,
        "frames": result.frames,
        "hours": round(result.hours, 4),
        "captions": result.captions,
        "skipped_by_reason": [{"reason": reason, "count": len(group), "items": [s.item for s in group]}
                              for reason, group in group_skips(result.skipped)],
        "skipped": [dataclasses.asdict(s) for s in result.skipped],
        "plausibility": result.plausibility,
    }
    with atomic_file(path, "w") as f:
        json.dump(body, f, indent=1)


def _reason_kind(skip: Skip) -> str:
    """A skip's reason with its file names and numbers blanked, so alike failures group together."""
    reason = skip.reason.replace(skip.item, "")
    reason = re.sub(r"\S*[/\\]\S*", "…", reason)
    return re.sub(r"\d+(\.\d+)?", "#", reason).strip(": ")


def group_skips(skipped: list[Skip]) -> list[tuple[str, list[Skip]]]:
    """Skips grouped by kind of reason, largest group first; each group is named by its first reason, less a leading
    ``ITEM:`` (the summary names the items). An item named inside a path stays: the path is a real file's."""
    groups: dict[str, list[Skip]] = {}
    for s in skipped:
        groups.setdefault(_reason_kind(s), []).append(s)
    return [(g[0].reason.removeprefix(f"{g[0].item}:").strip() or g[0].reason, g)
            for g in sorted(groups.values(), key=len, reverse=True)]


def format_skips(skipped: list[Skip], report: Path | None = None, groups: int = 8, examples: int = 3) -> str:
    """The skipped inputs for the terminal: one line per kind of reason, with a few of the names."""
    lines = []
    grouped = group_skips(skipped)
    for reason, group in grouped[:groups]:
        items = sorted({s.item for s in group})
        shown = ", ".join(Path(i).name for i in items[:examples]) + (", ..." if len(items) > examples else "")
        what = f"{len(items)} file{'s' if len(items) != 1 else ''}"
        if len(group) != len(items):
            what += f" ({len(group)} clips)"
        lines.append(f"  {what}: {reason} (e.g. {shown})" if len(items) > 1 else f"  {what}: {reason} ({shown})")
    if len(grouped) > groups:
        lines.append(f"  ... and {len(grouped) - groups} more kinds of failure")
    if report is not None:
        lines.append(f"  every skipped input and its reason: {report}")
    return "\n".join(lines)


def print_skips(result: PreprocessResult, stream=sys.stderr, warnings: int = 5) -> None:
    """The skipped inputs, grouped by reason, and the plausibility summary with its first warnings."""
    if result.skipped:
        print(format_skips(result.skipped, result.report), file=stream)
    if result.plausibility is not None:
        print(format_plausibility(result.plausibility), file=stream)
        lines = [w if w.startswith(name) else f"{name}: {w}"
                 for name, ws in result.plausibility["warnings"].items() for w in ws]
        for line in lines[:warnings]:
            print(f"  warning: {line}", file=stream)
        if len(lines) > warnings:
            print(f"  ... {len(lines) - warnings} more warnings in {result.report}", file=stream)
