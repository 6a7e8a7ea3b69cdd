"""Seam quality of long takes (``lsgan generate --timeline``, lsgan/timeline.py): jerk and foot sliding around
each seam against the same figures inside the segments.

``--timelines`` timelines (default 50) of 3-4 Bandai-like prompts (lsgan.data.captions' Bandai templates: a
random content label in a random style, one of the four paraphrases), each segment 40-120 frames (the Bandai
VAE's training lengths), are generated as ``generate --timeline ... --seed K`` does (timeline K with seed K), once
with ``--overlap`` (default 10) and once with hard cuts (overlap 0: the root still carried, the pose not blended).
Windows of 2 * ``--window`` + 1 frames (default +-5) are centred on each seam (the middle of the cross-fade; the cut
itself for hard cuts) and, as the reference, on the middle of each segment's own frames (outside any cross-fade).
Per window:

- jerk: lsgan.motion.quality.jerk of the window's frames (mean over joints and frame triples, m/s^3);
- skating: GMD's foot-skating flags (lsgan.motion.quality.foot_skating_ratio's rule, computed over the whole motion
  so the 5-frame speed average sees past the window's ends) averaged over the window's frame pairs;
- slide: the mean horizontal step (cm/frame) of the feet in GMD's ground contact (under 5 cm) in the window.

Means over windows are printed with a bootstrap 95% interval for the seam-to-inside ratio of each figure. A third
run joins the same timelines with ``--join continue`` (each segment optimised to start with the motion so far's
last 5 frames, lsgan.timeline.continued_motion), its seams centred where a segment's own frames begin.

    OMP_NUM_THREADS=2 python benchmarks/timeline.py --gan runs/bandai-gan --vae runs/bandai-vae --json timeline.json
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import uniform_filter1d
from tqdm import tqdm

from lsgan.data.captions import _CONTENT, _STYLE, bandai_captions
from lsgan.motion.quality import SKATE_SPEED, SKATE_WINDOW, _feet, foot_skating_ratio, jerk
from lsgan.generate import generate_loaded, load_models
from lsgan.timeline import Segment, continued_motion, timeline_motion


def timelines(n: int, seed: int) -> list[list[Segment]]:
    """``n`` timelines of 3-4 segments: a Bandai-like caption and 40-120 frames each."""
    rng = np.random.default_rng(seed)
    contents, styles = sorted(_CONTENT), sorted(_STYLE)
    out = []
    for k in range(n):
        out.append([Segment(bandai_captions(rng.choice(contents), rng.choice(styles))[rng.integers(4)],
                            int(rng.integers(40, 121)), f"timeline {k} item {i + 1}")
                    for i in range(int(rng.integers(3, 5)))])
    return out


def skating_flags(joints: np.ndarray) -> np.ndarray:
    """(T-1,) GMD's per-pair flag of ``foot_skating_ratio``: a foot in contact sliding over 0.5 m/s."""
    _, speed, contact = _feet(np.asarray(joints, np.float64), 20.0)
    window = uniform_filter1d(speed, size=SKATE_WINDOW, axis=-2, mode="constant", origin=0)
    return (contact & (speed > SKATE_SPEED) & (window > SKATE_SPEED)).any(axis=-1)


def contact_slide(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair: summed horizontal step (cm) of the feet in contact, and how many feet are in contact."""
    _, speed, contact = _feet(np.asarray(joints, np.float64), 20.0)
    return (np.where(contact, speed / 20.0 * 100.0, 0.0)).sum(-1), contact.sum(-1)


def windows(joints: np.ndarray, centres: list[int], half: int) -> list[dict]:
    """The three figures in [c - half, c + half] for each centre c."""
    flags = skating_flags(joints)
    assert abs(flags.mean() - foot_skating_ratio(joints)) < 1e-12  # the same rule as the library's figure
    slide, feet = contact_slide(joints)
    rows = []
    for c in centres:
        a, b = c - half, c + half  # frames a..b, pairs a..b-1
        rows.append({"jerk": float(jerk(joints[a : b + 1])), "skating": float(flags[a:b].mean()),
                     "slide_cm": float(slide[a:b].sum() / max(feet[a:b].sum(), 1)), "contact": int(feet[a:b].sum())})
    return rows


def measure(loaded, takes: list[list[Segment]], overlap: int, half: int, join: str = "crossfade") -> dict[str, list[dict]]:
    """{"seam": rows, "inside": rows} over all timelines joined with ``overlap`` (crossfade), or continued
    (``join`` "continue": the seam is where a segment's own frames begin, after the frames it shares)."""
    out: dict[str, list[dict]] = {"seam": [], "inside": []}
    for k, segments in enumerate(tqdm(takes, desc=f"{join} {overlap}", leave=False)):
        if join == "continue":
            result = continued_motion(loaded, segments, seed=k)
        else:
            result = timeline_motion(segments, overlap, lambda r: generate_loaded(loaded, r, seed=k),
                                     loaded.max_frames)
        joints = result.motions[0].joints
        frames = [s.frames for s in segments]
        starts = np.concatenate([[0], np.cumsum(frames)[:-1]])
        seams = [int(s + overlap // 2) for s in starts[1:]]
        own = [int((s + (overlap if i else 0) + s + n) // 2) for i, (s, n) in enumerate(zip(starts, frames))]
        out["seam"] += windows(joints, seams, half)
        out["inside"] += windows(joints, own, half)
    return out


def summary(rows: list[dict]) -> dict:
    """Means over windows; the slide weighted by the feet in contact."""
    contact = max(sum(r["contact"] for r in rows), 1)
    return {"windows": len(rows), **{k: float(np.mean([r[k] for r in rows])) for k in ("jerk", "skating")},
            "slide_cm": float(sum(r["slide_cm"] * r["contact"] for r in rows) / contact)}


def ratio_interval(seam: list[dict], inside: list[dict], key: str, seed: int = 0) -> tuple[float, float]:
    """Bootstrap 95% interval of mean(seam) / mean(inside) for ``key`` (1,000 resamples of the windows)."""
    rng = np.random.default_rng(seed)
    s, i = np.array([r[key] for r in seam]), np.array([r[key] for r in inside])
    ratios = [s[rng.integers(len(s), size=len(s))].mean() / max(i[rng.integers(len(i), size=len(i))].mean(), 1e-12)
              for _ in range(1000)]
    return float(np.percentile(ratios, 2.5)), float(np.percentile(ratios, 97.5))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--gan", required=True)
    parser.add_argument("--vae", required=True)
    parser.add_argument("--timelines", type=int, default=50)
    parser.add_argument("--overlap", type=int, default=10)
    parser.add_argument("--window", type=int, default=5, help="half width of a window, frames")
    parser.add_argument("--seed", type=int, default=0, help="seed of the prompts and lengths")
    parser.add_argument("--json", help="write the figures here as JSON")
    args = parser.parse_args()
    t0 = time.perf_counter()
    loaded = load_models(args.gan, args.vae, device="cpu")
    takes = timelines(args.timelines, args.seed)
    result = {"config": {**vars(args), "segments": sum(map(len, takes)), "machine": platform.processor() or
                         platform.machine()}, "runs": {}}
    print(f"{args.timelines} timelines, {sum(map(len, takes))} segments, windows of +-{args.window} frames")
    print(f"{'':28s} {'windows':>7s} {'jerk m/s^3':>11s} {'skating':>8s} {'slide cm/frame':>15s}")
    for overlap, name, join in ((args.overlap, f"overlap {args.overlap}", "crossfade"), (0, "hard cut", "crossfade"),
                                (0, "continue", "continue")):
        rows = measure(loaded, takes, overlap, args.window, join)
        run = {part: summary(r) for part, r in rows.items()}
        run["seam_over_inside_95"] = {k: ratio_interval(rows["seam"], rows["inside"], k) for k in ("jerk", "skating")}
        result["runs"][name] = run
        for part, label in (("inside", f"inside segments ({name})"), ("seam", f"seams, {name}")):
            s = run[part]
            print(f"{label:28s} {s['windows']:7d} {s['jerk']:11.1f} {s['skating']:8.3f} {s['slide_cm']:15.2f}")
        lo_j, hi_j = run["seam_over_inside_95"]["jerk"]
        lo_s, hi_s = run["seam_over_inside_95"]["skating"]
        print(f"{'  seam / inside (95%)':28s} {'':7s} {run['seam']['jerk'] / run['inside']['jerk']:6.2f} "
              f"[{lo_j:.2f}-{hi_j:.2f}] skating {run['seam']['skating'] / max(run['inside']['skating'], 1e-12):.2f} "
              f"[{lo_s:.2f}-{hi_s:.2f}]")
    result["seconds"] = time.perf_counter() - t0
    print(f"{result['seconds']:.0f} s", file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
