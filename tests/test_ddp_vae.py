"""train_vae under torchrun: two CPU processes (gloo) take the same optimiser steps and rank 0 writes one run."""
from __future__ import annotations

import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import torch.distributed as dist

from lsgan.data.shards import ClipRecord, write_shard
from lsgan.models.checkpoint import load_weights, read_meta
from lsgan.models.vae import VAEConfig, load_vae
from lsgan.train.vae import VAETrainConfig, train_vae

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not (dist.is_available() and dist.is_gloo_available()), reason="torch.distributed with gloo is not available"),
]

MODEL = dict(d_model=32, num_layers=3, num_heads=4, ff_size=64, latent_dim=32, max_len=256)
TRAIN = dict(batch_size=2, max_steps=6, val_every=3, ckpt_every=3, log_every=3, lr=1e-3)

SCRIPT = """
import json, os, sys
from lsgan.models.vae import VAEConfig
from lsgan.train.vae import VAETrainConfig, train_vae

model, train = json.loads(sys.argv[3]), json.loads(sys.argv[4])
metrics = train_vae(sys.argv[1], sys.argv[2], model=VAEConfig(**model), train=VAETrainConfig(**train), device="cpu",
                    resume=sys.argv[5] == "resume", progress=False)
with open(f"{sys.argv[2]}-rank{os.environ['RANK']}.json", "w") as f:  # one file each: stdout lines interleave
    json.dump(metrics, f)
"""


@pytest.fixture()
def shard(tmp_path) -> str:
    """Random features are enough here: 8 train clips (two batches per process) and 2 val clips."""
    rng = np.random.default_rng(0)
    clips = [ClipRecord(f"c{i}", rng.normal(0, 0.1, (int(rng.integers(40, 60)), 263)).astype(np.float32),
                        "train" if i < 8 else "val") for i in range(10)]
    path = tmp_path / "random.h5"
    write_shard(path, clips, source="test", action_names=[], provenance={})
    return str(path)


def _torchrun(script, shard: str, out, train: dict, resume: bool = False) -> list[dict]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", str(script), shard,
           str(out), json.dumps(MODEL), json.dumps(train), "resume" if resume else "new"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return [json.loads(open(f"{out}-rank{r}.json").read()) for r in (0, 1)]


def test_two_processes_match_the_single_process_step_count(shard, tmp_path):
    script = tmp_path / "ddp_train.py"
    script.write_text(SCRIPT)
    out = tmp_path / "ddp"
    ranks = _torchrun(script, shard, out, TRAIN)
    assert ranks[0] == ranks[1]  # losses and the validation metric are averaged over both processes

    single = train_vae(shard, tmp_path / "single", model=VAEConfig(**MODEL), train=VAETrainConfig(**TRAIN),
                       device="cpu", progress=False)
    assert ranks[0]["step"] == single["step"] == TRAIN["max_steps"]
    assert read_meta(out, "last")["step"] == read_meta(tmp_path / "single", "last")["step"] == TRAIN["max_steps"]

    vae, meta = load_vae(out)
    assert meta["kind"] == "vae" and meta["mean"].shape == (263,) and not vae.training
    with open(out / "log.csv", newline="") as f:
        steps = [row["step"] for row in csv.DictReader(f)]
    assert steps == ["3", "6"]  # rank 0 alone writes the log

    # Stopped at 3 and resumed to 6: every process gets its own RNG state and sampler position back.
    half = tmp_path / "half"
    _torchrun(script, shard, half, {**TRAIN, "max_steps": 3})
    assert _torchrun(script, shard, half, TRAIN, resume=True) == ranks
    a, _ = load_weights(out, prefer="last")
    b, _ = load_weights(half, prefer="last")
    assert all(torch.equal(a[k], b[k]) for k in a)
