"""``lsgan demo``: the whole pipeline on the built-in synthetic data, from nothing to metrics and GLB files.

Eight stages, each writing its output atomically and recording a marker when it is complete::

    [1/8] preprocess       data/synthetic.h5            the synthetic clips -> HumanML3D features
    [2/8] train-vae        runs/vae/                    the motion VAE (recipes/demo.yaml, vae:)
    [3/8] encode-latents   data/cache.h5                latents of every window, MiniLM caption embeddings
    [4/8] train-gan        runs/gan/                    deep-wgan-gp from the cache (demo.yaml, gan:)
    [5/8] train-evaluator  runs/evaluator/              our text-motion evaluator (demo.yaml, evaluator: text:)
    [6/8] evaluate         metrics.json, metrics.md     the T2M table: Real and GAN rows (few replications)
    [7/8] generate         motions/                     five prompts the synthetic families cover
    [8/8] export           glb/, gif/                   an animated GLB and a GIF preview per motion

``OUT/summary.json`` ends the run (paths, metrics, settings, stage timings). A marker (``OUT/.stages/NAME.json``)
names the markers of the stages it was built from, so a stage is reused only when everything it was made
from is still the same; a training stage that was interrupted resumes from its run's ``last/`` checkpoint
(the trainers resume exactly). Ctrl-C leaves finished stages, checkpoints and nothing half-written, and
raises :class:`DemoInterrupted` (a KeyboardInterrupt) naming the stage.

Size: ``scale`` (default: ``$LSGAN_DEMO_SCALE``, else 1) multiplies every step count, the number of clips and
the evaluation's replications and MultiModality draws (with floors that keep each stage meaningful: at least
400 clips, so that the test split holds the 32 windows R-precision needs). Scale 1 takes 5.6 minutes on an
idle 2-core CPU (7.8 with one thread); ``LSGAN_DEMO_SCALE=0.05`` runs the whole thing in about a minute, for tests.
The settings of a run are kept in ``OUT/demo.json``; a folder made at another scale is refused (``fresh=True``
starts over).
"""
from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

from lsgan import __version__
from lsgan.demo.folder import check_folder
from lsgan.demo.markers import STAGES, StageMarkers, StageRecord
from lsgan.demo.report import DemoResult
from lsgan.demo.settings import demo_settings
from lsgan.demo.stages import Body, Run, plan
from lsgan.io import atomic_file


class DemoInterrupted(KeyboardInterrupt):
    """Ctrl-C during a stage: finished stages and the last checkpoint are kept; run the demo again to go on."""

    def __init__(self, stage: str, index: int, out: Path) -> None:
        super().__init__(f"interrupted during [{index}/{len(STAGES)}] {stage}")
        self.stage, self.index, self.out = stage, index, out


def run_demo(
    out: str | os.PathLike = "demo_out",
    *,
    scale: float | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    device: str = "auto",
    fresh: bool = False,
    recipe: str | os.PathLike = "demo",
    threads: int | None = None,
) -> DemoResult:
    """Run (or continue) the demo in ``out``; returns where everything is, the metrics and the stage timings.

    scale: step counts, clips and evaluation draws x scale (default ``$LSGAN_DEMO_SCALE``, else 1).
    progress: tqdm bars of each stage on stderr. log: receives one line per stage (default: stderr when
    ``progress``). fresh: remove an earlier demo in ``out`` first (only the demo's own files).
    threads: a fixed torch thread count for the run (``LSGAN_THREADS``); default: lsgan's policy
    (:mod:`lsgan.threads`), which picks them per stage and lowers them while other processes keep cores busy.
    Raises DemoInterrupted on Ctrl-C (run again to continue), ValueError for a folder made at other settings.
    """
    from lsgan.threads import ENV

    if threads is not None and threads < 1:
        raise ValueError(f"threads must be >= 1, not {threads}")
    before = os.environ.get(ENV)
    if threads:
        os.environ[ENV] = str(threads)
    try:
        return _run(out, scale=scale, progress=progress, log=log, device=device, fresh=fresh, recipe=recipe)
    finally:
        if before is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = before


def _run(out, *, scale, progress, log, device, fresh, recipe) -> DemoResult:
    """:func:`run_demo` with the thread count already set: check the folder, then each stage of :func:`plan`."""
    import torch
    from tqdm import tqdm

    from lsgan.recipes import load_recipe
    from lsgan.threads import threads_said

    settings = demo_settings(scale, recipe)
    out = Path(out)
    say = log or ((lambda msg: tqdm.write(msg, file=sys.stderr)) if progress else (lambda msg: None))
    check_folder(out, settings, fresh)
    t_run = time.perf_counter()
    say(f"lsgan demo -> {out} (scale {settings.scale:g}: {settings.clips} synthetic clips, VAE {settings.vae_steps} / "
        f"GAN {settings.gan_steps} / evaluator {settings.evaluator_steps} steps; torch {torch.__version__}, "
        f"threads {threads_said()})")
    run = Run(out, settings, load_recipe(settings.recipe), device, progress, say, StageMarkers(out))
    for index, (name, output, describe, body) in enumerate(plan(run), 1):
        _stage(run, index, name, output, describe, body)
    return _finish(run, t_run)


def _stage(run: Run, index: int, name: str, output: Path | str, describe: str, body: Body) -> dict:
    """Reuse the stage if it is done on the current inputs, else run ``body`` and record its marker."""
    from tqdm import tqdm

    done = run.stages.done(name)
    if done is not None:
        run.say(f"[{index}/{len(STAGES)}] {name}: done earlier ({done['seconds']:.1f} s), reusing {output}")
        run.records.append(StageRecord(name, index, done["seconds"], "reused", str(output)))
        return done
    run.say(f"[{index}/{len(STAGES)}] {name}: {describe}")
    t0 = time.perf_counter()
    try:
        status, info = body(run)
    except KeyboardInterrupt as e:
        for bar in list(getattr(tqdm, "_instances", ())):  # the stage's bars end before the message
            bar.close()
        raise DemoInterrupted(name, index, run.out) from e
    seconds = time.perf_counter() - t0
    marker = run.stages.finish(name, seconds, str(output), info)
    note = f" ({info['note']})" if info.get("note") else ""
    run.say(f"[{index}/{len(STAGES)}] {name}: {'resumed and ' if status == 'resumed' else ''}done in {seconds:.1f} s"
            f"{note}")
    run.records.append(StageRecord(name, index, marker["seconds"], status, str(output)))
    return marker


def _finish(run: Run, t_run: float) -> DemoResult:
    """The result and ``OUT/summary.json``: paths, metrics, settings and stage timings."""
    import torch

    from lsgan.threads import threads_said

    p, settings = run.paths, run.settings
    metrics_json = p["metrics"].with_suffix(".json")
    saved = json.loads(metrics_json.read_text())
    metrics = {r_: {c: {"mean": v["mean"], "ci95": v["ci95"]} for c, v in cols.items()}
               for r_, cols in saved["rows"].items()}
    result = DemoResult(
        out=run.out, settings=settings, data=p["data"], cache=p["cache"], vae=p["vae"], gan=p["gan"],
        evaluator=p["evaluator"], metrics_json=metrics_json, metrics_md=p["metrics"].with_suffix(".md"),
        motions=p["motions"], glb=sorted(p["glb"].glob("*.glb")), gif=sorted(p["gif"].glob("*.gif")),
        summary=run.out / "summary.json", metrics=metrics, table=p["metrics"].with_suffix(".md").read_text().strip(),
        stages=run.records, seconds=time.perf_counter() - t_run,
    )
    paths = {"out": run.out, "data": result.data, "cache": result.cache, "vae": result.vae, "gan": result.gan,
             "evaluator": result.evaluator, "metrics_json": result.metrics_json, "metrics_md": result.metrics_md,
             "motions": result.motions}
    summary = {
        "lsgan_version": __version__,
        "settings": asdict(settings),
        "evaluation": settings.reduced,
        "paths": {k: str(v) for k, v in paths.items()} | {"glb": [str(f) for f in result.glb],
                                                         "gif": [str(f) for f in result.gif]},
        "gan_row": run.gan_name,
        "metrics": metrics,
        "stages": [asdict(s) | {"info": (run.stages.marker(s.name) or {}).get("info", {})} for s in run.records],
        "stages_seconds": round(sum(s.seconds for s in run.records), 2),
        "this_run_seconds": round(result.seconds, 2),
        "platform": {"torch": torch.__version__, "threads": threads_said(), "cpus": os.cpu_count(),
                     "loadavg": _loadavg()},
    }
    with atomic_file(result.summary, "w", encoding="utf-8") as fh:
        json.dump(summary, fh, indent=1, default=str)
    return result


def _loadavg() -> list[float] | None:
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return None
