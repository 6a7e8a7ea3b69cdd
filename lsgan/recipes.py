"""Recipes: YAML files that name every hyperparameter of a run, read into the config dataclasses.

Sections: ``text_encoder`` (a name), ``vae``, ``gan`` and ``diffusion`` (each ``model:`` and ``train:``, read by
train-vae, train-gan and train-diffusion into VAEConfig/VAETrainConfig, GANConfig/GANTrainConfig and
DiffusionConfig/DiffusionTrainConfig), ``evaluator`` and ``demo``. Every other section, a key beside ``model:`` and
``train:``, a key a dataclass does not have and a key given twice are refused, so no misspelt name trains on a default.
"""
from __future__ import annotations

import dataclasses
import math
import os
import reprlib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from lsgan.errors import reading

T = TypeVar("T")
U = TypeVar("U")
RECIPES = Path(__file__).resolve().parents[1] / "recipes"
SECTIONS = ("text_encoder", "vae", "gan", "diffusion", "evaluator", "demo")
TEXT_ENCODERS = ("minilm", "clip-vit-l-14")  # lsgan.models.text's names (a helper imports no layer; a test compares)


class _Loader(yaml.SafeLoader):
    """YAML's safe loader that refuses a key given twice in one mapping (PyYAML would keep the last silently)."""


def _mapping(loader: _Loader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen = set()
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":  # << merges another mapping; its keys may be overridden
            continue
        key = loader.construct_object(key_node, deep=True)
        if isinstance(key, (str, int, float, bool)):  # other keys are refused by construct_mapping or the sections
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"the key {_SHORT.repr(key)} is given twice",
                                                        key_node.start_mark)
            seen.add(key)
    return loader.construct_mapping(node, deep)


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping)
_SHORT = reprlib.Repr()  # values in error lines: a few items, levels and characters
_SHORT.maxlevel, _SHORT.maxlist, _SHORT.maxdict, _SHORT.maxstring, _SHORT.maxother, _SHORT.maxlong = 2, 4, 4, 60, 60, 40


class Recipe(dict):
    """A recipe's sections (or one section's keys), the file they came from (``source``) and the section's dotted
    name (``name``), which every error about them names."""

    source: str = ""
    name: str = ""


def load_recipe(path: str | os.PathLike) -> dict[str, Any]:
    """A recipe as a dict of sections (a :class:`Recipe`). A bare name ('demo') is looked up in the project's
    ``recipes/``."""
    p = Path(path)
    if not p.is_file() and not p.suffix and (RECIPES / f"{p}.yaml").exists():  # a folder named 'demo' is no recipe
        p = RECIPES / f"{p}.yaml"
    if not p.is_file():
        raise FileNotFoundError(f"recipe {path} not found (give a YAML file, or a name from {RECIPES})")
    with reading(p, "a recipe (YAML text)", also=(yaml.YAMLError,)):
        data = yaml.load(p.read_text(encoding="utf-8"), Loader=_Loader) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{p}: a recipe is a mapping of sections (vae:, gan:, diffusion:, ...)")
    unknown = sorted(map(str, set(data) - set(SECTIONS)))
    if unknown:  # a misspelt section would train on the defaults
        raise ValueError(f"{p}: unknown section(s) {_SHORT.repr(unknown)}; a recipe has {', '.join(SECTIONS)}")
    encoder = data.get("text_encoder")
    if encoder is not None:  # read as a name by train, encode and demo commands
        names = (*TEXT_ENCODERS, "none")
        if encoder not in names:
            raise ValueError(f"{p}: text_encoder is one of {', '.join(names)}, not {_SHORT.repr(encoder)}")
    recipe = Recipe(data)
    recipe.source = str(p)
    return recipe


class Bounds(typing.NamedTuple):
    """The values a numeric setting may take: ``low`` (excluded when ``open_low``) to ``high``."""

    low: float
    high: float
    open_low: bool = False

    def holds(self, value: float) -> bool:
        return (self.low < value if self.open_low else self.low <= value) and value <= self.high

    def __str__(self) -> str:
        def number(v: float) -> str:
            return f"{int(v):,}" if isinstance(v, int) or (v == int(v) and abs(v) < 1e16) else f"{v:g}"

        return f"{'above' if self.open_low else 'from'} {number(self.low)} to {number(self.high)}"


_STEPS, _WIDTH, _FRAMES, _WEIGHT = Bounds(1, 1e9), Bounds(1, 65536), Bounds(1, 100_000), Bounds(0, 1e6)
BOUNDS: dict[str, Bounds] = {
    # how many: steps, intervals, draws, batches
    **dict.fromkeys(("max_steps", "val_every", "ckpt_every", "log_every", "eval_every", "eval_repeats", "eval_steps",
                     "sample_steps", "train_timesteps", "critic_steps", "group_size", "batch_size",
                     "clips", "replications", "mm_captions", "mm_samples"), _STEPS),
    **dict.fromkeys(("warmup_steps", "val_batches"), Bounds(0, 1e9)),
    "fid_samples": Bounds(2, 1e9),  # a covariance needs two
    # sizes of the networks
    **dict.fromkeys(("latent_dim", "d_model", "ff_size", "hidden_dim", "hidden_size", "noise_dim", "action_emb_dim",
                     "movement_hidden", "movement_latent", "motion_hidden", "embed_dim", "text_hidden", "feature_dim"),
                    _WIDTH),
    "nfeats": Bounds(263, 263),  # the HumanML3D features every shard holds
    "num_joints": Bounds(22, 22),  # their skeleton's joints
    **dict.fromkeys(("cond_dim", "num_actions", "num_classes"), Bounds(0, 65536)),
    **dict.fromkeys(("num_layers", "num_heads"), Bounds(1, 1024)),
    "num_res_blocks": Bounds(0, 1024),
    "smooth_output": Bounds(0, 8),
    "time_tokens": Bounds(0, 1024),
    # lengths in frames
    **dict.fromkeys(("min_frames", "max_frames", "max_len", "max_motion_length", "frames"), _FRAMES),
    "unit_length": Bounds(1, 1000),
    # the rest
    "seed": Bounds(0, 2**63 - 1),
    "num_workers": Bounds(0, 256),
    "lr": Bounds(0, 10, open_low=True),
    **dict.fromkeys(("weight_decay", "grad_clip", "margin", "gp_weight", "kl_weight", "joint_weight",
                     "velocity_weight", "accel_weight", "bone_weight", "contact_weight"), _WEIGHT),
    **dict.fromkeys(("dropout", "cond_mask_prob", "leaky_slope", "eta"), Bounds(0, 1)),
    **dict.fromkeys(("beta_start", "beta_end"), Bounds(0, 1, open_low=True)),
    "betas": Bounds(0, 0.999999),
    **dict.fromkeys(("guidance_scale", "eval_guidance"), Bounds(0, 1000)),
}
"""Every numeric setting of a recipe, by name (the same name means the same thing in every section); a test fails
when a config gains a numeric field that is not here, so no setting reaches training unchecked."""


def numbers(value: Any) -> list[float]:
    """The numbers in a recipe value (a number, a list of them, or none)."""
    items = value if isinstance(value, (list, tuple)) else [value]
    return [v for v in items if isinstance(v, (int, float)) and not isinstance(v, bool)]


def build(cls: type[T], values: dict[str, Any] | None, where: str = "") -> T:
    """A dataclass from a dict; unknown keys, values that do not fit a field's annotation and numbers outside the
    setting's :data:`BOUNDS` are an error naming the section and the key (command-line overrides are ranged by
    click from the same table, :func:`lsgan.cli.options.setting`)."""
    values = dict(values or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(map(str, set(values) - names))
    if unknown:
        raise ValueError(f"{where or cls.__name__}: unknown key(s) {_SHORT.repr(unknown)}; allowed: {sorted(names)}")
    hints = typing.get_type_hints(cls)
    for name, value in values.items():
        key = f"recipe key {where or cls.__name__}.{name}"
        if not fits(value, hints[name]):
            raise ValueError(f"{key}: {_SHORT.repr(value)} is not {kind(hints[name])}{_exponent_hint(value)}")
        bounds = BOUNDS.get(name)
        if bounds is not None and not all(map(bounds.holds, numbers(value))):
            raise ValueError(f"{key}: {_SHORT.repr(value)} is not "
                             f"{'each ' if isinstance(value, (list, tuple)) else ''}{bounds}")
    try:
        return cls(**values)
    except ValueError as e:  # a dataclass's own check: say which section it is
        raise ValueError(f"{where or cls.__name__}: {e}") from None


def fits(value: Any, annotation: Any) -> bool:
    """Whether a recipe value fits a config field's annotation: int, float (a finite number; an int is one too),
    bool, str, None, a union of these, or a fixed-length tuple of them (a YAML list). Any other annotation raises
    TypeError, so a config field of a new kind cannot go unchecked (tests build every config's annotations)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        return any(fits(value, a) for a in args)
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        return isinstance(value, (list, tuple)) and all(fits(v, args[0]) for v in value)
    if origin is tuple and args and Ellipsis not in args:
        return isinstance(value, (list, tuple)) and len(value) == len(args) and all(map(fits, value, args))
    if annotation is type(None):
        return value is None
    if annotation is bool or annotation is str:
        return isinstance(value, annotation)
    if annotation is int or annotation is float:
        number = isinstance(value, (int, float)) and not isinstance(value, bool) and _finite(value)
        return number and (annotation is float or isinstance(value, int))
    raise TypeError(f"a recipe cannot check a value against {annotation!r}")


def kind(annotation: Any) -> str:
    """An annotation in words, for error lines ('a whole number or null')."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(map(kind, args))
    if origin is tuple and args[-1] is Ellipsis:
        return f"a list of {kind(args[0]).removeprefix('a ')}"
    if origin is tuple:
        return f"a list of {len(args)} ({', '.join(kind(a).removeprefix('a ') for a in args)})"
    return _KINDS[annotation]


_KINDS = {int: "a whole number", float: "a finite number", bool: "true or false", str: "text", type(None): "null"}


def _exponent_hint(value: Any) -> str:
    """YAML 1.1 (PyYAML) reads 2e-1 as text; say how to write it as a number."""
    if not (isinstance(value, str) and "e" in value.lower() and len(value) < 40):
        return ""
    try:
        float(value)
    except ValueError:
        return ""
    return " (YAML reads exponents without a point and a sign as text: write 2.0e-1, 1.0e+3)"


def _finite(value: int | float) -> bool:
    """Whether a float holds the number and it is not inf or NaN (a 400-digit integer is refused)."""
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def section(recipe: dict[str, Any], name: str, keys: tuple[str, ...] = ()) -> Recipe:
    """The recipe's section ``name`` ({} when absent or empty), refused unless it is a mapping holding only ``keys``
    (any key when none are given); errors name the file and the section's dotted name."""
    source, dotted = getattr(recipe, "source", ""), ".".join(filter(None, (getattr(recipe, "name", ""), name)))
    where = f"{source}: " if source else ""
    value = recipe.get(name)
    if value is None:
        value = {}
    if not isinstance(value, dict):
        raise ValueError(f"{where}{dotted} must be a mapping (key: value lines), not {_SHORT.repr(value)}")
    unknown = sorted(map(str, set(value) - set(keys))) if keys else []
    if unknown:
        raise ValueError(f"{where}{dotted}: unknown key(s) {_SHORT.repr(unknown)}; it holds {', '.join(keys)}")
    out = Recipe(value)
    out.source, out.name = source, dotted
    return out


def configs(recipe: dict[str, Any], kind: str, model_cls: type[T], train_cls: type[U],
            model_overrides: dict[str, Any] | None = None,
            train_overrides: dict[str, Any] | None = None, where: str | None = None) -> tuple[T, U]:
    """The recipe's ``kind:`` section as (model config, train config), each override that is not None replacing
    the recipe's value: what every training command builds from a recipe and its options. A train config with an
    ``against(model)`` method checks there the settings that depend on the model's (window lengths against the
    position code), so those errors name the file too. ``where``: the section's name in error messages (default
    ``kind``)."""
    r = section(recipe, kind, ("model", "train"))
    where = where or r.name
    if r.source:
        where = f"{r.source}: {where}"
    given = lambda values: {k: v for k, v in (values or {}).items() if v is not None}  # noqa: E731
    models, trains = given(model_overrides), given(train_overrides)
    model = build(model_cls, {**section(r, "model"), **models}, f"{where}.model")
    train = build(train_cls, {**section(r, "train"), **trains}, f"{where}.train")
    against = getattr(train, "against", None)
    try:
        if against is not None:
            against(model)
    except ValueError as e:  # a setting that does not fit the model's: say which section
        raise ValueError(f"{where}: {e}") from None
    return model, train
