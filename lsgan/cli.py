"""The ``lsgan`` command line: thin wrappers that parse options and call one library function each."""
from __future__ import annotations

import os
import sys

from lsgan.interrupts import InterruptGuard

# The lsgan program (console script or python -m lsgan.cli) counts Ctrl-C from before click and the commands are
# imported (~50 ms); LsganGroup.main takes this guard over. Importing this module from other code installs nothing.
_startup_guard = ([InterruptGuard(exiting=True)] if __name__ == "__main__" or (
    __name__ == "lsgan.cli" and os.path.splitext(os.path.basename(sys.argv[0]))[0] == "lsgan") else [])

import json  # noqa: E402
from pathlib import Path  # noqa: E402

import click  # noqa: E402

from lsgan import __version__  # noqa: E402
from lsgan.errors import debugging, describe  # noqa: E402

SOURCES = ("synthetic", "bvh", "humanml3d", "joints", "amass", "humanact12")
INTERRUPTED = 130  # the shell's code for a process stopped by Ctrl-C (128 + SIGINT)


class In(click.Path):
    """A path the command reads. Every path option is an :class:`In` or an :class:`Out` (tests/test_outputs.py
    checks it), so that :class:`LsganCommand` can refuse an output that is, holds or lies inside an input."""

    role = "input"

    def paths(self, value: str) -> list[str]:
        return [value]


class Out(In):
    """A path the command writes (a file, a folder, or the stem of several files)."""

    role = "output"


class NamedIn(click.ParamType):
    """``[NAME=]PATH``: an input path with an optional row name."""

    name = "[NAME=]PATH"
    role = "input"

    def paths(self, value: str) -> list[str]:
        return [value.rpartition("=")[2]] if "=" in value and not os.path.exists(value) else [value]


class MaybeIn(click.ParamType):
    """An input file when the value names an existing path; else a name (a built-in recipe) or inline text."""

    name = "TEXT"
    role = "input"

    def paths(self, value: str) -> list[str]:
        return [value] if os.path.exists(value) else []


def declared_paths(command: click.Command, params: dict) -> tuple[list[str], list[str]]:
    """The input and output paths given to ``command`` (``params`` as parsed), from its parameters' types."""
    found: dict[str, list[str]] = {"input": [], "output": []}
    for p in command.params:
        role = getattr(p.type, "role", None)
        values = params.get(p.name)
        if role is None or values is None:
            continue
        for v in values if isinstance(values, (tuple, list)) else [values]:
            found[role] += p.type.paths(os.fspath(v))
    return found["input"], found["output"]


def check_declared_paths(command: click.Command, params: dict) -> None:
    """Refuse an output that is, holds or lies inside an input, or that overlaps another output."""
    from lsgan.outputs import check_apart, check_inputs

    ins, outs = declared_paths(command, params)
    for out in outs:
        check_inputs(out, ins)
    check_apart(*outs)


class LsganCommand(click.Command):
    """A command whose declared outputs are checked against its declared inputs before it runs."""

    def invoke(self, ctx: click.Context):
        check_declared_paths(self, ctx.params)
        return super().invoke(ctx)


def _fail(message: str) -> None:
    """Print ``error: MESSAGE`` and exit 1; under --debug re-raise the exception being handled instead."""
    if debugging() and sys.exc_info()[1] is not None:
        raise sys.exc_info()[1]
    _close_progress_bars()
    click.echo(f"error: {message}", err=True)
    sys.exit(1)


def _close_progress_bars() -> None:
    """Close unfinished tqdm bars, so the error line starts a line of its own."""
    from tqdm import tqdm

    for bar in list(getattr(tqdm, "_instances", ())):
        bar.close()


def _stopped(hint: str) -> None:
    """Ctrl-C: say what is kept and how to go on, and exit 130."""
    click.echo(f"\ninterrupted: {hint}", err=True)
    sys.exit(INTERRUPTED)


def _plainly(error: Exception) -> str:
    """A command's failure as :func:`describe` words it; a missing text encoder's message says how to get it."""
    from lsgan.models.text import TextEncoderUnavailable

    return str(error) if isinstance(error, TextEncoderUnavailable) else describe(error)


class LsganGroup(click.Group):
    """Runs a command and turns every failure into one ``error: FILE: problem`` line and a non-zero exit.

    Usage errors exit 2, other errors 1, Ctrl-C 130; tracebacks only with ``--debug`` or ``LSGAN_DEBUG=1``.
    A Ctrl-C is never lost (:class:`lsgan.interrupts.InterruptGuard`): one that Python swallowed in a finaliser
    is raised again, and a run that received one exits 130 whatever became of the exception.
    """

    command_class = LsganCommand

    def main(self, *args, **kwargs):
        from lsgan.outputs import claims

        guard = _startup_guard.pop() if _startup_guard else InterruptGuard()
        try:
            with claims():  # what the command claims to write, noted for other lsgan processes while it runs
                code = self._run(guard, *args, **kwargs)
        except BaseException:  # --debug: the traceback, with the caller's handler back
            guard.stop()
            raise
        if guard.stop() and code != INTERRUPTED:
            _close_progress_bars()
            click.echo("\ninterrupted", err=True)
            code = INTERRUPTED
        sys.exit(code)

    def _run(self, guard, *args, **kwargs) -> int:
        """The command under ``guard``; its exit code, every failure reported as one line."""
        kwargs["standalone_mode"] = False
        try:
            code = guard.call(super().main, *args, **kwargs)
        except SystemExit as e:  # a command's own _fail or _stopped
            code = e.code
        except click.exceptions.Exit as e:
            code = e.exit_code
        except click.ClickException as e:
            hint = f" (see 'lsgan {e.ctx.info_name} --help')" if getattr(e, "ctx", None) is not None else ""
            click.echo(f"error: {e.format_message()}{hint}", err=True)
            code = e.exit_code
        except (click.Abort, KeyboardInterrupt):
            click.echo("\ninterrupted", err=True)
            code = INTERRUPTED
        except Exception as e:  # noqa: BLE001 - the promise: one line, no traceback unless asked
            if debugging():
                raise
            _close_progress_bars()
            click.echo(f"error: {describe(e)}", err=True)
            code = 1
        return code if isinstance(code, int) else 0


@click.group(cls=LsganGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="lsgan")
@click.option("--debug", is_flag=True, help="Show Python tracebacks on errors (also LSGAN_DEBUG=1).")
@click.option("--threads", type=click.IntRange(1), default=None,
              help="Fix the CPU threads of torch and onnxruntime (also LSGAN_THREADS=N). Default: lsgan picks them "
                   "per job and lowers them while other processes keep cores busy.")
def main(debug: bool, threads: int | None) -> None:
    """lsgan: text- and action-to-motion synthesis with a GAN in the latent space of a motion VAE.

    \b
    Everything at once, on built-in synthetic data (about 6 minutes on a 2-core CPU):
      lsgan demo
    \b
    Pipeline:
      lsgan preprocess --source synthetic -o synth.h5
      lsgan inspect synth.h5
      lsgan train-vae --data synth.h5 --recipe demo --out runs/vae
      lsgan encode-latents --data synth.h5 --vae runs/vae -o cache.h5
      lsgan train-gan --cache cache.h5 --recipe demo --out runs/gan
      lsgan train-diffusion --cache cache.h5 --recipe demo --out runs/diffusion   # the MLD baseline
      lsgan generate --gan runs/gan --vae runs/vae --text "a person walks forward" -o out/
    \b
    Errors are one line on stderr (`error: FILE: problem`) with exit code 1 (2 for a wrong option, 130 after
    Ctrl-C); `lsgan --debug COMMAND` (or LSGAN_DEBUG=1) shows the traceback. CPU threads: lsgan picks them per
    job and uses fewer while other processes keep cores busy; `lsgan --threads N COMMAND` fixes them. No command replaces a file it
    did not write: an existing output needs --force, which replaces only lsgan's own files.
    """
    if debug:
        os.environ["LSGAN_DEBUG"] = "1"
    if threads:
        os.environ["LSGAN_THREADS"] = str(threads)


@main.command(epilog="""\b
Stages (each is skipped when its output is complete; an interrupted training resumes):
  [1/8] preprocess  [2/8] train-vae  [3/8] encode-latents  [4/8] train-gan
  [5/8] train-evaluator  [6/8] evaluate  [7/8] generate  [8/8] export (GLB + GIF)
\b
Examples:
  lsgan demo                                  # -> demo_out/ (about 6 minutes on a 2-core CPU)
  lsgan demo -o my_demo
  LSGAN_DEMO_SCALE=0.05 lsgan demo -o tiny    # about a minute: steps, clips and evaluation draws x 0.05
  lsgan demo --scale 0.2 --fresh              # start over in demo_out at another scale
  lsgan demo --threads 2                      # a fixed thread count (default: lsgan adapts to the load)
""")
@click.option("-o", "--output", default="demo_out", show_default=True, type=Out(file_okay=False),
              help="Folder for everything the demo makes; run again to continue or reuse it.")
@click.option("--scale", type=float, default=None, metavar="FACTOR",
              help="Multiply step counts, the number of clips (at least 400) and the evaluation's replications "
                   "and MultiModality draws by FACTOR, e.g. 0.05 for a one-minute run. Default: the environment "
                   "variable LSGAN_DEMO_SCALE, else 1.")
@click.option("--fresh", is_flag=True, help="Remove an earlier demo in the output folder first (its own files only).")
@click.option("--threads", type=click.IntRange(1), default=None,
              help="Fix torch's CPU threads (as `lsgan --threads N`). Default: lsgan picks them per stage and "
                   "lowers them while other processes keep cores busy.")
@click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N.")
def demo(output, scale, fresh, threads, device) -> None:
    """Run the whole pipeline on built-in synthetic data: preprocess, train a VAE, a deep-wgan-gp GAN and an
    evaluator, evaluate (T2M metrics, Real and GAN rows), generate five prompts and export GLB + GIF.

    Settings come from recipes/demo.yaml. Ctrl-C stops cleanly (exit code 130); the next run continues.
    At the end it prints where everything is and the metrics table; OUTPUT/summary.json holds paths,
    metrics and stage timings.
    """
    from lsgan.demo import DemoInterrupted, run_demo
    from lsgan.train.common import TrainingDiverged

    try:
        result = run_demo(output, scale=scale, fresh=fresh, device=device, threads=threads)
    except DemoInterrupted as e:
        click.echo(f"\ninterrupted during [{e.index}/8] {e.stage}: finished stages (and the last checkpoint of a "
                   f"training) are kept in {output}; run `lsgan demo -o {output}` again to continue.", err=True)
        sys.exit(130)
    except KeyboardInterrupt:
        click.echo(f"\ninterrupted; run `lsgan demo -o {output}` again to continue.", err=True)
        sys.exit(130)
    except (ValueError, FileNotFoundError, TrainingDiverged) as e:
        _fail(str(e))
    click.echo(result.report())


def make_source(source: str, path: str | None, **opts):
    """Build the importer for ``--source`` from the command-line options (library entry point too)."""
    needs_path = source != "synthetic"
    if needs_path and not path:
        raise click.UsageError(f"--source {source} needs an input PATH")
    if needs_path and not Path(path).exists():
        raise click.UsageError(f"input path {path} does not exist")
    if source == "synthetic":
        from lsgan.data.sources.synthetic import SyntheticSource

        return SyntheticSource(num_clips=opts["num_clips"], seed=opts["seed"])
    if source == "bvh":
        from lsgan.data.sources.bvh import BvhSource

        return BvhSource(root=path, preset=opts["preset"], joint_map=opts["joint_map"], scale=opts["scale"], fps=opts["fps"])
    if source == "humanml3d":
        from lsgan.data.sources.humanml3d import HumanML3DSource

        return HumanML3DSource(root=path)
    if source == "joints":
        from lsgan.data.sources.joints import JointsSource

        return JointsSource(root=path, texts=opts["texts"])
    if source == "amass":
        from lsgan.data.sources.amass import AmassSource

        if not opts["body_models"]:
            raise click.UsageError("--source amass needs --body-models DIR (the SMPL-H model folder)")
        return AmassSource(root=path, body_models=opts["body_models"], index_csv=opts["index_csv"], device=opts["device"])
    if source == "humanact12":
        from lsgan.data.sources.humanact12 import HumanAct12Source

        return HumanAct12Source(path=path, up_axis=opts["up_axis"])
    raise click.UsageError(f"unknown source {source}")


@main.command(epilog="""\b
Examples:
  lsgan preprocess --source synthetic --num-clips 400 -o synth.h5
  lsgan preprocess --source bvh --preset bandai ../shared/data/bandai-namco-2 -o bandai.h5 --workers 2
  lsgan preprocess --source bvh --preset cmu mocap/cmu -o cmu.h5
  lsgan preprocess --source humanml3d HumanML3D/ -o hml3d.h5
  lsgan preprocess --source joints HumanML3D/joints -o hml3d.h5 --format humanml3d
  lsgan preprocess --source amass amass_data --body-models body_models/smplh --index-csv index.csv -o amass.h5
  lsgan preprocess --source humanact12 HumanAct12Poses/humanact12poses.pkl -o act12.h5
""")
@click.argument("path", required=False, type=In())
@click.option("--source", "source_name", type=click.Choice(SOURCES), required=True, help="Kind of input.")
@click.option("-o", "--output", required=True, type=Out(), help="Output .h5 shard (or folder with --format humanml3d).")
@click.option("--format", "fmt", type=click.Choice(["hdf5", "humanml3d"]), default="hdf5", show_default=True,
              help="hdf5: one lsgan shard; humanml3d: the original folder layout (new_joint_vecs/, texts/, ...).")
@click.option("--preset", default="bandai", show_default=True, help="BVH joint map: bandai or cmu.")
@click.option("--joint-map", type=In(exists=True, dir_okay=False), help="BVH joint map JSON (overrides --preset).")
@click.option("--scale", type=float, help="BVH units to metres (default: the preset's).")
@click.option("--fps", type=float, help="Override the BVH frame rate.")
@click.option("--texts", type=In(exists=True, file_okay=False), help="joints: caption folder (default PATH/texts).")
@click.option("--body-models", type=In(exists=True, file_okay=False), help="amass: SMPL-H model folder.")
@click.option("--index-csv", type=In(exists=True, dir_okay=False), help="amass: HumanML3D's index.csv.")
@click.option("--device", default="cpu", show_default=True, help="amass: torch device for the body model (cpu, cuda).")
@click.option("--up-axis", type=click.Choice(["y", "z"]), default="y", show_default=True, help="humanact12: up axis of joints3D.")
@click.option("--num-clips", default=400, show_default=True, help="synthetic: number of clips.")
@click.option("--seed", default=0, show_default=True, help="synthetic: random seed.")
@click.option("--mirror/--no-mirror", default=None, help="Add mirrored copies (default: per source; on for bvh, amass).")
@click.option("--min-frames", default=10, show_default=True, help="Skip clips shorter than this (20 fps frames).")
@click.option("--workers", default=1, show_default=True, help="Worker processes.")
@click.option("--resume", is_flag=True, help="Continue an interrupted run from its OUTPUT.parts/ folder (finished chunks "
              "are reused only when their input files, by SHA-256, and the options are unchanged).")
@click.option("--strict", is_flag=True, help="Stop at the first bad clip instead of skipping it.")
@click.option("--force", is_flag=True, help="Replace an existing OUTPUT that lsgan wrote (never another file).")
@click.option("--report", type=Out(), help="Where to write the JSON report (default OUTPUT.report.json).")
def preprocess(path, source_name, output, fmt, preset, joint_map, scale, fps, texts, body_models, index_csv, device, up_axis,
               num_clips, seed, mirror, min_frames, workers, resume, strict, force, report) -> None:
    """Turn mocap or a dataset into HumanML3D features in an HDF5 shard (or a HumanML3D folder).

    Bad clips are skipped and listed, grouped by reason, with every one in OUTPUT.report.json (--strict stops
    at the first). An existing OUTPUT is refused unless --force; an output that holds the inputs always is.
    Ctrl-C keeps the finished chunks: run again with --resume (exit code 130).
    """
    from tqdm import tqdm

    from lsgan.data.clip import ClipError
    from lsgan.data.preprocess import PreprocessError, print_skips
    from lsgan.data.preprocess import preprocess as run

    if resume and force:
        raise click.UsageError("--resume continues the run that --force would start over: give one of them")
    src = make_source(source_name, path, preset=preset, joint_map=joint_map, scale=scale, fps=fps, texts=texts,
                      body_models=body_models, index_csv=index_csv, device=device, up_axis=up_axis, num_clips=num_clips, seed=seed)
    bar = tqdm(total=0, unit="file", desc=f"preprocess {source_name}", file=sys.stderr, disable=None)

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    try:
        result = run(src, output, format=fmt, mirror=mirror, min_frames=min_frames, workers=workers,
                     resume=resume, strict=strict, force=force, report=report, on_progress=progress)
    except KeyboardInterrupt:
        bar.close()
        _stopped(f"finished chunks are kept in {output}.parts/; run the same command with --resume to continue")
    except (PreprocessError, ClipError, ValueError) as e:
        bar.close()
        _fail(str(e))
    bar.close()
    click.echo(result.summary(), err=True)
    print_skips(result)


@main.command(epilog="""\b
Examples:
  lsgan inspect bandai.h5
  lsgan inspect bandai.h5 --json
""")
@click.argument("file", type=In(exists=True, dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
def inspect(file, as_json) -> None:
    """Show what a shard holds: clips, frames, hours, captions, splits, labels and stats."""
    from lsgan.data.shards import format_summary, summarize

    try:
        info = summarize(file)
    except ValueError as e:
        _fail(str(e))
    click.echo(json.dumps(info, indent=1) if as_json else format_summary(info))


def _recipe(recipe: str | None) -> dict:
    from lsgan.recipes import load_recipe

    if recipe is None:
        return {}
    try:
        return load_recipe(recipe)
    except (FileNotFoundError, ValueError) as e:
        _fail(str(e))


def _overrides(values: dict, **options) -> dict:
    return {**values, **{k: v for k, v in options.items() if v is not None}}


def _cache_training_options(command):
    """The options of the commands that train on a latent cache (train-gan, train-diffusion)."""
    options = [
        click.option("--cache", required=True, type=In(exists=True, dir_okay=False),
                     help="Latent cache from encode-latents."),
        click.option("--recipe", type=MaybeIn(), help="Recipe YAML (or a name in recipes/); its gan: or diffusion: section sets "
                                      "every hyperparameter."),
        click.option("--cond", type=click.Choice(["text", "action"]),
                     help="Condition on caption embeddings or action labels."),
        click.option("--out", required=True, type=Out(), help="Run folder (checkpoints last/ best/, log.csv)."),
        click.option("--max-steps", type=int, help="Override the recipe's number of training steps (a GAN's: generator "
                                                        "steps)."),
        click.option("--seed", type=int),
        click.option("--cuda-graph/--no-cuda-graph", default=None,
                     help="On one CUDA device, replay each step as one CUDA graph (default: the recipe's, else on); "
                          "the same updates either way."),
        click.option("--vae", type=In(exists=True),
                     help="Check the cache against this VAE (default: the VAE it was encoded with)."),
        click.option("--allow-stale", is_flag=True, help="Train even if the VAE changed since the cache was encoded."),
        click.option("--device", default="auto", show_default=True),
        click.option("--resume", is_flag=True, help="Continue the run in --out from its last checkpoint."),
        click.option("--force", is_flag=True,
                     help="Start over in --out, removing the earlier run's own files (never others)."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def _train_on_cache(kind: str, model_config, train_config, model_options: dict, train_options: dict, cache, recipe,
                    out, vae, allow_stale, run) -> None:
    """The recipe's ``kind`` section with the command's overrides, the cache checked against its VAE, then
    ``run(model config, train config, expected VAE hash)``; its summary on stderr, failures as one line."""
    from lsgan.models.cache import check_cache_vae
    from lsgan.recipes import build, section
    from lsgan.train.common import TrainingDiverged

    r = section(_recipe(recipe), kind)
    try:
        expect = check_cache_vae(cache, vae=vae, allow_stale=allow_stale)
        model = build(model_config, _overrides(section(r, "model"), **model_options), f"{kind}.model")
        train = build(train_config, _overrides(section(r, "train"), **train_options), f"{kind}.train")
        result = run(model, train, expect)
    except KeyboardInterrupt:
        _stopped(f"checkpoints so far are kept in {out}; run the same command with --resume to continue")
    except (TrainingDiverged, ValueError, FileExistsError, FileNotFoundError) as e:
        _fail(str(e))
    click.echo(json.dumps(result, default=str), err=True)


@main.command("train-vae", epilog="""\b
Examples:
  lsgan train-vae --data synth.h5 --recipe demo --out runs/vae
  lsgan train-vae --data bandai.h5 --recipe recipes/bandai.yaml --out runs/bandai-vae --device cuda
  lsgan train-vae --data bandai.h5 --recipe bandai --out runs/bandai-vae --resume
  torchrun --nproc_per_node 4 -m lsgan.cli train-vae --data hml3d.h5 --recipe humanml3d --out runs/vae
""")
@click.option("--data", multiple=True, required=True, type=In(exists=True, dir_okay=False), help="Shard(s) to train on.")
@click.option("--recipe", type=MaybeIn(), help="Recipe YAML (or a name in recipes/); its vae: section sets every hyperparameter.")
@click.option("--out", required=True, type=Out(), help="Run folder (checkpoints last/ best/, log.csv).")
@click.option("--max-steps", type=int, help="Override the recipe's step budget.")
@click.option("--batch-size", type=int, help="Override the recipe's batch size.")
@click.option("--seed", type=int, help="Override the recipe's seed.")
@click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N.")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last checkpoint.")
@click.option("--force", is_flag=True, help="Start over in --out, removing the earlier run's own files (never others).")
def train_vae_cmd(data, recipe, out, max_steps, batch_size, seed, device, resume, force) -> None:
    """Train the motion VAE (MLD's skip-transformer VAE) on the train split of one or more shards."""
    from lsgan.models.vae import VAEConfig
    from lsgan.recipes import build, section
    from lsgan.train.common import TrainingDiverged
    from lsgan.train.vae import VAETrainConfig, train_vae

    r = section(_recipe(recipe), "vae")
    try:
        model = build(VAEConfig, section(r, "model"), "vae.model")
        train = build(VAETrainConfig, _overrides(section(r, "train"), max_steps=max_steps, batch_size=batch_size,
                                                seed=seed), "vae.train")
        result = train_vae(list(data), out, model=model, train=train, device=device, resume=resume, force=force)
    except KeyboardInterrupt:
        _stopped(f"checkpoints so far are kept in {out}; run the same command with --resume to continue")
    except (TrainingDiverged, ValueError, FileExistsError, FileNotFoundError) as e:
        _fail(str(e))
    click.echo(json.dumps(result), err=True)


@main.command("encode-latents", epilog="""\b
Examples:
  lsgan encode-latents --data synth.h5 --vae runs/vae -o cache.h5
  lsgan encode-latents --data hml3d.h5 --vae runs/vae --text-encoder clip-vit-l-14 --text-encoder-path clip-l14 -o cache.h5
  lsgan encode-latents --data act12.h5 --vae runs/vae --text-encoder none -o cache.h5
""")
@click.option("--data", multiple=True, required=True, type=In(exists=True, dir_okay=False), help="Shard(s) to encode.")
@click.option("--vae", required=True, type=In(exists=True), help="VAE run or checkpoint folder.")
@click.option("-o", "--output", required=True, type=Out(), help="Latent cache (.h5) to write.")
@click.option("--text-encoder", help="minilm (default), clip-vit-l-14, or none (default: the recipe's, else minilm).")
@click.option("--recipe", type=MaybeIn(), help="Recipe whose text_encoder: key picks the encoder.")
@click.option("--text-encoder-path", type=In(exists=True), help="Local folder of the text encoder's weights.")
@click.option("--min-frames", default=None, type=int, help="Shortest window (default: the VAE's training setting).")
@click.option("--max-frames", default=None, type=int, help="Longest window (default: the VAE's training setting).")
@click.option("--batch-size", default=64, show_default=True)
@click.option("--device", default="auto", show_default=True)
@click.option("--force", is_flag=True, help="Replace an existing OUTPUT that lsgan wrote (never another file).")
def encode_latents_cmd(data, vae, output, text_encoder, recipe, text_encoder_path, min_frames, max_frames, batch_size,
                       device, force) -> None:
    """Cache the VAE latent (mean, log-variance) of every window and the embedding of every caption."""
    from lsgan.models.cache import encode_latents
    from lsgan.models.checkpoint import read_meta

    text_encoder = text_encoder or _recipe(recipe).get("text_encoder") or "minilm"
    try:
        train_cfg = read_meta(vae)["config"].get("train", {})
        path = encode_latents(
            list(data), vae, output, text_encoder=None if text_encoder == "none" else text_encoder,
            text_encoder_path=text_encoder_path, min_frames=min_frames or train_cfg.get("min_frames", 40),
            max_frames=max_frames or train_cfg.get("max_frames", 196), batch_size=batch_size, device=device,
            force=force,
        )
    except Exception as e:  # noqa: BLE001 - every failure here is the user's input: report it plainly
        _fail(_plainly(e))
    click.echo(f"wrote {path}", err=True)


@main.command("train-gan", epilog="""\b
Examples:
  lsgan train-gan --cache cache.h5 --recipe demo --out runs/gan
  lsgan train-gan --cache cache.h5 --arch vanilla-wgan-gp --cond text --max-steps 20000 --out runs/vwgan
  lsgan train-gan --cache act12_cache.h5 --recipe humanact12 --cond action --out runs/act-gan
""")
@_cache_training_options
@click.option("--arch", type=click.Choice(["vanilla-gan", "vanilla-wgan-gp", "deep-gan", "deep-wgan-gp"]),
              help="GAN variant (default: the recipe's, else deep-wgan-gp).")
def train_gan_cmd(cache, recipe, arch, cond, out, max_steps, seed, cuda_graph, vae, allow_stale, device, resume,
                  force) -> None:
    """Train a latent GAN from the cache alone (the VAE is never run while training).

    The cache is refused when its VAE checkpoint has changed since it was encoded (a stale cache), so a
    GAN never learns latents its decoder does not understand.
    """
    from lsgan.models.gan import GANConfig
    from lsgan.train.gan import GANTrainConfig, train_gan

    _train_on_cache("gan", GANConfig, GANTrainConfig, dict(arch=arch, cond=cond),
                    dict(max_steps=max_steps, seed=seed, cuda_graph=cuda_graph), cache, recipe, out,
                    vae, allow_stale, lambda model, train, expect: train_gan(
                        cache, out, gan=model, train=train, device=device, resume=resume, force=force,
                        expect_vae_hash=expect))


@main.command("train-evaluator", epilog="""\b
Examples:
  lsgan train-evaluator --data synth.h5 --recipe demo --out runs/evaluator
  lsgan train-evaluator --data bandai.h5 --recipe bandai --out runs/bandai-evaluator
  lsgan train-evaluator --data bandai.h5 --recipe bandai --kind action --out runs/bandai-action-clf
  lsgan train-evaluator --data act12.h5 --recipe humanact12 --out runs/act12-classifier --device cuda
  lsgan train-evaluator --data hml3d.h5 --recipe humanml3d --out runs/hml3d-evaluator --resume
  lsgan evaluate ... --evaluator runs/evaluator     # or the folder of the official T2M files
""")
@click.option("--data", multiple=True, required=True, type=In(exists=True, dir_okay=False), help="Shard(s) to train on.")
@click.option("--out", required=True, type=Out(), help="Run folder (checkpoints last/ best/, log.csv, heldout.json).")
@click.option("--recipe", type=MaybeIn(), help="Recipe YAML (or a name in recipes/); its evaluator: section (text:, action:) sets the hyperparameters.")
@click.option("--kind", type=click.Choice(["text", "action"]),
              help="text: text-motion evaluator (captions); action: action-recognition GRU (action labels). "
                   "Default: the recipe's only evaluator kind, else text.")
@click.option("--max-steps", type=int, help="Override the recipe's number of training steps.")
@click.option("--batch-size", type=int, help="Override the recipe's batch size.")
@click.option("--seed", type=int, help="Override the recipe's seed.")
@click.option("--text-encoder", help="text: frozen sentence encoder, minilm or clip-vit-l-14 (default: the recipe's, else minilm).")
@click.option("--text-encoder-path", type=In(exists=True), help="text: local folder of the sentence encoder's weights.")
@click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N.")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last checkpoint.")
@click.option("--force", is_flag=True, help="Start over in --out, removing the earlier run's own files (never others).")
def train_evaluator_cmd(data, out, recipe, kind, max_steps, batch_size, seed, text_encoder, text_encoder_path, device,
                        resume, force) -> None:
    """Train an evaluator for `lsgan evaluate` on your data and report held-out figures.

    \b
    text:   our text-motion evaluator: T2M's motion encoder and, instead of GloVe, a head on a frozen sentence
            encoder; trained contrastively as T2M (margin 10). Prints held-out R-precision top-1/2/3 (groups
            of 32) and MM-Dist on the test split (else val).
    action: the action-recognition GRU (joints x 3, hidden 128, 2 layers, 30-d features); prints held-out accuracy.
    """
    from lsgan.models.evaluator import ActionClassifierConfig, EvaluatorConfig
    from lsgan.recipes import build, section
    from lsgan.train.common import TrainingDiverged
    from lsgan.train.evaluator import (
        ActionTrainConfig,
        EvaluatorTrainConfig,
        train_action_classifier,
        train_evaluator,
    )

    full = _recipe(recipe)
    try:
        sections = section(full, "evaluator")
        if kind is None:
            present = [k for k in ("text", "action") if k in sections]
            kind = present[0] if len(present) == 1 else "text"
        r = section(sections, kind)
        train_values = _overrides(section(r, "train"), max_steps=max_steps, batch_size=batch_size, seed=seed)
        if kind == "text":
            model_values = dict(section(r, "model"))
            if text_encoder or "text_encoder" not in model_values:
                model_values["text_encoder"] = text_encoder or full.get("text_encoder") or "minilm"
            result = train_evaluator(
                list(data), out, config=build(EvaluatorConfig, model_values, "evaluator.text.model"),
                train_config=build(EvaluatorTrainConfig, train_values, "evaluator.text.train"), device=device,
                resume=resume, force=force, text_encoder_path=text_encoder_path)
        else:
            result = train_action_classifier(
                list(data), out, config=build(ActionClassifierConfig, section(r, "model"), "evaluator.action.model"),
                train_config=build(ActionTrainConfig, train_values, "evaluator.action.train"), device=device,
                resume=resume, force=force)
    except KeyboardInterrupt:
        _stopped(f"checkpoints so far are kept in {out}; run the same command with --resume to continue")
    except (TrainingDiverged, ValueError, FileExistsError, FileNotFoundError) as e:
        _fail(str(e))
    except Exception as e:  # noqa: BLE001 - e.g. a text encoder whose weights are absent: say so plainly
        _fail(_plainly(e))
    click.echo(json.dumps(result, default=str), err=True)
    h = result["heldout"]
    if "r_precision_top3" in h:
        click.echo(f"held-out ({h['split']}, {h['pairs']} pairs, groups of {h['group_size']}): R-precision "
                   f"top-1 {h['r_precision_top1']:.3f}, top-2 {h['r_precision_top2']:.3f}, top-3 {h['r_precision_top3']:.3f} "
                   f"(chance {h['chance_top1']:.3f}/{h['chance_top2']:.3f}/{h['chance_top3']:.3f}); "
                   f"MM-Dist {h['mm_dist']:.3f}")
    elif "accuracy" in h:
        click.echo(f"held-out ({h['split']}, {h['clips']} clips): accuracy {h['accuracy']:.3f} "
                   f"(chance {h['chance']:.3f}, majority class {h['majority']:.3f})")
    else:
        click.echo("no held-out split (test or val) to report on")


@main.command("train-diffusion", epilog="""\b
Examples:
  lsgan train-diffusion --cache cache.h5 --recipe demo --out runs/diffusion
  lsgan train-diffusion --cache bandai-cache.h5 --recipe bandai --out runs/bandai-diffusion --device cuda
  lsgan train-diffusion --cache act12-cache.h5 --recipe humanact12 --out runs/act-diffusion --resume
  lsgan generate --gan runs/diffusion --vae runs/vae --text "a person walks forward" --steps 50 --guidance 7.5 -o out/
""")
@_cache_training_options
def train_diffusion_cmd(cache, recipe, cond, out, max_steps, seed, cuda_graph, vae, allow_stale, device, resume,
                        force) -> None:
    """Train the latent-diffusion baseline (MLD's denoiser, DDIM, classifier-free guidance) on the same cache.

    Like train-gan it reads the cache alone and refuses one whose VAE has changed since it was encoded;
    `lsgan generate --gan RUN` and `lsgan evaluate` take the result wherever they take a GAN.
    """
    from lsgan.models.diffusion import DiffusionConfig
    from lsgan.train.diffusion import DiffusionTrainConfig, train_diffusion

    _train_on_cache("diffusion", DiffusionConfig, DiffusionTrainConfig, dict(cond=cond),
                    dict(max_steps=max_steps, seed=seed, cuda_graph=cuda_graph), cache, recipe, out,
                    vae, allow_stale, lambda model, train, expect: train_diffusion(
                        cache, out, diffusion=model, train=train, device=device, resume=resume, force=force,
                        expect_vae_hash=expect))


@main.command(epilog="""\b
Examples:
  lsgan generate --gan runs/gan --vae runs/vae --text "a person walks forward" -o out/
  lsgan generate --gan runs/gan --vae runs/vae --text "someone jumps twice" --seconds 4 --num 4 --seed 1 -o out/
  lsgan generate --gan runs/gan --vae runs/vae --prompts prompts.txt -o out/     # lines: 'prompt' or 'prompt#frames'
  lsgan generate --gan runs/act-gan --vae runs/vae --action jump --num 8 -o out/
  lsgan generate --gan runs/gan --vae runs/vae --timeline "walk forward#80; turn around#60; wave#60" -o out/
  lsgan generate --gan runs/gan --vae runs/vae --timeline take.txt --overlap 16 -o out/   # lines: 'prompt#frames'
  lsgan generate --gan runs/diffusion --vae runs/vae --text "a person waves" --steps 50 --guidance 7.5 -o out/
  lsgan generate --runtime onnx --gan gan-onnx --text "a person walks forward" -o out/   # export-model's folder
  lsgan --threads 1 generate --runtime onnx --int8 --gan gan-onnx --prompts prompts.txt -o out/
""")
@click.option("--gan", required=True, type=In(exists=True),
              help="Generator checkpoint: GAN or diffusion (run or checkpoint folder); with --runtime onnx, the "
                   "folder `lsgan export-model --onnx` wrote.")
@click.option("--vae", type=In(exists=True),
              help="The VAE whose latents the generator learned (--runtime torch; an ONNX export holds its decoder).")
@click.option("--runtime", type=click.Choice(["torch", "onnx"]), default="torch", show_default=True,
              help="torch: the checkpoints; onnx: an exported folder, run by onnxruntime without torch (the same "
                   "--seed gives the same motions in both).")
@click.option("--int8", is_flag=True, help="--runtime onnx: the int8 graphs (an export made with --int8).")
@click.option("--text", "texts", multiple=True, help="A prompt (repeat for several).")
@click.option("--prompts", type=In(exists=True, dir_okay=False), help="File with one prompt per line (optional #frames).")
@click.option("--action", "actions", multiple=True, help="An action label, for action-conditioned models (repeatable).")
@click.option("--timeline", type=MaybeIn(), help="One continuous motion from several prompts, longer than the model's clips: a file "
              "of 'prompt#frames' lines, or the same inline separated by ';' ('walk forward#80; turn around#60'). A "
              "value naming an existing file is read as the file; any other value holding '#' is inline.")
@click.option("--overlap", type=click.IntRange(0), help="--timeline: frames over which consecutive segments are "
              "cross-faded (default 10; 0: hard cuts).")
@click.option("--frames", type=int, help="Length in frames at 20 fps (default 120).")
@click.option("--seconds", type=float, help="Length in seconds (instead of --frames).")
@click.option("--num", default=1, show_default=True, help="Motions per prompt or action.")
@click.option("--seed", default=0, show_default=True, help="Random seed: the same seed gives the same motions.")
@click.option("--text-encoder-path", type=In(exists=True), help="Local weights of the GAN's text encoder (CLIP).")
@click.option("--batch-size", default=256, show_default=True)
@click.option("--device", default="auto", show_default=True)
@click.option("--steps", type=click.IntRange(1), help="Diffusion: DDIM steps (default: the checkpoint's, 50 in MLD).")
@click.option("--guidance", type=float, help="Diffusion: classifier-free guidance scale (default: the checkpoint's).")
@click.option("-o", "--output", required=True, type=Out(), help="Output folder: *_features.npy, *_joints.npy, manifest.json.")
@click.option("--raw-joints", is_flag=True, help="Also write *_joints_raw.npy: the joints as decoded (recovered from "
              "*_features.npy), before they were made rigid; *_joints.npy, the previews and exports are the rigid ones.")
@click.option("--fix-feet/--no-fix-feet", default=False, show_default=True, help="Hold each foot still while "
              "the features' contact channels say it touches the ground (IK on the leg only), once, on the motion "
              "that every output then shows (*_joints.npy, previews, exports; the server serves motions without).")
@click.option("--force", is_flag=True, help="Write into an existing OUTPUT, first removing the files an earlier lsgan run "
              "wrote there (never other files).")
def generate(gan, vae, runtime, int8, texts, prompts, actions, timeline, overlap, frames, seconds, num, seed,
             text_encoder_path, batch_size, device, steps, guidance, output, raw_joints, fix_feet, force) -> None:
    """Generate motions from sentences or action labels: latents from the generator (a GAN pass, or DDIM steps
    of a diffusion denoiser), then one VAE decoder pass."""
    from lsgan.generation import Request, claim_generation, read_prompts, write_generation

    if frames is not None and seconds is not None:
        raise click.UsageError("give --frames or --seconds, not both")
    n_frames = frames if frames is not None else (round(seconds * 20) if seconds is not None else 120)
    if n_frames < 4:
        raise click.UsageError("a motion needs at least 4 frames")
    _check_runtime_options(runtime, vae=vae, int8=int8, text_encoder_path=text_encoder_path, device=device,
                           steps=steps, guidance=guidance)
    if timeline is not None or overlap is not None:
        _check_timeline_options(timeline, texts=texts, prompts=prompts, actions=actions, frames=frames,
                                seconds=seconds, num=num)
        return _generate_timeline(timeline, overlap, gan=gan, vae=vae, runtime=runtime, int8=int8, seed=seed,
                                  device=device, text_encoder_path=text_encoder_path, batch_size=batch_size,
                                  steps=steps, guidance=guidance, output=output, raw_joints=raw_joints, force=force,
                                  fix_feet=fix_feet)
    requests = [Request(text=t, frames=n_frames) for t in texts] + [Request(action=a, frames=n_frames) for a in actions]
    if prompts:
        requests += read_prompts(prompts, n_frames)
    if not requests:
        raise click.UsageError("give --text, --prompts or --action")
    try:
        claim_generation(output, gan, *([vae] if vae else []), *([prompts] if prompts else []), force=force)
        if runtime == "onnx":
            from lsgan.deploy.runtime import generate_onnx

            result = generate_onnx(gan, requests, num=num, seed=seed, variant="int8" if int8 else "fp32",
                                   batch_size=batch_size, fix_feet=fix_feet)
        else:
            from lsgan.generate import generate as run

            result = run(gan, vae, requests, num=num, seed=seed, device=device, text_encoder_path=text_encoder_path,
                         batch_size=batch_size, steps=steps, guidance=guidance, fix_feet=fix_feet)
        if result.kind == "gan" and (steps is not None or guidance is not None):
            click.echo(f"note: --steps/--guidance ignored: {gan} is a GAN (they set a diffusion model's sampling)",
                       err=True)
        manifest = write_generation(result, output, force=force, raw_joints=raw_joints)
    except (ValueError, FileNotFoundError) as e:
        _fail(str(e))
    t = result.timings_s
    click.echo(f"{len(result.motions)} motions in {output} ({manifest.name}); {result.ms_per_motion:.2f} ms per motion "
               f"(text {t['text_encoding'] * 1e3:.1f} ms, generator {t['generator'] * 1e3:.1f} ms, "
               f"VAE decoder {t['vae_decoding'] * 1e3:.1f} ms in all)", err=True)


def _check_timeline_options(timeline, *, texts, prompts, actions, frames, seconds, num) -> None:
    """--timeline sets the prompts and lengths itself; --overlap belongs to it."""
    if timeline is None:
        raise click.UsageError("--overlap goes with --timeline")
    given = [name for name, value in (("--text", texts), ("--prompts", prompts), ("--action", actions),
                                      ("--frames", frames), ("--seconds", seconds)) if value]
    given += ["--num"] if num != 1 else []
    if given:
        raise click.UsageError(f"{', '.join(given)}: not used with --timeline (its lines give the prompts and "
                               "lengths of one motion)")


def _generate_timeline(timeline: str, overlap: int | None, *, gan, vae, output, raw_joints, force, **options) -> None:
    """``generate --timeline``: parse (an inline timeline's errors are usage errors), generate, join, write."""
    from lsgan.generation import claim_generation, write_generation
    from lsgan.timeline import DEFAULT_OVERLAP, TimelineError, generate_timeline, parse_timeline

    try:
        segments, source = parse_timeline(timeline)
    except TimelineError as e:
        if e.inline:
            raise click.UsageError(str(e)) from None
        _fail(str(e))
    try:
        claim_generation(output, gan, *([vae] if vae else []), *([source] if source else []), force=force)
        result = generate_timeline(gan, vae, segments, overlap=DEFAULT_OVERLAP if overlap is None else overlap,
                                   source=source, **options)
        manifest = write_generation(result, output, force=force, raw_joints=raw_joints)
    except (ValueError, FileNotFoundError) as e:
        _fail(str(e))
    n = len(result.motions[0].features)
    click.echo(f"1 motion of {n} frames ({n / 20:.1f} s) from {len(segments)} segments in {output} ({manifest.name})",
               err=True)


def _check_runtime_options(runtime: str, *, vae, int8, text_encoder_path, device, steps, guidance) -> None:
    """Options that belong to the other runtime are usage errors, not silently ignored."""
    if runtime == "torch":
        if vae is None:
            raise click.UsageError("--vae is required (with --runtime onnx, --gan names an exported folder instead)")
        if int8:
            raise click.UsageError("--int8 goes with --runtime onnx")
        return
    given = [name for name, value in (("--vae", vae), ("--text-encoder-path", text_encoder_path), ("--steps", steps),
                                      ("--guidance", guidance)) if value is not None]
    if device not in ("auto", "cpu"):
        given.append("--device")
    if given:
        raise click.UsageError(f"{', '.join(given)}: not used with --runtime onnx (the exported folder holds the "
                               "decoder and text encoder; it runs on the CPU)")


@main.command("export-model", epilog="""\b
Examples:
  lsgan export-model runs/gan -o gan-onnx --onnx               # text encoder, generator, decoder + manifest.json
  lsgan export-model runs/gan -o gan-onnx --onnx --int8 --force   # also an int8 decoder, with its joint error
  lsgan export-model runs/act-gan --vae runs/vae -o act-onnx --onnx
  lsgan generate --runtime onnx --gan gan-onnx --text "a person walks forward" -o out/
\b
Calling the graphs from Python, C++ or C# without lsgan: docs/deploy.md.
""")
@click.argument("run", type=In(exists=True, file_okay=False))
@click.option("-o", "--output", required=True, type=Out(), help="Folder for the graphs, tokenizer and manifest.json.")
@click.option("--onnx", "as_onnx", is_flag=True, help="ONNX graphs (the one format so far).")
@click.option("--int8", is_flag=True, help="Also write a decoder with int8 feed-forward and self-attention "
              "products (dynamic quantisation, per-channel weights; everything else stays fp32) and measure its joint "
              "error against fp32 on 100 fixed motions.")
@click.option("--vae", type=In(exists=True), help="The GAN's VAE (default: the one its latent cache was "
              "encoded with, as its config.json records).")
@click.option("--text-encoder-path", type=In(exists=True, file_okay=False),
              help="Local MiniLM folder, when the GAN was trained with one (default: the packaged weights).")
@click.option("--opset", default=18, show_default=True, type=click.IntRange(18), help="ONNX opset (18 or later).")
@click.option("--force", is_flag=True, help="Write into an existing OUTPUT, replacing only files lsgan wrote there.")
def export_model(run, output, as_onnx, int8, vae, text_encoder_path, opset, force) -> None:
    """Export a latent GAN with its VAE decoder and text encoder as ONNX graphs that run without torch
    (onnxruntime; `lsgan generate --runtime onnx`), with a manifest.json saying how to feed them."""
    from lsgan.deploy.onnx_export import export_onnx
    from lsgan.models.text import TextEncoderUnavailable

    if not as_onnx:
        raise click.UsageError("choose a format: --onnx (the one format so far)")
    try:
        result = export_onnx(run, output, vae=vae, int8=int8, force=force, text_encoder_path=text_encoder_path,
                             opset=opset, progress=lambda m: click.echo(m, err=True))
    except (ValueError, FileNotFoundError, TextEncoderUnavailable) as e:
        _fail(str(e))
    m = result.manifest
    click.echo(f"wrote {len(m['files']) + 1} files to {result.folder} in {result.seconds:.1f} s "
               f"({m['condition']}-conditioned; {', '.join(m['variants'])})", err=True)
    error = m["variants"].get("int8", {}).get("joint_error_mm")
    if error:
        click.echo(f"int8 joint error against fp32 ({error['motions']} motions): mean {error['mean']:.2f} mm, "
                   f"max {error['max']:.2f} mm", err=True)


@main.command(epilog="""\b
Examples:
  lsgan export --glb out/000_a-person-walks-forward_joints.npy -o walk.glb
  lsgan export --glb out/ -o glb/                  # every motion of a generate folder
  lsgan export --glb out/ --body-model ~/models -o glb/   # SMPL body (skinned) + fitted .npz per motion
  lsgan export --glb walk.npy --body-model ~/models/smplx/SMPLX_MALE.npz --gender male -o walk.glb
  lsgan export --bvh out/ -o bvh/
  lsgan export --bvh out/ -o bvh/                 # the motions of record, as generate wrote them
  lsgan export --bvh motion_features.npy --fps 30 -o motion.bvh
  lsgan export --gif out/ -o previews/             # stick-figure previews, captions as titles
  lsgan export --mp4 out/ -o previews/             # the same as H.264 videos (ffmpeg comes with the package)
  lsgan export --mp4 --title "a wave" out/000_wave_joints.npy --fps 30 -o wave.mp4
  lsgan export --bvh out/ --rig character.bvh --preset mixamo -o rig/   # on your character's skeleton
  lsgan export --bvh walk.npy --rig hero.bvh --joint-map hero_map.json -o walk_hero.bvh
  lsgan export --glb out/ --rig character.bvh --preset bandai -o rig_glb/   # a skinned armature of your rig
""")
@click.argument("input", type=In(exists=True))
@click.option("--glb", "as_glb", is_flag=True, help="Animated glTF binary: named joint nodes, a visible skeleton, one animation.")
@click.option("--bvh", "as_bvh", is_flag=True, help="BVH on the 22-joint skeleton (centimetres, ZYX channels).")
@click.option("--gif", "as_gif", is_flag=True, help="Stick-figure preview with ground grid, root path and caption.")
@click.option("--mp4", "as_mp4", is_flag=True, help="The --gif preview as an H.264 MP4 (plays in browsers and QuickTime).")
@click.option("--title", help="--gif/--mp4: the title (default: the prompt from a generate manifest, else the file name).")
@click.option("--body-model", type=In(), help="--glb: fit this SMPL/SMPL-H/SMPL-X model (file or folder, "
              "smplx layout) and write one skinned body mesh, plus the fitted poses/trans/betas as .npz.")
@click.option("--gender", default="neutral", show_default=True, type=click.Choice(["neutral", "male", "female"]),
              help="--body-model: which model file to use.")
@click.option("--model-type", default="auto", show_default=True, type=click.Choice(["auto", "smpl", "smplh", "smplx"]),
              help="--body-model: the model family (auto: the first found of SMPL, SMPL-H, SMPL-X).")
@click.option("--fit-iterations", default=100, show_default=True, type=click.IntRange(1),
              help="--body-model: L-BFGS iterations of the batched pose refinement.")
@click.option("--fps", default=20.0, show_default=True, help="Frame rate written in the file.")
@click.option("--rig", type=In(exists=True, dir_okay=False), help="--bvh/--glb: write the motion on this "
              "BVH character's skeleton by IK (BVH: its hierarchy, rest offsets, channel order and units; GLB: its "
              "hierarchy as a skinned armature in metres).")
@click.option("--joint-map", type=In(exists=True, dir_okay=False),
              help="--rig: the JSON joint map naming the rig's joint for each SMPL joint (the importer's format).")
@click.option("--preset", type=click.Choice(["bandai", "cmu", "mixamo"]), help="--rig: a built-in joint map.")
@click.option("-o", "--output", required=True, type=Out(), help="Output file, or folder when INPUT holds several motions.")
@click.option("--force", is_flag=True, help="Replace existing outputs that lsgan wrote (never other files).")
@click.option("--fix-feet/--no-fix-feet", default=None, help="Hold each foot still while in contact, by IK on the "
              "leg only. Generated motions carry their feet from `lsgan generate` (its --fix-feet), "
              "so that the export shows the motion of record; --fix-feet here holds them again (the contacts of "
              "their features), or on a plain joints .npy with contacts estimated from its joints.")
def export(input, as_glb, as_bvh, as_gif, as_mp4, title, body_model, gender, model_type, fit_iterations, fps,
           rig, joint_map, preset, output, force, fix_feet) -> None:
    """Export motions (joints .npy, features .npy or a generate folder) for Blender, three.js and game engines."""
    from lsgan.data.body_model import BodyModelError
    from lsgan.data.clip import ClipError
    from lsgan.export.motions import export_motions
    from lsgan.export.preview import EncodeError

    if as_glb + as_bvh + as_gif + as_mp4 != 1:
        raise click.UsageError("choose one format: --glb, --bvh, --gif or --mp4")
    if body_model is not None and not as_glb:
        raise click.UsageError("--body-model goes with --glb")
    if rig is not None and not (as_bvh or as_glb):
        raise click.UsageError("--rig goes with --bvh or --glb")
    if rig is not None and body_model is not None:
        raise click.UsageError("--body-model and --rig do not go together: the body fit is SMPL's skeleton, --rig is "
                               "yours")
    if rig is not None and (joint_map is None) == (preset is None):
        raise click.UsageError("--rig needs one joint map: --joint-map MAP.json or --preset bandai|cmu|mixamo")
    if rig is None and (joint_map is not None or preset is not None):
        raise click.UsageError("--joint-map and --preset go with --rig")
    fmt = "glb" if as_glb else "bvh" if as_bvh else "gif" if as_gif else "mp4"
    try:
        done = export_motions(input, output, fmt=fmt, fps=fps, title=title, body_model=body_model, gender=gender,
                              model_type=model_type, fit_iterations=fit_iterations, force=force, rig=rig,
                              joint_map=joint_map, preset=preset, fix_feet=fix_feet)
    except (ValueError, ClipError, BodyModelError, EncodeError) as e:
        _fail(describe(e))
    for item in done:
        if item.params is not None:
            click.echo(f"{item.path}: body fit error mean {item.fit_mean_error_mm:.1f} mm, "
                       f"max {item.fit_max_error_mm:.1f} mm; parameters in {item.params}", err=True)
    shown = ", ".join(str(d.path) for d in done[:3]) + (" ..." if len(done) > 3 else "")
    click.echo(f"wrote {len(done)} {fmt.upper()} file(s): {shown}", err=True)
    if fmt in ("glb", "bvh") and done:
        from lsgan.export.blender import blender_hint

        longest = max(d.frames for d in done)
        click.echo(blender_hint(fmt, fps, longest, scale=done[0].unit_m)
                   + ("" if len(done) == 1 else f" (the longest, {longest} frames)"), err=True)


@main.command(epilog="""\b
Examples:
  lsgan evaluate --gan runs/gan --vae runs/vae --data bandai.h5 --evaluator runs/evaluator -o results/bandai
  lsgan evaluate --gan deep=runs/gan --gan diffusion=runs/diffusion --vae runs/vae --data bandai.h5 \\
      --evaluator runs/evaluator --replications 20 -o results/bandai
  lsgan evaluate --vae-only --vae runs/vae --data bandai.h5 --evaluator runs/evaluator -o results/vae
  lsgan evaluate --action --gan runs/act-gan --vae runs/vae --data humanact12.h5 --evaluator runs/action-clf -o act
  lsgan evaluate ... --evaluator ~/t2m-official     # the official T2M evaluator (finest.tar + GloVe + meta)
  lsgan evaluate ... --fid-reference same           # FID as MLD computes it (default: T2M's separate pass)
""")
@click.option("--gan", "models", multiple=True, type=NamedIn(),
              help="A generator checkpoint (GAN or diffusion); repeat to compare several in one table.")
@click.option("--vae", required=True, type=In(exists=True), help="The VAE the generators decode with.")
@click.option("--data", required=True, type=In(exists=True), help="Shard with the evaluation split.")
@click.option("--evaluator", type=In(exists=True),
              help="Text-motion evaluator (train-evaluator run or official T2M folder); the action classifier with --action.")
@click.option("--split", default="test", show_default=True)
@click.option("--replications", default=None, type=click.IntRange(1), help="[default: 20; 1 with --vae-only]")
@click.option("--mm-captions", default=100, show_default=True, help="MultiModality: captions (0 skips it).")
@click.option("--mm-samples", default=30, show_default=True, help="MultiModality: motions per caption.")
@click.option("--min-frames", default=40, show_default=True, help="Shortest test window (Bandai recipe: 16).")
@click.option("--max-frames", default=196, show_default=True, help="Longest test window (crop beyond).")
@click.option("--samples", default=1000, show_default=True, help="--action: generated motions per replication.")
@click.option("--steps", type=click.IntRange(1), help="Diffusion: DDIM steps (default: the checkpoint's).")
@click.option("--guidance", type=float, help="Diffusion: classifier-free guidance scale (default: the checkpoint's).")
@click.option("--vae-only", is_flag=True, help="The VAE reconstruction table (APE/AVE, MPJPE, FID).")
@click.option("--action", "action_table", is_flag=True, help="The action-to-motion table (HumanAct12 style).")
@click.option("--fid-reference", type=click.Choice(["separate", "same"]), default=None,
              help="Text-to-motion FID's real set: a separate real pass (T2M, MDM) or, for model rows, the draw "
                   "that gave their captions and lengths (MLD).  [default: separate]")
@click.option("--seed", default=0, show_default=True)
@click.option("--device", default="auto", show_default=True)
@click.option("-o", "--output", required=True, type=Out(), help="Writes OUTPUT.md and OUTPUT.json.")
@click.option("--force", is_flag=True, help="Replace OUTPUT.md/.json that lsgan wrote (never other files).")
def evaluate(models, vae, data, evaluator, split, replications, mm_captions, mm_samples, min_frames, max_frames,
             samples, steps, guidance, vae_only, action_table, fid_reference, seed, device, output, force) -> None:
    """The paper's tables: Real row, model rows, 95% confidence half-widths (markdown + JSON)."""
    from lsgan.eval.evaluate import (claim_table, evaluate_action_to_motion, evaluate_reconstruction,
                                     evaluate_text_to_motion, write_table)

    named = {}
    for spec in models:
        name, _, path = spec.rpartition("=") if "=" in spec else (Path(spec).name, "", spec)
        if not Path(path).exists():
            raise click.BadParameter(f"{path} does not exist", param_hint="--gan")
        named[name] = path
    if vae_only and action_table:
        raise click.UsageError("choose one of --vae-only and --action")
    if fid_reference and (vae_only or action_table):
        raise click.UsageError("--fid-reference applies to the text-to-motion table only")
    if not vae_only and not named:
        raise click.UsageError("give at least one --gan checkpoint (or --vae-only)")
    if not vae_only and evaluator is None:
        raise click.UsageError("--evaluator is required (train one with `lsgan train-evaluator`)")
    progress = lambda msg: click.echo(msg, err=True)  # noqa: E731
    claim_table(output, force=force)  # before the minutes of evaluation, not after
    try:
        if vae_only:
            table = evaluate_reconstruction(vae, data, evaluator=evaluator, split=split, replications=replications or 1,
                                            min_frames=min_frames, max_frames=max_frames, seed=seed, device=device)
        elif action_table:
            table = evaluate_action_to_motion(named, vae, data, evaluator, split=split, replications=replications or 20,
                                              samples=samples, seed=seed, device=device, min_frames=min_frames,
                                              max_frames=max_frames, steps=steps, guidance=guidance, progress=progress)
        else:
            table = evaluate_text_to_motion(named, vae, data, evaluator, split=split, replications=replications or 20,
                                            mm_captions=mm_captions, mm_samples=mm_samples, min_frames=min_frames,
                                            max_frames=max_frames, seed=seed, device=device, steps=steps,
                                            guidance=guidance, fid_reference=fid_reference or "separate",
                                            progress=progress)
    except (ValueError, FileNotFoundError) as e:
        _fail(str(e))
    md, js = write_table(table, output, force=force)
    click.echo(table.to_markdown())
    click.echo(f"wrote {md} and {js}", err=True)


@main.command(epilog="""\b
Examples:
  lsgan bench                                   # paper-sized GANs and MLD denoiser, random weights, CPU (+GPU)
  lsgan bench --json bench.json --steps 50 --frames 196
  lsgan bench --gan runs/gan --diffusion runs/diffusion --vae runs/vae   # your checkpoints
""")
@click.option("--gan", "gans", multiple=True, type=In(exists=True), help="GAN checkpoint(s) instead of paper-sized ones.")
@click.option("--diffusion", type=In(exists=True), help="Diffusion checkpoint instead of a paper-sized denoiser.")
@click.option("--vae", type=In(exists=True), help="VAE checkpoint for decoding (default: paper-sized).")
@click.option("--steps", default=50, show_default=True, help="DDIM steps of the denoiser.")
@click.option("--guidance", default=7.5, show_default=True, help="Classifier-free guidance (2 passes per step).")
@click.option("--frames", default=120, show_default=True, help="Motion length decoded per sample (20 fps).")
@click.option("--repeats", default=3, show_default=True, help="Timed runs per figure (median).")
@click.option("--device", "devices", multiple=True, help="cpu, cuda (default: cpu, and cuda when present).")
@click.option("--json", "json_out", type=Out(), help="Write the rows as JSON.")
@click.option("--force", is_flag=True, help="Replace a --json file that lsgan wrote (never another file).")
def bench(gans, diffusion, vae, steps, guidance, frames, repeats, devices, json_out, force) -> None:
    """FLOPs per clip and per 2048 clips (generator or denoiser alone; end to end with the text encoder and VAE
    decoder) and measured time per motion (b1, b256), for each generator and the denoiser."""
    from lsgan.eval.bench import bench_samplers, format_table, rows_as_dicts, run_bench
    from lsgan.io import atomic_file
    from lsgan.models.text import TextEncoderUnavailable
    from lsgan.outputs import claim_file

    if json_out:
        claim_file(json_out, force=force)
    try:
        samplers, decoder = bench_samplers(gans=gans, diffusion=diffusion, vae=vae, steps=steps, guidance=guidance)
        rows = run_bench(samplers, vae=decoder, devices=list(devices) or None, frames=frames, repeats=repeats,
                         progress=lambda m: click.echo(m, err=True))
    except (ValueError, FileNotFoundError, TextEncoderUnavailable) as e:
        _fail(str(e))
    click.echo(format_table(rows))
    if json_out:
        with atomic_file(json_out, "w", encoding="utf-8") as fh:
            json.dump(rows_as_dicts(rows), fh, indent=1)


@main.command("plot-latents", epilog="""\b
Examples:
  lsgan plot-latents --cache bandai-cache.h5 --gan runs/bandai-gan -o figures/latents.png
  lsgan plot-latents --cache bandai-cache.h5 --gan runs/bandai-diffusion --per-class 100 -o diffusion.png
""")
@click.option("--cache", required=True, type=In(exists=True), help="Latent cache (encode-latents).")
@click.option("--gan", "model", required=True, type=In(exists=True), help="GAN or diffusion checkpoint.")
@click.option("--split", default="test", show_default=True)
@click.option("--per-class", default=50, show_default=True, help="Clips per action.")
@click.option("--steps", type=click.IntRange(1), help="Diffusion: DDIM steps.")
@click.option("--guidance", type=float, help="Diffusion: guidance scale.")
@click.option("--seed", default=0, show_default=True)
@click.option("--device", default="auto", show_default=True)
@click.option("-o", "--output", required=True, type=Out(), help="PNG file.")
@click.option("--force", is_flag=True, help="Replace an existing PNG that lsgan wrote (never another file).")
def plot_latents_cmd(cache, model, split, per_class, steps, guidance, seed, device, output, force) -> None:
    """t-SNE of real and generated latents coloured by action (the paper's Figure 4), as PNG."""
    from lsgan.eval.plot import plot_latents

    try:
        path = plot_latents(cache, model, output, split=split, per_class=per_class, seed=seed, device=device,
                            steps=steps, guidance=guidance, force=force)
    except ValueError as e:
        _fail(str(e))
    click.echo(f"wrote {path}", err=True)


@main.command(epilog="""\b
Examples:
  lsgan serve --gan runs/gan --vae runs/vae                 # http://127.0.0.1:8000/ : the page; the API at /v1
  lsgan serve --model gan-onnx                              # an `export-model --onnx` folder (onnxruntime)
  lsgan serve --model gan-onnx --int8 --port 8080
  LSGAN_API_KEY=secret lsgan serve --gan runs/gan --vae runs/vae --host 0.0.0.0   # reachable from other machines
  lsgan serve --gan runs/gan --vae runs/vae --api-key-file key.txt --allow-host motion.example.org
  lsgan serve --gan runs/gan --vae runs/vae --max-num 4 --max-in-flight 32 --timeout 5
  lsgan serve --gan runs/gan --vae runs/vae --workers 1     # one engine process (least memory)
  curl -s localhost:8000/v1/generate -H 'Content-Type: application/json' -d '{"text": "a person waves", "seed": 1}'
\b
The API (endpoints, limits, errors): docs/api.md, and /docs on the running server. SIGTERM finishes the requests
in flight and exits 0.
""")
@click.option("--gan", type=In(exists=True), help="GAN checkpoint (run or checkpoint folder); with --vae.")
@click.option("--vae", type=In(exists=True), help="The VAE whose latents the GAN learned.")
@click.option("--model", type=In(exists=True, file_okay=False),
              help="Instead of --gan/--vae: a folder `lsgan export-model --onnx` wrote (runs without torch's models).")
@click.option("--int8", is_flag=True, help="--model: the int8 decoder (an export made with --int8).")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on; anything but loopback makes the server reachable from other machines.")
@click.option("--port", default=8000, show_default=True, type=click.IntRange(0, 65535), help="TCP port (0: any free one).")
@click.option("--api-key", envvar="LSGAN_API_KEY", show_envvar=True,
              help="Require this key on /v1 (Authorization: Bearer KEY or X-API-Key); the page and /healthz stay open. "
                   "Visible ASCII only. On the command line it shows in the process list: prefer LSGAN_API_KEY or "
                   "--api-key-file.")
@click.option("--api-key-file", type=In(exists=True, dir_okay=False),
              help="Read the API key from this file's first line (instead of --api-key).")
@click.option("--allow-host", "allow_hosts", multiple=True, metavar="NAME",
              help="Also answer requests whose Host header names NAME (repeatable; '*': any). By default only the "
                   "bound address's names are served (127.0.0.1, localhost, [::1] on loopback), against DNS rebinding.")
@click.option("--device", default="auto", show_default=True, help="--gan/--vae: auto, cpu, cuda or cuda:N.")
@click.option("--text-encoder-path", type=In(exists=True), help="Local weights of the GAN's text encoder.")
@click.option("--text-cache", default=1024, show_default=True, type=click.IntRange(0),
              help="Prompt embeddings kept across requests (0: none).")
@click.option("--workers", type=click.IntRange(1),
              help="Engine processes, each with its own copy of the models, whose passes run side by side under "
                   "load (default: one per core, at most 4; one on a GPU).")
@click.option("--max-text-chars", default=500, show_default=True, type=click.IntRange(1), help="Longest prompt.")
@click.option("--min-frames", default=4, show_default=True, type=click.IntRange(1), help="Shortest motion.")
@click.option("--max-frames", type=click.IntRange(1),
              help="Longest motion (default: the model's maximum, at most 196; never more than the model's).")
@click.option("--default-frames", type=click.IntRange(1), help="Length when a request gives none (default 120).")
@click.option("--max-num", default=8, show_default=True, type=click.IntRange(1), help="Motions per request.")
@click.option("--max-body-bytes", default=16384, show_default=True, type=click.IntRange(64), help="Largest request body.")
@click.option("--max-in-flight", default=64, show_default=True, type=click.IntRange(1),
              help="Requests admitted at once; more get 503 with Retry-After.")
@click.option("--timeout", "timeout_s", default=10.0, show_default=True, type=click.FloatRange(min=0, min_open=True),
              help="Seconds a request may take; then 503.")
@click.option("--gather-ms", default=1.0, show_default=True, type=click.FloatRange(0, 1000),
              help="How long a pass waits for more requests to batch with the first.")
@click.option("--max-batch", default=8, show_default=True, type=click.IntRange(1),
              help="Motions in one engine pass (smaller passes let answers go out while the next pass runs).")
@click.option("--store-size", default=256, show_default=True, type=click.IntRange(1),
              help="Motions kept for download (least recently used dropped first).")
@click.option("--max-line-bytes", default=8192, show_default=True, type=click.IntRange(64),
              help="Longest request target (path and query); longer gets 414.")
@click.option("--max-header-bytes", default=65536, show_default=True, type=click.IntRange(1024),
              help="Largest request head (request line and headers); larger gets 431.")
@click.option("--max-headers", default=100, show_default=True, type=click.IntRange(8),
              help="Most header lines in a request; more gets 431.")
@click.option("--header-timeout", "header_timeout_s", default=10.0, show_default=True,
              type=click.FloatRange(min=0, min_open=True), help="Seconds for a request's head to arrive; then 408.")
@click.option("--body-timeout", "body_timeout_s", default=10.0, show_default=True,
              type=click.FloatRange(min=0, min_open=True), help="Seconds for a request's body to arrive; then 408.")
@click.option("--keep-alive", "keep_alive_s", default=5.0, show_default=True,
              type=click.FloatRange(min=0, min_open=True), help="Seconds an idle keep-alive connection stays open.")
@click.option("--max-connections", default=1024, show_default=True, type=click.IntRange(1),
              help="Open connections at once; past it the longest-idle one is closed (503 when none is idle).")
def serve(gan, vae, model, int8, host, port, api_key, api_key_file, allow_hosts, device, text_encoder_path,
          text_cache, workers, **limits) -> None:
    """Serve the model over HTTP: the API (/v1/generate, /v1/motions/ID.glb|.bvh|.npy, /v1/info), its OpenAPI
    docs (/docs) and a page at / to type a sentence, watch the motion and download it. Models load once;
    concurrent requests are batched into one generator and decoder pass."""
    from lsgan.models.text import TextEncoderUnavailable
    from lsgan.serve.limits import Limits
    from lsgan.serve.server import serve as run

    if model is not None and (gan is not None or vae is not None):
        raise click.UsageError("give --model (an exported folder) or --gan and --vae (checkpoints), not both")
    if model is None and (gan is None or vae is None):
        raise click.UsageError("give --gan RUN and --vae RUN, or --model EXPORT_DIR")
    if int8 and model is None:
        raise click.UsageError("--int8 goes with --model (an ONNX export made with --int8)")
    if model is not None and (text_encoder_path is not None or device not in ("auto", "cpu")):
        raise click.UsageError("--text-encoder-path and --device go with --gan/--vae (an export runs on the CPU)")
    if api_key_file is not None and api_key is not None:
        raise click.UsageError("give the key once: --api-key (or LSGAN_API_KEY) or --api-key-file")
    if api_key is None and os.environ.get("LSGAN_API_KEY") == "":
        _fail("LSGAN_API_KEY is set but empty: give the key, or unset it to serve without one")
    try:
        from lsgan.serve.server import read_key_file

        key = read_key_file(api_key_file) if api_key_file is not None else api_key
        run(gan=gan, vae=vae, model=model, int8=int8, host=host, port=port, api_key=key, limits=Limits(**limits),
            device=device, text_encoder_path=text_encoder_path, text_cache=text_cache, workers=workers,
            allow_hosts=tuple(allow_hosts))
    except (ValueError, OSError, RuntimeError, TextEncoderUnavailable) as e:
        _fail(describe(e))


if __name__ == "__main__":
    main()
