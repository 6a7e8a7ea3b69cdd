"""Export time per motion on this machine: skeleton GLB, BVH, SMPL GLB with body fitting, GIF and MP4 previews.

The motion is a 196-frame generated clip (HumanML3D's longest length). The SMPL figure uses the stand-in model of
tests/body_models.py padded to the real SMPL's size (6,890 vertices, 13,776 faces, 24 joints), or the user's own
model with ``--body-model DIR``. Each export runs ``--repeats`` times; the median is reported.

    python benchmarks/export.py
    python benchmarks/export.py --body-model ~/models --json export.json
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from body_models import make_model  # noqa: E402

from lsgan.data.body_model import read_body_model  # noqa: E402
from lsgan.data.synthetic import generate  # noqa: E402
from lsgan.export.body import fit_body  # noqa: E402
from lsgan.export.bvh import write_bvh  # noqa: E402
from lsgan.export.glb import write_body_glb, write_glb  # noqa: E402
from lsgan.export.preview import write_gif, write_mp4  # noqa: E402

FRAMES = 196


def motion(frames: int = FRAMES) -> np.ndarray:
    """A generated clip looped (mirror-continued) to exactly ``frames`` frames."""
    joints = generate(1, seed=0)[0].joints
    while len(joints) < frames:
        joints = np.concatenate([joints, joints[::-1]])
    return joints[:frames]


def timed(fn, repeats: int) -> float:
    fn()  # warm-up (imports, allocator)
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return statistics.median(samples)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--body-model", help="a real SMPL/SMPL-H/SMPL-X model (file or folder)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", help="write the rows here as JSON")
    args = parser.parse_args()
    joints = motion()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        if args.body_model:
            model = read_body_model(args.body_model)
            model_name = model.path
        else:
            np.savez(out / "SMPL_NEUTRAL.npz", **make_model("smpl", min_vertices=6890, min_faces=13776))
            model = read_body_model(out / "SMPL_NEUTRAL.npz")
            model_name = "stand-in SMPL (6,890 vertices, 13,776 faces)"
        fit = fit_body(joints, model)
        rows = [
            ("skeleton GLB", timed(lambda: write_glb(out / "m.glb", joints), args.repeats)),
            ("BVH", timed(lambda: write_bvh(out / "m.bvh", joints), args.repeats)),
            ("SMPL fit (IK + L-BFGS)", timed(lambda: fit_body(joints, model), args.repeats)),
            ("SMPL GLB with fitting", timed(lambda: write_body_glb(out / "b.glb", fit_body(joints, model), model),
                                            args.repeats)),
            ("GIF preview", timed(lambda: write_gif(out / "m.gif", joints), max(1, args.repeats // 2))),
            ("MP4 preview", timed(lambda: write_mp4(out / "m.mp4", joints), max(1, args.repeats // 2))),
        ]
    print(f"# export of one {FRAMES}-frame motion, {platform.processor() or platform.machine()}, "
          f"{torch.get_num_threads()} threads; body model: {model_name}")
    print(f"# SMPL fit error on this motion: mean {fit.mean_error_mm:.2f} mm, max {fit.max_joint_error_mm:.2f} mm")
    print("| export | ms per motion |\n| --- | ---: |")
    for name, seconds in rows:
        print(f"| {name} | {seconds * 1000:.0f} |")
    if args.json:
        Path(args.json).write_text(json.dumps(
            [{"export": n, "ms_per_motion": s * 1000, "frames": FRAMES} for n, s in rows], indent=2))


if __name__ == "__main__":
    main()
