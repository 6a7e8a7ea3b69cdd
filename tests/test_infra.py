"""Checkpoints, recipes, the latent cache format and the Fréchet distance."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
import torch

from lsgan.eval.metrics import fid
from lsgan.models.cache import StaleCache, read_latent_cache, write_latent_cache
from lsgan.models.checkpoint import load_state, load_weights, resolve, save_checkpoint, weights_hash
from lsgan.recipes import build, load_recipe
from lsgan.train.common import RunLog, TrainingDiverged, check_finite


def test_checkpoint_round_trip_is_exact_and_atomic(tmp_path):
    model = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.GELU(), torch.nn.Linear(8, 2))
    opt = torch.optim.AdamW(model.parameters())
    model(torch.randn(3, 4)).sum().backward()
    opt.step()
    save_checkpoint(tmp_path / "run" / "last", model=model, kind="toy", config={"w": 8}, step=7,
                    state={"optimizer": opt.state_dict(), "rng": torch.get_rng_state()})
    weights, meta = load_weights(tmp_path / "run", kind="toy")
    for k, v in model.state_dict().items():
        assert torch.equal(weights[k], v)
    assert meta["step"] == 7 and meta["config"] == {"w": 8}
    assert resolve(tmp_path / "run").name == "last"
    state = load_state(tmp_path / "run")
    assert state["optimizer"]["state"][0]["step"].item() == 1
    with pytest.raises(ValueError, match="not a 'vae'"):
        load_weights(tmp_path / "run", kind="vae")
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        resolve(tmp_path)
    h = weights_hash(tmp_path / "run")
    save_checkpoint(tmp_path / "run" / "last", model=model, kind="toy", config={}, step=8)
    assert weights_hash(tmp_path / "run") == h  # same weights, same hash
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [".lsgan-outputs.json", "last"]


def test_a_checkpoint_of_the_same_model_is_the_same_bytes(tmp_path):
    """Identical runs write identical files (safetensors orders a metadata mapping at random: ours has one key)."""
    model = torch.nn.Linear(3, 2)
    digests = set()
    for i in range(12):
        folder = save_checkpoint(tmp_path / f"c{i}", model=model, kind="toy", config={"b": 1, "a": 2}, step=3,
                                 state={"rng": torch.zeros(4, dtype=torch.uint8), "step": 3})
        digests.add(tuple((folder / name).read_bytes() for name in ("model.safetensors", "config.json", "state.pt")))
    assert len(digests) == 1


def test_recipes_build_dataclasses_and_refuse_unknown_keys(tmp_path):
    from dataclasses import dataclass

    @dataclass
    class Cfg:
        a: int = 1
        b: float = 2.0

    (tmp_path / "r.yaml").write_text("vae:\n  a: 3\n")
    recipe = load_recipe(tmp_path / "r.yaml")
    assert build(Cfg, recipe["vae"]).a == 3
    with pytest.raises(ValueError, match="unknown key"):
        build(Cfg, {"c": 1})
    with pytest.raises(FileNotFoundError):
        load_recipe(tmp_path / "missing.yaml")


def test_recipes_take_yaml_merges_and_refuse_a_key_given_twice(tmp_path):
    """A ``<<`` merge may be overridden (YAML's rule), but a mapping's own keys may not repeat."""
    base = "gan:\n  train: &t {lr: 1.0e-3, max_steps: 5}\nvae:\n  train: {<<: *t, max_steps: 7"
    (tmp_path / "r.yaml").write_text(base + "}\n")
    assert load_recipe(tmp_path / "r.yaml")["vae"]["train"] == {"lr": 1e-3, "max_steps": 7}
    (tmp_path / "r.yaml").write_text(base + ", max_steps: 8}\n")
    with pytest.raises(ValueError, match="the key 'max_steps' is given twice"):
        load_recipe(tmp_path / "r.yaml")


def test_latent_cache_round_trip_and_staleness(tmp_path):
    rng = np.random.default_rng(0)
    mu = rng.normal(size=(10, 8)).astype(np.float32)
    path = write_latent_cache(
        tmp_path / "c.h5", names=[f"c{i}" for i in range(10)], splits=["train"] * 8 + ["val"] * 2,
        actions=np.arange(10) % 2, lengths=np.full(10, 60), mu=mu, logvar=np.zeros_like(mu),
        caption_clip=np.array([0, 0, 1]), caption_text=["a", "b", "c"], caption_embedding=rng.normal(size=(3, 5)),
        action_names=["walk", "wave"], vae_hash="abc", text_encoder="minilm:x",
    )
    c = read_latent_cache(path)
    np.testing.assert_array_equal(c.mu, mu)
    np.testing.assert_allclose(c.mean, mu[:8].mean(0), rtol=1e-5)
    assert c.caption_embedding.shape == (3, 5) and c.action_names == ["walk", "wave"]
    with pytest.raises(StaleCache, match="another VAE"):
        read_latent_cache(path, expect_vae_hash="def")
    with pytest.raises(StaleCache, match="text encoder"):
        read_latent_cache(path, expect_text_encoder="clip")


def test_fid_closed_forms():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(20000, 3))
    assert fid(a, a) < 1e-8
    assert abs(fid(a, a + np.array([2.0, 0.0, 0.0])) - 4.0) < 1e-6  # a shift adds its squared length


def test_check_finite_and_run_log(tmp_path):
    with pytest.raises(TrainingDiverged, match="loss is nan at step 3"):
        check_finite({"loss": float("nan")}, 3)
    log = RunLog(tmp_path, tensorboard=False)
    log.write(1, loss=0.5)
    log.write(2, loss=0.4, val=1.0)
    lines = (tmp_path / "log.csv").read_text().splitlines()
    assert lines[0] == "step,loss,val" and lines[2].startswith("2,0.4,1.0")
    json.dumps(lines)


def _toy_trainer(nan_at: int):
    """A real loop over a one-layer model whose step reports a NaN loss (a tensor, read back later) at step
    ``nan_at`` (1-based), and plain floats beside it."""
    from lsgan.train.loop import SeededSteps, Trainer

    model = torch.nn.Linear(3, 1)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    done = []

    def step(g: torch.Generator) -> dict:
        done.append(1)
        loss = model(torch.randn(4, 3, generator=g)).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        bad = torch.tensor(float("nan")) if len(done) == nan_at else torch.tensor(0.0)
        return {"loss": loss.detach() + bad, "steps_so_far": float(len(done))}

    return Trainer(kind="toy", desc="toy", model=model, config={"model": {}}, optimizers={"opt": opt}, step=step,
                   batches=SeededSteps(0, 0, torch.device("cpu")), validate=lambda: {}, metric="loss",
                   extra=lambda p: {}, log_details=False), done


def test_the_loop_reads_losses_back_in_windows_and_stops_at_the_first_nan(tmp_path):
    """Step scalars are read back at log/checkpoint steps only: the window means are those of each step's values,
    and a NaN in step 7 (read back at step 8) stops the run naming step 7, before step 8's checkpoint."""
    from lsgan.train.common import Dist
    from lsgan.train.loop import Env, Schedule, fit

    env = Env("toy", tmp_path, torch.device("cpu"), Dist(), resume=False, progress=False)
    t, _ = _toy_trainer(nan_at=0)
    p = fit(env, t, Schedule(max_steps=8, log_every=4, val_every=100, ckpt_every=4))
    rows = [line.split(",") for line in (tmp_path / "log.csv").read_text().splitlines()]
    header = rows[0]
    assert [r[0] for r in rows[1:]] == ["4", "8"] and "sec_per_step" in header
    assert [float(r[header.index("steps_so_far")]) for r in rows[1:]] == [2.5, 6.5]  # means of 1..4 and 5..8
    assert p.step == 8 and load_state(tmp_path / "last")["step"] == 8

    out = tmp_path / "nan"
    env = Env("toy", out, torch.device("cpu"), Dist(), resume=False, progress=False)
    t, done = _toy_trainer(nan_at=7)
    with pytest.raises(TrainingDiverged, match="loss is nan at step 7"):
        fit(env, t, Schedule(max_steps=12, log_every=4, val_every=100, ckpt_every=4))
    assert len(done) == 8 and load_state(out / "last")["step"] == 4


def _recipe_dataclasses() -> list[type]:
    """Every config a recipe section is built into: each ``*Config`` dataclass in lsgan, and the demo section."""
    import dataclasses
    import importlib
    import pkgutil

    import lsgan
    from lsgan.demo.settings import DemoSection

    found = {DemoSection}
    for m in pkgutil.walk_packages(lsgan.__path__, "lsgan."):
        if not m.name.endswith("__main__"):
            for name, obj in vars(importlib.import_module(m.name)).items():
                if isinstance(obj, type) and dataclasses.is_dataclass(obj) and name.endswith("Config"):
                    found.add(obj)
    return sorted(found, key=lambda c: c.__qualname__)


def test_every_recipe_field_is_checked_and_every_default_fits_it():
    """A recipe value is checked against its field's annotation by one function, and every number against its
    setting's bounds; a field of a kind it cannot check, or a number without bounds, fails here, not silently in a
    user's run."""
    import dataclasses
    import typing

    from lsgan.recipes import BOUNDS, fits, kind, numbers

    classes = _recipe_dataclasses()
    assert {"VAETrainConfig", "GANTrainConfig", "DiffusionTrainConfig", "DemoSection"} <= {c.__name__ for c in classes}
    for cls in classes:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            assert fits(default, hints[f.name]), (cls.__name__, f.name)
            assert kind(hints[f.name])
            if "int" in str(hints[f.name]) or "float" in str(hints[f.name]):
                assert f.name in BOUNDS, f"{cls.__name__}.{f.name} has no bounds in lsgan.recipes.BOUNDS"
                assert all(map(BOUNDS[f.name].holds, numbers(default))), (cls.__name__, f.name, default)


_YAML_VALUES = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                            lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                                        max_size=3), max_leaves=6)


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_any_recipe_values_build_a_config_or_raise_one_value_error(data):
    """Whatever a YAML file holds under a section's keys, build() gives the config or a ValueError (one line for
    the user), never a TypeError deep in training."""
    import dataclasses

    cls = data.draw(st.sampled_from(_recipe_dataclasses()))
    names = [f.name for f in dataclasses.fields(cls)]
    values = data.draw(st.dictionaries(st.sampled_from(names), _YAML_VALUES, max_size=4))
    try:
        build(cls, values, "s")
    except ValueError as e:
        assert "\n" not in str(e)


def test_a_recipe_names_the_text_encoders_lsgan_has():
    """The recipe reader's list of text encoders (it may import no model code) is the registry's."""
    from lsgan.models.text import available_encoders
    from lsgan.recipes import TEXT_ENCODERS

    assert list(TEXT_ENCODERS) == available_encoders()


def test_error_lines_are_worded_in_one_place():
    """Every failure line comes from lsgan.cli.options.say_error: no other code prints 'error: ...' itself."""
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1] / "lsgan"
    writers = [f"{p.relative_to(root)}:{i}" for p in sorted(root.rglob("*.py"))
               for i, line in enumerate(p.read_text().splitlines(), 1)
               if '"error: ' in line or "'error: " in line or '"error:"' in line]
    assert len(writers) == 1 and writers[0].startswith("cli/options.py:"), writers


@given(st.text())
@settings(max_examples=300, deadline=None)
def test_an_error_is_one_line_whatever_its_message_holds(message):
    """Any message prints as one line, with what a terminal would act on (line breaks, escapes, bidi marks)
    written as escapes: no file name can add a line, move the cursor or wipe the 'error:' before it."""
    import unicodedata

    import click
    from click.testing import CliRunner

    from lsgan.cli.options import say_error

    @click.command()
    def command():
        say_error(message)

    out = CliRunner().invoke(command)
    assert out.exit_code == 0
    assert len(out.stderr.splitlines()) == 1 and out.stderr.startswith("error:") and out.stderr.endswith("\n")
    shown = out.stderr[len("error: "):-1]
    assert not any(unicodedata.category(c) in ("Cc", "Cf", "Cs", "Zl", "Zp") for c in shown.replace("\t", ""))
    plain = all(c == "\t" or unicodedata.category(c) not in ("Cc", "Cf", "Cs", "Zl", "Zp") for c in message)
    assert (shown == message) == plain  # a message a terminal shows as it is prints unchanged, any other escaped
