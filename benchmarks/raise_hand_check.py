"""The Bandai acceptance check of a trained text-to-motion model: does "raise the right hand" raise the right hand?

For each prompt, ``--num`` motions are generated; a sample passes when the named wrist rises above its
shoulder in some frame while the other wrist stays below its own shoulder throughout (SMPL joints: left
wrist 20 / shoulder 16, right wrist 21 / shoulder 17). Prints the pass rate per prompt.

    python benchmarks/raise_hand_check.py --gan runs/bandai-gan --vae runs/bandai-vae --num 16
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from lsgan.generate import Request, generate

PROMPTS = {"right": "a person raises the right hand", "left": "a person raises the left hand"}
WRIST, SHOULDER = {"left": 20, "right": 21}, {"left": 16, "right": 17}


def raises(joints: np.ndarray, side: str) -> bool:
    """The ``side`` wrist above its shoulder at some frame, the other wrist below its shoulder at every frame."""
    other = "left" if side == "right" else "right"
    up = (joints[:, WRIST[side], 1] > joints[:, SHOULDER[side], 1]).any()
    down = (joints[:, WRIST[other], 1] < joints[:, SHOULDER[other], 1]).all()
    return bool(up and down)


def check(gan: str, vae: str, num: int = 16, frames: int = 60, seed: int = 0) -> dict:
    out = {}
    for side, prompt in PROMPTS.items():
        result = generate(gan, vae, [Request(text=prompt, frames=frames)], num=num, seed=seed)
        passed = [raises(m.joints, side) for m in result.motions]
        out[side] = {"prompt": prompt, "passed": int(sum(passed)), "of": num, "rate": sum(passed) / num}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gan", required=True)
    ap.add_argument("--vae", required=True)
    ap.add_argument("--num", type=int, default=16)
    ap.add_argument("--frames", type=int, default=60, help="length of each motion (20 fps)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(json.dumps(check(args.gan, args.vae, args.num, args.frames, args.seed), indent=1))


if __name__ == "__main__":
    main()
