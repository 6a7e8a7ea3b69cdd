"""Do decoded walks step? The foot-skating figure of issue 32, taken apart.

GMD's skating ratio counts frame pairs where a toe under 5 cm moves faster than 0.5 m/s. A walk whose feet swing
low and glide at the body's speed (no steps) scores high; so does a planted foot that slides. This separates them
on the test windows (one per clip, ``--min-frames``-``--max-frames``) whose caption says "walk" or "run":

- step height: each window's toe-height variation (standard deviation over frames of joints 10 and 11's height,
  mean of the two) for the VAE's reconstruction (encoder mean, decoder) over the real window's, median and 10th /
  90th percentiles over the windows (1: the real steps; near 0: gliding);
- with ``--gan``: the same variation for the GAN's motions of the same captions and lengths, over Real's, as the
  ratio of the medians (the GAN's motions are not paired with the windows);
- the skating ratio of Real, the reconstructions and the GAN's motions, on these windows and on all;
- whether the root is to blame: the skating of the reconstructions with the real root channels (0-3), and of the
  real features with the reconstructed root channels.

    LSGAN_THREADS=2 python benchmarks/gait.py --vae runs/bandai-vae --data bandai.h5 --gan runs/bandai-gan
"""
from __future__ import annotations

import argparse
import json
import os

import numpy as np
import torch

from lsgan.data.features import recover_from_ric
from lsgan.eval.evaluate import _draw, _windows
from lsgan.models.vae import load_vae
from lsgan.motion.quality import foot_skating_ratio

TOES = [10, 11]


def step_height(joints: np.ndarray) -> float:
    """Toe-height variation (m) of one motion (T, 22, 3): the height's standard deviation, mean of both toes."""
    return float(joints[:, TOES, 1].std(0).mean())


def reconstruct(vae: str, motions: list[np.ndarray]) -> list[np.ndarray]:
    """Each window encoded (mean) and decoded by the VAE, de-normalised features."""
    model, meta = load_vae(vae)
    mean, std = np.asarray(meta["mean"], np.float32), np.asarray(meta["std"], np.float32)
    out = []
    with torch.no_grad():
        for m in motions:
            x = torch.from_numpy(((m - mean) / std)[None].astype(np.float32))
            mask = torch.ones(1, len(m), dtype=torch.bool)
            mu, _ = model.encode(x, mask)
            out.append(model.decode(mu, mask)[0].numpy() * std + mean)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vae", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--gan")
    ap.add_argument("--min-frames", type=int, default=16)
    ap.add_argument("--max-frames", type=int, default=120)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json")
    args = ap.parse_args()
    torch.set_num_threads(int(os.environ.get("LSGAN_THREADS", "2")))
    draw = _draw(_windows(args.data, "test", args.min_frames, args.max_frames), args.seed)
    gait = [i for i, c in enumerate(draw.captions) if "walk" in c or "run" in c]
    real = [recover_from_ric(m.astype(np.float32)) for m in draw.motions]
    decoded = reconstruct(args.vae, draw.motions)
    recon = [recover_from_ric(m.astype(np.float32)) for m in decoded]
    swap = {"recon_with_real_root": [np.concatenate([r[:, :4], d[:, 4:]], 1) for r, d in zip(draw.motions, decoded)],
            "real_with_recon_root": [np.concatenate([d[:, :4], r[:, 4:]], 1) for r, d in zip(draw.motions, decoded)]}
    ratio = [step_height(recon[i]) / max(step_height(real[i]), 1e-6) for i in gait]
    report = {"windows": len(real), "walk_or_run_windows": len(gait),
              "recon_step_height_ratio_p10_p50_p90": np.percentile(ratio, [10, 50, 90]).round(3).tolist(),
              "real_step_height_m_median": float(np.median([step_height(real[i]) for i in gait])),
              "skating_walk_run": {"real": float(np.mean([foot_skating_ratio(real[i]) for i in gait])),
                                   "recon": float(np.mean([foot_skating_ratio(recon[i]) for i in gait]))},
              "skating_all": {"real": float(np.mean([foot_skating_ratio(j) for j in real])),
                              "recon": float(np.mean([foot_skating_ratio(j) for j in recon])),
                              **{k: float(np.mean([foot_skating_ratio(recover_from_ric(m.astype(np.float32)))
                                                   for m in v])) for k, v in swap.items()}}}
    if args.gan:
        from lsgan.generate import Request, generate

        reqs = [Request(text=draw.captions[i], frames=len(draw.motions[i])) for i in gait]
        made = [m.joints for m in generate(args.gan, args.vae, reqs, seed=args.seed, device="cpu").motions]
        report["gan_step_height_ratio_of_medians"] = float(
            np.median([step_height(j) for j in made]) / report["real_step_height_m_median"])
        report["skating_walk_run"]["gan"] = float(np.mean([foot_skating_ratio(j) for j in made]))
    print(json.dumps(report, indent=1))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main()
