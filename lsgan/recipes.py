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

T = TypeVar("T")
RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def load_recipe(path: str | os.PathLike) -> dict[str, Any]:
    """A recipe as a dict of sections. A bare name ('demo') is looked up in the project's ``recipes/``."""
    p = Path(path)
    if not p.is_file() and not p.suffix and (RECIPES / f"{p}.yaml").exists():  # a folder named 'demo' is no recipe
        p = RECIPES / f"{p}.yaml"
    if not p.is_file():
        raise FileNotFoundError(f"recipe {path} not found (give a YAML file, or a name from {RECIPES})")
    data = yaml.safe_load(p.read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{p}: a recipe is a mapping of sections (vae:, gan:, diffusion:, ...)")
    return data


def build(cls: type[T], values: dict[str, Any] | None, where: str = "") -> T:
    """A dataclass from a dict; unknown keys are an error naming the allowed ones."""
    values = dict(values or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"{where or cls.__name__}: unknown key(s) {unknown}; allowed: {sorted(names)}")
    return cls(**values)


def section(recipe: dict[str, Any], name: str) -> dict[str, Any]:
    value = recipe.get(name) or {}
    if not isinstance(value, dict):
        raise ValueError(f"recipe section {name!r} must be a mapping")
    return value
