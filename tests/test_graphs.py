"""CUDA-graph training steps (lsgan.train.graphs): on one CUDA device a latent model's step is captured once and
replayed; the replays must train exactly as the eager steps do, resume exactly, and never be used where they
cannot be (CPU, torchrun). The runs on a GPU skip on a machine without one."""
from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from lsgan.models.diffusion import DiffusionConfig
from lsgan.models.gan import GANConfig, load_gan
from lsgan.models.checkpoint import load_state
from lsgan.train.diffusion import train_diffusion
from lsgan.train.gan import train_gan
from lsgan.train.graphs import GraphedStep, optimizer_options, use_cuda_graph

sys.path.insert(0, str(Path(__file__).parent))
from test_diffusion import SMALL as DIFFUSION_SMALL  # noqa: E402
from test_diffusion import quick as diffusion_quick  # noqa: E402
from test_gan import SMALL, quick, toy_cache  # noqa: E402

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(),
                                reason="needs a CUDA device: CUDA graphs exist only there (run on a GPU machine)")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cache") / "text.h5"
    toy_cache(path)
    return path


def weights(folder: Path) -> dict[str, torch.Tensor]:
    model, _ = load_gan(folder, prefer="last")
    return model.state_dict()


def log_rows(folder: Path) -> list[dict]:
    """log.csv without its timing columns (the one thing graphs are meant to change)."""
    rows = list(csv.DictReader(open(folder / "log.csv")))
    return [{k: v for k, v in r.items() if k not in ("sec_per_step", "steps_per_s")} for r in rows]


def assert_same_weights(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


# ---------------------------------------------------------------------------------------------------- anywhere


def test_graphs_only_on_one_cuda_device() -> None:
    cuda, cpu = torch.device("cuda", 0), torch.device("cpu")
    assert use_cuda_graph(True, cuda, distributed=False)
    assert not use_cuda_graph(False, cuda, distributed=False)
    assert not use_cuda_graph(True, cpu, distributed=False)
    assert not use_cuda_graph(True, cuda, distributed=True)  # DDP steps talk to their peers
    assert optimizer_options(cuda) == {"capturable": True}  # in both modes on CUDA: the same update kernels
    assert optimizer_options(cpu) == {}
    with pytest.raises(ValueError, match="warm-up"):
        GraphedStep(lambda g: {}, warmup=0)


def test_the_setting_is_recorded_and_changes_nothing_on_a_cpu(cache: Path, tmp_path: Path) -> None:
    gan = GANConfig(arch="deep-wgan-gp", **SMALL)
    on = train_gan(cache, tmp_path / "on", gan=gan, train=quick(max_steps=6), device="cpu", progress=False)
    off = train_gan(cache, tmp_path / "off", gan=gan, train=quick(max_steps=6, cuda_graph=False), device="cpu",
                    progress=False)
    assert on["config"]["train"]["cuda_graph"] is True and off["config"]["train"]["cuda_graph"] is False
    assert not any("CUDA graph" in n for n in on["notes"])  # nothing replayed on a CPU, nothing said
    assert_same_weights(weights(tmp_path / "on"), weights(tmp_path / "off"))


def test_the_cli_switch_reaches_the_run(cache: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "lsgan.cli", "train-gan", "--cache", str(cache), "--recipe", "demo",
                        "--out", str(out), "--max-steps", "2", "--no-cuda-graph", "--device", "cpu",
                        "--allow-stale"],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    config = json.loads((out / "last" / "config.json").read_text())
    assert config["config"]["train"]["cuda_graph"] is False


# ---------------------------------------------------------------------------------------------------- on a GPU


@needs_cuda
@pytest.mark.parametrize("arch", ["deep-wgan-gp", "deep-gan"])
def test_replayed_steps_train_exactly_as_eager_steps(cache: Path, tmp_path: Path, arch: str) -> None:
    """The same run with graphs on and off: bit-identical weights, losses and latent FIDs."""
    gan = GANConfig(arch=arch, **SMALL)
    on = train_gan(cache, tmp_path / "on", gan=gan, train=quick(), device="cuda", progress=False)
    off = train_gan(cache, tmp_path / "off", gan=gan, train=quick(cuda_graph=False), device="cuda", progress=False)
    assert any("CUDA graph" in n for n in on["notes"]) and not any("CUDA graph" in n for n in off["notes"])
    assert on["fid_history"] == off["fid_history"]
    assert log_rows(tmp_path / "on") == log_rows(tmp_path / "off")
    assert_same_weights(weights(tmp_path / "on"), weights(tmp_path / "off"))
    state_on, state_off = load_state(tmp_path / "on"), load_state(tmp_path / "off")
    for name in ("opt_g", "opt_d"):
        for a, b in zip(state_on[name]["state"].values(), state_off[name]["state"].values()):
            assert all(torch.equal(a[k], b[k]) for k in a), name


@needs_cuda
def test_a_graphed_run_resumes_exactly(cache: Path, tmp_path: Path) -> None:
    """Stopped at step 10 and resumed (three eager steps, then a new capture) = straight through, in graphs."""
    gan = GANConfig(arch="deep-wgan-gp", **SMALL)
    whole = train_gan(cache, tmp_path / "whole", gan=gan, train=quick(max_steps=20), device="cuda", progress=False)
    train_gan(cache, tmp_path / "split", gan=gan, train=quick(max_steps=10), device="cuda", progress=False)
    resumed = train_gan(cache, tmp_path / "split", gan=gan, train=quick(max_steps=20), device="cuda", progress=False,
                        resume=True)
    assert resumed["last_val_latent_fid"] == whole["last_val_latent_fid"]
    assert_same_weights(weights(tmp_path / "whole"), weights(tmp_path / "split"))


@needs_cuda
def test_a_diffusion_step_replays_exactly_too(cache: Path, tmp_path: Path) -> None:
    cfg = DiffusionConfig(**DIFFUSION_SMALL | {"dropout": 0.1})  # dropout draws from torch's default generator
    on = train_diffusion(cache, tmp_path / "on", diffusion=cfg, train=diffusion_quick(), device="cuda", progress=False)
    off = train_diffusion(cache, tmp_path / "off", diffusion=cfg, train=diffusion_quick(cuda_graph=False),
                          device="cuda", progress=False)
    assert on["fid_history"] == off["fid_history"]
    assert log_rows(tmp_path / "on") == log_rows(tmp_path / "off")


@needs_cuda
def test_each_replay_hands_back_its_own_values() -> None:
    """Replays overwrite the graph's outputs; what a call returned must not change with the next replay."""
    x = torch.zeros((), device="cuda")
    g = torch.Generator("cuda")

    def step(gen: torch.Generator) -> dict[str, torch.Tensor]:
        x.add_(1)
        return {"x": x * 1, "u": torch.rand((), device="cuda", generator=gen)}

    graphed = GraphedStep(step, warmup=1)
    first = [graphed(g.manual_seed(s)) for s in (1, 2, 3)]  # eager, then capture + replay, replay
    assert graphed.captured
    assert [float(o["x"]) for o in first] == [1.0, 2.0, 3.0]
    eager = [torch.rand((), device="cuda", generator=g.manual_seed(s)) for s in (1, 2, 3)]
    assert [float(o["u"]) for o in first] == [float(u) for u in eager]  # each replay draws from the step's seed
    with pytest.raises(ValueError, match="generator it was captured with"):
        graphed(torch.Generator("cuda"))
