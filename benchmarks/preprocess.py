"""Benchmark of the data pipeline: the features step (frames/s, one process) and a whole Bandai import.

    python benchmarks/preprocess.py                 # both parts (the import needs ../shared)
    python benchmarks/preprocess.py --skip-import   # features step only
    python benchmarks/preprocess.py --json out.json

The features step is timed on synthetic clips of HumanML3D-like lengths, batched as the pipeline runs it,
against a baseline measured in the same run: the same code called one clip at a time. Targets on the
2-core CI machine: >= 50,000 frames/s, and the whole Bandai import (5,804 clips with mirrors) < 120 s.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lsgan.data.features import joints_to_features
from lsgan.data.sources.synthetic import SyntheticSource

SHARED = Path(__file__).resolve().parents[2] / "shared"


def _clips(n: int) -> list[np.ndarray]:
    source = SyntheticSource(num_clips=n, seed=1)
    return [source.load(item)[0].joints for item in source.scan()]


def bench_features(clips: list[np.ndarray], repeats: int = 3) -> dict:
    frames = sum(len(c) for c in clips)
    joints_to_features(clips[:4])  # warm-up
    batched = min(_timed(lambda: joints_to_features(clips)) for _ in range(repeats))
    one_by_one = min(_timed(lambda: [joints_to_features(c) for c in clips]) for _ in range(repeats))
    return {
        "clips": len(clips),
        "frames": frames,
        "frames_per_s": frames / batched,
        "baseline_one_clip_per_call_frames_per_s": frames / one_by_one,
        "ratio_vs_baseline": one_by_one / batched,
        "target_frames_per_s": 50_000,
    }


def bench_bandai_import(workers: int) -> dict:
    from lsgan.data.preprocess import preprocess
    from lsgan.data.sources.bvh import BvhSource

    root = SHARED / "data" / "bandai-namco-2"
    if not root.exists():
        return {"not_run": f"{root} is absent"}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        result = preprocess(BvhSource(root=str(root), preset="bandai"), Path(tmp) / "bandai.h5", workers=workers)
        wall = time.perf_counter() - t0
    return {"workers": workers, "clips": result.clips, "skipped_clips": len(result.skipped), "frames": result.frames,
            "wall_s": wall, "target_wall_s": 120}


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", type=int, default=300, help="synthetic clips for the features step")
    ap.add_argument("--workers", type=int, default=2, help="worker processes for the Bandai import")
    ap.add_argument("--skip-import", action="store_true")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    out = {"machine": f"{platform.machine()} {platform.processor() or ''} python {platform.python_version()}".strip(),
           "features": bench_features(_clips(args.clips))}
    f = out["features"]
    print(f"features step: {f['frames_per_s']:,.0f} frames/s batched, {f['baseline_one_clip_per_call_frames_per_s']:,.0f}"
          f" one clip per call (x{f['ratio_vs_baseline']:.2f}); {f['frames']:,} frames in {f['clips']} clips", file=sys.stderr)
    if not args.skip_import:
        out["bandai_import"] = b = bench_bandai_import(args.workers)
        if "not_run" in b:
            print(f"bandai import: not run ({b['not_run']})", file=sys.stderr)
        else:
            print(f"bandai import: {b['clips']:,} clips, {b['frames']:,} frames in {b['wall_s']:.1f} s"
                  f" with {b['workers']} workers", file=sys.stderr)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
