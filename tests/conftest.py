"""Shared test fixtures. Tests that need ../shared skip with a reason when it is absent."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

SHARED = Path(__file__).resolve().parents[2] / "shared"
# The quick subset (`python -m pytest -q -m quick`: 3 minutes on the 2-core CPU against 18-21 for the whole
# suite): whole modules (or MODULE::TEST), chosen so that every layer of lsgan is imported (tests/test_layers.py
# checks it).
QUICK = ("test_bvh.py", "test_cli.py", "test_dataset.py", "test_export_bvh.py", "test_features.py", "test_gan.py",
         "test_infra.py", "test_jsonfmt.py", "test_layers.py", "test_metrics.py", "test_onnx_rewrite.py",
         "test_outputs.py", "test_pickles.py", "test_quality.py", "test_rigid.py", "test_serve_worker.py",
         "test_synthetic.py", "test_text.py", "test_textcache.py", "test_threads.py", "test_timeline.py",
         "test_vae.py", "test_vae_loss.py", "test_demo.py::test_settings_follow_the_recipe_and_shrink_with_floors")


def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        if item.path.name in QUICK or f"{item.path.name}::{getattr(item, 'originalname', item.name)}" in QUICK:
            item.add_marker(pytest.mark.quick)


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"{path} is absent: this test reads the shared data beside the project root (../shared)")
    return path


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    return _need(SHARED)


@pytest.fixture(scope="session")
def hml_fixtures() -> Path:
    return _need(SHARED / "fixtures" / "humanml3d")


@pytest.fixture(scope="session")
def bandai_dir() -> Path:
    return _need(SHARED / "data" / "bandai-namco-2")


@pytest.fixture(scope="session")
def cmu_dir() -> Path:
    return _need(SHARED / "data" / "cmu")


@pytest.fixture()
def one_thread(monkeypatch):
    """Run torch on one thread, in this process and in lsgan's (LSGAN_THREADS): tiny models gain nothing from
    intra-op threads."""
    threads = torch.get_num_threads()
    monkeypatch.setenv("LSGAN_THREADS", "1")
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def serve_models(tmp_path_factory) -> Path:
    """What the ``lsgan serve`` tests serve: cli_runs' tiny pipeline (a text GAN ``gan`` on ``vae``), an action GAN
    ``act-gan`` on the same cache, and the text GAN exported as ONNX (``gan-onnx``). Built once per session."""
    from cli_runs import tiny_pipeline

    return tiny_pipeline(
        tmp_path_factory.mktemp("serve"),
        ("train-gan", "--cache", "cache.h5", "--recipe", "tiny.yaml", "--cond", "action", "--out", "act-gan"),
        ("export-model", "gan", "-o", "gan-onnx", "--onnx"),
    )
