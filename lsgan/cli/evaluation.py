"""Commands that measure: ``evaluate`` (the T2M table), ``bench`` (cost) and ``plot-latents``."""
from __future__ import annotations

import json
from pathlib import Path

import click

from lsgan.cli.group import main
from lsgan.cli.options import In, NamedIn, Out, fail, setting


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
@click.option("--seed", default=0, show_default=True, type=setting("seed"))
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
        fail(str(e))
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
        fail(str(e))
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
@click.option("--seed", default=0, show_default=True, type=setting("seed"))
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
        fail(str(e))
    click.echo(f"wrote {path}", err=True)
