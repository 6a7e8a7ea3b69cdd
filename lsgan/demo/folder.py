"""The demo's folder is its own: a folder made at other settings is refused, ``fresh`` removes only the demo's files,
and a training run folder is kept to resume only when it was started on the same inputs."""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from lsgan import __version__, outputs
from lsgan.demo.settings import DemoSettings
from lsgan.io import atomic_file

# What the demo's folder holds (``fresh`` removes exactly these, nothing else of a folder).
CONTENTS = ("demo.json", ".stages", "data", "runs", "metrics.json", "metrics.md", "motions", "glb", "gif",
            "summary.json")


def prepare_run_folder(run: Path, inputs: dict) -> bool:
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


def check_folder(out: Path, settings: DemoSettings, fresh: bool) -> None:
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
