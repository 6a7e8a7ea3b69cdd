"""Which stages are done: a marker per finished stage in ``OUT/.stages/``, naming the markers of the stages it was
built from, so a stage is reused only when everything it was made from is still the same."""
from __future__ import annotations

import json
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from lsgan.io import atomic_file

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


class StageMarkers:
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


@dataclass
class StageRecord:
    """One stage of a run: seconds it took when it was done, and what this run did with it."""

    name: str
    index: int
    seconds: float
    status: str  # "ran", "resumed" (an interrupted training continued), or "reused" (done by an earlier run)
    output: str
