"""Recipes: YAML files that name every hyperparameter of a run, read into the config dataclasses.

Sections: ``text_encoder`` (a name), ``vae``, ``gan`` and ``diffusion`` (each ``model:`` and ``train:``, read by
train-vae, train-gan and train-diffusion into VAEConfig/VAETrainConfig, GANConfig/GANTrainConfig and
DiffusionConfig/DiffusionTrainConfig), ``evaluator``. ``build`` refuses keys a dataclass does not have.
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, TypeVar

import yaml

from lsgan.errors import reading

T = TypeVar("T")
U = TypeVar("U")
RECIPES = Path(__file__).resolve().parents[1] / "recipes"


class Recipe(dict):
    """A recipe's sections, and the file they came from (``source``), which every error about them names."""

    source: str = ""


def load_recipe(path: str | os.PathLike) -> dict[str, Any]:
    """A recipe as a dict of sections (a :class:`Recipe`). A bare name ('demo') is looked up in the project's
    ``recipes/``."""
    p = Path(path)
    if not p.is_file() and not p.suffix and (RECIPES / f"{p}.yaml").exists():  # a folder named 'demo' is no recipe
        p = RECIPES / f"{p}.yaml"
    if not p.is_file():
        raise FileNotFoundError(f"recipe {path} not found (give a YAML file, or a name from {RECIPES})")
    with reading(p, "a recipe (YAML text)", also=(yaml.YAMLError,)):
        data = yaml.safe_load(p.read_text(encoding="utf-8")) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{p}: a recipe is a mapping of sections (vae:, gan:, diffusion:, ...)")
    recipe = Recipe(data)
    recipe.source = str(p)
    return recipe


def build(cls: type[T], values: dict[str, Any] | None, where: str = "") -> T:
    """A dataclass from a dict; unknown keys are an error naming the allowed ones."""
    values = dict(values or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"{where or cls.__name__}: unknown key(s) {unknown}; allowed: {sorted(names)}")
    for f in dataclasses.fields(cls):
        if f.name in values and not _fits(values[f.name], f.type):
            raise ValueError(f"recipe key {where or cls.__name__}.{f.name}: {values[f.name]!r} is not "
                             f"{_KINDS.get(str(f.type), f.type)}")
    try:
        return cls(**values)
    except ValueError as e:  # a dataclass's own check: say which section it is
        raise ValueError(f"{where or cls.__name__}: {e}") from None


_KINDS = {"int": "a whole number", "float": "a number", "bool": "true or false", "str": "text"}


def _fits(value: Any, annotation: Any) -> bool:
    """Whether a recipe value fits its field's plain annotation (int, float, bool, str); others are not checked."""
    kind = str(getattr(annotation, "__name__", annotation))
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    return {"int": isinstance(value, int) and not isinstance(value, bool), "float": number,
            "bool": isinstance(value, bool), "str": isinstance(value, str)}.get(kind, True)

def section(recipe: dict[str, Any], name: str) -> dict[str, Any]:
    value = recipe.get(name) or {}
    if not isinstance(value, dict):
        where = f"{recipe.source}: " if getattr(recipe, "source", "") else ""
        raise ValueError(f"{where}recipe section {name!r} must be a mapping")
    return value


def configs(recipe: dict[str, Any], kind: str, model_cls: type[T], train_cls: type[U],
            model_overrides: dict[str, Any] | None = None,
            train_overrides: dict[str, Any] | None = None, where: str | None = None) -> tuple[T, U]:
    """The recipe's ``kind:`` section as (model config, train config), each override that is not None replacing
    the recipe's value: what every training command builds from a recipe and its options. ``where``: the
    section's name in error messages (default ``kind``)."""
    r, where = section(recipe, kind), where or kind
    if getattr(recipe, "source", ""):
        where = f"{recipe.source}: {where}"
    given = lambda values: {k: v for k, v in (values or {}).items() if v is not None}  # noqa: E731
    return (build(model_cls, {**section(r, "model"), **given(model_overrides)}, f"{where}.model"),
            build(train_cls, {**section(r, "train"), **given(train_overrides)}, f"{where}.train"))
