"""Bad input and faults through the real command line, one table row each.

Every row builds its inputs in a fresh folder (real files: BVH, .npy, HDF5, checkpoints of a tiny real
pipeline), runs ``lsgan`` as a user would, and checks: the exit code; one ``error:`` line on stderr that
holds the expected phrase; no traceback; and that no file that existed before the command was changed
or removed (in the row's folder and in the shared tiny pipeline).
"""
from __future__ import annotations

import contextlib
import gzip
import io
import json
import os
import pickle
import resource
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from cli_runs import forked_lsgan, linked_pipeline, lsgan, snapshot

from lsgan.data.skeleton import JOINT_NAMES
from lsgan.data.synthetic import generate as synthetic_clips
from lsgan.export.bvh import write_bvh

pytestmark = pytest.mark.slow

@pytest.fixture(scope="module")
def pipe(serve_models: Path, tmp_path_factory) -> Path:
    """A tiny real pipeline: shard, VAE, latent cache, GAN and one generate folder (read-only for the rows)."""
    return linked_pipeline(serve_models, tmp_path_factory.mktemp("pipe"),
                           ("generate", "--gan", "gan", "--vae", "vae", "--text", "a person walks", "--frames", 40,
                            "-o", "gen"))


# ---- inputs -------------------------------------------------------------------------------------------------

IDENTITY_MAP = {"joints": {n: n for n in JOINT_NAMES}, "scale": 0.01, "up": "y"}


def good_joints(n: int = 1, seed: int = 0) -> list[np.ndarray]:
    return [c.joints for c in synthetic_clips(n, seed=seed)]


def bvh_folder(w: Path, n: int = 3) -> Path:
    """Real BVH files (our exporter's 22-joint skeleton) and a joint map naming its joints."""
    d = w / "bvh"
    d.mkdir()
    for i, j in enumerate(good_joints(n)):
        write_bvh(d / f"clip{i}.bvh", j)
    (w / "map.json").write_text(json.dumps(IDENTITY_MAP))
    return d


def truncated_bvh(w: Path) -> list:
    d = bvh_folder(w)
    for p in d.glob("*.bvh"):
        text = p.read_text()
        p.write_text(text[: text.index("MOTION") + len("MOTION\nFrames: 120\nFrame Time: 0.05\n") + 40])
    return ["preprocess", "--source", "bvh", "--joint-map", w / "map.json", d, "-o", w / "out.h5"]


def nan_bvh(w: Path) -> list:
    d = bvh_folder(w)
    for p in d.glob("*.bvh"):
        head, motion = p.read_text().split("MOTION", 1)
        lines = motion.splitlines()
        lines[3] = " ".join(["nan"] * len(lines[3].split()))
        p.write_text(head + "MOTION" + "\n".join(lines) + "\n")
    return ["preprocess", "--source", "bvh", "--joint-map", w / "map.json", d, "-o", w / "out.h5"]


def malformed_map(w: Path) -> list:
    d = bvh_folder(w)
    (w / "map.json").write_text('{"joints": {"pelvis": "pelvis",')
    return ["preprocess", "--source", "bvh", "--joint-map", w / "map.json", d, "-o", w / "out.h5"]


def map_missing_joint(w: Path) -> list:
    d = bvh_folder(w)
    m = json.loads(json.dumps(IDENTITY_MAP))
    del m["joints"]["left_wrist"]
    (w / "map.json").write_text(json.dumps(m))
    return ["preprocess", "--source", "bvh", "--joint-map", w / "map.json", d, "-o", w / "out.h5"]


def gz_not_gzip(w: Path) -> list:
    d = bvh_folder(w, 1)
    (d / "clip0.bvh.gz").write_bytes(b"not gzip at all")
    (d / "clip0.bvh").unlink()
    return ["preprocess", "--source", "bvh", "--joint-map", w / "map.json", d, "-o", w / "out.h5"]


def joints_dir(w: Path, files: dict[str, bytes | np.ndarray]) -> Path:
    d = w / "joints"
    d.mkdir()
    for name, content in files.items():
        if isinstance(content, np.ndarray):
            np.save(d / name, content)
        else:
            (d / name).write_bytes(content)
    return d


def zero_byte_npy(w: Path) -> list:
    d = joints_dir(w, {"a.npy": b"", "b.npy": b""})
    return ["preprocess", "--source", "joints", d, "-o", w / "out.h5"]


def pickled_npy(w: Path) -> list:
    d = w / "joints"
    d.mkdir()
    np.save(d / "obj.npy", np.array([{"x": 1}], dtype=object), allow_pickle=True)
    return ["preprocess", "--source", "joints", d, "-o", w / "out.h5"]


def strict_one_bad(w: Path) -> list:
    d = joints_dir(w, {"good.npy": good_joints()[0], "short.npy": good_joints()[0][:3]})
    return ["preprocess", "--source", "joints", d, "-o", w / "out.h5", "--strict"]


def output_holds_inputs(w: Path) -> list:
    """The reported case: -o DIR where DIR holds the input joints/ and the user's texts/."""
    joints_dir(w, {"a.npy": good_joints()[0]})
    (w / "texts").mkdir()
    (w / "texts" / "a.txt").write_text("a person walks#a/DET person/NOUN walk/VERB#0.0#0.0\n")
    (w / "notes.md").write_text("my notes")
    return ["preprocess", "--source", "joints", w / "joints", "-o", w, "--format", "humanml3d", "--force"]


def output_inside_input(w: Path) -> list:
    d = joints_dir(w, {"a.npy": good_joints()[0]})
    return ["preprocess", "--source", "joints", d, "-o", d / "hml", "--format", "humanml3d"]


def output_is_user_file(w: Path, force: bool = False) -> list:
    d = joints_dir(w, {"a.npy": good_joints()[0]})
    (w / "out.h5").write_bytes(b"the user's own file")
    return ["preprocess", "--source", "joints", d, "-o", w / "out.h5", *(["--force"] if force else [])]


def output_is_folder(w: Path) -> list:
    d = joints_dir(w, {"a.npy": good_joints()[0]})
    (w / "out.h5").mkdir()
    (w / "out.h5" / "keep.txt").write_text("keep")
    return ["preprocess", "--source", "joints", d, "-o", w / "out.h5"]


def output_under_a_file(w: Path) -> list:
    d = joints_dir(w, {"a.npy": good_joints()[0]})
    (w / "afile").write_text("x")
    return ["preprocess", "--source", "joints", d, "-o", w / "afile" / "out.h5"]


def report_is_user_file(w: Path) -> list:
    d = joints_dir(w, {"a.npy": good_joints()[0]})
    (w / "r.json").write_text("{}")
    return ["preprocess", "--source", "joints", d, "-o", w / "out.h5", "--report", w / "r.json"]


def staging_is_user_folder(w: Path) -> list:
    d = joints_dir(w, {"a.npy": good_joints()[0]})
    (w / "out.h5.parts").mkdir()
    (w / "out.h5.parts" / "mine.txt").write_text("mine")
    return ["preprocess", "--source", "joints", d, "-o", w / "out.h5", "--resume"]


def not_a_humanml3d_folder(w: Path) -> list:
    (w / "hml").mkdir()
    return ["preprocess", "--source", "humanml3d", w / "hml", "-o", w / "out.h5"]


def existing_lsgan_shard(w: Path, pipe: Path) -> list:
    return ["preprocess", "--source", "synthetic", "--num-clips", 40, "-o", pipe / "synth.h5"]


def rig_export(w: Path, p: Path, *extra, drop: str | None = None) -> list:
    """``export --bvh --rig``: a rig BVH (our 22-joint skeleton) and its map (without ``drop``) in ``w``."""
    write_bvh(w / "rig.bvh", good_joints()[0][:5])
    m = json.loads(json.dumps(IDENTITY_MAP))
    m["joints"].pop(drop, None)
    (w / "map.json").write_text(json.dumps(m))
    return ["export", "--bvh", next((p / "gen").glob("*_joints.npy")), "--rig", w / "rig.bvh", *extra,
            "-o", w / "out.bvh"]


def text_file(w: Path, name: str = "notes.txt") -> Path:
    (w / name).write_text("not what lsgan expects")
    return w / name


def user_folder(w: Path, name: str = "notes.txt") -> Path:
    """A folder of the user's, holding one file of theirs."""
    (w / "mine").mkdir()
    (w / "mine" / name).write_text("the user's own file")
    return w / "mine"


def hdf5_not_shard(w: Path) -> Path:
    with h5py.File(w / "other.h5", "w") as f:
        f["x"] = np.arange(3)
    return w / "other.h5"


def run_with_user_files(w: Path, pipe: Path) -> list:
    (w / "run").mkdir()
    (w / "run" / "thesis.tex").write_text("mine")
    return ["train-vae", "--data", pipe / "synth.h5", "--recipe", pipe / "tiny.yaml", "--out", w / "run"]


def generate_args(pipe: Path, out: Path, *extra) -> list:
    return ["generate", "--gan", pipe / "gan", "--vae", pipe / "vae", "--text", "a person walks", "--frames", 40,
            "-o", out, *extra]


def path_args(w: Path, pipe: Path, content: str | bytes, name: str = "path.csv", *extra) -> list:
    """generate --path from a file ``name`` holding ``content``."""
    return generate_args(pipe, w / "out", "--path", written(w / name, content if isinstance(content, bytes)
                                                             else content.encode()), *extra)


def keyframe_args(w: Path, pipe: Path, frame: int, pose, name: str = "pose.npy") -> list:
    """generate --keyframe FRAME:FILE with ``pose`` saved as .npy (an array) or .json (text)."""
    f = w / name
    if isinstance(pose, str):
        f.write_text(pose)
    else:
        np.save(f, pose)
    return generate_args(pipe, w / "out", "--keyframe", f"{frame}:{f}")


PELVIS_FAR = b'{"pelvis": [50, 0.9, 0]}'


def stretched_pose() -> np.ndarray:
    """A standing pose whose left forearm is three times its length (all bones together within 1.5x)."""
    j = standing_pose()
    j[20] = j[18] + 3 * (j[20] - j[18])
    return j


def earlier_run(w: Path, pipe: Path) -> list:
    """A folder ``out`` that an earlier ``generate`` wrote (lsgan's own files), and that command's arguments."""
    args = generate_args(pipe, w / "out")
    res = lsgan(*args, cwd=w)
    assert res.returncode == 0, res.stderr
    return args


def standing_pose() -> np.ndarray:
    from lsgan.data.skeleton import TARGET_OFFSETS, PARENTS

    j = np.zeros((22, 3), np.float32)
    for i in range(1, 22):
        j[i] = j[PARENTS[i]] + TARGET_OFFSETS[i]
    return j + np.array([0.0, 0.95, 0.0], np.float32)


def timeline_args(w: Path, pipe: Path, content: str | None = None, inline: str | None = None) -> list:
    """generate --timeline from a file take.txt holding ``content``, or from ``inline`` text."""
    if content is not None:
        (w / "take.txt").write_text(content)
    return ["generate", "--gan", pipe / "gan", "--vae", pipe / "vae", "--timeline",
            inline if inline is not None else w / "take.txt", "-o", w / "out"]


def copy_run(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def corrupt_state(w: Path, pipe: Path, content: bytes) -> list:
    from lsgan import outputs

    run = copy_run(pipe / "vae", w / "vae")
    (run / "last" / "state.pt").write_bytes(content)
    outputs.record(run / "last")  # the registry vouches for it (a forged or copied one): the reader must refuse it
    return ["train-vae", "--data", pipe / "synth.h5", "--recipe", pipe / "tiny.yaml", "--out", run, "--resume",
            "--max-steps", 6]


def truncated_weights(w: Path, pipe: Path) -> list:
    run = copy_run(pipe / "vae", w / "vae")
    for sub in ("best", "last"):
        p = run / sub / "model.safetensors"
        p.write_bytes(p.read_bytes()[:100])
    return generate_args(pipe, w / "out")[:4] + [run] + generate_args(pipe, w / "out")[5:]


def evaluate_into_user_table(w: Path, pipe: Path) -> list:
    text_file(w, "t.md")
    return ["evaluate", "--gan", pipe / "gan", "--vae", pipe / "vae", "--data", pipe / "synth.h5", "--evaluator",
            pipe / "vae", "-o", w / "t"]


class _Run:
    """Unpickling this calls os.system: a crafted file that must never run."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


def gadget(w: Path) -> bytes:
    return pickle.dumps({"v_template": _Run(f"touch {w / 'PWNED'}")}, protocol=2)


def body_model_gadget(w: Path, pipe: Path) -> list:
    (w / "evil.pkl").write_bytes(gadget(w))
    return ["export", "--glb", next((pipe / "gen").glob("*_joints.npy")), "--body-model", w / "evil.pkl",
            "-o", w / "body.glb"]


def humanact12_gadget(w: Path) -> list:
    (w / "humanact12poses.pkl").write_bytes(gadget(w))
    return ["preprocess", "--source", "humanact12", w / "humanact12poses.pkl", "-o", w / "out.h5"]


def state_gadget(w: Path, pipe: Path) -> list:
    buf = io.BytesIO()
    torch.save({"step": _Run(f"touch {w / 'PWNED'}")}, buf)
    return corrupt_state(w, pipe, buf.getvalue())


def saved_state(w: Path, pipe: Path, edit: Callable[[dict], object]) -> list:
    """--resume from a copy of the pipeline's VAE run whose state.pt is ``edit(its real state)``, saved by torch."""
    state = torch.load(pipe / "vae" / "last" / "state.pt", weights_only=True)
    buf = io.BytesIO()
    torch.save(edit(state), buf)
    return corrupt_state(w, pipe, buf.getvalue())


def without(d: dict, key: str) -> dict:
    return {k: v for k, v in d.items() if k != key}


def edited_checkpoint(w: Path, pipe: Path, which: str, edit: Callable[[dict], None]) -> list:
    """generate with a copy of the pipeline's ``which`` run ('gan' or 'vae') whose config.json files were
    ``edit``-ed in place."""
    run = copy_run(pipe / which, w / which)
    for sub in ("best", "last"):
        meta = json.loads((run / sub / "config.json").read_text())
        edit(meta)
        (run / sub / "config.json").write_text(json.dumps(meta))
    return ["generate", "--gan", run if which == "gan" else pipe / "gan", "--vae", run if which == "vae" else
            pipe / "vae", "--text", "a person walks", "--frames", 40, "-o", w / "out"]


def generate_folder_with_manifest(w: Path, pipe: Path, text: str) -> Path:
    gen = copy_run(pipe / "gen", w / "gen")
    (gen / "manifest.json").write_text(text)
    return gen


def tiny_bvh(w: Path) -> Path:
    """A BVH of one joint and two frames: a rig no joint map knows."""
    return written(w / "tiny.bvh", b"HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 6 Xposition Yposition "
                   b"Zposition Zrotation Xrotation Yrotation\n  End Site\n  {\n    OFFSET 0 10 0\n  }\n}\nMOTION\n"
                   b"Frames: 2\nFrame Time: 0.05\n0 90 0 0 0 0\n0 90 0 0 0 0\n")


def sparse(path: Path, size: int) -> Path:
    """A file of ``size`` zero bytes that takes no disk space."""
    with open(path, "wb") as fh:
        fh.truncate(size)
    return path


ALIAS_BOMB = b"vae:\n  train:\n    joint_weight:\n      - &a [x, x, x, x, x, x, x, x, x]\n" + b"".join(
    b"      - &%c [%s]\n" % (n, b", ".join([b"*%c" % p] * 9)) for p, n in zip(b"abcdefg", b"bcdefgh"))  # 9^8 x's


def written(path: Path, content: bytes) -> Path:
    path.write_bytes(content)
    return path


def npy_file(w: Path, name: str, array: np.ndarray) -> Path:
    np.save(w / name, array)
    return w / name


@contextlib.contextmanager
def small_disk(folder: Path, size: int):
    """``folder`` as a full disk of ``size`` bytes: a tmpfs mounted there (as root), else, where mounting is not
    allowed, a file-size limit of ``size`` for the command (EFBIG, the stand-in for a full disk). Yields (the
    function that sets the limit in the child, or None; the words the error line must say)."""
    folder.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                             capture_output=True).returncode == 0
    try:
        if mounted:
            yield None, "disk full"
        else:
            yield (lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))), "file too large"
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(folder)], check=True)


@dataclass(frozen=True)
class Case:
    id: str
    args: Callable[[Path, Path], list]  # (row folder, tiny pipeline) -> command-line arguments
    code: int
    phrase: str
    disk: int = 0  # bytes: ``w/full`` is a disk of this size, full once the command writes more (small_disk)


def copied_run(w: Path, pipe: Path, note: str | None = None, extra: dict | None = None) -> Path:
    """A copy of the pipeline's VAE run in ``w/run`` (with its registry), ``note`` appended by the user to its
    log.csv, and ``extra`` files of the user's."""
    run = copy_run(pipe / "vae", w / "run")
    if note is not None:
        (run / "log.csv").write_text((run / "log.csv").read_text() + note)
    for name, text in (extra or {}).items():
        (run / name).write_text(text)
    return run


def train_into(run: Path, pipe: Path, *flags) -> list:
    return ["train-vae", "--data", pipe / "synth.h5", "--recipe", pipe / "tiny.yaml", "--out", run, "--max-steps", 2,
            *flags]


def user_run_folder(w: Path, files: dict) -> Path:
    d = w / "run"
    d.mkdir()
    for name, text in files.items():
        (d / name).write_bytes(text) if isinstance(text, bytes) else (d / name).write_text(text)
    return d


CASES = [
    # preprocess: inputs
    Case("bvh-truncated", lambda w, p: truncated_bvh(w), 1, "no clip could be imported"),
    Case("bvh-nan", lambda w, p: nan_bvh(w), 1, "no clip could be imported"),
    Case("bvh-gz-not-gzip", lambda w, p: gz_not_gzip(w), 1, "no clip could be imported"),
    Case("joint-map-malformed", lambda w, p: malformed_map(w), 1, "map.json"),
    Case("joint-map-missing-joint", lambda w, p: map_missing_joint(w), 1, "left_wrist"),
    Case("npy-zero-byte", lambda w, p: zero_byte_npy(w), 1, "no clip could be imported"),
    Case("npy-pickled-object", lambda w, p: pickled_npy(w), 1, "no clip could be imported"),
    Case("strict-one-bad-clip", lambda w, p: strict_one_bad(w), 1, "short.npy"),
    Case("input-missing", lambda w, p: ["preprocess", "--source", "bvh", w / "nope", "-o", w / "o.h5"], 2,
         "does not exist"),
    Case("humanml3d-not-a-folder-of-it", lambda w, p: not_a_humanml3d_folder(w), 1, "not a processed HumanML3D"),
    Case("resume-and-force", lambda w, p: ["preprocess", "--source", "synthetic", "-o", w / "o.h5", "--resume",
                                           "--force"], 2, "give one of them"),
    Case("unknown-option", lambda w, p: ["preprocess", "--sorce", "bvh"], 2, "no such option"),
    # preprocess: outputs
    Case("output-holds-inputs", lambda w, p: output_holds_inputs(w), 1, "holds the input"),
    Case("output-inside-input", lambda w, p: output_inside_input(w), 1, "inside the input folder"),
    Case("output-user-file", lambda w, p: output_is_user_file(w), 1, "pass --force"),
    Case("output-user-file-force", lambda w, p: output_is_user_file(w, force=True), 1, "not a file lsgan wrote"),
    Case("output-lsgan-shard-no-force", existing_lsgan_shard, 1, "pass --force"),
    Case("output-is-folder", lambda w, p: output_is_folder(w), 1, "is a folder"),
    Case("output-under-a-file", lambda w, p: output_under_a_file(w), 1, "is not a folder"),
    Case("report-user-file", lambda w, p: report_is_user_file(w), 1, "pass --force"),
    Case("staging-user-folder", lambda w, p: staging_is_user_folder(w), 1, "not a staging folder lsgan made"),
    # training
    Case("train-out-user-files", run_with_user_files, 1, "not an lsgan run"),
    Case("train-out-existing-run", lambda w, p: ["train-vae", "--data", p / "synth.h5", "--recipe", p / "tiny.yaml",
                                                 "--out", p / "vae"], 1, "--resume"),
    Case("train-out-is-file", lambda w, p: ["train-vae", "--data", p / "synth.h5", "--recipe", p / "tiny.yaml",
                                            "--out", text_file(w)], 1, "is not a folder"),
    Case("train-recipe-missing", lambda w, p: ["train-vae", "--data", p / "synth.h5", "--recipe", w / "no.yaml",
                                               "--out", w / "run"], 1, "no.yaml"),
    Case("train-data-text-file", lambda w, p: ["train-vae", "--data", text_file(w, "x.h5"), "--out", w / "run"], 1,
         "x.h5"),
    Case("train-data-hdf5-not-shard", lambda w, p: ["train-vae", "--data", hdf5_not_shard(w), "--out", w / "run"], 1,
         "not an lsgan motion shard"),
    Case("state-truncated", lambda w, p: corrupt_state(w, p, b"PK\x03\x04 truncated"), 1, "state.pt"),
    Case("state-not-torch", lambda w, p: corrupt_state(w, p, b"hello"), 1, "state.pt"),
    Case("weights-truncated", truncated_weights, 1, "model.safetensors"),
    Case("state-runs-code", state_gadget, 1, "refused"),
    Case("state-holds-a-list", lambda w, p: saved_state(w, p, lambda s: [1, 2]), 1,
         "state.pt: not a training state lsgan wrote (it holds a list"),
    Case("state-lacks-optimizer", lambda w, p: saved_state(w, p, lambda s: without(s, "optimizer")), 1,
         "state.pt: not a training state lsgan wrote (no 'optimizer')"),
    Case("state-step-is-text", lambda w, p: saved_state(w, p, lambda s: {**s, "step": "six"}), 1,
         "state.pt: not a training state lsgan wrote ('step' is a str)"),
    Case("recipe-malformed-yaml", lambda w, p: ["train-vae", "--data", p / "synth.h5", "--recipe",
                                                written(w / "r.yaml", b"vae: [1, 2\n"), "--out", w / "run"], 1,
         "r.yaml: not a recipe (YAML text) (line 2"),
    Case("recipe-velocity-weight-inf", lambda w, p: ["train-vae", "--data", p / "synth.h5", "--recipe",
                                                     written(w / "r.yaml", b"vae:\n  train: {velocity_weight: .inf}\n"),
                                                     "--out", w / "run"], 1,
         "r.yaml: vae.train.velocity_weight: inf is not a finite number"),
    *[Case(f"recipe-{name}", lambda w, p, text=text: ["train-vae", "--data", p / "synth.h5", "--recipe",
                                                        written(w / "r.yaml", text), "--out", w / "run"], 1, phrase)
      for name, text, phrase in (
          ("key-given-twice", b"vae:\n  train: {joint_weight: 0.2, joint_weight: -5}\n",
           "r.yaml: not a recipe (YAML text) (line 2, column 30: the key 'joint_weight' is given twice)"),
          ("exponent-read-as-text", b"vae:\n  train: {joint_weight: 2e-1}\n", "write 2.0e-1"),
          ("key-beside-model-and-train", b"vae:\n  joint_weight: 0.5\n",
           "r.yaml: vae: unknown key(s) ['joint_weight']"),
          ("train-not-a-mapping", b"vae: {train: [joint_weight, 0.2]}\n", "r.yaml: vae.train must be a mapping"),
          ("integer-beyond-a-float", b"vae:\n  train: {joint_weight: " + b"9" * 400 + b"}\n",
           "joint_weight: 999999999999999999...9999999999999999999 is not a finite number"),
          ("section-not-a-mapping", b"vae: 0\n", "r.yaml: vae must be a mapping (key: value lines), not 0"),
          ("model-false", b"vae: {model: false}\n", "r.yaml: vae.model must be a mapping"),
          ("misspelt-section", b"vea:\n  train: {max_steps: 3}\n", "r.yaml: unknown section(s) ['vea']"),
          ("lr-infinite", b"vae:\n  train: {lr: .inf}\n", "r.yaml: vae.train.lr: inf is not a finite number"),
          ("heads-zero", b"vae:\n  model: {num_heads: 0}\n", "r.yaml: vae.model.num_heads: 0 is not from 1 to 1,024"),
          ("sine-code-odd-width", b"vae:\n  model: {d_model: 33, num_heads: 1, position_embedding: sine}\n",
           "r.yaml: vae.model: a sine position code needs an even d_model, got 33"),
          ("windows-beyond-position-code", b"vae:\n  model: {max_len: 8}\n",
           "r.yaml: vae: train.max_frames (196) is more than model.max_len (8)"),
          ("size-a-float-holds", b"vae:\n  model: {ff_size: 99999999999999999999999999}\n",
           "r.yaml: vae.model.ff_size: 99999999999999999999999999 is not from 1 to 65,536"),
          ("text-encoder-a-mapping", b"text_encoder: {name: minilm}\n",
           "r.yaml: text_encoder is one of minilm, clip-vit-l-14, none, not {'name': 'minilm'}"),
          ("alias-bomb", ALIAS_BOMB, "joint_weight: [['x', 'x', 'x', 'x', ...], [[...], [...], [...], [...], ...], "),
      )],
    Case("recipe-evaluator-unit-above-windows", lambda w, p: ["train-evaluator", "--data", p / "synth.h5", "--recipe",
                                                             written(w / "r.yaml", b"evaluator:\n  text:\n    model: "
                                                                     b"{unit_length: 50}\n"), "--out", w / "run"], 1,
         "r.yaml: evaluator.text: train.min_frames (40) is below the unit length (50)"),
    *[Case(f"option-{name}", lambda w, p, args=args: [*args[:1], *(x(p) if callable(x) else x for x in args[1:]),
                                                        "--out", w / "run"], 2, phrase)
      for name, args, phrase in (
          ("max-steps-zero", ("train-vae", "--data", lambda p: p / "synth.h5", "--max-steps", 0),
           "'--max-steps': 0 is not in the range 1<=x<=1000000000"),
          ("batch-size-zero", ("train-vae", "--data", lambda p: p / "synth.h5", "--batch-size", 0),
           "'--batch-size': 0 is not in the range 1<=x<=1000000000"),
          ("seed-negative", ("train-gan", "--cache", lambda p: p / "cache.h5", "--seed", -1),
           "'--seed': -1 is not in the range 0<=x<=9223372036854775807"))],
    Case("recipe-evaluator-misspelt", lambda w, p: ["train-evaluator", "--data", p / "synth.h5", "--recipe",
                                                    written(w / "r.yaml", b"evaluator:\n  txet: {}\n"),
                                                    "--out", w / "run"], 1,
         "r.yaml: evaluator: unknown key(s) ['txet']; it holds text, action"),
    Case("recipe-joint-weight-with-mld", lambda w, p: ["train-vae", "--data", p / "synth.h5", "--recipe",
                                                       written(w / "r.yaml",
                                                               b"vae:\n  train: {loss: mld, joint_weight: 0.5}\n"),
                                                       "--out", w / "run"], 1,
         "vae.train: joint_weight is for loss mse"),
    Case("recipe-smooth-output-negative", lambda w, p: ["train-vae", "--data", p / "synth.h5", "--recipe",
                                                        written(w / "r.yaml", b"vae:\n  model: {smooth_output: -1}\n"),
                                                        "--out", w / "run"], 1,
         "r.yaml: vae.model.smooth_output: -1 is not from 0 to 8"),
    Case("recipe-unknown-schedule", lambda w, p: ["train-vae", "--data", p / "synth.h5", "--recipe",
                                                  written(w / "r.yaml", b"vae:\n  train: {lr_schedule: Cosine}\n"),
                                                  "--out", w / "run"], 1,
         "vae.train: lr_schedule must be one of constant, cosine, not 'Cosine'"),
    Case("evaluate-empty-split", lambda w, p: ["evaluate", "--vae-only", "--vae", p / "vae", "--data", p / "synth.h5",
                                               "--split", "nosuch", "-o", w / "t"], 1,
         "synth.h5: no clips of 40+ frames in the 'nosuch' split"),
    # a full disk: the error names the file being written and says so plainly
    Case("disk-full-preprocess", lambda w, p: ["preprocess", "--source", "synthetic", "--num-clips", 60,
                                               "-o", w / "full" / "s.h5"], 1, "s.h5.parts", disk=1 << 20),
    Case("disk-full-generate", lambda w, p: ["generate", "--gan", p / "gan", "--vae", p / "vae", "--text", "walk",
                                             "--frames", 196, "-o", w / "full" / "gen"], 1, "full/gen/000_walk",
         disk=100 << 10),
    # files that would run code when unpickled: refused, nothing runs (no PWNED file appears)
    Case("body-model-runs-code", body_model_gadget, 1, "refused to unpickle"),
    Case("humanact12-runs-code", lambda w, p: humanact12_gadget(w), 1, "refused to unpickle"),
    # encode-latents, train-gan
    Case("encode-output-user-file", lambda w, p: ["encode-latents", "--data", p / "synth.h5", "--vae", p / "vae",
                                                  "-o", text_file(w, "c.h5")], 1, "pass --force"),
    *[Case(f"encode-clip-{name}", lambda w, p, files=files: [
        "encode-latents", "--data", p / "synth.h5", "--vae", p / "vae", "--text-encoder", "clip-vit-l-14",
        "--text-encoder-path", user_run_folder(w, files), "-o", w / "c.h5"], 1,
        "CLIP ViT-L/14 text encoder (weights + tokenizer) not found at")
      for name, files in (("folder-empty", {"notes.txt": "x"}),
                          ("weights-missing", {"config.json": json.dumps({
                              "model_type": "clip_text_model", "hidden_size": 768, "intermediate_size": 3072,
                              "num_hidden_layers": 12, "num_attention_heads": 12, "projection_dim": 768})}))],
    *[Case(f"encode-clip-{name}", lambda w, p, files=files: [
        "encode-latents", "--data", p / "synth.h5", "--vae", p / "vae", "--text-encoder", "clip-vit-l-14",
        "--text-encoder-path", user_run_folder(w, files), "-o", w / "c.h5"], 1, phrase)
      for name, files, phrase in (
          ("config-not-json", {"config.json": "{bad json"}, "run: not a CLIP ViT-L/14 text-encoder folder"),
          ("config-a-list", {"config.json": "[]"}, "run: holds a 'list' model, not a CLIP checkpoint"),
          ("config-not-utf8", {"config.json": b"\xff\xfe{}"}, "run: not a CLIP ViT-L/14 text-encoder folder"),
          ("config-width-text", {"config.json": json.dumps({"model_type": "clip_text_model", "hidden_size": "x"})},
           "run: not a CLIP ViT-L/14 text-encoder folder"))],
    Case("encode-vae-not-checkpoint", lambda w, p: ["encode-latents", "--data", p / "synth.h5", "--vae",
                                                    user_run_folder(w, {"notes.txt": "x"}), "-o", w / "c.h5"], 1,
         "no checkpoint here"),
    Case("gan-cache-not-cache", lambda w, p: ["train-gan", "--cache", p / "synth.h5", "--out", w / "g"], 1,
         "synth.h5"),
    # generate
    Case("generate-into-earlier-run", lambda w, p: generate_args(p, p / "gen"), 1, "pass --force"),
    Case("generate-gan-is-vae", lambda w, p: ["generate", "--gan", p / "vae", "--vae", p / "vae", "--text", "x",
                                              "-o", w / "out"], 1, "vae"),
    Case("generate-too-few-frames", lambda w, p: generate_args(p, w / "out", "--frames", 2), 2,
         "'--frames': 2 is not in the range 4<=x<=100000"),
    *[Case(f"generate-{name}", lambda w, p, extra=extra: generate_args(p, w / "out", *extra), 2, phrase)
      for name, extra, phrase in (
          ("seconds-nan", ("--seconds", "nan"), "'--seconds': 'nan' is not a number"),
          ("seconds-inf", ("--seconds", "inf"), "'--seconds': inf is not in the range"),
          ("num-zero", ("--num", 0), "'--num': 0 is not in the range"),
          ("batch-size-zero", ("--batch-size", 0), "'--batch-size': 0 is not in the range"),
          ("seed-negative", ("--seed", -1), "'--seed': -1 is not in the range"),
          ("seed-beyond-64-bits", ("--seed", 2**64), "'--seed': 18446744073709551616 is not in the range"))],
    Case("generate-frames-beyond-the-vae", lambda w, p: generate_args(p, w / "out", "--frames", 201), 1,
         "vae: this VAE decodes at most 200 frames (its max_len); asked for 201"),
    Case("generate-prompt-line-too-short", lambda w, p: ["generate", "--gan", p / "gan", "--vae", p / "vae",
                                                         "--prompts", written(w / "prompts.txt", b"walk#40\nrun#3\n"),
                                                         "-o", w / "out"], 1,
         "prompts.txt: line 2 asks for 3 frames: a motion has 4 to 100,000"),
    *[Case(f"generate-prompt-line-{name}", lambda w, p, line=line: [
        "generate", "--gan", p / "gan", "--vae", p / "vae", "--prompts", written(w / "prompts.txt", b"walk#40\n" + line),
        "-o", w / "out"], 1, phrase) for name, line, phrase in (
          ("frames-not-a-number", b"walk#x\n", "prompts.txt: line 2: 'x' after '#' is not a number of frames"),
          ("frames-negative", b"walk#-40\n", "prompts.txt: line 2: '-40' after '#' is not a number of frames"),
          ("frames-fraction", b"walk # 40.5\n", "prompts.txt: line 2: '40.5' after '#' is not a number of frames"),
          ("frames-other-digits", "walk#\u0663\u0660".encode(), "line 2: '\u0663\u0660' after '#'"),
          ("frames-alone", b"#40\n", "prompts.txt: line 2: text is empty"),
          ("escape", b"walk \x1b[2J fast\n", "prompts.txt: line 2: text holds a control character (U+001B)"),
          ("line-separator", "walk#40\u2028run#60\n".encode(), "line 2: text holds a control character (U+2028)"),
          ("long-tail", b"walk#" + b"x" * 5000, "line 2: 'xxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx...' after '#'"))],
    *[Case(f"generate-text-{name}", lambda w, p, text=text: generate_args(p, w / "out", "--text", text), 1, phrase)
      for name, text, phrase in (("empty", "", "request 2 (''): text is empty"),
                                 ("blank", "   ", "request 2 ('   '): text is empty"),
                                 ("escape", "walk\x1b[2J", "request 2 ('walk\\x1b[2J'): text holds a control character "
                                                           "(U+001B)"))],
    Case("generate-no-prompt", lambda w, p: ["generate", "--gan", p / "gan", "--vae", p / "vae", "-o", w / "out"], 2,
         "--text"),
    Case("generate-output-is-file", lambda w, p: generate_args(p, text_file(w)), 1, "not a folder"),
    Case("generate-gan-config-lacks-section", lambda w, p: edited_checkpoint(w, p, "gan", lambda m: m["config"].pop(
        "gan")), 1, "gan/best/config.json: not a checkpoint config this lsgan version reads (no 'gan')"),
    Case("generate-gan-config-wrong-type", lambda w, p: edited_checkpoint(w, p, "gan", lambda m: m["config"]["gan"]
                                                                          .update(latent_dim="sixteen")), 1,
         "gan/best/config.json: not a checkpoint config"),
    Case("generate-gan-extra-not-object", lambda w, p: edited_checkpoint(w, p, "gan", lambda m: m.update(extra="x")),
         1, "gan/best/config.json: not a generator's config"),
    Case("generate-gan-latent-stats-wrong-size", lambda w, p: edited_checkpoint(
        w, p, "gan", lambda m: m["extra"].update(latent_mean=[0.0])), 1, "'latent_mean' holds (1,) values"),
    Case("generate-vae-config-unknown-key", lambda w, p: edited_checkpoint(w, p, "vae", lambda m: m["config"]["model"]
                                                                           .update(bogus=1)), 1,
         "vae/best/config.json: not a checkpoint config"),
    Case("generate-vae-mean-wrong-size", lambda w, p: edited_checkpoint(w, p, "vae", lambda m: m["extra"].update(
        mean=[0.0, 1.0])), 1, "vae/best/config.json: not a checkpoint config"),
    Case("generate-vae-bone-lengths-negative", lambda w, p: edited_checkpoint(w, p, "vae", lambda m: m["extra"].update(
        bone_lengths=[-0.1] * 21)), 1, "vae/best/config.json: not a checkpoint config this lsgan version reads "
         "(ValueError: its 'bone_lengths' is not 21 finite positive numbers)"),
    Case("generate-vae-bone-lengths-missing", lambda w, p: edited_checkpoint(w, p, "vae", lambda m: m["extra"].pop(
        "bone_lengths")), 1, "its config has no 'bone_lengths'"),
    Case("generate-vae-rigid-std-zero", lambda w, p: edited_checkpoint(w, p, "vae", lambda m: m["extra"].update(
        std=[0.0] * 263)), 1, "its 'std' is not 263 finite positive numbers"),
    Case("generate-prompts-not-utf8", lambda w, p: ["generate", "--gan", p / "gan", "--vae", p / "vae", "--prompts",
                                                    written(w / "prompts.txt", b"\xff\xfewalk\n"), "-o", w / "out"],
         1, "prompts.txt: not a prompts file of UTF-8 text"),
    Case("timeline-blank-line", lambda w, p: timeline_args(w, p, "walk#40\n\nrun#40\n"), 1,
         "take.txt: line 2 is blank"),
    Case("timeline-line-without-frames", lambda w, p: timeline_args(w, p, "walk#40\nrun forward\n"), 1,
         "take.txt: line 2 has no '#frames'"),
    Case("timeline-frames-not-a-number", lambda w, p: timeline_args(w, p, "walk#forty\n"), 1,
         "line 1 'forty' is not a whole number of frames"),
    Case("timeline-empty-file", lambda w, p: timeline_args(w, p, ""), 1, "take.txt: no segments"),
    Case("timeline-file-missing", lambda w, p: timeline_args(w, p), 1, "take.txt: no such timeline file"),
    Case("timeline-inline-item-without-frames", lambda w, p: timeline_args(w, p, inline="walk#40; run"), 2,
         "--timeline: item 2 has no '#frames'"),
    Case("timeline-segment-over-max-len", lambda w, p: timeline_args(w, p, "walk#195\nrun#40\n"), 1,
         "line 1: 195 frames + 10 of overlap is more than this model decodes"),
    Case("timeline-segment-within-overlap", lambda w, p: timeline_args(w, p, "walk#40\nrun#8\n"), 1,
         "line 2: 8 frames; a segment needs at least 11"),
    # control: paths, keyframes, continuation, in-betweening (each refused before the output folder is touched)
    Case("path-nan", lambda w, p: path_args(w, p, "t,x,z\n0,0,0\n1,nan,1\n"), 1,
         "path.csv: not a path: rows of (time s, x, z) waypoints or (x, z) per frame, as CSV or JSON (ValueError: a "
         "number is NaN, infinite or beyond 10000"),
    Case("path-too-fast", lambda w, p: path_args(w, p, "0,0,0\n0.5,30,0\n"), 1,
         "path.csv: the root would move at 60.0 m/s from the path at"),
    Case("path-too-fast-force-keeps-earlier-run", lambda w, p: earlier_run(w, p) + ["--path", written(
        w / "fast.csv", b"0,0,0\n0.5,30,0\n"), "--force"], 1, "the root would move at 60.0 m/s"),
    Case("path-first-step-too-fast", lambda w, p: path_args(w, p, "0,0\n0,0\n", "p.csv") + [
        "--keyframe", "3:" + str(written(w / "k.json", PELVIS_FAR))], 1,
         "k.json: the root would move at 500.0 m/s from the path at 0.05 s to keyframe 3's root at 0.15 s"),
    Case("path-times-decrease", lambda w, p: path_args(w, p, "0,0,0\n1,1,0\n0.5,2,0\n"), 1,
         "waypoints at 1 and 0.5 s are less than a frame (0.05 s) apart"),
    Case("path-waypoints-within-a-frame", lambda w, p: path_args(w, p, "0,0,0\n0.04,5,5\n"), 1,
         "waypoints at 0 and 0.04 s are less than a frame"),
    Case("path-starts-before-the-motion", lambda w, p: path_args(w, p, "-1,0,0\n1,1,0\n"), 1,
         "the first waypoint is at -1 s"),
    Case("path-beyond-the-motion", lambda w, p: path_args(w, p, "0,0,0\n3,1,0\n"), 1,
         "the path runs to 3 s; the motion ends at 1.95 s"),
    Case("path-too-many-points", lambda w, p: path_args(w, p, "0,0\n" * 41), 1, "41 points for a motion of 40 frames"),
    Case("path-not-numbers", lambda w, p: path_args(w, p, "0,0,0\nleft,1,1\n"), 1, "'left' is not a number"),
    Case("path-underscore-number", lambda w, p: path_args(w, p, "0,0\n1_0,0\n"), 1, "'1_0' is not a number"),
    Case("path-json-boolean", lambda w, p: path_args(w, p, "[[0, 0], [true, 1]]", "path.json"), 1,
         "row 2 is not a list of numbers"),
    Case("path-json-object", lambda w, p: path_args(w, p, '{"pts": [[0, 0]]}', "path.json"), 1,
         "path.json: not a path"),
    Case("path-huge", lambda w, p: path_args(w, p, "0,0\n1e30,0\n"), 1, "beyond 10000"),
    Case("path-with-timeline", lambda w, p: timeline_args(w, p, "walk#40\n") + ["--path", written(
        w / "path.csv", b"0,0\n")], 2, "--path, --keyframe, --continue and --inbetween make one motion: not with --timeline"),
    Case("path-one-point", lambda w, p: path_args(w, p, "0,0\n"), 1, "a path needs at least two points"),
    Case("path-file-too-large", lambda w, p: generate_args(p, w / "out", "--path", sparse(w / "big.csv", 17 * 2**20)),
         1, "larger than 16 MB"),
    Case("keyframe-json-nan", lambda w, p: keyframe_args(w, p, 5, '{"head": [NaN, 1.6, 0]}', "k.json"), 1,
         "NaN is not JSON (leave a coordinate free with null)"),
    Case("keyframe-json-key-twice", lambda w, p: keyframe_args(
        w, p, 5, '{"head": [0, 1.6, 0], "head": [0, 1.5, 0]}', "k.json"), 1, "'head' is given twice"),
    Case("keyframe-joint-by-name-and-index", lambda w, p: keyframe_args(
        w, p, 5, '{"15": [0, 1.6, 0], "head": [0, 1.5, 0]}', "k.json"), 1, "joint head is set twice"),
    Case("keyframe-unicode-digit-joint", lambda w, p: keyframe_args(w, p, 5, '{"\u00b2": [0, 1.6, 0]}', "k.json"), 1,
         "unknown joint '\u00b2': give an index 0-21"),
    Case("keyframe-below-ground", lambda w, p: keyframe_args(w, p, 5, '{"head": [0, -3, 0]}', "k.json"), 1,
         "head at y = -3.00 m is below the ground"),
    Case("facing-without-path", lambda w, p: generate_args(p, w / "out", "--facing"), 2,
         "--facing turns the root along --path"),
    Case("bvh-keyframe-past-its-frames", lambda w, p: generate_args(p, w / "out", "--keyframe", f"5:{tiny_bvh(w)}@5"),
         1, "has 2 frames (0..1), not a frame 5"),
    Case("bvh-keyframe-unmapped-rig", lambda w, p: generate_args(p, w / "out", "--keyframe", f"5:{tiny_bvh(w)}@1"),
         1, "no joint map fits its joints"),
    Case("bvh-keyframe-without-frame", lambda w, p: generate_args(p, w / "out", "--keyframe", f"5:{tiny_bvh(w)}"),
         1, "a BVH keyframe is FRAME:FILE.bvh@BVH_FRAME"),
    Case("keyframe-map-without-bvh", lambda w, p: generate_args(p, w / "out", "--keyframe-map", "cmu"), 2,
         "--keyframe-map reads --keyframe BVH files"),
    Case("keyframe-beyond-motion", lambda w, p: keyframe_args(w, p, 40, standing_pose()), 1, "keyframe 40 (40:"),
    Case("keyframe-no-frame", lambda w, p: generate_args(p, w / "out", "--keyframe", "pose.npy"), 1,
         "a keyframe is FRAME:FILE"),
    Case("keyframe-no-file", lambda w, p: generate_args(p, w / "out", "--keyframe", "5:"), 1,
         "a keyframe is FRAME:FILE"),
    Case("keyframe-unicode-digit", lambda w, p: generate_args(p, w / "out", "--keyframe", "\u00b2:f.npy"), 1,
         "a keyframe is FRAME:FILE"),
    Case("keyframe-folder", lambda w, p: generate_args(p, w / "out", "--keyframe", f"3:{w}"), 1,
         "a folder, not a keyframe file"),
    Case("keyframe-missing-file", lambda w, p: generate_args(p, w / "out", "--keyframe", f"3:{w / 'nope.npy'}"), 1,
         "nope.npy: no such keyframe file"),
    Case("keyframe-nan", lambda w, p: keyframe_args(w, p, 3, np.where(np.eye(22, 3, dtype=bool), np.nan,
                                                                       standing_pose())), 1,
         "pose.npy: not a keyframe"),
    Case("keyframe-json-null", lambda w, p: keyframe_args(w, p, 3, '{"right_wrist": [null, null, null]}', "k.json"),
         1, "joint 'right_wrist' sets no coordinate"),
    Case("keyframe-complex", lambda w, p: keyframe_args(w, p, 3, standing_pose().astype(np.complex64)), 1,
         "pose.npy: holds complex64 data"),
    Case("keyframe-other-skeleton", lambda w, p: keyframe_args(w, p, 3, np.zeros((24, 3), np.float32)), 1,
         "a pose of this skeleton is (22, 3) joints"),
    Case("keyframe-in-centimetres", lambda w, p: keyframe_args(w, p, 3, standing_pose() * 100), 1,
         "keyframe 3: its bones are"),
    Case("keyframe-one-bone-stretched", lambda w, p: keyframe_args(w, p, 3, stretched_pose()), 1,
         "the bone to left_wrist"),
    Case("keyframe-zero-off-origin", lambda w, p: keyframe_args(w, p, 0, '{"pelvis": [1, 0.9, 1]}', "k.json"), 1,
         "keyframe 0's root on frame 0 is the motion's start, the origin (0, 0), not (1.000, 1.000)"),
    Case("keyframe-unknown-joint", lambda w, p: keyframe_args(w, p, 3, '{"left_hand": [0, 1, 0]}', "pose.json"), 1,
         "unknown joint 'left_hand'"),
    Case("keyframe-pickle", lambda w, p: keyframe_args(w, p, 3, np.array([{"a": 1}], dtype=object)), 1,
         "pose.npy"),
    Case("continue-with-fix-feet", lambda w, p: generate_args(p, w / "out", "--fix-feet", "--continue", npy_file(
        w, "m.npy", np.stack([standing_pose()] * 8))), 2, "--fix-feet would move the feet of the frames"),
    Case("path-empty", lambda w, p: path_args(w, p, "t,x,z\n"), 1, "path.csv: not a path"),
    Case("path-deep-json", lambda w, p: path_args(w, p, "[" * 100000 + "]" * 100000, "path.json"), 1,
         "JSON nested too deeply"),
    Case("keyframe-centimetres-far-from-the-root", lambda w, p: keyframe_args(w, p, 10, standing_pose() * 100 + [
        50, 0, 50]), 1, "keyframe 10: its bones are"),
    Case("continue-not-npy", lambda w, p: generate_args(p, w / "out", "--continue", text_file(w, "m.txt")), 1,
         "m.txt: not a .npy array file"),
    Case("continue-too-short", lambda w, p: generate_args(p, w / "out", "--continue", npy_file(
        w, "m.npy", np.stack([standing_pose()] * 4))), 1, "m.npy: the motion to continue has 4 frames"),
    Case("continue-far-away", lambda w, p: generate_args(p, w / "out", "--continue", npy_file(
        w, "m.npy", np.stack([standing_pose()] * 8) + [1e6, 0, 0])), 1, "m.npy: the motion to continue holds a "
         "coordinate that is not finite or beyond 10000 m"),
    Case("continue-in-centimetres", lambda w, p: generate_args(p, w / "out", "--continue", npy_file(
        w, "m.npy", np.stack([standing_pose()] * 8) * 100)), 1, "m.npy: keyframe 0: its bones are"),
    Case("inbetween-too-far", lambda w, p: generate_args(p, w / "out", "--inbetween", npy_file(
        w, "a.npy", np.stack([standing_pose()] * 8)), npy_file(w, "b.npy", np.stack([standing_pose()] * 8) +
                                                               [100, 0, 0])), 1, "b.npy: the root would move at"),
    Case("timeline-continue-segment-too-short", lambda w, p: timeline_args(w, p, inline="walk#4; run#40") + [
        "--join", "continue"], 1, "--timeline: item 1: 4 frames; a segment needs 5"),
    # export
    Case("export-two-formats", lambda w, p: ["export", "--glb", "--bvh", p / "gen", "-o", w / "x"], 2, "one format"),
    Case("export-user-file", lambda w, p: ["export", "--glb", next((p / "gen").glob("*_joints.npy")),
                                           "-o", text_file(w, "walk.glb")], 1, "pass --force"),
    Case("export-user-file-force", lambda w, p: ["export", "--bvh", next((p / "gen").glob("*_joints.npy")),
                                                 "-o", text_file(w, "walk.bvh"), "--force"], 1,
         "not a file lsgan wrote"),
    Case("export-into-input-folder", lambda w, p: ["export", "--bvh", p / "gen", "-o", p / "gen"], 1,
         "the input"),
    Case("export-manifest-not-object", lambda w, p: ["export", "--gif", generate_folder_with_manifest(w, p, "[1]"),
                                                     "-o", w / "gifs"], 1, "gen/manifest.json: not a manifest"),
    Case("export-manifest-truncated", lambda w, p: ["export", "--gif", generate_folder_with_manifest(w, p, '{"moti'),
                                                    "-o", w / "gifs"], 1, "gen/manifest.json: not a manifest"),
    Case("export-no-frames", lambda w, p: ["export", "--bvh", npy_file(w, "m_joints.npy", np.zeros((0, 22, 3))),
                                           "-o", w / "m.bvh"], 1, "m_joints.npy: holds no frames"),
    Case("export-nan-joints", lambda w, p: ["export", "--bvh", npy_file(w, "m_joints.npy",
                                                                        np.full((8, 22, 3), np.nan)),
                                            "-o", w / "m.bvh"], 1, "m_joints.npy: holds NaN"),
    Case("export-corrupt-npy", lambda w, p: ["export", "--bvh", text_file(w, "m_joints.npy"), "-o", w / "m.bvh"], 1,
         "m_joints.npy"),
    Case("export-body-model-missing", lambda w, p: ["export", "--glb", p / "gen", "--body-model", w / "nomodels",
                                                    "-o", w / "body"], 1, "does not exist"),
    Case("export-rig-missing", lambda w, p: ["export", "--bvh", p / "gen", "--rig", w / "nope.bvh", "--preset",
                                             "bandai", "-o", w / "x"], 2, "does not exist"),
    Case("export-rig-not-bvh", lambda w, p: ["export", "--bvh", p / "gen", "--rig", text_file(w, "char.bvh"),
                                             "--preset", "bandai", "-o", w / "x"], 1, "not a BVH file"),
    Case("export-rig-lacks-map-joints", lambda w, p: rig_export(w, p, "--preset", "mixamo"), 1,
         "needs joints ['mixamorig:Hips'"),
    Case("export-rig-map-missing-joint", lambda w, p: rig_export(w, p, "--joint-map", w / "map.json",
                                                                  drop="left_wrist"), 1, "lacks SMPL joints"),
    Case("export-rig-no-map", lambda w, p: rig_export(w, p), 2, "--rig needs one joint map"),
    Case("export-rig-with-gif", lambda w, p: ["export", "--gif", p / "gen", "--rig", text_file(w, "char.bvh"),
                                              "--preset", "bandai", "-o", w / "x"], 2, "--rig goes with --bvh or --glb"),
    Case("export-rig-with-body-model", lambda w, p: ["export", "--glb", p / "gen", "--body-model", w / "models",
                                                     "--rig", text_file(w, "char.bvh"), "--preset", "bandai",
                                                     "-o", w / "x"], 2, "--body-model and --rig do not go together"),
    Case("export-rig-glb-lacks-map-joints",
         lambda w, p: ["export", "--glb", *rig_export(w, p, "--preset", "mixamo")[2:]], 1,
         "needs joints ['mixamorig:Hips'"),
    # export-model (ONNX); the rows of generate --runtime onnx, which need an export, are in test_deploy.py
    Case("export-model-run-missing", lambda w, p: ["export-model", w / "nope", "-o", w / "x", "--onnx"], 2,
         "does not exist"),
    Case("export-model-not-a-gan", lambda w, p: ["export-model", p / "vae", "-o", w / "x", "--onnx"], 1, "not a GAN"),
    Case("export-model-no-format", lambda w, p: ["export-model", p / "gan", "-o", w / "x"], 2, "--onnx"),
    Case("export-model-output-user-file", lambda w, p: ["export-model", p / "gan", "-o", text_file(w), "--onnx"], 1,
         "not a folder"),
    Case("export-model-output-user-folder", lambda w, p: ["export-model", p / "gan", "-o", user_folder(w), "--onnx"],
         1, "pass --force"),
    Case("export-model-output-user-manifest-force", lambda w, p: ["export-model", p / "gan", "-o",
                                                                  user_folder(w, "manifest.json"), "--onnx",
                                                                  "--force"], 1, "not a file lsgan wrote"),
    Case("export-model-output-inside-run", lambda w, p: ["export-model", p / "gan", "-o", p / "gan" / "onnx",
                                                         "--onnx"], 1, "inside the input folder"),
    # serve (every row fails before or instead of serving; a port of 0 would be any free one)
    Case("serve-gan-missing", lambda w, p: ["serve", "--gan", w / "nope", "--vae", p / "vae"], 2, "does not exist"),
    Case("serve-model-and-gan", lambda w, p: ["serve", "--model", p / "gan", "--gan", p / "gan", "--vae",
                                              p / "vae"], 2, "not both"),
    Case("serve-nothing-to-serve", lambda w, p: ["serve"], 2, "--gan RUN and --vae RUN"),
    Case("serve-int8-without-model", lambda w, p: ["serve", "--gan", p / "gan", "--vae", p / "vae", "--int8"], 2,
         "--int8 goes with --model"),
    Case("serve-model-not-an-export", lambda w, p: ["serve", "--model", p / "gan", "--port", 0], 1,
         "no manifest.json"),
    Case("serve-gan-is-vae", lambda w, p: ["serve", "--gan", p / "vae", "--vae", p / "vae", "--port", 0], 1,
         "not a generator"),
    Case("serve-frames-over-model", lambda w, p: ["serve", "--gan", p / "gan", "--vae", p / "vae", "--port", 0,
                                                  "--max-frames", 5000], 1, "more than this model decodes"),
    Case("serve-empty-api-key", lambda w, p: ["serve", "--gan", p / "gan", "--vae", p / "vae", "--port", 0,
                                              "--api-key", " "], 1, "the API key holds ' '"),
    Case("serve-no-engine-process", lambda w, p: ["serve", "--gan", p / "gan", "--vae", p / "vae", "--workers", 0], 2,
         "--workers"),
    Case("serve-bad-port", lambda w, p: ["serve", "--gan", p / "gan", "--vae", p / "vae", "--port", 70000], 2,
         "--port"),
    # evaluate, bench, inspect
    Case("evaluate-output-user-file", evaluate_into_user_table, 1, "pass --force"),
    Case("bench-json-user-file", lambda w, p: ["bench", "--json", text_file(w, "b.json")], 1, "pass --force"),
    Case("inspect-text-file", lambda w, p: ["inspect", text_file(w, "s.h5")], 1, "s.h5"),
    Case("inspect-hdf5-not-shard", lambda w, p: ["inspect", hdf5_not_shard(w)], 1, "not an lsgan motion shard"),
    # outputs: nothing of the user's is replaced, and no output lies inside an input (issue 28)
    Case("force-keeps-annotated-log", lambda w, p: train_into(copied_run(w, p, "# my note\n"), p, "--force"), 1,
         "log.csv: is not what lsgan wrote"),
    Case("resume-keeps-annotated-log", lambda w, p: train_into(copied_run(w, p, "# my note\n"), p, "--resume"), 1,
         "log.csv: is not what lsgan wrote"),
    Case("resume-into-user-folder", lambda w, p: train_into(user_run_folder(w, {"thesis.tex": "x"}), p, "--resume"), 1,
         "no lsgan run to resume"),
    Case("resume-user-log-no-run", lambda w, p: train_into(user_run_folder(w, {"log.csv": "step,x\n1,2\n",
                                                                          "thesis.tex": "x"}), p, "--resume"), 1,
         "log.csv: is not what lsgan wrote"),
    Case("force-keeps-user-heldout", lambda w, p: train_into(copied_run(w, p, None, {"heldout.json": "{}"}), p,
                                                             "--force"),
         1, "heldout.json: is not what lsgan wrote"),
    Case("report-is-the-output", lambda w, p: ["preprocess", "--source", "synthetic", "--num-clips", 8, "-o",
                                               w / "d.h5", "--report", w / "d.h5"], 1, "is also the output"),
    Case("report-is-the-registry", lambda w, p: ["preprocess", "--source", "synthetic", "--num-clips", 8, "-o",
                                                 w / "a.h5", "--report", w / ".lsgan-outputs.json"], 1, "registry"),
    Case("report-is-the-staging", lambda w, p: ["preprocess", "--source", "synthetic", "--num-clips", 8, "-o",
                                                w / "b.h5", "--report", w / "b.h5.parts"], 1, "is also the output"),
    Case("report-inside-staging", lambda w, p: ["preprocess", "--source", "synthetic", "--num-clips", 8, "-o",
                                                w / "c.h5", "--report", w / "c.h5.parts" / "r.json"], 1,
         "is also the output"),
    Case("report-onto-a-shard", lambda w, p: ["preprocess", "--source", "synthetic", "--num-clips", 8, "-o",
                                              w / "b.h5", "--report", p / "synth.h5"], 1, "pass --force"),
    Case("evaluate-into-its-run", lambda w, p: ["evaluate", "--gan", p / "gan", "--vae", p / "vae", "--data",
                                                p / "synth.h5", "-o", p / "gan" / "metrics"], 1,
         "lies inside the input folder"),
    Case("bench-json-into-its-run", lambda w, p: ["bench", "--gan", p / "gan", "--json", p / "gan" / "x.json"], 1,
         "lies inside the input folder"),
    Case("texts-output-inside", lambda w, p: ["preprocess", "--source", "joints",
                                              joints_dir(w, {"a.npy": good_joints()[0]}), "--texts",
                                              user_run_folder(w, {"a.txt": "a person walks#0.0#0.0"}), "-o",
                                              w / "run" / "x.h5"], 1, "lies inside the input folder"),
    Case("unknown-command", lambda w, p: ["fly"], 2, "no such command"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case: Case, pipe: Path, tmp_path: Path) -> None:
    w = tmp_path / "w"
    w.mkdir()
    with small_disk(w / "full", case.disk) if case.disk else contextlib.nullcontext((None, "")) as (limit, words):
        args = case.args(w, pipe)
        before = snapshot(w, pipe)
        out = forked_lsgan(*args, cwd=w, preexec_fn=limit)
        after = snapshot(w, pipe)
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert out.returncode == case.code, out.stderr
    assert len(errors) == 1, out.stderr
    assert out.stderr.rstrip().splitlines()[-1] == errors[0], f"the error runs over one line:\n{out.stderr}"
    assert case.phrase.lower() in errors[0].lower(), out.stderr
    assert words in errors[0], out.stderr
    assert "Traceback" not in out.stderr and "Warning:" not in out.stderr, out.stderr
    assert not list(w.rglob("PWNED")), "a crafted pickle ran code"
    changed = [str(p) for p, h in before.items() if after.get(p) != h]
    assert not changed, f"pre-existing files changed or removed: {changed}"


def test_all_failed_inputs_are_reported_by_reason(tmp_path: Path) -> None:
    """When every input fails, the reasons are printed grouped and the JSON report is written anyway."""
    d = joints_dir(tmp_path, {**{f"z{i}.npy": b"junk" for i in range(5)}, "short.npy": good_joints()[0][:3]})
    out = lsgan("preprocess", "--source", "joints", d, "-o", tmp_path / "out.h5", cwd=tmp_path)
    assert out.returncode == 1
    assert "5 files: " in out.stderr and "(e.g. z0.npy, z1.npy, z2.npy, ...)" in out.stderr
    assert "1 file: too short" in out.stderr
    report = json.loads((tmp_path / "out.h5.report.json").read_text())
    assert report["clips"] == 0 and len(report["skipped"]) == 6
    assert [g["count"] for g in report["skipped_by_reason"]] == [5, 1]
    assert not (tmp_path / "out.h5").exists() and not (tmp_path / "out.h5.parts").exists()


def test_force_replaces_only_lsgan_files(pipe: Path, tmp_path: Path) -> None:
    """generate --force into an earlier run's folder clears that run's files and keeps the user's; a new motion
    whose file name is the user's is refused before anything of the new run is written."""
    out = tmp_path / "gen"
    assert lsgan(*generate_args(pipe, out, "--num", 3), cwd=tmp_path).returncode == 0
    (out / "my_edit_joints.txt").write_text("mine")
    edited = sorted(out.glob("*_joints.npy"))[0]
    edited.write_bytes(edited.read_bytes() + b"\0")  # the user changed it: it is theirs now
    res = lsgan(*generate_args(pipe, out, "--num", 1, "--force"), cwd=tmp_path)
    assert res.returncode == 1 and "not a file lsgan wrote" in res.stderr  # same name as a new motion: refused
    assert len(list(out.glob("*.npy"))) == 6 and (out / "manifest.json").exists()  # refused before anything changed
    edited.unlink()
    res = lsgan(*generate_args(pipe, out, "--num", 1, "--force"), cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (out / "my_edit_joints.txt").read_text() == "mine"
    assert len(list(out.glob("*_joints.npy"))) == 1
    assert json.loads((out / "manifest.json").read_text())["motions"][0]["index"] == 0


def test_debug_shows_the_traceback(tmp_path: Path) -> None:
    args = ["inspect", text_file(tmp_path, "s.h5")]
    assert "Traceback" not in lsgan(*args, cwd=tmp_path).stderr
    assert "Traceback" in lsgan(*args, cwd=tmp_path, env={"LSGAN_DEBUG": "1"}).stderr
    assert "Traceback" in lsgan("--debug", *args, cwd=tmp_path).stderr


def test_bvh_gz_inputs_still_import(tmp_path: Path) -> None:
    """A control for the rows above: the same real BVH files import when intact (also gzip-compressed)."""
    d = bvh_folder(tmp_path)
    for p in list(d.glob("*.bvh"))[:1]:
        (d / (p.name + ".gz")).write_bytes(gzip.compress(p.read_bytes()))
        p.unlink()
    out = lsgan("preprocess", "--source", "bvh", "--joint-map", tmp_path / "map.json", d, "-o", tmp_path / "o.h5",
                "--no-mirror", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "3 clips" in out.stderr


@pytest.mark.parametrize("change, cause", [({"up": "z"}, "wrong `up`"), ({"scale": 1.0}, "wrong `scale`")])
def test_implausible_imports_are_warned_by_name(tmp_path: Path, change: dict, cause: str) -> None:
    """A joint map with the wrong up axis or units imports, but every clip is named with the likely cause."""
    d = bvh_folder(tmp_path)
    (tmp_path / "map.json").write_text(json.dumps({**IDENTITY_MAP, **change}))
    out = lsgan("preprocess", "--source", "bvh", "--joint-map", tmp_path / "map.json", d, "-o", tmp_path / "o.h5",
                cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    warned = [line for line in out.stderr.splitlines() if line.strip().startswith("warning:")]
    assert len(warned) == 3 and all(cause in line for line in warned), out.stderr
    assert sorted(line.split()[1].rstrip(":") for line in warned) == ["clip0", "clip1", "clip2"]
    report = json.loads((tmp_path / "o.h5.report.json").read_text())
    assert report["plausibility"]["flagged"] == 3


def test_plausible_imports_are_not_warned(tmp_path: Path) -> None:
    d = bvh_folder(tmp_path)
    out = lsgan("preprocess", "--source", "bvh", "--joint-map", tmp_path / "map.json", d, "-o", tmp_path / "o.h5",
                cwd=tmp_path)
    assert out.returncode == 0 and "warning:" not in out.stderr, out.stderr
    assert "3 clips checked, 0 flagged" in out.stderr


def test_staging_cleanup_keeps_files_lsgan_did_not_write(tmp_path: Path) -> None:
    """A file the user put in OUTPUT.parts/ (even named like a chunk) survives the resumed run's clean-up."""
    from lsgan.data.preprocess import preprocess
    from lsgan.data.sources.synthetic import SyntheticSource

    def stop(done, total):
        if done >= 16:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        preprocess(SyntheticSource(num_clips=40), tmp_path / "s.h5", on_progress=stop)
    mine = tmp_path / "s.h5.parts" / "chunk_mine.npz"
    mine.write_bytes(b"the user's own file")
    preprocess(SyntheticSource(num_clips=40), tmp_path / "s.h5", resume=True)
    assert mine.read_bytes() == b"the user's own file"
    assert sorted(p.name for p in mine.parent.iterdir()) == [".lsgan-outputs.json", "chunk_mine.npz"]  # ours gone
    assert json.loads((mine.parent / ".lsgan-outputs.json").read_text())["entries"] == {}  # the folder's id only


def test_force_keeps_a_last_folder_lsgan_did_not_write(tmp_path: Path) -> None:
    """--force on a training folder removes only lsgan's checkpoints: a user's own last/ is refused."""
    from lsgan.outputs import OutputError
    from lsgan.train.common import claim_run

    (tmp_path / "run" / "last").mkdir(parents=True)
    (tmp_path / "run" / "last" / "notes.txt").write_text("mine")
    (tmp_path / "run" / "log.csv").write_text("step\n")
    with pytest.raises(OutputError, match="last: is not what lsgan wrote"):
        claim_run(tmp_path / "run", resume=False, force=True)
    assert (tmp_path / "run" / "last" / "notes.txt").read_text() == "mine"
    assert (tmp_path / "run" / "log.csv").exists()
