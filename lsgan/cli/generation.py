"""Commands that make motion and files: ``generate``, ``export`` (GLB, BVH, previews) and ``export-model`` (ONNX)."""
from __future__ import annotations

import click

from lsgan.cli.group import main
from lsgan.cli.options import Finite, In, MaybeIn, Out, fail, setting
from lsgan.errors import describe


@main.command(epilog="""\b
Examples:
  lsgan generate --gan runs/gan --vae runs/vae --text "a person walks forward" -o out/
  lsgan generate --gan runs/gan --vae runs/vae --text "someone jumps twice" --seconds 4 --num 4 --seed 1 -o out/
  lsgan generate --gan runs/gan --vae runs/vae --prompts prompts.txt -o out/     # lines: 'prompt' or 'prompt#frames'
  lsgan generate --gan runs/act-gan --vae runs/vae --action jump --num 8 -o out/
  lsgan generate --gan runs/gan --vae runs/vae --timeline "walk forward#80; turn around#60; wave#60" -o out/
  lsgan generate --gan runs/gan --vae runs/vae --timeline take.txt --overlap 16 -o out/   # lines: 'prompt#frames'
  lsgan generate --gan runs/gan --vae runs/vae --timeline "walk#80; sit down#60" --join continue -o out/
  lsgan generate --gan runs/diffusion --vae runs/vae --text "a person waves" --steps 50 --guidance 7.5 -o out/
  lsgan generate --runtime onnx --gan gan-onnx --text "a person walks forward" -o out/   # export-model's folder
  lsgan generate --gan runs/gan --vae runs/vae --text "a person walks" --path path.csv -o out/  # rows: t,x,z or x,z
  lsgan generate --gan runs/gan --vae runs/vae --text "a person waves" --keyframe 60:pose.npy -o out/
  lsgan generate --gan runs/gan --vae runs/vae --text "then sits down" --continue out/000_a-person-walks_joints.npy -o next/
  lsgan generate --gan runs/gan --vae runs/vae --text "a person turns" --inbetween a.npy b.npy --frames 80 -o mid/
  lsgan generate --runtime onnx --gan gan-onnx --text "a person walks" --path path.csv -o out/  # met, not steered
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
@click.option("--join", type=click.Choice(["crossfade", "continue"]), help="--timeline: how segments meet "
              "(default crossfade: blended over --overlap frames; continue: each segment optimised to start with the "
              "last 5 frames of the motion so far, torch runtime).")
@click.option("--frames", type=click.IntRange(4, 100_000), help="Length in frames at 20 fps (default 120).")
@click.option("--seconds", type=Finite(0.2, 5_000), help="Length in seconds (instead of --frames).")
@click.option("--num", default=1, show_default=True, type=click.IntRange(1, 100_000), help="Motions per prompt or action.")
@click.option("--seed", default=0, show_default=True, type=setting("seed"),
              help="Random seed: the same seed gives the same motions.")
@click.option("--text-encoder-path", type=In(exists=True), help="Local weights of the GAN's text encoder (CLIP).")
@click.option("--batch-size", default=256, show_default=True, type=click.IntRange(1, 1_000_000))
@click.option("--device", default="auto", show_default=True)
@click.option("--steps", type=click.IntRange(1), help="Diffusion: DDIM steps (default: the checkpoint's, 50 in MLD).")
@click.option("--guidance", type=float, help="Diffusion: classifier-free guidance scale (default: the checkpoint's).")
@click.option("-o", "--output", required=True, type=Out(), help="Output folder: *_features.npy, *_joints.npy, manifest.json.")
@click.option("--raw-joints", is_flag=True, help="Also write *_joints_raw.npy: the joints as decoded (recovered from "
              "*_features.npy), before they were made rigid; *_joints.npy, the previews and exports are the rigid ones.")
@click.option("--fix-feet/--no-fix-feet", default=False, show_default=True, help="Hold each foot still while "
              "the features' contact channels say it touches the ground (IK on the leg only), once, on the motion "
              "that every output then shows (*_joints.npy, previews, exports; the server serves motions without).")
@click.option("--path", "path_file", type=In(exists=True, dir_okay=False), help="A root path on the ground for every "
              "motion: CSV or JSON rows of 'time_s,x,z' waypoints (linear between them) or 'x,z' per frame, in metres, "
              "shifted to start where the motion starts (the origin, facing +z). The root passes through it exactly; "
              "manifest.json says how far every constraint was missed (docs/control.md).")
@click.option("--facing", is_flag=True, help="--path: the root also faces along the path wherever it moves (faster "
              "than 0.2 m/s); keyframe poses still set their own facing.")
@click.option("--keyframe", "keyframes", multiple=True, metavar="FRAME:FILE", help="Joints to hit at FRAME: a .npy of "
              "the 22 joints (22, 3) or a .json of {joint name: [x, y, z]} for some (null: a free coordinate), in the "
              "motion's frame; or a BVH file's frame, FILE.bvh@K, a pose taken wherever the motion is (repeatable).")
@click.option("--keyframe-map", metavar="PRESET|FILE.json", help="The joint map of --keyframe BVH files: a preset "
              "(bandai, cmu, mixamo) or a JSON map (default: the first preset that finds every joint).")
@click.option("--continue", "continue_from", type=In(exists=True, dir_okay=False), help="A motion to continue "
              "(joints (T, 22, 3) or features (T, 263) .npy, e.g. an earlier *_joints.npy): each new motion starts with "
              "its last 5 frames (position, heading, pose, velocity) and is placed where it is.")
@click.option("--inbetween", nargs=2, type=In(exists=True, dir_okay=False), metavar="A.npy B.npy", help="Two motions "
              "in one frame: each new motion starts with A's last 5 frames and ends with B's first 5, placed there.")
@click.option("--force", is_flag=True, help="Write into an existing OUTPUT, first removing the files an earlier lsgan run "
              "wrote there (never other files).")
def generate(gan, vae, runtime, int8, texts, prompts, actions, timeline, overlap, join, frames, seconds, num, seed,
             text_encoder_path, batch_size, device, steps, guidance, output, raw_joints, fix_feet, path_file,
             facing, keyframes, keyframe_map, continue_from, inbetween, force) -> None:
    """Generate motions from sentences or action labels: latents from the generator (a GAN pass, or DDIM steps
    of a diffusion denoiser), then one VAE decoder pass."""
    from lsgan.data.clip import ClipError
    from lsgan.generation import (Request, claim_generation, generation_files, motion_stems, read_prompts,
                                  write_generation)

    if frames is not None and seconds is not None:
        raise click.UsageError("give --frames or --seconds, not both")
    n_frames = frames if frames is not None else (round(seconds * 20) if seconds is not None else 120)
    if n_frames < 4:
        raise click.UsageError("a motion needs at least 4 frames")
    _check_runtime_options(runtime, vae=vae, int8=int8, text_encoder_path=text_encoder_path, device=device,
                           steps=steps, guidance=guidance)
    bridged = continue_from is not None or bool(inbetween)
    controlled = path_file is not None or bool(keyframes) or bridged
    if controlled and timeline is not None:
        raise click.UsageError("--path, --keyframe, --continue and --inbetween make one motion: not with --timeline "
                               "(its --join continue chains segments)")
    if facing and path_file is None:
        raise click.UsageError("--facing turns the root along --path: give a path")
    if keyframe_map and not any(".bvh" in k.lower() for k in keyframes):
        raise click.UsageError("--keyframe-map reads --keyframe BVH files (FRAME:FILE.bvh@K): give one")
    if bridged and fix_feet:
        raise click.UsageError("--fix-feet would move the feet of the frames --continue and --inbetween share with "
                               "the motions they join: give one or the other")
    if bridged and (continue_from is not None) + bool(inbetween) + (path_file is not None) + bool(keyframes) > 1:
        raise click.UsageError("--continue and --inbetween set every constraint themselves: give one of them, "
                               "without --path or --keyframe")
    if timeline is not None or overlap is not None or join is not None:
        _check_timeline_options(timeline, texts=texts, prompts=prompts, actions=actions, frames=frames,
                                seconds=seconds, num=num)
        if join == "continue" and (overlap is not None or runtime == "onnx"):
            raise click.UsageError("--join continue shares 5 frames between segments and optimises through the "
                                   "models: not with --overlap or --runtime onnx")
        return _generate_timeline(timeline, overlap, join=join or "crossfade", gan=gan, vae=vae, runtime=runtime, int8=int8, seed=seed,
                                  device=device, text_encoder_path=text_encoder_path, batch_size=batch_size,
                                  steps=steps, guidance=guidance, output=output, raw_joints=raw_joints, force=force,
                                  fix_feet=fix_feet)
    requests = [Request(text=t, frames=n_frames) for t in texts] + [Request(action=a, frames=n_frames) for a in actions]
    if prompts:
        requests += read_prompts(prompts, n_frames)
    if not requests:
        raise click.UsageError("give --text, --prompts or --action")
    try:
        constraints, placement = _constraints((path_file, facing), (keyframes, keyframe_map), continue_from, inbetween,
                                              requests, _reach_of(runtime, gan, vae, int8)) if controlled else (None, None)
        inputs = [p for p in (vae, prompts, path_file, continue_from, *(inbetween or ())) if p] + [
            _keyframe_file(k) for k in keyframes] + [m for m in (keyframe_map,) if m and m.lower().endswith(".json")]
        stems = motion_stems([r for r in requests for _ in range(num)])
        claim_generation(output, gan, *inputs, force=force, files=generation_files(stems, raw_joints))
        if runtime == "onnx":
            from lsgan.deploy.runtime import generate_onnx

            result = generate_onnx(gan, requests, num=num, seed=seed, variant="int8" if int8 else "fp32",
                                   batch_size=batch_size, fix_feet=fix_feet, constraints=constraints,
                                   placement=placement)
        else:
            from lsgan.generate import generate as run

            result = run(gan, vae, requests, num=num, seed=seed, device=device, text_encoder_path=text_encoder_path,
                         batch_size=batch_size, steps=steps, guidance=guidance, fix_feet=fix_feet,
                         constraints=constraints, placement=placement)
        if result.kind == "gan" and (steps is not None or guidance is not None):
            click.echo(f"note: --steps/--guidance ignored: {gan} is a GAN (they set a diffusion model's sampling)",
                       err=True)
        manifest = write_generation(result, output, force=force, raw_joints=raw_joints)
    except (ValueError, FileNotFoundError, ClipError) as e:
        fail(str(e))
    _report_control(result)
    t = result.timings_s
    click.echo(f"{len(result.motions)} motions in {output} ({manifest.name}); {result.ms_per_motion:.2f} ms per motion "
               f"(text {t['text_encoding'] * 1e3:.1f} ms, generator {t['generator'] * 1e3:.1f} ms, "
               f"VAE decoder {t['vae_decoding'] * 1e3:.1f} ms in all)", err=True)


def _report_control(result) -> None:
    """One line per kind of constraint: how closely the motions met it (manifest.json has each motion's)."""
    import numpy as np

    misses = [m.control for m in result.motions if m.control is not None]
    for kind, what, unit, scale in (("path_m", "root path: missed by", "cm", 100), ("keyframes_m", "keyframe joints: "
                                    "missed by", "cm", 100), ("poses_m", "poses (wherever the motion is): missed by",
                                    "cm", 100), ("facing_deg", "facing along the path: missed by",
                                    "degrees", 1), ("seam_velocity_m_s", "velocity where the shared "
                                    "frames end: changed by", "m/s", 1)):
        got = [c[kind] for c in misses if kind in c]
        if got:
            click.echo(f"{what} {np.mean([g['mean'] for g in got]) * scale:.2f} {unit} on average, "
                       f"{max(g['max'] for g in got) * scale:.2f} {unit} at most ({len(got)} motions)", err=True)


def _reach_of(runtime, gan, vae, int8):
    """What the model holds constraints to (:func:`lsgan.constraints.model_reach`): its VAE's feature statistics, or
    the ONNX export's."""
    from lsgan.constraints import model_reach

    if runtime == "onnx":
        from lsgan.deploy.runtime import load

        return load(gan, variant="int8" if int8 else "fp32").reach()
    from lsgan.models.vae import load_vae

    meta = load_vae(vae)[1]
    return model_reach(meta["mean"], meta["std"])


def _constraints(path, keyframes, continue_from, inbetween, requests, reach):
    """(constraints, placement) of --path (``path``: the file and --facing) and --keyframe (``keyframes``: the specs
    and --keyframe-map), or of --continue / --inbetween, for motions of one length (every request's), checked against
    the model's ``reach`` before anything is written."""
    import numpy as np

    lengths = {r.frames for r in requests}
    if len(lengths) > 1:
        raise ValueError(f"constraints need motions of one length; the prompts ask for {sorted(lengths)}")
    with np.errstate(all="ignore"):  # a huge or broken number is refused by its check, not warned about by numpy
        return _read_constraints(path, keyframes, continue_from, inbetween, reach, lengths.pop())


def _keyframe_file(spec: str) -> str:
    """The file a --keyframe names (without a BVH frame's @K)."""
    from lsgan.constraints import BVH_FRAME

    file = spec.partition(":")[2].strip()
    m = BVH_FRAME.fullmatch(file)
    return m["file"] if m else file


def _read_constraints(path_and_facing, keyframes_and_map, continue_from, inbetween, reach, frames):
    """:func:`_constraints` once the length is known."""
    from lsgan.constraints import (Constraints, check_reach, continuing, inbetween as bridge, is_bvh_keyframe,
                                   read_bvh_pose, read_keyframe, read_path)
    from lsgan.export.bvh import load_motion_joints

    placement = None
    if continue_from is not None:
        constraints, placement = continuing(load_motion_joints(continue_from)[0][1], frames, source=continue_from)
    elif inbetween:
        a, b = (load_motion_joints(f)[0][1] for f in inbetween)
        constraints, placement = bridge(a, b, frames, source=f"{inbetween[0]} to {inbetween[1]}")
    else:
        path_file, facing = path_and_facing
        keyframes, keyframe_map = keyframes_and_map
        path = read_path(path_file, frames) if path_file else None
        read = [(k, (read_bvh_pose(k, frames, keyframe_map), True) if is_bvh_keyframe(k) else
                 (read_keyframe(k, frames), False)) for k in keyframes]
        named = [f for _, ((f, _), _) in read]
        twice = next((f for f in named if named.count(f) > 1), None)
        if twice is not None:
            raise ValueError(f"two --keyframe options name frame {twice}: "
                             f"{', '.join(k for k, ((f, _), _) in read if f == twice)}")
        points = {f: p for _, ((f, p), bvh) in read if not bvh}
        poses = {f: p for _, ((f, p), bvh) in read if bvh}
        origin = ", ".join([path_file] * bool(path_file) + list(keyframes))
        constraints = Constraints(frames, path=path, keyframes=points, poses=poses, facing=facing, origin=origin)
    check_reach(constraints, *reach)
    return constraints, placement


def _check_timeline_options(timeline, *, texts, prompts, actions, frames, seconds, num) -> None:
    """--timeline sets the prompts and lengths itself; --overlap belongs to it."""
    if timeline is None:
        raise click.UsageError("--overlap and --join go with --timeline")
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
        fail(str(e))
    try:
        claim_generation(output, gan, *([vae] if vae else []), *([source] if source else []), force=force)
        overlap = DEFAULT_OVERLAP if overlap is None else overlap
        if options.pop("runtime") == "onnx":
            from lsgan.deploy.runtime import generate_timeline_onnx

            options.pop("join")
            result = generate_timeline_onnx(gan, segments, overlap=overlap, source=source, **{
                k: options[k] for k in ("int8", "seed", "batch_size", "fix_feet")})
        else:
            options.pop("int8")
            result = generate_timeline(gan, vae, segments, overlap=overlap, source=source, **options)
        manifest = write_generation(result, output, force=force, raw_joints=raw_joints)
    except (ValueError, FileNotFoundError) as e:
        fail(str(e))
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
        fail(str(e))
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
  lsgan export --bvh out/ -o bvh/                 # the motions of record, as generate wrote them
  lsgan export --bvh motion_features.npy --fps 30 -o motion.bvh
  lsgan export --gif out/ -o previews/             # stick-figure previews, captions as titles
  lsgan export --mp4 out/ -o videos/               # the same as H.264 videos (ffmpeg comes with the package)
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
        fail(describe(e))
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
