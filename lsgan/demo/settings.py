"""The demo's size: ``scale`` (default ``$LSGAN_DEMO_SCALE``, else 1) applied to the recipe's step counts and its
``demo:`` section, with floors that keep each stage meaningful."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

SCALE_ENV = "LSGAN_DEMO_SCALE"
MIN_CLIPS = 400  # the hash split gives 42 test windows: R-precision needs groups of 32
DEFAULT_DEMO = {
    "clips": 800, "seed": 0, "frames": 120, "replications": 3, "mm_captions": 20, "mm_samples": 10,
    "prompts": ["a person walks forward", "a person runs forward", "a person waves their right hand",
                "a person jumps up", "a person does a squat"],
}


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
