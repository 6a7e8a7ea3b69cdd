"""The eight stages of the demo: what each runs (through the library's own training, evaluation, generation and
export), on the paths and recipe sections of one run."""
from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from lsgan.demo.folder import prepare_run_folder
from lsgan.demo.markers import StageMarkers, StageRecord
from lsgan.demo.settings import DemoSettings
from lsgan.io import atomic_folder

@dataclass
class Run:
    """What the stages of one run share: its folder, settings, recipe and device, and what it did so far."""

    out: Path
    settings: DemoSettings
    recipe: dict
    device: str
    progress: bool
    say: Callable[[str], None]
    stages: StageMarkers
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


Body = Callable[[Run], tuple[str, dict]]  # a stage's work: ("ran" | "resumed", what its marker records)


def plan(run: Run) -> list[tuple[str, Path | str, str, Body]]:
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


def _bar(run: Run, total: int, unit: str, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, desc=desc, file=sys.stderr, disable=not run.progress, dynamic_ncols=True)


def _preprocess(run: Run) -> tuple[str, dict]:
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


def _train_vae(run: Run) -> tuple[str, dict]:
    from lsgan.models.vae import VAEConfig
    from lsgan.train.vae import VAETrainConfig, train_vae

    p = run.paths
    model, train, resume = _training(run, "train-vae", "vae", ("vae",), VAEConfig, VAETrainConfig,
                                     run.settings.vae_steps, ("val_every", "ckpt_every", "log_every"))
    # the demo's own run folder: without a checkpoint to resume, a start's leftovers (logs) are cleared
    res = train_vae(p["data"], p["vae"], model=model, train=train, device=run.device, resume=resume,
                    force=not resume, progress=run.progress)
    return ("resumed" if resume else "ran"), {
        "steps": res["step"], "best_val_mpjpe_m": res["best_val_mpjpe_m"],
        "note": f"validation MPJPE {res['best_val_mpjpe_m']:.3f} m" if res["best_val_mpjpe_m"] else ""}


def _training(run: Run, stage: str, folder: str, kind: tuple[str, ...], model_cls, train_cls, steps: int,
              intervals: tuple[str, ...], model_overrides: dict | None = None):
    """A training stage's model and train configs (the recipe's section at ``kind``, e.g. ``("evaluator", "text")``,
    its ``train:`` scaled to ``steps``) and whether its run folder holds a checkpoint to resume. The folder is the
    demo's own: one started on other inputs is cleared."""
    from lsgan.recipes import configs

    model, train = configs(_section2(run.recipe, *kind[:-1]), kind[-1], model_cls, train_cls, model_overrides, where=".".join(kind))
    return model, _scale_train(train, steps, intervals), prepare_run_folder(run.paths[folder],
                                                                            run.stages.inputs(stage))


def _encode_latents(run: Run) -> tuple[str, dict]:
    from lsgan.models.cache import encode_latents
    from lsgan.models.checkpoint import read_meta

    p = run.paths
    t = read_meta(p["vae"])["config"].get("train", {})
    encode_latents(p["data"], p["vae"], p["cache"], text_encoder=run.recipe.get("text_encoder") or "minilm",
                   min_frames=t.get("min_frames", 40), max_frames=t.get("max_frames", 196), device=run.device,
                   progress=run.progress)
    return "ran", {}


def _train_gan(run: Run) -> tuple[str, dict]:
    from lsgan.models.checkpoint import weights_hash
    from lsgan.models.gan import GANConfig
    from lsgan.train.gan import GANTrainConfig, train_gan

    p = run.paths
    gan, train, resume = _training(run, "train-gan", "gan", ("gan",), GANConfig, GANTrainConfig,
                                   run.settings.gan_steps, ("eval_every", "ckpt_every", "log_every"))
    res = train_gan(p["cache"], p["gan"], gan=gan, train=train, device=run.device, resume=resume,
                    force=not resume, progress=run.progress, expect_vae_hash=weights_hash(p["vae"]))
    fid = res["best_val_latent_fid"]
    return ("resumed" if resume else "ran"), {
        "steps": res["step"], "best_val_latent_fid": fid, "fid_history": res["fid_history"],
        "note": (f"validation latent FID {res['fid_history'][0][1]:.1f} -> {fid:.2f}"
                 if fid is not None and res["fid_history"] else "")}


def _train_evaluator(run: Run) -> tuple[str, dict]:
    from lsgan.models.evaluator import EvaluatorConfig
    from lsgan.train.evaluator import EvaluatorTrainConfig, train_evaluator

    p = run.paths
    named = "text_encoder" in _section2(run.recipe, "evaluator", "text", "model")
    encoder = None if named else run.recipe.get("text_encoder") or "minilm"
    config, train, resume = _training(run, "train-evaluator", "evaluator", ("evaluator", "text"), EvaluatorConfig,
                                      EvaluatorTrainConfig, run.settings.evaluator_steps,
                                      ("val_every", "ckpt_every", "log_every"), {"text_encoder": encoder})
    res = train_evaluator(p["data"], p["evaluator"], config=config, train_config=train, device=run.device,
                          resume=resume, force=not resume, progress=run.progress)
    h = res["heldout"]
    note = (f"held-out R-precision top-3 {h['r_precision_top3']:.3f} (chance {h['chance_top3']:.3f})"
            if "r_precision_top3" in h else "")
    return ("resumed" if resume else "ran"), {"steps": res["step"], "heldout": h, "note": note}


def _evaluate(run: Run) -> tuple[str, dict]:
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


def _generate(run: Run) -> tuple[str, dict]:
    from lsgan.generate import Request, generate, write_generation

    s, p = run.settings, run.paths
    requests = [Request(text=q, frames=s.frames) for q in s.prompts]
    res = generate(p["gan"], p["vae"], requests, num=1, seed=s.seed, device=run.device, fix_feet=True)
    with atomic_folder(p["motions"]) as tmp:
        write_generation(res, tmp)
    return "ran", {"ms_per_motion": res.ms_per_motion, "note": f"{res.ms_per_motion:.1f} ms per motion"}


def _export(run: Run) -> tuple[str, dict]:
    from lsgan.export.motions import export_motions

    # Each format is built in a temporary folder and renamed whole; the titles come from the motions'
    # manifest, which export_motions reads beside the source.
    for fmt in ("glb", "gif"):
        with atomic_folder(run.paths[fmt]) as tmp:
            export_motions(run.paths["motions"], tmp, fmt=fmt, fps=20.0)
    return "ran", {}


def _section2(r: dict, *names: str) -> dict:
    """The nested recipe section ``r[names[0]][names[1]]...`` ({} where absent)."""
    from lsgan.recipes import section

    for name in names:
        r = section(r, name)
    return r


def _scale_train(cfg, steps: int, intervals: tuple[str, ...]):
    """``cfg`` with ``max_steps = steps`` and each interval (and a warm-up) shrunk in proportion (at least 1, at most
    ``steps``)."""
    ratio = steps / cfg.max_steps
    changes = {"max_steps": steps}
    for name in intervals:
        changes[name] = min(steps, max(1, int(round(getattr(cfg, name) * ratio))))
    if getattr(cfg, "warmup_steps", 0):  # the warm-up keeps its share of the run
        changes["warmup_steps"] = min(steps, int(round(cfg.warmup_steps * ratio)))
    return replace(cfg, **changes)
