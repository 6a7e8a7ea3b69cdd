"""Clean feet (lsgan.export.feet) on generated motions: foot skating and ground penetration before and after.

Generates 100 motions (lsgan.generate.generate, the 100 prompts of lsgan.deploy.int8.REFERENCE_PROMPTS, 120
frames, seed 0, CPU) with the trained Bandai runs, fixes their feet with the contacts of their own features
(what ``lsgan export`` does by default) and reports, averaged over motions: GMD's foot-skating ratio and
ground penetration (lsgan.eval.quality: frame pairs where a toe under 5 cm slides > 2.5 cm/frame; metres
below y = 0 of the lowest joint), the share of frames with a toe above 5 cm, mean jerk, the share of contact
frames the fix holds, the change of the non-leg joints (max, mean), the change of the leg joints, and the
largest leg-bone length change. Also per speed band of the root (gliding motions cannot be held by the legs).

    OMP_NUM_THREADS=1 python benchmarks/feet.py --json feet.json
    python benchmarks/feet.py --gan RUN --vae RUN
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from lsgan.deploy.int8 import REFERENCE_PROMPTS
from lsgan.eval.quality import foot_skating_ratio, ground_penetration, jerk
from lsgan.export.feet import LEG_JOINTS, contacts_from_features, fix_feet, ground_contacts, held_spans
from lsgan.generate import generate
from lsgan.generation import Request

RUNS = "/work/bandai_runs/runs"
BONES = ((1, 4), (4, 7), (7, 10), (2, 5), (5, 8), (8, 11))
BANDS = ((0.0, 0.1), (0.1, 0.3), (0.3, 0.6), (0.6, np.inf))  # root speed, m/s


def measure(joints: np.ndarray, features: np.ndarray) -> dict:
    """Figures for (N,T,22,3) motions and their features (N,T,263)."""
    t0 = time.perf_counter()
    fixed = np.stack([fix_feet(j, contacts_from_features(f)) for j, f in zip(joints, features)])
    seconds = time.perf_counter() - t0
    contact = held = 0
    for j, f in zip(joints, features):
        c = ground_contacts(j, contacts_from_features(f))
        contact += int(c.sum())
        held += sum(b - a + 1 for spans in held_spans(j, c) for a, b in spans)
    other = [k for k in range(22) if k not in LEG_JOINTS]
    change = np.abs(fixed[:, :, other].astype(np.float64) - joints[:, :, other])
    legs = np.linalg.norm(fixed[:, :, list(LEG_JOINTS)] - joints[:, :, list(LEG_JOINTS)], axis=-1)
    bone = max(np.abs(np.linalg.norm(fixed[:, :, b] - fixed[:, :, a], axis=-1)
                      - np.linalg.norm(joints[:, :, b] - joints[:, :, a], axis=-1)).max() for a, b in BONES)
    speed = np.linalg.norm(joints[:, -1, 0, [0, 2]] - joints[:, 0, 0, [0, 2]], axis=-1) / (joints.shape[1] / 20)
    before, after = foot_skating_ratio(joints), foot_skating_ratio(fixed)
    return {
        "motions": len(joints),
        "foot_skating_ratio": [float(before.mean()), float(after.mean())],
        "penetration_mm": [float(ground_penetration(joints).mean() * 1e3), float(ground_penetration(fixed).mean() * 1e3)],
        "toe_above_5cm": [float((joints[..., [10, 11], 1] > 0.05).mean()), float((fixed[..., [10, 11], 1] > 0.05).mean())],
        "jerk_m_s3": [float(jerk(joints).mean()), float(jerk(fixed).mean())],
        "held_share_of_contact_frames": held / max(contact, 1),
        "other_joints_change_m": {"max": float(change.max()), "mean": float(change.mean())},
        "leg_joints_change_mm": {"mean": float(legs.mean() * 1e3), "max": float(legs.max() * 1e3)},
        "leg_bone_length_change_mm": float(bone * 1e3),
        "nan": bool(np.isnan(fixed).any()),
        "ms_per_motion": 1e3 * seconds / len(joints),
        "by_root_speed": {f"{lo}-{hi} m/s": {"motions": int(m.sum()),
                                             "foot_skating_ratio": [float(before[m].mean()), float(after[m].mean())]}
                          for lo, hi in BANDS if (m := (speed >= lo) & (speed < hi)).any()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gan", default=f"{RUNS}/bandai-gan")
    ap.add_argument("--vae", default=f"{RUNS}/bandai-vae")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    gen = generate(args.gan, args.vae, [Request(text=p, frames=args.frames) for p in REFERENCE_PROMPTS],
                   seed=args.seed, device="cpu")
    joints = np.stack([m.joints for m in gen.motions])
    features = np.stack([m.features for m in gen.motions])
    result = {"gan": args.gan, "vae": args.vae, "frames": args.frames, "seed": args.seed, **measure(joints, features)}
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            fh.write(text + "\n")


if __name__ == "__main__":
    main()
