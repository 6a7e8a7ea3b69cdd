"""How far the motion of record is from the decoded joints, and what making it rigid (and holding its feet) does
to the quality columns.

    python benchmarks/rigid.py --gan RUN/gan --vae RUN/vae [--prompts five|reference] [--per-prompt 20] \
        [--frames 120] [--seed 0]

Generates the prompts x per-prompt motions once (``five``: PROMPTS, 20 each by default; ``reference``: the 100
prompts of lsgan.deploy.int8.REFERENCE_PROMPTS, one each), then prints: per motion, the distance of the rigid
joints from the decoded ones (mean and max over joints and frames, then over motions), the bone-length spread
within a motion, and a markdown table of the quality metrics (lsgan.motion.quality, per-motion means) of the
decoded, rigid, and rigid + ``fix_feet`` joints: skating ratio, penetration, floating, jerk, share of toe-frames
above 5 cm, and pops (ankle or toe moves beyond the rigid motion's fastest of that foot + 2 cm: total, and the
motions with any). Last, the motions whose feet were already clean (rigid skating ratio 0): how many stay so.
"""
from __future__ import annotations

import argparse

import numpy as np

from lsgan.data.skeleton import bone_lengths
from lsgan.deploy.int8 import REFERENCE_PROMPTS
from lsgan.motion.quality import foot_pops, quality_metrics, toe_above
from lsgan.motion.feet import contacts_from_features, fix_feet
from lsgan.generate import Request, generate

PROMPTS = ("a person walks forward", "a person runs forward", "a person waves their right hand", "a person jumps up",
           "a person does a squat")


def spread_mm(joints: np.ndarray) -> float:
    """The largest change of one bone's length within a motion, in mm."""
    lengths = bone_lengths(np.asarray(joints, np.float64))
    return float((lengths.max(axis=0) - lengths.min(axis=0)).max() * 1000)


def table(raw: list, rigid: list, held: list) -> None:
    """The quality columns of the decoded, rigid and rigid + fix_feet joints, and whether clean feet stay clean."""
    print("| joints | skating ratio | penetration (mm) | floating (mm) | jerk (m/s^3) | toe above 5 cm | pops "
          "(motions) |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name, joints in (("decoded", raw), ("rigid (motion of record)", rigid), ("rigid + fix_feet", held)):
        q = quality_metrics(joints)
        pops = np.array([int(foot_pops(r, j)) for r, j in zip(rigid, joints)])
        popped = "-" if joints is raw else f"{pops.sum()} ({(pops > 0).sum()})"
        print(f"| {name} | {q['foot_skating_ratio']:.3f} | {q['penetration_m'] * 1000:.1f} | "
              f"{q['floating_m'] * 1000:.1f} | {q['jerk_m_s3']:.0f} | {np.mean([toe_above(j) for j in joints]):.1%} "
              f"| {popped} |")
    clean = [k for k, j in enumerate(rigid) if quality_metrics([j])["foot_skating_ratio"] == 0.0]
    after = [quality_metrics([held[k]])["foot_skating_ratio"] for k in clean]
    same = sum(np.array_equal(h, j) for h, j in zip(held, rigid))
    print(f"\nskating ratio 0 before fix_feet: {len(clean)} motions; after it {sum(a == 0.0 for a in after)} still "
          f"0, largest ratio {max(after, default=0.0):.3f}; left bit for bit (every stance planted already): {same}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gan", required=True)
    ap.add_argument("--vae", required=True)
    ap.add_argument("--prompts", choices=("five", "reference"), default="five")
    ap.add_argument("--per-prompt", type=int, default=None, help="motions per prompt (five: 20, reference: 1)")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    prompts = PROMPTS if a.prompts == "five" else REFERENCE_PROMPTS
    per_prompt = a.per_prompt or (20 if a.prompts == "five" else 1)
    requests = [Request(text=p, frames=a.frames) for p in prompts]
    motions = generate(a.gan, a.vae, requests, num=per_prompt, seed=a.seed, device="cpu").motions
    raw = [m.raw_joints for m in motions]
    rigid = [m.joints for m in motions]
    held = [fix_feet(m.joints, contacts_from_features(m.features)) for m in motions]
    gaps = [np.linalg.norm(r - d, axis=-1) * 1000 for r, d in zip(rigid, raw)]
    print(f"{len(motions)} motions of {a.frames} frames ({len(prompts)} prompts x {per_prompt}, seed {a.seed})\n")
    print(f"rigid vs decoded joints: mean {np.mean([g.mean() for g in gaps]):.1f} mm, "
          f"max {max(g.max() for g in gaps):.1f} mm; bone-length spread within a motion: decoded median "
          f"{np.median([spread_mm(j) for j in raw]):.0f} mm (max {max(spread_mm(j) for j in raw):.0f}), rigid "
          f"max {max(spread_mm(j) for j in rigid):.4f} mm\n")
    table(raw, rigid, held)


if __name__ == "__main__":
    main()
