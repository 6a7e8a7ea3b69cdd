"""train_gan under torchrun: two CPU processes (gloo), DistributedDataParallel for generator and critic."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from lsgan.models.checkpoint import read_meta
from lsgan.models.gan import GANConfig, load_gan
from lsgan.train.gan import GANTrainConfig, train_gan

sys.path.insert(0, str(Path(__file__).parent))
from test_gan import SMALL, toy_cache  # noqa: E402

STEPS = 6

# Each rank records a digest of its final weights: DDP must keep them identical although the ranks draw
# different batches.
SCRIPT = """
import sys
import torch
import torch.distributed as dist
import lsgan.train.gan as tg
from lsgan.models.gan import GANConfig

built = []
class Recorded(tg.LatentGAN):
    def __init__(self, cfg):
        super().__init__(cfg)
        built.append(self)
tg.LatentGAN = Recorded

cache, out, arch, cond, steps = sys.argv[1:6]
result = tg.train_gan(cache, out, gan=GANConfig(arch=arch, cond=cond, **{small}), train=tg.GANTrainConfig(**{train}),
                      device="cpu", progress=False)
digest = sum(float(p.double().sum()) * (i + 1) for i, p in enumerate(built[0].state_dict().values()))
rank = int(__import__("os").environ["RANK"])
open(f"{{out}}/digest{{rank}}.txt", "w").write(repr(digest))
assert result["step"] == int(steps), result
"""


def train_config() -> dict:
    return dict(lr=1e-3, batch_size=16, max_steps=STEPS, eval_every=3, ckpt_every=3, log_every=2, fid_samples=128)


@pytest.mark.slow
@pytest.mark.parametrize("arch,cond", [("deep-wgan-gp", "text"), ("vanilla-gan", "action")])
def test_torchrun_two_processes(arch: str, cond: str, tmp_path: Path) -> None:
    cache = tmp_path / "c.h5"
    toy_cache(cache, k=2, per=20, actions=cond == "action")
    script = tmp_path / "run_gan.py"
    script.write_text(SCRIPT.format(small=SMALL, train=train_config()))
    out = tmp_path / "ddp"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", str(script),
           str(cache), str(out), arch, cond, str(STEPS)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]

    torch.set_num_threads(1)
    single = train_gan(cache, tmp_path / "single", gan=GANConfig(arch=arch, cond=cond, **SMALL),
                       train=GANTrainConfig(**train_config()), device="cpu", progress=False)
    meta = read_meta(out, "last")
    assert meta["step"] == single["step"] == STEPS
    model, meta = load_gan(out)
    assert meta["kind"] == "gan" and model.config.arch == arch and model.config.cond == cond
    c = torch.randn(3, SMALL["cond_dim"]) if cond == "text" else torch.tensor([0, 1, 0])
    assert torch.isfinite(model.sample(c)).all()
    assert (out / "log.csv").exists() and (out / "best").is_dir()
    digests = [(out / f"digest{r}.txt").read_text() for r in range(2)]
    assert digests[0] == digests[1], digests
