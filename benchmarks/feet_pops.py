"""Clean feet (lsgan.motion.feet) before and after on saved motions and on Bandai mocap: skating, pops, jerk.

For each motion: the joints as given and after ``fix_feet`` with the contacts of its own features (what ``lsgan
export`` does), optionally also after a ``--baseline`` copy of lsgan/motion/feet.py (e.g. ``git show
COMMIT:lsgan/motion/feet.py > old_feet.py``). ``--glide`` makes the motions instead: synthetic walks, runs and
sprints (lsgan.data.synthetic) through the features, their whole body gliding on at 5 or 10 cm/frame with the feet
marked in contact on every frame, as a generator's gliding motions come. Reports, averaged over motions
(lsgan.motion.quality): GMD's foot-skating ratio, ground penetration (mm), jerk (m/s^3), the share of toe-frames
above 5 cm, and pops (frame-to-frame ankle or toe moves over the original foot's fastest plus 2 cm: their count,
the motions with any, the largest excess); the skating ratio also by root speed (under and over 2 m/s) and
after the first second.

    python benchmarks/feet_pops.py --motions out/ [--baseline old_feet.py] [--json feet.json]
    python benchmarks/feet_pops.py --bandai /work/shared/data/bandai-namco-2 --clips 'dataset-2_run_*' --limit 20
    python benchmarks/feet_pops.py --glide
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

from lsgan.motion.quality import POP_JOINTS, POP_SLACK, foot_pops, foot_skating_ratio, ground_penetration, jerk, toe_above
from lsgan.motion.feet import contacts_from_features, fix_feet

FAST = 2.0  # m/s: root speed that splits the bands


def saved_motions(folder: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, joints, contacts) of each *_joints.npy with its *_features.npy in ``folder``."""
    out = []
    for path in sorted(folder.glob("*_joints.npy")):
        features = np.load(path.with_name(path.name.replace("_joints.npy", "_features.npy")))
        out.append((path.stem, np.load(path), contacts_from_features(features)))
    return out


def bandai_motions(root: Path, pattern: str, limit: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Bandai clips through the BVH importer and HumanML3D's features: the joints recovered from them, contacts."""
    from lsgan.data.features import joints_to_features, recover_from_ric
    from lsgan.data.sources.bvh import BvhSource

    out = []
    for path in sorted((root / "data").glob(f"{pattern}.bvh.gz"))[:limit]:
        clip = BvhSource(root=str(path), preset="bandai", mirror=False).load(str(path))[0]
        features = joints_to_features(clip.joints)
        joints = recover_from_ric(features.astype(np.float64)).astype(np.float32)
        out.append((path.name, joints, contacts_from_features(features)))
    return out


def glide_motions() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """24 gliding gaits (module docstring), 120 frames: a fast walk, slow, normal and fast runs, three seeds each,
    at 5 and 10 cm/frame; contacts (T,4) all True."""
    from lsgan.data.features import joints_to_features, recover_from_ric
    from lsgan.data.synthetic.gait import _gait_pose
    from lsgan.data.synthetic.rig import _assemble, _finish

    out = []
    for seed in range(3):
        for kind, speed in (("walk", "fast"), ("run", "slow"), ("run", "normal"), ("run", "fast")):
            clip = _finish(_assemble(_gait_pose(np.random.default_rng(seed), 121, kind, "forward", speed)))
            joints = recover_from_ric(joints_to_features(clip).astype(np.float64)).astype(np.float32)
            for glide in (0.05, 0.1):
                shift = (np.arange(len(joints))[:, None] * np.float32([0.0, 0.0, glide]))[:, None]
                out.append((f"{kind}-{speed}-{seed}-{glide}", joints + shift, np.ones((len(joints), 4), dtype=bool)))
    return out


def excess(before: np.ndarray, after: np.ndarray) -> float:
    """The largest ankle or toe move in ``after`` beyond the same foot's fastest in ``before`` plus POP_SLACK, m."""
    moves = [np.linalg.norm(np.diff(x[:, POP_JOINTS].astype(np.float64), axis=0), axis=-1) for x in (before, after)]
    limit = np.repeat([moves[0][:, :2].max(), moves[0][:, 2:].max()], 2) + POP_SLACK
    return float((moves[1] - limit).max())


def figures(motions, fixed: list[np.ndarray]) -> dict:
    """Averages over motions of the fixed (or raw) joints, pops against the raw ones."""
    raw = [m[1] for m in motions]
    speed = np.array([np.linalg.norm(j[-1, 0, [0, 2]] - j[0, 0, [0, 2]]) / (len(j) / 20) for j in raw])
    skate = np.array([float(foot_skating_ratio(f)) for f in fixed])
    pops = np.array([int(foot_pops(r, f)) for r, f in zip(raw, fixed)])
    return {
        "foot_skating_ratio": float(skate.mean()),
        "skating_under_2m_s": float(skate[speed < FAST].mean()) if (speed < FAST).any() else None,
        "skating_over_2m_s": float(skate[speed >= FAST].mean()) if (speed >= FAST).any() else None,
        "penetration_mm": float(np.mean([ground_penetration(f) for f in fixed]) * 1e3),
        "jerk_m_s3": float(np.mean([jerk(f) for f in fixed])),
        "toe_above_5cm": float(np.mean([toe_above(f) for f in fixed])),
        "pops": int(pops.sum()), "motions_with_pops": int((pops > 0).sum()),
        "largest_pop_excess_cm": max(0.0, max(excess(r, f) for r, f in zip(raw, fixed)) * 100),
        "skating_after_1_s": float(np.mean([foot_skating_ratio(f[20:]) for f in fixed])),
        "motions": len(raw), "over_2m_s": int((speed >= FAST).sum()),
    }


def load_baseline(path: Path):
    spec = importlib.util.spec_from_file_location("baseline_feet", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module.fix_feet


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motions", type=Path, help="folder of *_joints.npy and *_features.npy")
    parser.add_argument("--bandai", type=Path, help="the Bandai-Namco-Research-Motiondataset-2 folder")
    parser.add_argument("--clips", default="dataset-2_*", help="--bandai: glob of the clip names")
    parser.add_argument("--limit", type=int, default=20, help="--bandai: the first this many clips")
    parser.add_argument("--glide", action="store_true", help="gliding synthetic gaits (module docstring)")
    parser.add_argument("--baseline", type=Path, help="another feet.py to compare")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.glide:
        motions = glide_motions()
    else:
        motions = saved_motions(args.motions) if args.motions else bandai_motions(args.bandai, args.clips, args.limit)
    fixers = {"now": fix_feet, **({"baseline": load_baseline(args.baseline)} if args.baseline else {})}
    result = {"raw": figures(motions, [m[1] for m in motions])}
    for name, fix in fixers.items():
        result[name] = figures(motions, [fix(j, c) for _, j, c in motions])
    print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
