"""The VAE-objective ablation of docs/fidelity.md: one whole recipe per row, the same shard, split and evaluator.

Each row trains a VAE (the recipe's ``vae:`` section with the row's train values), caches its latents, trains the
recipe's GAN on them, then measures both: the VAE's reconstruction table and the GAN's text-to-motion table
(``lsgan evaluate``'s own functions), each over ``--replications`` draws of the test split. A row's figures and
stage times go to ``WORK/rows/NAME.json``; ``--table`` writes the markdown table from the rows there.

    python benchmarks/fidelity.py --data bandai.h5 --recipe bandai --work runs/fidelity            # every row
    python benchmarks/fidelity.py --data bandai.h5 --recipe bandai --work runs/fidelity --rows shipped,kinematic
    python benchmarks/fidelity.py --data bandai.h5 --recipe bandai --work runs/fidelity --jobs 7 --device cuda
    python benchmarks/fidelity.py --work runs/fidelity --table                                     # the table

With ``--jobs N`` the rows run as N processes side by side (a machine with many cores and one GPU); the evaluator
is trained first, once. ``--text-encoder-path`` points every stage at a MiniLM folder.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NONE = {"joint_weight": 0.0, "velocity_weight": 0.0, "accel_weight": 0.0, "bone_weight": 0.0, "contact_weight": 0.0}
MLD = {**NONE, "loss": "mld"}
ALL = {**NONE, "loss": "mld", "velocity_weight": 0.5, "accel_weight": 0.02, "bone_weight": 10.0, "contact_weight": 0.5}
NO_HEAD = {"smooth_output": 0, "rigid_output": False}  # the decoder without lsgan.models.decoder_head
ROWS = {  # name: (what changes, the VAE train values over the recipe's, the VAE model values over the recipe's)
    "shipped": ("the recipe before issue 32: features-only MSE, 1,000 steps, constant lr",
                {**NONE, "loss": "mse", "max_steps": 1000, "lr_schedule": "constant", "warmup_steps": 0}, NO_HEAD),
    "mse": ("features-only MSE", {**NONE, "loss": "mse"}, NO_HEAD),
    "mld": ("MLD's loss (SmoothL1 on features and joints)", MLD, NO_HEAD),
    "velocity": ("MLD + velocity 0.5", {**MLD, "velocity_weight": 0.5}, NO_HEAD),
    "bones": ("MLD + velocity 0.5 + bones 10", {**MLD, "velocity_weight": 0.5, "bone_weight": 10.0}, NO_HEAD),
    "accel": ("MLD + velocity 0.5 + bones 10 + accel 0.02", {**ALL, "contact_weight": 0.0}, NO_HEAD),
    "all": ("MLD + velocity 0.5 + bones 10 + accel 0.02 + contact 0.5", ALL, NO_HEAD),
    "strong": ("MLD + velocity 1 + bones 20 + accel 0.05 + contact 1",
               {**NONE, "loss": "mld", "velocity_weight": 1.0, "accel_weight": 0.05, "bone_weight": 20.0,
                "contact_weight": 1.0}, NO_HEAD),
    "constant-lr": ("all terms, constant lr (no warm-up, no cosine)",
                    {**ALL, "lr_schedule": "constant", "warmup_steps": 0}, NO_HEAD),
    "vel2": ("MLD + squared velocity 1", {**MLD, "kinematic_loss": "squared", "velocity_weight": 1.0}, NO_HEAD),
    "sq": ("MLD + squared velocity 1 + acceleration 0.002 + bones 1000",
           {**MLD, "kinematic_loss": "squared", "velocity_weight": 1.0, "accel_weight": 0.002, "bone_weight": 1000.0},
           NO_HEAD),
    "head": ("features-only MSE, the decoder smoothed (1 pass) and on the data's skeleton",
             {**NONE, "loss": "mse"}, {"smooth_output": 1, "rigid_output": True}),
    "joints": ("MSE + MLD's joint term 0.2, the decoder smoothed and rigid", {**NONE, "joint_weight": 0.2},
               {"smooth_output": 1, "rigid_output": True}),
    "recipe": ("the recipe as it is", {}, {}),
}
GAN_COLUMNS = ("fid", "r_precision_top3", "mm_dist", "diversity", "foot_skating_ratio", "jerk_m_s3",
               "penetration_m", "bone_std_mm")
VAE_COLUMNS = ("mpjpe", "mpjpe_rel", "bone_std_mm", "jerk_m_s3", "foot_skating_ratio", "fid")


MARK = ".fidelity"  # in WORK: this script made the folder, so what is inside is its own


def _claim(work: Path) -> None:
    """Refuse a ``--work`` folder this script did not make (it writes and replaces files there)."""
    if work.exists() and not (work / MARK).exists() and any(work.iterdir()):
        raise SystemExit(f"error: {work}: a folder benchmarks/fidelity.py did not make; give a new or empty one")
    work.mkdir(parents=True, exist_ok=True)
    (work / MARK).touch()


def _write(path: Path, text: str) -> None:
    from lsgan.io import atomic_file

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, "w", encoding="utf-8") as fh:
        fh.write(text)


def _cache_matches(cache: Path, vae: Path) -> bool:
    from lsgan.models.cache import StaleCache, check_cache_vae

    try:
        return cache.exists() and check_cache_vae(cache, vae=vae) is not None
    except StaleCache:
        return False


def _scaled(cfg, scale: float, *every: str):
    """``cfg`` with max_steps (the warm-up, the named periods) times ``scale``, at least 1 step."""
    if scale == 1.0:
        return cfg
    steps = max(1, round(cfg.max_steps * scale))
    warmup = {"warmup_steps": min(steps, round(cfg.warmup_steps * scale))} if hasattr(cfg, "warmup_steps") else {}
    return replace(cfg, max_steps=steps, **warmup, **{k: max(1, min(steps, round(getattr(cfg, k) * scale)))
                                                      for k in every})


def _stage(times: dict, name: str, fn):
    tic = time.perf_counter()
    out = fn()
    times[name] = round(time.perf_counter() - tic, 1)
    return out


def _evaluator(args, recipe: dict) -> Path:
    """The evaluator every row is measured with: ``--evaluator``, else WORK/evaluator, trained here once. Its
    training result goes to ``<evaluator>.json`` when it is done; a row process waits for that file."""
    from lsgan.recipes import section
    from lsgan.train.evaluator import train_from_recipe

    out = Path(args.evaluator or Path(args.work) / "evaluator")
    done, failed = out.with_suffix(".json"), out.with_suffix(".failed")
    if args.evaluator:
        return out
    while args.wait_evaluator and not done.exists():  # a row process of --jobs: the driver trains it
        if failed.exists():
            raise SystemExit(f"error: {out}: the evaluator's training failed: {failed.read_text().strip()}")
        time.sleep(5)
    if not done.exists():
        steps = section(section(section(recipe, "evaluator"), "text"), "train")["max_steps"]
        scaled = {k: max(1, round(steps * args.scale)) for k in ("max_steps", "val_every", "ckpt_every")}
        try:
            res = train_from_recipe([args.data], out, recipe, kind="text", text_encoder_path=args.text_encoder_path,
                                    overrides=scaled if args.scale != 1.0 else None, device=args.device,
                                    resume=out.exists(), progress=False)
        except Exception as e:
            _write(failed, f"{type(e).__name__}: {e}")
            raise
        _write(done, json.dumps(res, indent=1, default=str))
    return out


def run_row(args, name: str) -> dict:
    """Train and measure one row; its JSON is written when it is done."""
    from lsgan.eval.evaluate import evaluate_reconstruction, evaluate_text_to_motion
    from lsgan.models.cache import check_cache_vae, encode_latents
    from lsgan.models.gan import GANConfig
    from lsgan.models.vae import VAEConfig
    from lsgan.recipes import configs, load_recipe
    from lsgan.train.gan import GANTrainConfig, train_gan
    from lsgan.train.vae import VAETrainConfig, train_vae

    recipe, (what, overrides, model) = load_recipe(args.recipe), ROWS[name]
    work, times = Path(args.work) / name, {}
    vcfg, tcfg = configs(recipe, "vae", VAEConfig, VAETrainConfig, model_overrides=model, train_overrides=overrides)
    gcfg, gtcfg = configs(recipe, "gan", GANConfig, GANTrainConfig)
    tcfg, gtcfg = _scaled(tcfg, args.scale, "val_every", "ckpt_every"), _scaled(gtcfg, args.scale, "eval_every",
                                                                              "ckpt_every")
    frames = dict(min_frames=tcfg.min_frames, max_frames=tcfg.max_frames)
    enc = dict(text_encoder=recipe.get("text_encoder") or "minilm", text_encoder_path=args.text_encoder_path)
    out = Path(args.work) / "rows" / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    row = {"name": name, "what": what, "scale": args.scale, "recipe": args.recipe,
           "vae_train": {k: getattr(tcfg, k) for k in overrides} | {"max_steps": tcfg.max_steps,
                                                                    "lr_schedule": tcfg.lr_schedule},
           "vae_model": {k: getattr(vcfg, k) for k in ("smooth_output", "rigid_output")},
           "seconds": times, "device": args.device, "machine": platform.node(), "cpus": os.cpu_count(),
           "replications": args.replications}
    save = lambda: _write(out, json.dumps(row, indent=1))  # noqa: E731  (after every stage: a cut run keeps some)
    row["vae_result"] = _stage(times, "train_vae", lambda: train_vae(
        args.data, work / "vae", model=vcfg, train=tcfg, device=args.device, resume=(work / "vae").exists(),
        progress=False))
    save()
    if args.vae_only:
        row["vae"] = _stage(times, "eval_vae", lambda: evaluate_reconstruction(
            work / "vae", args.data, evaluator=args.evaluator, replications=args.replications, device=args.device,
            **frames)).to_json()["rows"]
        save()
        return row
    cache = work / "cache.h5"
    if not _cache_matches(cache, work / "vae"):  # absent, or encoded by an earlier VAE of this row
        _stage(times, "encode", lambda: encode_latents(args.data, work / "vae", cache, **enc, **frames,
                                                       device=args.device, progress=False, force=cache.exists()))
    _stage(times, "train_gan", lambda: train_gan(
        cache, work / "gan", gan=gcfg, train=gtcfg, device=args.device, resume=(work / "gan").exists(),
        progress=False, expect_vae_hash=check_cache_vae(cache, vae=work / "vae")))
    evaluator = _evaluator(args, recipe)
    row["vae"] = _stage(times, "eval_vae", lambda: evaluate_reconstruction(
        work / "vae", args.data, evaluator=evaluator, replications=args.replications, device=args.device,
        **frames)).to_json()["rows"]
    save()
    row["gan"] = _stage(times, "eval_gan", lambda: evaluate_text_to_motion(
        {"deep-wgan-gp": work / "gan"}, work / "vae", args.data, evaluator, replications=args.replications,
        mm_captions=args.mm_captions, mm_samples=10, device=args.device, **frames)).to_json()["rows"]
    save()
    return row


def _cell(rows: dict, who: str, col: str, digits: int) -> str:
    c = rows.get(who, {}).get(col)
    return "–" if c is None else f"{c['mean']:.{digits}f}"


DIGITS = {"fid": 3, "r_precision_top3": 3, "mm_dist": 3, "diversity": 2, "foot_skating_ratio": 3, "jerk_m_s3": 1,
          "penetration_m": 4, "bone_std_mm": 2, "mpjpe": 3, "mpjpe_rel": 3}


def table(work: Path) -> str:
    """The markdown table of every row JSON under ``work/rows`` (in ROWS order), Real's figures first."""
    rows = [json.loads(p.read_text()) for p in sorted((work / "rows").glob("*.json"))]
    rows.sort(key=lambda r: list(ROWS).index(r["name"]) if r["name"] in ROWS else len(ROWS))
    head = ("| row | VAE MPJPE (m) | root-rel. (m) | VAE bone σ (mm) | FID | top-3 | MM-Dist | diversity | skating | "
            "jerk (m/s³) | penetration (m) | bone σ (mm) | VAE + GAN train (s) |")
    lines = [head, "|" + " --- |" * 13]
    done = [r for r in rows if "gan" in r]
    if done:
        g = done[0]["gan"]
        lines.append("| Real | – | – | 0 | " + " | ".join(_cell(g, "Real", c, DIGITS[c]) for c in GAN_COLUMNS)
                     + " | – |")
    for r in rows:
        vae, gan, s = r.get("vae", {}), r.get("gan", {}), r["seconds"]
        cells = [_cell(vae, "VAE", c, DIGITS[c]) for c in ("mpjpe", "mpjpe_rel", "bone_std_mm")]
        cells += [_cell(gan, "deep-wgan-gp", c, DIGITS[c]) for c in GAN_COLUMNS]
        train = s.get("train_vae", 0) + s.get("train_gan", 0)
        lines.append(f"| {r['name']}: {r['what']} | " + " | ".join(cells) + f" | {train:.0f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="the shard (lsgan preprocess)")
    ap.add_argument("--recipe", default="bandai")
    ap.add_argument("--work", required=True, help="the folder every row trains in")
    ap.add_argument("--rows", default=",".join(ROWS), help=f"comma-separated, from: {', '.join(ROWS)}")
    ap.add_argument("--jobs", type=int, default=1, help="rows side by side, each in its own process")
    ap.add_argument("--threads", type=int, default=2, help="torch threads per row process with --jobs")
    ap.add_argument("--replications", type=int, default=20)
    ap.add_argument("--mm-captions", type=int, default=20)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every training's steps (a smoke run)")
    ap.add_argument("--text-encoder-path", default=None)
    ap.add_argument("--evaluator", default=None, help="the evaluator to measure with, once EVALUATOR.json exists "
                    "(default: WORK/evaluator, trained here)")
    ap.add_argument("--vae-only", action="store_true", help="train and measure the VAE alone (no GAN; FID only "
                    "with --evaluator)")
    ap.add_argument("--wait-evaluator", action="store_true", help=argparse.SUPPRESS)  # a row process of --jobs
    ap.add_argument("--table", action="store_true", help="print the table of the rows done and exit")
    args = ap.parse_args()
    if args.table:
        print(table(Path(args.work)))
        return
    names = [n for n in args.rows.split(",") if n]
    unknown = [n for n in names if n not in ROWS]
    if unknown or not names or not args.data:
        ap.error(f"unknown rows {unknown}" if unknown else "no rows given" if not names else "--data is needed to train")
    if not args.scale > 0 or args.scale == float("inf"):
        ap.error(f"--scale must be a positive number, not {args.scale}")
    if not args.wait_evaluator:
        _claim(Path(args.work))
    if args.jobs <= 1:
        for name in names:
            run_row(args, name)
            print(f"{name} done", flush=True)
        return
    argv = [sys.executable, __file__, "--data", args.data, "--recipe", args.recipe, "--work", args.work,
            "--replications", str(args.replications), "--mm-captions", str(args.mm_captions), "--device", args.device,
            "--scale", str(args.scale), "--wait-evaluator"] + (["--vae-only"] if args.vae_only else []) + (["--evaluator", args.evaluator] if args.evaluator else [])
    if args.text_encoder_path:
        argv += ["--text-encoder-path", args.text_encoder_path]
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads), "LSGAN_THREADS": str(args.threads)}
    Path(args.work).mkdir(parents=True, exist_ok=True)
    trainer = None
    if not args.evaluator and not args.vae_only:  # trained beside the rows, which wait for it only when they measure
        from lsgan.recipes import load_recipe

        recipe, failures = load_recipe(args.recipe), []

        def train() -> None:
            try:
                _evaluator(args, recipe)
            except Exception as e:  # recorded in <evaluator>.failed too: the rows stop on it
                failures.append(e)

        trainer = threading.Thread(target=train)
        trainer.start()
    running: list[subprocess.Popen] = []
    for name in names:
        while sum(p.poll() is None for p in running) >= args.jobs:
            time.sleep(1)
        log = open(Path(args.work) / f"{name}.log", "w")
        running.append(subprocess.Popen(argv + ["--rows", name], env=env, stdout=log, stderr=subprocess.STDOUT))
    for p in running:
        p.wait()
    if trainer is not None:
        trainer.join()
        if failures:
            raise failures[0]
    bad = [name for name, p in zip(names, running) if p.returncode]
    if bad:
        raise SystemExit(f"error: rows {', '.join(bad)} failed: see their logs in {args.work}")


if __name__ == "__main__":
    try:
        main()
    except (KeyboardInterrupt, SystemExit):
        raise
    except Exception as e:  # one line, as lsgan's own commands
        sys.exit(f"error: {e}")
