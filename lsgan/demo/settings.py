"""The demo's size: ``scale`` (default ``$LSGAN_DEMO_SCALE``, else 1) applied to the recipe's step counts and its
``demo:`` section, with floors that keep each stage meaningful."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields

SCALE_ENV = "LSGAN_DEMO_SCALE"
MIN_CLIPS = 400  # the hash split gives 42 test windows: R-precision needs groups of 32


@dataclass(frozen=True)
class DemoSection:
    """A recipe's ``demo:`` section: what the demo does besides the vae/gan/evaluator sections."""

    clips: int = 800  # synthetic clips
    seed: int = 0
    frames: int = 120  # length of each generated motion
    replications: int = 3  # of the T2M evaluation (the protocol: 20)
    mm_captions: int = 20  # MultiModality: captions x motions per caption (the protocol: 100 x 30)
    mm_samples: int = 10
    prompts: tuple[str, ...] = ("a person walks forward", "a person runs forward", "a person waves their right hand",
                                "a person jumps up", "a person does a squat")

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "seed" and not 0 <= value < 2**63:
                raise ValueError(f"seed must be from 0 to 2**63 - 1, not {value}")
            if f.name not in ("seed", "prompts") and not 1 <= value <= LIMITS[f.name]:
                raise ValueError(f"{f.name} must be a whole number from 1 to {LIMITS[f.name]}, not {value}")
        if not self.prompts or any(not p.strip() for p in self.prompts):
            raise ValueError("prompts must be a list of non-empty sentences")


LIMITS = {"clips": 1_000_000, "frames": 10_000, "replications": 1_000, "mm_captions": 10_000, "mm_samples": 1_000}


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


def _steps(recipe: dict, names: tuple[str, ...], default: int) -> int:
    """``max_steps`` of the recipe's section ``names`` (default when absent), refused unless a whole number >= 1."""
    from lsgan.recipes import fits, section

    for name in names:
        recipe = section(recipe, name)
    steps = recipe.get("max_steps", default)
    if not (fits(steps, int) and steps >= 1):
        raise ValueError(f"{recipe.source}: {recipe.name}.max_steps must be a whole number >= 1, not {steps!r}")
    return steps


def demo_settings(scale: float | None = None, recipe: str | os.PathLike = "demo") -> DemoSettings:
    """The settings at ``scale`` from the recipe (its vae/gan/evaluator step counts and its ``demo:`` section)."""
    from lsgan.recipes import build, fits, load_recipe, section

    scale = scale_from_env() if scale is None else scale_from_env(str(scale))
    r = load_recipe(recipe)
    d = build(DemoSection, section(r, "demo"), f"{r.source}: demo")
    longest = section(section(r, "vae"), "model").get("max_len", 1024)  # VAEConfig's default
    if fits(longest, int) and d.frames > longest:
        raise ValueError(f"{r.source}: demo: frames {d.frames} is more than the VAE decodes (vae.model.max_len "
                         f"{longest})")
    steps = {"vae": _steps(r, ("vae", "train"), 300), "gan": _steps(r, ("gan", "train"), 1500),
             "evaluator": _steps(r, ("evaluator", "text", "train"), 200)}
    return DemoSettings(
        scale=scale, clips=_scaled(d.clips, scale, min(MIN_CLIPS, d.clips)), seed=d.seed,
        vae_steps=_scaled(steps["vae"], scale, 10), gan_steps=_scaled(steps["gan"], scale, 20),
        evaluator_steps=_scaled(steps["evaluator"], scale, 10),
        replications=_scaled(d.replications, scale, 1),
        mm_captions=_scaled(d.mm_captions, scale, 4), mm_samples=_scaled(d.mm_samples, scale, 4),
        frames=d.frames, prompts=tuple(d.prompts), recipe=os.fspath(recipe),
    )
