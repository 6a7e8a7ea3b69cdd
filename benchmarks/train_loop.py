"""How fast ``lsgan train-vae``, ``train-evaluator`` or ``train-gan`` steps as a user runs it, loading and logging
included, against an earlier lsgan.

Each arm is a whole ``python -m lsgan.cli COMMAND`` process on the same data and recipe (the recipe's ``vae:``,
``evaluator: text:`` or ``gan:`` section with its schedule replaced: ``--steps`` steps, the loss logged every
``--steps / 4``, one validation and one checkpoint at the end). Its figure is the loop's own ``sec_per_step`` in
log.csv (the steps alone: no validation, no checkpoint), the median of the windows after the first (warm-up); the
process's wall time is printed beside it. (A train-gan of an lsgan that did not log sec_per_step is compared by its
whole run's steps_per_s instead, warm-up included, for both arms.) Arms alternate A B B A ... so that a drift of
the machine falls on both.

    python benchmarks/train_loop.py --device cuda --baseline /tmp/lsgan-before    # this checkout against another
    python benchmarks/train_loop.py --data bandai.h5 --recipe recipes/bandai-gpu.yaml --device cuda --steps 400
    python benchmarks/train_loop.py --command train-evaluator --device cuda --baseline /tmp/lsgan-before
    python benchmarks/train_loop.py --command train-gan --data cache.h5 --device cuda --baseline /tmp/lsgan-before

``--baseline DIR`` is a checkout of lsgan (its ``lsgan/`` package is imported from there); without it only this
checkout is timed. Without ``--data`` a synthetic shard of ``--clips`` clips is made first (about Bandai-Namco's
size at the default).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


SECTIONS = {"train-vae": ("vae",), "train-evaluator": ("evaluator", "text"), "train-gan": ("gan",)}


def run_arm(src: Path, command: str, data: Path, recipe: Path, out: Path, device: str) -> dict:
    """One training process with ``src``'s lsgan (checked), in ``out``; its log's sec_per_step per window and its
    wall time."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(src), os.environ.get("PYTHONPATH", "")])}
    tic = time.perf_counter()
    given = "--cache" if command == "train-gan" else "--data"
    out.mkdir(parents=True)  # and run there: ``python -m`` puts the working folder before PYTHONPATH
    where = subprocess.run([sys.executable, "-c", "import lsgan; print(lsgan.__file__)"], env=env, cwd=out,
                           capture_output=True, text=True).stdout.strip()
    if not Path(where).resolve().is_relative_to(src.resolve()):
        raise SystemExit(f"the arm for {src} imports lsgan from {where}")
    done = subprocess.run([sys.executable, "-m", "lsgan.cli", command, given, str(data.resolve()), "--recipe",
                           str(recipe.resolve()), "--out", "run", "--device", device], env=env, capture_output=True,
                          text=True, cwd=out)
    wall = time.perf_counter() - tic
    if done.returncode != 0:
        raise SystemExit(f"{command} from {src} failed:\n{done.stderr[-3000:]}")
    with open(out / "run" / "log.csv", newline="") as f:
        windows = [float(r["sec_per_step"]) for r in csv.DictReader(f) if r.get("sec_per_step")]
    result = json.loads(done.stderr.strip().splitlines()[-1])  # the command's summary (train-gan: steps_per_s)
    rate = result.get("steps_per_s")
    return {"sec_per_step": windows, "run_sec_per_step": 1.0 / rate if rate else None, "wall_s": wall}


def timing_recipe(recipe: Path, command: str, steps: int, folder: Path) -> Path:
    """``recipe`` with the command's schedule set to ``steps`` steps, 4 log windows, one validation and checkpoint."""
    spec = yaml.safe_load(recipe.read_text())
    section = spec
    for key in SECTIONS[command]:
        section = section[key]
    every = "eval_every" if command == "train-gan" else "val_every"
    section["train"].update({"max_steps": steps, "log_every": max(1, steps // 4), every: steps, "ckpt_every": steps})
    path = folder / "timing.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--command", choices=sorted(SECTIONS), default="train-vae")
    ap.add_argument("--data", type=Path, help="a shard, or a latent cache for train-gan (default: a synthetic shard)")
    ap.add_argument("--clips", type=int, default=5800, help="clips of the synthetic shard")
    ap.add_argument("--recipe", type=Path, default=ROOT / "recipes" / "bandai-gpu.yaml")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=2, help="A B (B A) pairs")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--baseline", type=Path, help="an earlier lsgan checkout to compare against")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = args.data
        if data is None:
            data = tmp / "synthetic.h5"
            subprocess.run([sys.executable, "-m", "lsgan.cli", "preprocess", "--source", "synthetic", "--num-clips",
                            str(args.clips), "-o", str(data), "--workers", str(min(8, os.cpu_count() or 1))],
                           env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True, capture_output=True)
        recipe = timing_recipe(args.recipe, args.command, args.steps, tmp)
        arms = {"this": ROOT} | ({"baseline": args.baseline.resolve()} if args.baseline else {})
        order = [name for r in range(args.rounds) for name in (list(arms) if r % 2 == 0 else list(arms)[::-1])]
        runs: dict[str, list[dict]] = {name: [] for name in arms}
        for i, name in enumerate(order):
            runs[name].append(run_arm(arms[name], args.command, data, recipe, tmp / f"run{i}", args.device))
            print(f"{name}: windows {[round(s, 4) for s in runs[name][-1]['sec_per_step']]} s/step, "
                  f"wall {runs[name][-1]['wall_s']:.1f} s", flush=True)
    summary = {}
    by_window = all(r["sec_per_step"] for rs in runs.values() for r in rs)  # else (an older train-gan) whole runs
    for name, rs in runs.items():
        steady = [s for r in rs for s in (r["sec_per_step"][1:] if by_window else [r["run_sec_per_step"]])]
        summary[name] = {"median_sec_per_step": statistics.median(steady), "min": min(steady), "max": max(steady),
                         "wall_s": [round(r["wall_s"], 1) for r in rs]}
        print(f"{name}: {summary[name]['median_sec_per_step'] * 1e3:.1f} ms/step median "
              f"({summary[name]['min'] * 1e3:.1f}-{summary[name]['max'] * 1e3:.1f}), walls {summary[name]['wall_s']} s")
    if "baseline" in summary:
        print(f"baseline / this: x{summary['baseline']['median_sec_per_step'] / summary['this']['median_sec_per_step']:.2f}")
    if args.json:
        args.json.write_text(json.dumps({"command": args.command, "steps": args.steps, "recipe": str(args.recipe), "data": str(args.data or
                                         f"synthetic, {args.clips} clips"), "runs": runs, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
