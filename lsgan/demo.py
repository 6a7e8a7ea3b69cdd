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
import math
import os
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from lsgan import __version__, outputs
from lsgan.io import atomic_file, atomic_folder

SCALE_ENV = "LSGAN_DEMO_SCALE"
STAGES = ("preprocess", "train-vae", "encode-latents", "train-gan", "train-evaluator", "evaluate", "generate",
          "export")
# What each stage is built from: its marker records theirs, and it is redone when one of them was redone.
DEPENDS = {
    "preprocess": (),
    "train-vae": ("preprocess",),
    "encode-latents": ("preprocess", "train-vae"),
    "train-gan": ("encode-latents",),
    "train-evaluator": ("preprocess",),
    "evaluate": ("preprocess", "train-vae", "train-gan", "train-evaluator"),
    "generate": ("train-vae", "train-gan"),
    "export": ("generate",),
}
# What the demo's folder holds (``fresh`` removes exactly these, nothing else of a folder).
CONTENTS = ("demo.json", ".stages", "data", "runs", "metrics.json", "metrics.md", "motions", "glb", "gif",
            "summary.json")
MIN_CLIPS = 400  # the hash split gives 42 test windows: R-precision needs groups of 32
DEFAULT_DEMO = {
    "clips": 800, "seed": 0, "frames": 120, "replications": 3, "mm_captions": 20, "mm_samples": 10,
    "prompts": ["a person walks forward", "a person runs forward", "a person waves their right hand",
                "a person jumps up", "a person does a squat"],
}


class DemoInterrupted(KeyboardInterrupt):
    """Ctrl-C during a stage: finished stages and the last checkpoint are kept; run the demo again to go on."""

    def __init__(self, stage: str, index: int, out: Path) -> None:
        super().__init__(f"interrupted during [{index}/{len(STAGES)}] {stage}")
        self.stage, self.index, self.out = stage, index, out


def scale_from_env(value: str | None = None) -> float:
    """The demo scale: ``value`` or ``$LSGAN_DEMO_SCALE`` (a number > 0), else 1."""
    raw = os.environ.get(SCALE_ENV) if value is None else value
    if raw is None or str(raw).strip() == "":
        return 1.0
    try:
        scale = float(raw)
    except ValueError:
        raise ValueError(f"{SCALE_ENV} must be a number > 0 (e.g. 0.05), not {raw!r}") from None
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"the demo scale must be a number > 0 (e.g. 0.05), not {raw!r}")
    return scale


@dataclass(frozen=True)
class DemoSettings:
    """Everything that decides what the demo computes (kept in ``OUT/demo.json``)."""

    scale: float
    clips: int
    seed: int
    vae_steps: int
    gan_steps: int
    evaluator_steps: int
    replications: int
    mm_captions: int
    mm_samples: int
    frames: int
    prompts: tuple[str, ...]
    recipe: str = "demo"

    @property
    def reduced(self) -> str:
        """How this evaluation differs from the protocol (20 replications, MultiModality 100 x 30)."""
        return (f"{self.replications} replication{'s' if self.replications != 1 else ''} (the protocol: 20), "
                f"MultiModality over {self.mm_captions} captions x {self.mm_samples} motions (the protocol: 100 x 30)")


def _scaled(n: int, scale: float, floor: int) -> int:
    return max(floor, int(round(n * scale)))


def demo_settings(scale: float | None = None, recipe: str | os.PathLike = "demo") -> DemoSettings:
    """The settings at ``scale`` from the recipe (its vae/gan/evaluator step counts and its ``demo:`` section)."""
    from lsgan.recipes import load_recipe, section

    scale = scale_from_env() if scale is None else scale_from_env(str(scale))
    r = load_recipe(recipe)
    demo = {**DEFAULT_DEMO, **section(r, "demo")}
    steps = {
        "vae": section(section(r, "vae"), "train").get("max_steps", 300),
        "gan": section(section(r, "gan"), "train").get("max_steps", 1500),
        "evaluator": section(section(section(r, "evaluator"), "text"), "train").get("max_steps", 200),
    }
    return DemoSettings(
        scale=scale, clips=_scaled(int(demo["clips"]), scale, min(MIN_CLIPS, int(demo["clips"]))), seed=int(demo["seed"]),
        vae_steps=_scaled(steps["vae"], scale, 10), gan_steps=_scaled(steps["gan"], scale, 20),
        evaluator_steps=_scaled(steps["evaluator"], scale, 10),
        replications=_scaled(int(demo["replications"]), scale, 1),
        mm_captions=_scaled(int(demo["mm_captions"]), scale, 4), mm_samples=_scaled(int(demo["mm_samples"]), scale, 4),
        frames=int(demo["frames"]), prompts=tuple(demo["prompts"]), recipe=os.fspath(recipe),
    )


@dataclass
class StageRecord:
    """One stage of a run: seconds it took when it was done, and what this run did with it."""

    name: str
    index: int
    seconds: float
    status: str  # "ran", "resumed" (an interrupted training continued), or "reused" (done by an earlier run)
    output: str


@dataclass
class DemoResult:
    """Where everything is, the metrics and the stage timings of one ``run_demo``."""

    out: Path
    settings: DemoSettings
    data: Path
    cache: Path
    vae: Path
    gan: Path
    evaluator: Path
    metrics_json: Path
    metrics_md: Path
    motions: Path
    glb: list[Path]
    gif: list[Path]
    summary: Path
    metrics: dict  # row -> column -> {"mean", "ci95"}
    table: str  # the metrics as markdown
    stages: list[StageRecord] = field(default_factory=list)
    seconds: float = 0.0  # this run's wall time

    def report(self) -> str:
        """What ``lsgan demo`` prints at the end: the files, the table and what it is (not)."""
        s = self.settings
        rel = lambda p: os.path.relpath(p) if not os.path.relpath(p).startswith("..") else str(p)  # noqa: E731
        lines = [f"lsgan demo: done ({self.seconds:.0f} s this run; the stages took "
                 f"{sum(st.seconds for st in self.stages):.0f} s in all; scale {s.scale:g})", "",
                 "Stages:"]
        for st in self.stages:
            lines.append(f"  [{st.index}/{len(STAGES)}] {st.name:<16} {st.seconds:7.1f} s  {st.status:<8} {st.output}")
        lines += [
            "", "Files:",
            f"  data (synthetic clips)   {rel(self.data)}",
            f"  VAE / GAN / evaluator    {rel(self.vae)}  {rel(self.gan)}  {rel(self.evaluator)}",
            f"  motions (.npy)           {rel(self.motions)}",
            f"  animated GLB             {rel(self.glb[0].parent)}/ ({len(self.glb)} files: Blender, three.js, "
            "any glTF viewer)",
            f"  GIF previews             {rel(self.gif[0].parent)}/ ({len(self.gif)} files)",
            f"  metrics                  {rel(self.metrics_md)}  {rel(self.metrics_json)}",
            f"  summary                  {rel(self.summary)}",
            "", f"Text-to-motion on the synthetic test split (our own evaluator; {s.reduced}):", "", self.table, "",
            "R-precision by chance: top-1 0.031, top-2 0.063, top-3 0.094 (groups of 32). The data are synthetic and",
            "the evaluator is ours: these numbers are not comparable with published HumanML3D tables.",
        ]
        return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ the runner


class _Stages:
    """Markers in ``OUT/.stages/``: a stage is done when its marker names the current markers of its inputs."""

    def __init__(self, out: Path) -> None:
        self.dir = out / ".stages"

    def marker(self, name: str) -> dict | None:
        p = self.dir / f"{name}.json"
        try:
            return json.loads(p.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def inputs(self, name: str) -> dict[str, str | None]:
        return {d: (self.marker(d) or {}).get("id") for d in DEPENDS[name]}

    def done(self, name: str) -> dict | None:
        m = self.marker(name)
        return m if m is not None and m.get("inputs") == self.inputs(name) else None

    def finish(self, name: str, seconds: float, output: str, info: dict) -> dict:
        m = {"stage": name, "id": uuid.uuid4().hex, "inputs": self.inputs(name), "seconds": round(seconds, 2),
             "output": output, "finished": time.strftime("%Y-%m-%dT%H:%M:%S"), "info": info}
        with atomic_file(self.dir / f"{name}.json", "w", encoding="utf-8") as fh:
            json.dump(m, fh, indent=1)
        return m


def _prepare_run_folder(run: Path, inputs: dict) -> bool:
    """Keep ``run`` (to resume) only when it was started on the same inputs, else clear lsgan's files in it;
    returns whether there is a checkpoint to resume from."""
    tag = run / "demo-inputs.json"
    if run.exists():
        try:
            same = json.loads(tag.read_text()) == inputs
        except (FileNotFoundError, json.JSONDecodeError):
            same = False
        if not same:
            outputs.clear_ours(run)
    if not tag.exists():
        with atomic_file(tag, "w", encoding="utf-8") as fh:
            json.dump(inputs, fh)
    return (run / "last" / "config.json").exists()


def _clear_demo(out: Path) -> None:
    """``--fresh``: remove what the demo wrote in ``out`` (its own files, by the registry), nothing else."""
    for name in CONTENTS:
        outputs.clear_path(out / name)  # a folder still holding the user's files stays, with them


def _check_folder(out: Path, settings: DemoSettings, fresh: bool) -> None:
    path = out / "demo.json"
    mine = {"lsgan_version": __version__, "settings": json.loads(json.dumps(asdict(settings)))}
    if path.exists():
        old = json.loads(path.read_text())
        if fresh:
            _clear_demo(out)
        elif old.get("settings") != mine["settings"]:
            o = old.get("settings", {})
            raise ValueError(
                f"{out} holds a demo made with other settings (scale {o.get('scale')}, {o.get('clips')} clips, "
                f"{o.get('vae_steps')}/{o.get('gan_steps')} VAE/GAN steps; now scale {settings.scale:g}): "
                f"choose another output folder, or start over in this one with --fresh")
        else:
            return
    elif out.exists() and any(out.iterdir()) and not (out / ".stages").exists():
        raise ValueError(f"{out} exists and is not a demo folder: choose an empty or new output folder")
    with atomic_file(path, "w", encoding="utf-8") as fh:
        json.dump(mine, fh, indent=1)


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
    """:func:`run_demo` with the thread count already set: check the folder, then each stage of :func:`_plan`."""
    import torch
    from tqdm import tqdm

    from lsgan.threads import threads_said

    settings = demo_settings(scale, recipe)
    out = Path(out)
    say = log or ((lambda msg: tqdm.write(msg, file=sys.stderr)) if progress else (lambda msg: None))
    _check_folder(out, settings, fresh)
    t_run = time.perf_counter()
    say(f"lsgan demo -> {out} (scale {settings.scale:g}: {settings.clips} synthetic clips, VAE {settings.vae_steps} / "
        f"GAN {settings.gan_steps} / evaluator {settings.evaluator_steps} steps; torch {torch.__version__}, "
        f"threads {threads_said()})")
    run = _Run(out, settings, _load(settings.recipe), device, progress, say, _Stages(out))
    for index, (name, output, describe, body) in enumerate(_plan(run), 1):
        _stage(run, index, name, output, describe, body)
    return _finish(run, t_run)


@dataclass
class _Run:
    """What the stages of one run share: its folder, settings, recipe and device, and what it did so far."""

    out: Path
    settings: DemoSettings
    recipe: dict
    device: str
    progress: bool
    say: Callable[[str], None]
    stages: _Stages
    records: list[StageRecord] = field(default_factory=list)

    def __post_init__(self) -> None:
        o = self.out
        self.paths = {
            "data": o / "data" / "synthetic.h5", "cache": o / "data" / "cache.h5", "vae": o / "runs" / "vae",
            "gan": o / "runs" / "gan", "evaluator": o / "runs" / "evaluator", "metrics": o / "metrics",
            "motions": o / "motions", "glb": o / "glb", "gif": o / "gif",
        }

    @property
    def gan_name(self) -> str:
        return _section2(self.recipe, "gan", "model").get("arch", "deep-wgan-gp")


Body = Callable[[_Run], tuple[str, dict]]  # a stage's work: ("ran" | "resumed", what its marker records)


def _plan(run: _Run) -> list[tuple[str, Path | str, str, Body]]:
    """The eight stages in order (STAGES): name, output, what the log line says it does, and its work."""
    s, p = run.settings, run.paths
    vae_cfg = _section2(run.recipe, "vae", "model")
    return [
        ("preprocess", p["data"], f"{s.clips} procedural clips (walk, run, turns, jump, waves, raises, squat, kicks) "
         "-> 263-d HumanML3D features", _preprocess),
        ("train-vae", p["vae"], f"motion VAE ({vae_cfg.get('num_layers')} layers, d {vae_cfg.get('d_model')}), "
         f"{s.vae_steps} steps", _train_vae),
        ("encode-latents", p["cache"], "VAE latents of every window + MiniLM embeddings of every caption",
         _encode_latents),
        ("train-gan", p["gan"], f"{run.gan_name} on the cached latents, {s.gan_steps} generator steps", _train_gan),
        ("train-evaluator", p["evaluator"], f"our text-motion evaluator (T2M's recipe, MiniLM text side), "
         f"{s.evaluator_steps} steps", _train_evaluator),
        ("evaluate", p["metrics"].with_suffix(".json"), f"T2M metrics, Real and {run.gan_name} rows ({s.reduced})",
         _evaluate),
        ("generate", p["motions"], f"{len(s.prompts)} prompts, {s.frames / 20:g} s each: "
         + "; ".join(f'"{q}"' for q in s.prompts), _generate),
        ("export", f"{p['glb']}/ {p['gif']}/", "an animated GLB (skeleton, one animation) and a GIF preview per "
         "motion", _export),
    ]


def _stage(run: _Run, index: int, name: str, output: Path | str, describe: str, body: Body) -> dict:
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


def _bar(run: _Run, total: int, unit: str, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, desc=desc, file=sys.stderr, disable=not run.progress, dynamic_ncols=True)


def _preprocess(run: _Run) -> tuple[str, dict]:
    from lsgan.data.preprocess import preprocess
    from lsgan.data.sources.synthetic import SyntheticSource

    s, data = run.settings, run.paths["data"]
    bar = _bar(run, s.clips, "clip", "preprocess synthetic")

    def on_progress(done: int, total: int) -> None:
        bar.total, bar.n = total, done
        bar.refresh()

    parts = data.with_name(data.name + ".parts")
    try:
        res = preprocess(SyntheticSource(num_clips=s.clips, seed=s.seed), data, resume=parts.exists(),
                         on_progress=on_progress)
    finally:
        bar.close()
    return "ran", {"clips": res.clips, "frames": res.frames, "captions": res.captions,
                   "note": f"{res.clips} clips, {res.frames:,} frames, {res.captions} captions"}


def _train_vae(run: _Run) -> tuple[str, dict]:
    from lsgan.models.vae import VAEConfig
    from lsgan.recipes import build, section
    from lsgan.train.vae import VAETrainConfig, train_vae

    v, p = section(run.recipe, "vae"), run.paths
    model = build(VAEConfig, section(v, "model"), "vae.model")
    train, resume = _training(run, "train-vae", "vae", v, VAETrainConfig, run.settings.vae_steps,
                              ("val_every", "ckpt_every", "log_every"))
    # the demo's own run folder: without a checkpoint to resume, a start's leftovers (logs) are cleared
    res = train_vae(p["data"], p["vae"], model=model, train=train, device=run.device, resume=resume,
                    force=not resume, progress=run.progress)
    return ("resumed" if resume else "ran"), {
        "steps": res["step"], "best_val_mpjpe_m": res["best_val_mpjpe_m"],
        "note": f"validation MPJPE {res['best_val_mpjpe_m']:.3f} m" if res["best_val_mpjpe_m"] else ""}


def _training(run: _Run, stage: str, folder: str, recipe: dict, train_cls, steps: int, intervals: tuple[str, ...],
              label: str | None = None):
    """A training stage's settings (the recipe section's ``train:`` scaled to ``steps``) and whether its run folder
    holds a checkpoint to resume. The folder is the demo's own: one started on other inputs is cleared."""
    from lsgan.recipes import build, section

    name = label or folder
    train = _scale_train(build(train_cls, section(recipe, "train"), f"{name}.train"), steps, intervals)
    return train, _prepare_run_folder(run.paths[folder], run.stages.inputs(stage))


def _encode_latents(run: _Run) -> tuple[str, dict]:
    from lsgan.models.cache import encode_latents
    from lsgan.models.checkpoint import read_meta

    p = run.paths
    t = read_meta(p["vae"])["config"].get("train", {})
    encode_latents(p["data"], p["vae"], p["cache"], text_encoder=run.recipe.get("text_encoder") or "minilm",
                   min_frames=t.get("min_frames", 40), max_frames=t.get("max_frames", 196), device=run.device,
                   progress=run.progress)
    return "ran", {}


def _train_gan(run: _Run) -> tuple[str, dict]:
    from lsgan.models.checkpoint import weights_hash
    from lsgan.models.gan import GANConfig
    from lsgan.recipes import build, section
    from lsgan.train.gan import GANTrainConfig, train_gan

    g, p = section(run.recipe, "gan"), run.paths
    gan = build(GANConfig, section(g, "model"), "gan.model")
    train, resume = _training(run, "train-gan", "gan", g, GANTrainConfig, run.settings.gan_steps,
                              ("eval_every", "ckpt_every", "log_every"))
    res = train_gan(p["cache"], p["gan"], gan=gan, train=train, device=run.device, resume=resume,
                    force=not resume, progress=run.progress, expect_vae_hash=weights_hash(p["vae"]))
    fid = res["best_val_latent_fid"]
    return ("resumed" if resume else "ran"), {
        "steps": res["step"], "best_val_latent_fid": fid, "fid_history": res["fid_history"],
        "note": (f"validation latent FID {res['fid_history'][0][1]:.1f} -> {fid:.2f}"
                 if fid is not None and res["fid_history"] else "")}


def _train_evaluator(run: _Run) -> tuple[str, dict]:
    from lsgan.models.evaluator import EvaluatorConfig
    from lsgan.recipes import build, section
    from lsgan.train.evaluator import EvaluatorTrainConfig, train_evaluator

    e, p = section(section(run.recipe, "evaluator"), "text"), run.paths
    model = dict(section(e, "model"))
    model.setdefault("text_encoder", run.recipe.get("text_encoder") or "minilm")
    train, resume = _training(run, "train-evaluator", "evaluator", e, EvaluatorTrainConfig,
                              run.settings.evaluator_steps, ("val_every", "ckpt_every", "log_every"),
                              label="evaluator.text")
    res = train_evaluator(p["data"], p["evaluator"], config=build(EvaluatorConfig, model, "evaluator.text.model"),
                          train_config=train, device=run.device, resume=resume, force=not resume,
                          progress=run.progress)
    h = res["heldout"]
    note = (f"held-out R-precision top-3 {h['r_precision_top3']:.3f} (chance {h['chance_top3']:.3f})"
            if "r_precision_top3" in h else "")
    return ("resumed" if resume else "ran"), {"steps": res["step"], "heldout": h, "note": note}


def _evaluate(run: _Run) -> tuple[str, dict]:
    from lsgan.eval.evaluate import evaluate_text_to_motion, write_table

    s, p, name = run.settings, run.paths, run.gan_name
    e = _section2(run.recipe, "evaluator", "text", "train")
    bar = _bar(run, s.replications, "replication", "evaluate")
    seen = [0]

    def on_progress(msg: str) -> None:  # "replication r/R: name", before the model's draw is generated
        bar.n = seen[0]
        bar.refresh()
        seen[0] += 1

    try:
        table = evaluate_text_to_motion(
            {name: p["gan"]}, p["vae"], p["data"], p["evaluator"], split="test", replications=s.replications,
            mm_captions=s.mm_captions, mm_samples=s.mm_samples, min_frames=e.get("min_frames", 40),
            max_frames=e.get("max_frames", 196), seed=s.seed, device=run.device, progress=on_progress)
        bar.n = s.replications
        bar.refresh()
    finally:
        bar.close()
    table.info["reduced"] = s.reduced
    write_table(table, p["metrics"], force=True)
    top3 = table.summary()[name]["r_precision_top3"][0]
    return "ran", {"note": f"{name} R-precision top-3 {top3:.3f} (chance 0.094)"}


def _generate(run: _Run) -> tuple[str, dict]:
    from lsgan.generate import Request, generate, write_generation

    s, p = run.settings, run.paths
    requests = [Request(text=q, frames=s.frames) for q in s.prompts]
    res = generate(p["gan"], p["vae"], requests, num=1, seed=s.seed, device=run.device, fix_feet=True)
    with atomic_folder(p["motions"]) as tmp:
        write_generation(res, tmp)
    return "ran", {"ms_per_motion": res.ms_per_motion, "note": f"{res.ms_per_motion:.1f} ms per motion"}


def _export(run: _Run) -> tuple[str, dict]:
    from lsgan.export.motions import export_motions

    # Each format is built in a temporary folder and renamed whole; the titles come from the motions'
    # manifest, which export_motions reads beside the source.
    for fmt in ("glb", "gif"):
        with atomic_folder(run.paths[fmt]) as tmp:
            export_motions(run.paths["motions"], tmp, fmt=fmt, fps=20.0)
    return "ran", {}


def _finish(run: _Run, t_run: float) -> DemoResult:
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


def _load(recipe: str | os.PathLike) -> dict:
    from lsgan.recipes import load_recipe

    return load_recipe(recipe)


def _section2(r: dict, *names: str) -> dict:
    """The nested recipe section ``r[names[0]][names[1]]...`` ({} where absent)."""
    from lsgan.recipes import section

    for name in names:
        r = section(r, name)
    return r


def _scale_train(cfg, steps: int, intervals: tuple[str, ...]):
    """``cfg`` with ``max_steps = steps`` and each interval shrunk in proportion (at least 1, at most ``steps``)."""
    ratio = steps / cfg.max_steps
    changes = {"max_steps": steps}
    for name in intervals:
        changes[name] = min(steps, max(1, int(round(getattr(cfg, name) * ratio))))
    return replace(cfg, **changes)


def _loadavg() -> list[float] | None:
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return None
