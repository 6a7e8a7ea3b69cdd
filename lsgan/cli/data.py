"""Commands for data: ``preprocess`` (any source to a shard of HumanML3D features) and ``inspect``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from lsgan.cli.group import main
from lsgan.cli.options import In, Out, fail, setting, stopped_keeping


SOURCES = ("synthetic", "bvh", "humanml3d", "joints", "amass", "humanact12")


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
@click.option("--seed", default=0, show_default=True, type=setting("seed"), help="synthetic: random seed.")
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
        stopped_keeping(f"{output}.parts", "finished chunks")
    except (PreprocessError, ClipError, ValueError) as e:
        bar.close()
        fail(str(e))
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
        fail(str(e))
    click.echo(json.dumps(info, indent=1) if as_json else format_summary(info))
