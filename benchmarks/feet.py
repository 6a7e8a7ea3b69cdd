"""Clean feet (lsgan.motion.feet) on generated motions: foot skating, sliding, steps and penetration, before and after.

Generates 100 motions (lsgan.generate.generate, the 100 prompts of lsgan.deploy.int8.REFERENCE_PROMPTS, 120
frames, seed 0, CPU) with the trained Bandai runs, fixes their feet with the contacts of their own features
(what ``lsgan export`` does by default) and reports, averaged over motions: GMD's foot-skating ratio and
ground penetration (lsgan.motion.quality: frame pairs where a toe under 5 cm slides > 2.5 cm/frame; metres
below y = 0 of the lowest joint), the share of frames with a toe above 5 cm, mean jerk, the fastest toe; the
horizontal toe travel (m per motion) on frame pairs the model's own channels mark in contact (ankle or toe of
that side), all of it and the part on the floor (toe under 2 cm above its lowest height in the clip in both
frames: a slide, not a step), and the share of those pairs in which the toe stays still (< 5 mm); the steps the
fix makes (per motion, length, frames between plants, toe and ankle lift above the plants they join), the share of
contact frames the fix holds, the change of the non-leg joints (max, mean), the change of the leg joints, and
the largest leg-bone length change. Also per speed band of the root (gliding motions need steps).

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
from lsgan.motion.quality import foot_skating_ratio, ground_penetration, jerk
from lsgan.motion.feet import LEG_JOINTS, contacts_from_features, fix_feet, ground_contacts, held_spans
from lsgan.generate import generate
from lsgan.generation import Request

RUNS = "runs"  # where the README's Bandai commands put them
BONES = ((1, 4), (4, 7), (7, 10), (2, 5), (5, 8), (8, 11))
BANDS = ((0.0, 0.1), (0.1, 0.3), (0.3, 0.6), (0.6, np.inf))  # root speed, m/s
FLOOR_BAND = 0.02  # m: a toe lower than this above its lowest height in the clip is on the floor
STILL = 0.005  # m/frame: a toe moving less is still


def contact_travel(joints: np.ndarray, features: np.ndarray) -> dict:
    """Per motion (N,): horizontal toe travel in metres on frame pairs the model marks in contact (ankle or toe
    channel of that side, both frames), that travel on the floor (toe < FLOOR_BAND above its clip-lowest height
    in both frames), and the share of those pairs in which the toe moves < STILL."""
    total, floor, still, pairs = (np.zeros(len(joints)) for _ in range(4))
    for i, (j, f) in enumerate(zip(joints.astype(np.float64), features)):
        c = contacts_from_features(f)
        for side, toe in enumerate((10, 11)):
            marked = c[:-1, 2 * side] | c[:-1, 2 * side + 1]
            marked &= c[1:, 2 * side] | c[1:, 2 * side + 1]
            step = np.linalg.norm(np.diff(j[:, toe, [0, 2]], axis=0), axis=-1)
            low = j[:, toe, 1] - j[:, toe, 1].min() < FLOOR_BAND
            total[i] += step[marked].sum()
            floor[i] += step[marked & low[:-1] & low[1:]].sum()
            still[i] += (step[marked] < STILL).sum()
            pairs[i] += marked.sum()
    return {"travel_m": total, "floor_m": floor, "still": still / np.maximum(pairs, 1)}


def steps(fixed: np.ndarray, joints: np.ndarray, features: np.ndarray) -> dict:
    """The steps of the fixed motions: each gap between two spans that hold a toe (held_spans). Its length (the
    toe's horizontal move between the plants), frames between the plants, and the toe's and ankle's highest point
    above the higher of the two plants' heights."""
    rows = []
    for f, j, feat in zip(fixed.astype(np.float64), joints, features):
        spans = held_spans(j, contacts_from_features(feat))
        for side, (ankle, toe) in enumerate(((7, 10), (8, 11))):
            held = spans[2 * side + 1]
            for (_, a), (b, _) in zip(held[:-1], held[1:]):
                gap = slice(a + 1, b)
                rows.append((np.linalg.norm(f[b, toe, [0, 2]] - f[a, toe, [0, 2]]), b - a - 1,
                             f[gap, toe, 1].max() - max(f[a, toe, 1], f[b, toe, 1]),
                             f[gap, ankle, 1].max() - max(f[a, ankle, 1], f[b, ankle, 1])))
    if not rows:
        return {"per_motion": 0.0}
    r = np.asarray(rows)
    return {"per_motion": len(r) / len(fixed), "length_m": float(r[:, 0].mean()), "frames": float(r[:, 1].mean()),
            "toe_lift_m": {"mean": float(r[:, 2].mean()), "min": float(r[:, 2].min()), "max": float(r[:, 2].max())},
            "ankle_lift_m": float(r[:, 3].mean())}


def pair(before: np.ndarray, after: np.ndarray, scale: float = 1.0) -> list[float]:
    """[mean before, mean after], times ``scale``."""
    return [float(before.mean() * scale), float(after.mean() * scale)]


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
    skate = foot_skating_ratio(joints), foot_skating_ratio(fixed)
    jerks = jerk(joints), jerk(fixed)
    travel = contact_travel(joints, features), contact_travel(fixed, features)
    toe_speed = [float(np.linalg.norm(np.diff(x[:, :, [10, 11]], axis=1), axis=-1).max() * 20) for x in (joints, fixed)]
    return {
        "motions": len(joints),
        "foot_skating_ratio": pair(*skate),
        "penetration_mm": pair(ground_penetration(joints), ground_penetration(fixed), 1e3),
        "toe_above_5cm": pair(joints[..., [10, 11], 1] > 0.05, fixed[..., [10, 11], 1] > 0.05),
        "jerk_m_s3": pair(*jerks),
        "toe_speed_max_m_s": toe_speed,
        **{f"contact_{k}": pair(travel[0][k], travel[1][k]) for k in travel[0]},
        "steps": steps(fixed, joints, features),
        "held_share_of_contact_frames": held / max(contact, 1),
        "other_joints_change_m": {"max": float(change.max()), "mean": float(change.mean())},
        "leg_joints_change_mm": {"mean": float(legs.mean() * 1e3), "max": float(legs.max() * 1e3)},
        "leg_bone_length_change_mm": float(bone * 1e3),
        "nan": bool(np.isnan(fixed).any()),
        "ms_per_motion": 1e3 * seconds / len(joints),
        "by_root_speed": {f"{lo}-{hi} m/s": {
            "motions": int(m.sum()), "foot_skating_ratio": pair(skate[0][m], skate[1][m]),
            "jerk_m_s3": pair(jerks[0][m], jerks[1][m]),
            **{f"contact_{k}": pair(travel[0][k][m], travel[1][k][m]) for k in ("floor_m", "still")}}
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
