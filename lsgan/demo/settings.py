"""The demo's size: ``scale`` (default ``$LSGAN_DEMO_SCALE``, else 1) applied to the recipe's step counts and its
``demo:`` section, with floors that keep each stage meaningful."""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

SCALE_ENV = "LSGAN_DEMO_SCALE"
MAX_SCALE = 100
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

    def __post_init__(self) -> None:  # numbers: lsgan.recipes.BOUNDS
        if self.clips < MIN_CLIPS:
            raise ValueError(f"clips must be at least {MIN_CLIPS} (the test split must hold 32 windows for "
                             f"R-precision), not {self.clips}")
        if not 1 <= len(self.prompts) <= 100 or any(not p.strip() or len(p) > 500 or not p.isprintable()
                                                    for p in self.prompts):
            raise ValueError("prompts must be a list of 1 to 100 sentences of printable text, each at most 500 "
                             "characters")


def scale_from_env(value: str | None = None) -> float:
    """The demo scale: ``value`` or ``$LSGAN_DEMO_SCALE`` (a number > 0), else 1."""
    raw = os.environ.get(SCALE_ENV) if value is None else value
    if raw is None or str(raw).strip() == "":
        return 1.0
    try:
        scale = float(raw)
    except ValueError:
        raise ValueError(f"{SCALE_ENV} must be a number > 0 (e.g. 0.05), not {raw!r}") from None
    if not (math.isfinite(scale) and 0 < scale <= MAX_SCALE):
        raise ValueError(f"the demo scale must be a number > 0 and at most {MAX_SCALE} (e.g. 0.05), not {raw!r}")
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


def _trained(recipe: dict) -> tuple[int, dict[str, int]]:
    """Every config the demo trains, built from the recipe now so that a bad value is refused before any stage
    runs: the VAE's longest motion and each training's ``max_steps``."""
    from lsgan.models.evaluator import EvaluatorConfig
    from lsgan.models.gan import GANConfig
    from lsgan.models.vae import VAEConfig
    from lsgan.recipes import configs, section
    from lsgan.train.evaluator import EvaluatorTrainConfig
    from lsgan.train.gan import GANTrainConfig
    from lsgan.train.vae import VAETrainConfig

    vae, vae_train = configs(recipe, "vae", VAEConfig, VAETrainConfig)
    gan_train = configs(recipe, "gan", GANConfig, GANTrainConfig)[1]
    evaluator_train = configs(section(recipe, "evaluator"), "text", EvaluatorConfig, EvaluatorTrainConfig)[1]
    return vae.max_len, {"vae": vae_train.max_steps, "gan": gan_train.max_steps,
                         "evaluator": evaluator_train.max_steps}


def demo_settings(scale: float | None = None, recipe: str | os.PathLike = "demo") -> DemoSettings:
    """The settings at ``scale`` from the recipe (its vae/gan/evaluator step counts and its ``demo:`` section)."""
    from lsgan.recipes import build, load_recipe, section

    scale = scale_from_env() if scale is None else scale_from_env(str(scale))
    r = load_recipe(recipe)
    d = build(DemoSection, section(r, "demo"), f"{r.source}: demo")
    if r.get("text_encoder") == "none":
        raise ValueError(f"{r.source}: text_encoder is none, but the demo trains a text-to-motion GAN")
    longest, steps = _trained(r)
    if d.frames > longest:
        raise ValueError(f"{r.source}: demo: frames {d.frames} is more than the VAE decodes (vae.model.max_len "
                         f"{longest})")
    return DemoSettings(
        scale=scale, clips=_scaled(d.clips, scale, MIN_CLIPS), seed=d.seed,
        vae_steps=_scaled(steps["vae"], scale, 10), gan_steps=_scaled(steps["gan"], scale, 20),
        evaluator_steps=_scaled(steps["evaluator"], scale, 10),
        replications=_scaled(d.replications, scale, 1),
        mm_captions=_scaled(d.mm_captions, scale, 4), mm_samples=_scaled(d.mm_samples, scale, 4),
        frames=d.frames, prompts=tuple(d.prompts), recipe=os.fspath(recipe),
    )
