"""False-positive rate and cost of the import plausibility checks (lsgan.data.plausibility) on real BVH mocap.

Every Bandai-Namco-2 and CMU clip in ../shared is read with lsgan's BVH reader and its preset joint map,
resampled to 20 fps and checked as imported (``ok``), with the other up axis (``up``: a Y-up file read as
Z-up), with the scale x100, x0.01, x10 (a mm file read as cm), x2.54 (a cm file read as inches) and x0.394
(an inch file read as cm), and with the left and right knees (``knees``) or elbows (``elbows``) swapped in the
joint map. Reports, per variant, the clips warned about by kind and the ranges of the figures, and the time
per clip of the checks (and of reading the BVH file, for comparison).

    OMP_NUM_THREADS=1 python benchmarks/plausibility.py --json plausibility.json
    python benchmarks/plausibility.py --limit 100 --variants ok up
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from lsgan.data.bvh import forward_kinematics, read_bvh
from lsgan.data.joint_maps import PRESETS, apply_joint_map
from lsgan.data.plausibility import clip_checks, format_summary, summarise
from lsgan.data.resample import resample
from lsgan.data.skeleton import FPS
from lsgan.data.sources.bvh import BvhSource, clip_name

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
VARIANTS = {
    "ok": {},
    "up": {"up": "z"},
    "x100": {"scale_factor": 100.0},
    "x0.01": {"scale_factor": 0.01},
    "x10": {"scale_factor": 10.0},
    "x2.54": {"scale_factor": 2.54},
    "x0.394": {"scale_factor": 1 / 2.54},
    "knees": {"swap": ("left_knee", "right_knee")},
    "elbows": {"swap": ("left_elbow", "right_elbow")},
}


def variant_map(preset: str, variant: str):
    """The preset's joint map with the variant's up axis or scale factor."""
    jmap = PRESETS[preset]
    spec = VARIANTS[variant]
    if "up" in spec:
        jmap = replace(jmap, up=spec["up"])
    if "swap" in spec:
        a, b = spec["swap"]
        jmap = replace(jmap, joints={**jmap.joints, a: jmap.joints[b], b: jmap.joints[a]})
    return replace(jmap, scale=jmap.scale * spec.get("scale_factor", 1.0))


def measure(files: list[tuple[str, Path]], variants: list[str]) -> dict:
    """Checks of every (preset, file) under every variant, {variant: {name: checks}}, and the milliseconds
    per clip spent reading and in the checks (on the ``ok`` variant, else the first one)."""
    out: dict[str, dict] = {v: {} for v in variants}
    timed = "ok" if "ok" in variants else variants[0]
    read_s = check_s = 0.0
    for preset, path in files:
        t0 = time.perf_counter()
        bvh = read_bvh(path)
        positions = forward_kinematics(bvh)
        read_s += time.perf_counter() - t0
        for v in variants:
            joints = apply_joint_map(positions, bvh.names, variant_map(preset, v), str(path))
            joints = resample(joints, float(bvh.fps), float(FPS)).astype(np.float32)
            t1 = time.perf_counter()
            out[v][clip_name(path)] = clip_checks(joints)
            check_s += (time.perf_counter() - t1) if v == timed else 0.0
    n = max(len(files), 1)
    return {"checks": out, "read_ms_per_clip": 1e3 * read_s / n, "check_ms_per_clip": 1e3 * check_s / n}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bandai", default=str(SHARED / "bandai-namco-2"))
    p.add_argument("--cmu", default=str(SHARED / "cmu"))
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--limit", type=int, default=None, help="only the first N Bandai clips")
    p.add_argument("--json", default=None, help="write the summaries and timings here")
    a = p.parse_args(argv)
    files = [("bandai", f) for f in BvhSource(root=a.bandai).scan()[: a.limit]]
    files += [("cmu", f) for f in BvhSource(root=a.cmu, preset="cmu").scan()]
    t0 = time.perf_counter()
    result = measure(files, a.variants)
    report = {"clips": len(files), "read_ms_per_clip": result["read_ms_per_clip"],
              "check_ms_per_clip": result["check_ms_per_clip"], "wall_s": time.perf_counter() - t0,
              "variants": {v: summarise(c) for v, c in result["checks"].items()}}
    for v, s in report["variants"].items():
        print(f"[{v}] {format_summary(s)}")
    print(f"{len(files)} clips; reading {report['read_ms_per_clip']:.2f} ms per clip, checks "
          f"{report['check_ms_per_clip']:.3f} ms per clip; {report['wall_s']:.1f} s in all")
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
