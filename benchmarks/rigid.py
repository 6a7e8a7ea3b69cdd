"""How far the motion of record is from the decoded joints, and what making it rigid (and holding its feet) does
to the quality columns.

    python benchmarks/rigid.py --gan RUN/gan --vae RUN/vae [--per-prompt 20] [--frames 120] [--seed 0]

Generates ``len(PROMPTS) x per-prompt`` motions once, then prints a markdown table: per motion, the distance of
the rigid joints from the decoded ones (mean and max over joints and frames, then over motions), the bone-length
spread within a motion, and the quality metrics (lsgan.eval.quality) of the decoded, rigid, and rigid +
``fix_feet`` joints.
"""
from __future__ import annotations

import argparse

import numpy as np

from lsgan.data.skeleton import bone_lengths
from lsgan.eval.quality import quality_metrics
from lsgan.export.feet import contacts_from_features, fix_feet
from lsgan.generate import Request, generate

PROMPTS = ("a person walks forward", "a person runs forward", "a person waves their right hand", "a person jumps up",
           "a person does a squat")


def spread_mm(joints: np.ndarray) -> float:
    """The largest change of one bone's length within a motion, in mm."""
    lengths = bone_lengths(np.asarray(joints, np.float64))
    return float((lengths.max(axis=0) - lengths.min(axis=0)).max() * 1000)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gan", required=True)
    ap.add_argument("--vae", required=True)
    ap.add_argument("--per-prompt", type=int, default=20)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    requests = [Request(text=p, frames=a.frames) for p in PROMPTS]
    motions = generate(a.gan, a.vae, requests, num=a.per_prompt, seed=a.seed, device="cpu").motions
    raw = [m.raw_joints for m in motions]
    rigid = [m.joints for m in motions]
    held = [fix_feet(m.joints, contacts_from_features(m.features)) for m in motions]
    gaps = [np.linalg.norm(r - d, axis=-1) * 1000 for r, d in zip(rigid, raw)]
    print(f"{len(motions)} motions of {a.frames} frames ({len(PROMPTS)} prompts x {a.per_prompt}, seed {a.seed})\n")
    print(f"rigid vs decoded joints: mean {np.mean([g.mean() for g in gaps]):.1f} mm, "
          f"max {max(g.max() for g in gaps):.1f} mm; bone-length spread within a motion: decoded median "
          f"{np.median([spread_mm(j) for j in raw]):.0f} mm (max {max(spread_mm(j) for j in raw):.0f}), rigid "
          f"max {max(spread_mm(j) for j in rigid):.4f} mm\n")
    print("| joints | skating ratio | penetration (mm) | floating (mm) | jerk (m/s^3) |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name, joints in (("decoded", raw), ("rigid (motion of record)", rigid), ("rigid + fix_feet", held)):
        q = quality_metrics(joints)
        print(f"| {name} | {q['foot_skating_ratio']:.3f} | {q['penetration_m'] * 1000:.1f} | "
              f"{q['floating_m'] * 1000:.1f} | {q['jerk_m_s3']:.0f} |")


if __name__ == "__main__":
    main()
