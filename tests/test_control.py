"""Control (lsgan.control): constraints met by optimising the generator's noise and then the latent, through the real
tiny pipeline's generator and decoder; the constraint checks."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lsgan.control import Constraints, ControlSettings, control, path_points
from lsgan.data.features import recover_from_ric
from lsgan.generate import Request, _conditions, draw_noise, load_models

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def models(serve_models: Path):
    loaded = load_models(serve_models / "gan", serve_models / "vae", device="cpu")
    extra = loaded.meta["extra"]
    stats = dict(latent_mean=torch.tensor(extra["latent_mean"]), latent_std=torch.tensor(extra["latent_std"]),
                 feat_mean=torch.from_numpy(loaded.vae_meta["mean"]), feat_std=torch.from_numpy(loaded.vae_meta["std"]))
    return loaded, stats


def _run(models, constraints: list[Constraints], seed: int = 0, **settings):
    loaded, stats = models
    cond = _conditions(loaded.model, loaded.meta["extra"], "gan", [Request(text="a person walks", frames=40)] *
                       len(constraints), loaded.device, loaded.encoder, {})
    noise, _ = draw_noise(seed, len(constraints), loaded.model.config.noise_dim)
    z, report = control(loaded.model.generator, loaded.decoder, cond, noise, constraints,
                        settings=ControlSettings(**settings), **stats)
    lengths = torch.tensor([c.frames for c in constraints])
    mask = torch.arange(int(lengths.max()))[None] < lengths[:, None]
    with torch.no_grad():
        x = loaded.decoder.decode(z, mask) * stats["feat_std"] + stats["feat_mean"]
    return z, report, recover_from_ric(x).numpy()


def test_a_reachable_path_and_keyframe_are_approached_and_the_report_measures_what_was_decoded(models):
    """The root path and a wrist of another seed's motion (so a latent meets them exactly): the optimised motion is
    much closer than the seed's own, and the reported errors are those of the decoded joints."""
    _, _, other = _run(models, [Constraints(40)], seed=7, noise_steps=0, latent_steps=0)
    path = other[0, :, 0, [0, 2]].T.copy()
    pose = np.full((22, 3), np.nan, np.float32)
    pose[21] = other[0, 30, 21]
    c = Constraints(40, path=path, keyframes={30: pose})
    z, report, joints = _run(models, [c], noise_steps=20, latent_steps=60, lr=0.1)
    assert report["mean_error_m"][0] < 0.5 * report["mean_error_m_before"][0], report
    root = np.linalg.norm(joints[0, :, 0, [0, 2]].T - path, axis=-1)  # (40,)
    wrist = np.linalg.norm(joints[0, 30, 21] - pose[21])
    assert np.isclose(report["mean_error_m"][0], (root.sum() + wrist) / 41, atol=1e-4)
    assert np.isclose(report["max_error_m"][0], max(root.max(), wrist), atol=1e-4)


def test_the_same_seed_and_constraints_give_the_same_latent_and_free_rows_stay_free(models):
    path = path_points(np.array([[0.5, 0.0, 0.0], [1.5, 0.0, 1.0]]), 40)  # frames before 0.5 s and after 1.5 s free
    assert np.isnan(path[:10]).all() and np.isnan(path[31:]).all() and not np.isnan(path[10:31]).any()
    c = [Constraints(40, path=path), Constraints(40)]
    z1, r1, _ = _run(models, c, noise_steps=5, latent_steps=5)
    z2, r2, _ = _run(models, c, noise_steps=5, latent_steps=5)
    assert torch.equal(z1, z2) and r1 == r2
    assert r1["mean_error_m"][1] == r1["max_error_m"][1] == 0.0  # no constraint: nothing to miss


@pytest.mark.parametrize("make, phrase", [
    (lambda: Constraints(40, path=np.zeros((39, 2))), "is (40, 2) ground points"),
    (lambda: Constraints(40, path=np.full((40, 2), np.inf)), "infinite"),
    (lambda: Constraints(40, keyframes={40: np.zeros((22, 3))}), "keyframe 40 is beyond the motion's 40 frames"),
    (lambda: Constraints(40, keyframes={3: np.zeros((24, 3))}), "a pose is 22 joints"),
    (lambda: path_points(np.array([[1.0, 0, 0], [0.5, 1, 1]]), 40), "waypoint times must increase"),
    (lambda: path_points(np.array([[0.0, np.nan, 0]]), 40), "finite (time, x, z)"),
])
def test_bad_constraints_are_refused_with_what_is_wrong(make, phrase):
    with pytest.raises(ValueError, match=phrase.replace("(", r"\(").replace(")", r"\)")):
        make()
