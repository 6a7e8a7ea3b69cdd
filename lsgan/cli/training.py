"""Commands that train: ``train-vae``, ``encode-latents``, ``train-gan``, ``train-diffusion``,
``train-evaluator``, and ``demo`` (the whole pipeline on built-in data)."""
from __future__ import annotations

import json
import os
import sys

import click

from lsgan.cli.group import main
from lsgan.cli.options import In, MaybeIn, Out, fail, load_recipe_or_fail, plainly, setting, say_interrupted, stopped_keeping


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
        sys.exit(say_interrupted(f"during [{e.index}/8] {e.stage}: finished stages (and the last checkpoint of a "
                                 f"training) are kept in {output}; run `lsgan demo -o {output}` again to continue."))
    except KeyboardInterrupt:
        sys.exit(say_interrupted(f"run `lsgan demo -o {output}` again to continue."))
    except (ValueError, FileNotFoundError, TrainingDiverged) as e:
        fail(str(e))
    click.echo(result.report())


def cache_training_options(command):
    """The options of the commands that train on a latent cache (train-gan, train-diffusion)."""
    options = [
        click.option("--cache", required=True, type=In(exists=True, dir_okay=False),
                     help="Latent cache from encode-latents."),
        click.option("--recipe", type=MaybeIn(), help="Recipe YAML (or a name in recipes/); its gan: or diffusion: section sets "
                                      "every hyperparameter."),
        click.option("--cond", type=click.Choice(["text", "action"]),
                     help="Condition on caption embeddings or action labels."),
        click.option("--out", required=True, type=Out(), help="Run folder (checkpoints last/ best/, log.csv)."),
        click.option("--max-steps", type=setting("max_steps"), help="Override the recipe's number of training steps (a GAN's: generator "
                                                        "steps)."),
        click.option("--seed", type=setting("seed")),
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


def train_on_cache(kind: str, model_config, train_config, model_options: dict, train_options: dict, cache, recipe,
                    out, vae, allow_stale, run) -> None:
    """The recipe's ``kind`` section with the command's overrides, the cache checked against its VAE, then
    ``run(model config, train config, expected VAE hash)``; its summary on stderr, failures as one line."""
    from lsgan.models.cache import check_cache_vae
    from lsgan.recipes import configs
    from lsgan.train.common import TrainingDiverged

    full = load_recipe_or_fail(recipe)
    try:
        expect = check_cache_vae(cache, vae=vae, allow_stale=allow_stale)
        model, train = configs(full, kind, model_config, train_config, model_options, train_options)
        result = run(model, train, expect)
    except KeyboardInterrupt:
        stopped_keeping(os.path.join(out, "last"), "checkpoints")
    except (TrainingDiverged, ValueError, FileExistsError, FileNotFoundError) as e:
        fail(str(e))
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
@click.option("--max-steps", type=setting("max_steps"), help="Override the recipe's step budget.")
@click.option("--batch-size", type=setting("batch_size"), help="Override the recipe's batch size.")
@click.option("--seed", type=setting("seed"), help="Override the recipe's seed.")
@click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N.")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last checkpoint.")
@click.option("--force", is_flag=True, help="Start over in --out, removing the earlier run's own files (never others).")
def train_vae_cmd(data, recipe, out, max_steps, batch_size, seed, device, resume, force) -> None:
    """Train the motion VAE (MLD's skip-transformer VAE) on the train split of one or more shards."""
    from lsgan.models.vae import VAEConfig
    from lsgan.recipes import configs
    from lsgan.train.common import TrainingDiverged
    from lsgan.train.vae import VAETrainConfig, train_vae

    full = load_recipe_or_fail(recipe)
    try:
        model, train = configs(full, "vae", VAEConfig, VAETrainConfig,
                               train_overrides={"max_steps": max_steps, "batch_size": batch_size, "seed": seed})
        result = train_vae(list(data), out, model=model, train=train, device=device, resume=resume, force=force)
    except KeyboardInterrupt:
        stopped_keeping(os.path.join(out, "last"), "checkpoints")
    except (TrainingDiverged, ValueError, FileExistsError, FileNotFoundError) as e:
        fail(str(e))
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
@click.option("--min-frames", default=None, type=click.IntRange(min=1),
              help="Shortest window (default: the VAE's training setting).")
@click.option("--max-frames", default=None, type=click.IntRange(min=1),
              help="Longest window (default: the VAE's training setting).")
@click.option("--batch-size", default=64, show_default=True, type=click.IntRange(min=1))
@click.option("--device", default="auto", show_default=True)
@click.option("--force", is_flag=True, help="Replace an existing OUTPUT that lsgan wrote (never another file).")
def encode_latents_cmd(data, vae, output, text_encoder, recipe, text_encoder_path, min_frames, max_frames, batch_size,
                       device, force) -> None:
    """Cache the VAE latent (mean, log-variance) of every window and the embedding of every caption."""
    from lsgan.models.cache import encode_latents
    from lsgan.models.checkpoint import read_meta

    text_encoder = text_encoder or load_recipe_or_fail(recipe).get("text_encoder") or "minilm"
    try:
        train_cfg = read_meta(vae)["config"].get("train", {})
        path = encode_latents(
            list(data), vae, output, text_encoder=None if text_encoder == "none" else text_encoder,
            text_encoder_path=text_encoder_path, min_frames=min_frames or train_cfg.get("min_frames", 40),
            max_frames=max_frames or train_cfg.get("max_frames", 196), batch_size=batch_size, device=device,
            force=force,
        )
    except Exception as e:  # noqa: BLE001 - every failure here is the user's input: report it plainly
        fail(plainly(e))
    click.echo(f"wrote {path}", err=True)


@main.command("train-gan", epilog="""\b
Examples:
  lsgan train-gan --cache cache.h5 --recipe demo --out runs/gan
  lsgan train-gan --cache cache.h5 --arch vanilla-wgan-gp --cond text --max-steps 20000 --out runs/vwgan
  lsgan train-gan --cache act12_cache.h5 --recipe humanact12 --cond action --out runs/act-gan
""")
@cache_training_options
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

    train_on_cache("gan", GANConfig, GANTrainConfig, dict(arch=arch, cond=cond),
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
@click.option("--max-steps", type=setting("max_steps"), help="Override the recipe's number of training steps.")
@click.option("--batch-size", type=setting("batch_size"), help="Override the recipe's batch size.")
@click.option("--seed", type=setting("seed"), help="Override the recipe's seed.")
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
    from lsgan.train.common import TrainingDiverged
    from lsgan.train.evaluator import describe_heldout, train_from_recipe

    full = load_recipe_or_fail(recipe)
    try:
        result = train_from_recipe(data, out, full, kind=kind, text_encoder=text_encoder,
                                   overrides={"max_steps": max_steps, "batch_size": batch_size, "seed": seed},
                                   device=device, resume=resume, force=force, text_encoder_path=text_encoder_path)
    except KeyboardInterrupt:
        stopped_keeping(os.path.join(out, "last"), "checkpoints")
    except (TrainingDiverged, ValueError, FileExistsError, FileNotFoundError) as e:
        fail(str(e))
    except Exception as e:  # noqa: BLE001 - e.g. a text encoder whose weights are absent: say so plainly
        fail(plainly(e))
    click.echo(json.dumps(result, default=str), err=True)
    click.echo(describe_heldout(result["heldout"]))


@main.command("train-diffusion", epilog="""\b
Examples:
  lsgan train-diffusion --cache cache.h5 --recipe demo --out runs/diffusion
  lsgan train-diffusion --cache bandai-cache.h5 --recipe bandai --out runs/bandai-diffusion --device cuda
  lsgan train-diffusion --cache act12-cache.h5 --recipe humanact12 --out runs/act-diffusion --resume
  lsgan generate --gan runs/diffusion --vae runs/vae --text "a person walks forward" --steps 50 --guidance 7.5 -o out/
""")
@cache_training_options
def train_diffusion_cmd(cache, recipe, cond, out, max_steps, seed, cuda_graph, vae, allow_stale, device, resume,
                        force) -> None:
    """Train the latent-diffusion baseline (MLD's denoiser, DDIM, classifier-free guidance) on the same cache.

    Like train-gan it reads the cache alone and refuses one whose VAE has changed since it was encoded;
    `lsgan generate --gan RUN` and `lsgan evaluate` take the result wherever they take a GAN.
    """
    from lsgan.models.diffusion import DiffusionConfig
    from lsgan.train.diffusion import DiffusionTrainConfig, train_diffusion

    train_on_cache("diffusion", DiffusionConfig, DiffusionTrainConfig, dict(cond=cond),
                    dict(max_steps=max_steps, seed=seed, cuda_graph=cuda_graph), cache, recipe, out,
                    vae, allow_stale, lambda model, train, expect: train_diffusion(
                        cache, out, diffusion=model, train=train, device=device, resume=resume, force=force,
                        expect_vae_hash=expect))
