"""The skip-transformer VAE and its training loop, on tiny configs (the whole file runs in well under a minute)."""
from __future__ import annotations

import csv
from dataclasses import asdict, replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lsgan import outputs
from lsgan.outputs import OutputError
import torch

from lsgan.data.features import joints_to_features, recover_from_ric
from lsgan.data.shards import ClipRecord, write_shard
from lsgan.data.skeleton import PARENTS, TARGET_OFFSETS
from lsgan.models.checkpoint import load_state, load_weights, read_meta, save_checkpoint
from lsgan.models.vae import MotionVAE, VAEConfig, load_vae, vae_loss
from lsgan.train.common import TrainingDiverged
from lsgan.train.vae import VAETrainConfig, mld_vae_loss, train_vae

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = VAEConfig(d_model=32, num_layers=3, num_heads=4, ff_size=64, latent_dim=32, dropout=0.1, max_len=256)


def _rot_x(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _rot_y(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _walk(T: int, speed: float, freq: float, swing: float, turn: float) -> np.ndarray:
    """A crude walk (T,22,3): legs and arms swing about x, the root turns and moves forward, bobbing."""
    t = np.arange(T) / 20.0
    phase = 2 * np.pi * freq * t
    local = np.broadcast_to(np.eye(3), (T, 22, 3, 3)).copy()
    local[:, 0] = _rot_y(turn * t)
    for j, sign in ((1, 1), (2, -1), (16, -1), (17, 1)):  # hips and shoulders, in antiphase
        local[:, j] = _rot_x(sign * swing * np.sin(phase))
    for j, sign in ((4, 1), (5, -1)):  # knees bend only backwards
        local[:, j] = _rot_x(swing * np.maximum(0.0, sign * np.sin(phase)))
    yaw = turn * t
    root = np.stack([np.cumsum(speed * np.sin(yaw)) / 20, 0.95 + 0.02 * np.cos(2 * phase), np.cumsum(speed * np.cos(yaw)) / 20], -1)
    world = np.empty_like(local)
    joints = np.empty((T, 22, 3))
    world[:, 0], joints[:, 0] = local[:, 0], root
    for j in range(1, 22):
        p = PARENTS[j]
        world[:, j] = world[:, p] @ local[:, j]
        joints[:, j] = joints[:, p] + world[:, p] @ TARGET_OFFSETS[j].astype(np.float64)
    return joints



@pytest.fixture(scope="module")
def shard(tmp_path_factory) -> str:
    """Three short walks, each three times in 'train' (a batch averages three posterior samples) and once in 'val'."""
    rng = np.random.default_rng(0)
    walks = [_walk(int(rng.integers(44, 56)) // 4 * 4 + 1, rng.uniform(0.5, 1.0), rng.uniform(0.6, 1.2),
                   rng.uniform(0.2, 0.6), rng.uniform(-0.3, 0.3)) for _ in range(3)]
    feats = joints_to_features(walks)  # 44, 48 or 52 frames: whole windows when unit_length=1
    clips = [ClipRecord(f"t{k}-{i}", f, "train") for k in range(3) for i, f in enumerate(feats)]
    clips += [ClipRecord(f"v{i}", f, "val") for i, f in enumerate(feats)]
    path = tmp_path_factory.mktemp("vae") / "walks.h5"
    write_shard(path, clips, source="test", action_names=[], provenance={})
    return str(path)


def _batch(lengths: list[int], T: int | None = None, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    T = T or max(lengths)
    x = torch.randn(len(lengths), T, 263, generator=g)
    mask = torch.arange(T)[None] < torch.tensor(lengths)[:, None]
    return x, mask


@pytest.mark.parametrize("config", [TINY, replace(TINY, position_embedding="sine", latent_dim=16, norm_first=False),
                                    replace(TINY, time_tokens=4), replace(TINY, time_tokens=2, latent_dim=64)],
                         ids=["learned", "sine-post-norm-projected", "time-tokens-projected", "time-tokens"])
def test_shapes_and_masks(config):
    torch.manual_seed(0)
    vae = MotionVAE(config)
    x, mask = _batch([50, 31, 7])
    x_hat, mu, logvar = vae(x, mask)
    assert x_hat.shape == x.shape and mu.shape == logvar.shape == (3, config.latent_dim)
    assert torch.all(x_hat[~mask] == 0)  # padded frames are exactly zero, even in training mode

    vae.eval()
    with torch.no_grad():
        mu, logvar = vae.encode(x, mask)
        garbage = x.clone()
        garbage[~mask] = torch.randn(int((~mask).sum()), 263) * 1e3
        garbage[2, -1] = float("nan")
        mu2, logvar2 = vae.encode(garbage, mask)
        assert torch.equal(mu, mu2) and torch.equal(logvar, logvar2)  # padded frames are ignored

        alone_mu, alone_logvar = vae.encode(x[1:2, :31], mask[1:2, :31])  # clip 1 without padding
        torch.testing.assert_close(alone_mu[0], mu[1], atol=1e-5, rtol=0)
        torch.testing.assert_close(alone_logvar[0], logvar[1], atol=1e-5, rtol=0)
        out = vae.decode(mu, mask)
        alone = vae.decode(mu[1:2], mask[1:2, :31])
        torch.testing.assert_close(alone[0], out[1, :31], atol=1e-5, rtol=0)
        assert torch.equal(vae(x, mask, sample=False)[0], out)  # no sampling: z = mu



@pytest.mark.parametrize("norm_first", [True, False])
def test_inference_decoder_computes_the_one_token_cross_attention_once(norm_first):
    """In eval mode decode() skips the cross-attention's per-frame products (one memory token: softmax is 1) and
    runs the self-attention by the fused kernel; the features equal those of torch's TransformerDecoderLayer
    stack to float rounding, padding included."""
    torch.manual_seed(0)
    vae = MotionVAE(VAEConfig(d_model=32, num_heads=4, ff_size=64, num_layers=5, norm_first=norm_first)).eval()
    z = torch.randn(3, 256)
    mask = torch.arange(40)[None] < torch.tensor([[40], [25], [7]])
    with torch.no_grad():
        fast = vae.decode(z, mask)
        memory = vae.from_latent(z)[:, None]
        queries = vae.dec_pos(memory.new_zeros(3, 40, 32))
        full = vae.final(vae.decoder(queries, memory, tgt_key_padding_mask=~mask)).masked_fill(~mask[..., None], 0)
    torch.testing.assert_close(fast, full, rtol=0, atol=1e-6)
    vae.train()  # training keeps torch's layers (dropout acts per frame there)
    torch.manual_seed(1)
    a = vae.decode(z, mask)
    torch.manual_seed(1)
    b = vae.final(vae.decoder(queries, memory, tgt_key_padding_mask=~mask)).masked_fill(~mask[..., None], 0)
    torch.testing.assert_close(a, b, rtol=0, atol=0)

@settings(max_examples=60, deadline=None)
@given(lengths=st.lists(st.integers(1, 90), min_size=1, max_size=5), k=st.integers(1, 12))
def test_time_token_weights_cover_each_real_frame_once(lengths, k):
    """Each real frame lies in exactly one token's segment and its interpolation weights sum to 1, padding in none;
    segments run in time order and split a motion evenly (sizes differ by one frame at most)."""
    from lsgan.models.vae import interpolation_weights, segment_weights

    mask = torch.arange(max(lengths) + 3)[None] < torch.tensor(lengths)[:, None]
    seg, interp = segment_weights(mask, k), interpolation_weights(mask, k)
    assert torch.equal(seg.sum(-1), mask.float()) and (interp >= 0).all()
    torch.testing.assert_close(interp.sum(-1), mask.float(), rtol=0, atol=1e-6)
    for b, n in enumerate(lengths):
        owner = seg[b, :n].argmax(-1)
        assert (owner.diff() >= 0).all()
        sizes = seg[b, :n].sum(0)[: min(k, n)]
        assert n < k or sizes.max() - sizes.min() <= 1


def test_a_run_saved_before_a_model_field_existed_resumes():
    """A checkpoint's model config that lacks a field added since is that field at its default (what the model did
    before it existed); any other difference still refuses the resume."""
    from lsgan.train.loop import _with_defaults

    vae = MotionVAE(TINY)
    now = asdict(TINY)
    old = {k: v for k, v in now.items() if k != "time_tokens"}
    assert _with_defaults(old, vae) == now
    assert _with_defaults({**old, "d_model": 64}, vae) != now
    assert _with_defaults({**now, "time_tokens": 4}, vae) != now


@pytest.mark.parametrize("layers", [0, 2, 4, 8])
def test_even_layer_counts_are_rejected(layers):
    with pytest.raises(ValueError, match="odd"):
        VAEConfig(num_layers=layers)
    with pytest.raises(ValueError, match="divisible"):
        VAEConfig(d_model=30, num_heads=4)


def test_loss_counts_real_frames_only():
    x, mask = _batch([10, 4], T=10)
    x_hat = x.clone()
    x_hat[1, 4:] += 100.0  # error on padding only
    mu, logvar = torch.zeros(2, 8), torch.zeros(2, 8)
    loss = vae_loss(x_hat, x, mu, logvar, mask, kl_weight=0.5)
    assert loss["recon"].item() == 0 and loss["kl"].item() == 0 and loss["total"].item() == 0
    x_hat[0, 0, 0] += 1.0
    loss = vae_loss(x_hat, x, mu + 1.0, logvar, mask, kl_weight=0.5)
    assert loss["recon"].item() == pytest.approx(1 / (14 * 263))
    assert loss["kl"].item() == pytest.approx(0.5)  # 0.5 * mu^2, averaged over dims and batch (as MLD)
    assert loss["total"].item() == pytest.approx(loss["recon"].item() + 0.25)


def test_torch_recover_from_ric_matches_numpy_and_is_differentiable():
    """The MLD loss recovers joints in torch with the same function as the numpy pipeline."""
    feats = np.stack(joints_to_features([_walk(60, 1.0, 1.0, 0.4, 0.3), _walk(60, 0.7, 0.8, 0.3, -0.2)]))
    feats = feats.astype(np.float32)  # (2, 59, 263): turning walks
    want = recover_from_ric(feats)
    got = recover_from_ric(torch.from_numpy(feats))
    assert isinstance(got, torch.Tensor) and got.shape == (2, 59, 22, 3)
    np.testing.assert_allclose(got.numpy(), want, atol=1e-5, rtol=0)
    x = torch.from_numpy(feats[:1, :6].astype(np.float64)).requires_grad_()
    assert torch.autograd.gradcheck(recover_from_ric, (x,))


def _smooth_l1(d: np.ndarray) -> np.ndarray:
    return np.where(np.abs(d) < 1, 0.5 * d * d, np.abs(d) - 0.5)


def test_mld_loss_is_smooth_l1_on_features_and_joints_plus_kl():
    """MLD's loss written out in numpy on a tiny batch: real frames only, joints from de-normalised features."""
    rng = np.random.default_rng(0)
    lengths, T = [6, 3], 6
    mask = np.arange(T)[None] < np.array(lengths)[:, None]
    mean, std = rng.normal(0, 0.5, 263), rng.uniform(0.2, 1.0, 263)
    x = rng.normal(size=(2, T, 263)) * mask[..., None]
    x_hat = x + rng.normal(0, 1.5, x.shape)  # differences on both sides of SmoothL1's |d| = 1
    x_hat[1, 3:] = 100.0  # padding: ignored
    mu, logvar = rng.normal(size=(2, 8)), rng.normal(0, 0.5, (2, 8))

    d = (x_hat - x)[mask]  # (real frames, 263)
    assert (np.abs(d) < 1).any() and (np.abs(d) > 1).any()
    recon = _smooth_l1(d).mean()
    dj = (recover_from_ric(x_hat * std + mean) - recover_from_ric(x * std + mean))[mask]  # (real frames, 22, 3)
    joints = _smooth_l1(dj).mean()
    kl = (-0.5 * (1 + logvar - mu**2 - np.exp(logvar))).mean()

    t = {k: torch.from_numpy(v) for k, v in dict(x=x, mu=mu, logvar=logvar, mean=mean, std=std).items()}
    x_hat_t = torch.from_numpy(x_hat).requires_grad_()
    got = mld_vae_loss(x_hat_t, t["x"], t["mu"], t["logvar"], torch.from_numpy(mask), 1e-4, t["mean"], t["std"])
    assert got["recon"].item() == pytest.approx(recon, rel=1e-12)
    assert got["recon_joints"].item() == pytest.approx(joints, rel=1e-12)
    assert got["kl"].item() == pytest.approx(kl, rel=1e-12)
    assert got["total"].item() == pytest.approx(recon + joints + 1e-4 * kl, rel=1e-12)
    got["total"].backward()
    assert x_hat_t.grad[0, :5, 0].abs().min() > 0  # the root's rotation velocity reaches the loss through the joints
    assert torch.all(x_hat_t.grad[1, 3:] == 0)
    with pytest.raises(ValueError, match="loss must be one of mse, mld"):
        VAETrainConfig(loss="l1")


def _log(out) -> list[dict]:
    with open(out / "log.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_overfits_a_handful_of_clips(shard, tmp_path):
    """Global MPJPE (root trajectory integrated) of the three walks falls over tenfold in 500 steps.

    unit_length=1 keeps every window whole, so the VAE sees the same three clips again and again; the
    first validation comes after 5 steps, before the model has learnt much more than the mean motion.
    """
    model = replace(TINY, dropout=0.0)
    cfg = VAETrainConfig(lr=1e-2, kl_weight=1e-6, batch_size=16, max_steps=500, val_every=5, ckpt_every=250,
                         log_every=50, unit_length=1, seed=0)
    metrics = train_vae(shard, tmp_path, model=model, train=cfg, device="cpu", progress=False)
    vals = [float(r["val_mpjpe_m"]) for r in _log(tmp_path) if r.get("val_mpjpe_m")]
    assert len(vals) == 100 and metrics["step"] == 500
    assert vals[-1] < vals[0] / 10, vals
    assert metrics["val_mpjpe_m"] == pytest.approx(vals[-1])
    assert metrics["best_val_mpjpe_m"] == pytest.approx(min(vals))
    meta = read_meta(tmp_path, "best")
    assert meta["extra"]["val_mpjpe_m"] == pytest.approx(min(vals)) and meta["kind"] == "vae"
    assert read_meta(tmp_path, "last")["step"] == 500

    vae, meta = load_vae(tmp_path)  # the run folder's best/, with the normalisation to decode without a shard
    assert not vae.training and meta["mean"].shape == meta["std"].shape == (263,)
    assert meta["config"]["model"] == asdict(model) and meta["config"]["train"]["lr"] == 1e-2


def test_checkpoint_round_trip_is_exact(tmp_path):
    torch.manual_seed(0)
    vae = MotionVAE(replace(TINY, latent_dim=16)).eval()
    mean, std = np.linspace(-1, 1, 263).tolist(), np.linspace(0.1, 2, 263).tolist()
    save_checkpoint(tmp_path / "ckpt", model=vae, kind="vae", config={"model": asdict(vae.config), "train": {}},
                    step=7, extra={"mean": mean, "std": std})
    loaded, meta = load_vae(tmp_path / "ckpt")
    x, mask = _batch([40, 25])
    with torch.no_grad():
        assert all(torch.equal(a, b) for a, b in zip(vae(x, mask, sample=False), loaded(x, mask, sample=False)))
    assert meta["step"] == 7 and meta["mean"].tolist() == np.float32(mean).tolist()
    assert np.array_equal(meta["std"], np.float32(std))


@pytest.mark.parametrize("loss", ["mse", "mld"])
def test_resume_continues_at_the_same_step(shard, tmp_path, loss):
    """10 steps, then resumed to 20 == 20 uninterrupted steps: bitwise on CPU with num_workers=0.

    Dropout, the reparameterisation noise and the dataset's random crops all draw from the restored
    torch RNG, the sampler continues at the saved epoch and batch, and AdamW's state is restored,
    so every operation repeats exactly.
    """
    cfg = VAETrainConfig(lr=1e-3, batch_size=4, max_steps=10, val_every=5, ckpt_every=10, log_every=5, seed=3,
                         loss=loss)
    train_vae(shard, tmp_path / "a", model=TINY, train=cfg, device="cpu", progress=False)
    assert load_state(tmp_path / "a")["step"] == 10
    with pytest.raises(OutputError, match="--resume"):
        train_vae(shard, tmp_path / "a", model=TINY, train=cfg, device="cpu", progress=False)
    resumed = train_vae(shard, tmp_path / "a", model=TINY, train=replace(cfg, max_steps=20), device="cpu",
                        resume=True, progress=False)
    straight = train_vae(shard, tmp_path / "b", model=TINY, train=replace(cfg, max_steps=20), device="cpu",
                         progress=False)
    assert resumed["step"] == straight["step"] == 20
    wa, meta = load_weights(tmp_path / "a", prefer="last")
    wb, _ = load_weights(tmp_path / "b", prefer="last")
    assert meta["step"] == 20
    assert all(torch.equal(wa[k], wb[k]) for k in wb)
    log_a, log_b = _log(tmp_path / "a"), _log(tmp_path / "b")
    assert [r["step"] for r in log_a] == [r["step"] for r in log_b] == ["5", "10", "15", "20"]
    assert ("recon_joints" in log_a[0]) == (loss == "mld")
    for ra, rb in zip(log_a, log_b):
        assert {k: v for k, v in ra.items() if k != "sec_per_step"} == {k: v for k, v in rb.items() if k != "sec_per_step"}
    assert resumed == straight
    with pytest.raises(ValueError, match="model config"):
        train_vae(shard, tmp_path / "a", model=replace(TINY, d_model=64), train=replace(cfg, max_steps=30),
                  device="cpu", resume=True, progress=False)


def test_divergence_stops_and_keeps_the_last_good_checkpoint(shard, tmp_path):
    cfg = VAETrainConfig(lr=1e-3, batch_size=4, max_steps=4, val_every=4, ckpt_every=4, log_every=2)
    train_vae(shard, tmp_path, model=TINY, train=cfg, device="cpu", progress=False)
    good, _ = load_weights(tmp_path, prefer="last")
    # lr = 1e30: AdamW moves every weight by ~1e30, the next forward pass overflows to inf/NaN.
    with pytest.raises(TrainingDiverged, match="step"):
        train_vae(shard, tmp_path, model=TINY, train=replace(cfg, lr=1e30, max_steps=50, ckpt_every=1000),
                  device="cpu", resume=True, progress=False)
    vae, meta = load_vae(tmp_path / "last")
    assert meta["step"] == 4
    assert all(torch.equal(v, good[k]) for k, v in vae.state_dict().items())


def test_a_run_saved_before_the_shared_loop_resumes_exactly(shard, tmp_path):
    """A state.pt in train_vae's own earlier layout (best_val_mpjpe_m, val_mpjpe_m) is continued bit for bit."""
    cfg = VAETrainConfig(lr=1e-3, batch_size=4, max_steps=6, val_every=3, ckpt_every=6, log_every=3, seed=5)
    train_vae(shard, tmp_path / "old", model=TINY, train=cfg, device="cpu", progress=False)
    state = load_state(tmp_path / "old")
    best, val = state.pop("best"), state.pop("val")
    torch.save({**state, "best_val_mpjpe_m": best, "val_mpjpe_m": val["mpjpe_m"]}, tmp_path / "old/last/state.pt")
    outputs.record(tmp_path / "old" / "last")  # as the earlier version recorded its checkpoint
    longer = replace(cfg, max_steps=12)
    resumed = train_vae(shard, tmp_path / "old", model=TINY, train=longer, device="cpu", resume=True, progress=False)
    straight = train_vae(shard, tmp_path / "new", model=TINY, train=longer, device="cpu", progress=False)
    assert resumed == straight and resumed["best_val_mpjpe_m"] <= best
    wa, wb = load_weights(tmp_path / "old", prefer="last")[0], load_weights(tmp_path / "new", prefer="last")[0]
    assert all(torch.equal(wa[k], wb[k]) for k in wb)


def test_a_run_keeps_its_cpu_threads_across_resumes(shard, tmp_path, monkeypatch):
    """The count a run starts with is recorded in last/state.pt and reused by a resume, whatever the load then;
    a count fixed by the user on resume wins, and train.log says the steps now differ in rounding."""
    cfg = VAETrainConfig(lr=1e-3, batch_size=4, max_steps=2, val_every=2, ckpt_every=2, log_every=2, seed=3)
    monkeypatch.setenv("LSGAN_THREADS", "2")
    train_vae(shard, tmp_path, model=TINY, train=cfg, device="cpu", progress=False)
    assert load_state(tmp_path)["threads"] == 2
    monkeypatch.delenv("LSGAN_THREADS")
    train_vae(shard, tmp_path, model=TINY, train=replace(cfg, max_steps=4), device="cpu", resume=True, progress=False)
    assert load_state(tmp_path)["threads"] == 2
    monkeypatch.setenv("LSGAN_THREADS", "1")
    train_vae(shard, tmp_path, model=TINY, train=replace(cfg, max_steps=6), device="cpu", resume=True, progress=False)
    assert load_state(tmp_path)["threads"] == 1
    log = (tmp_path / "train.log").read_text()
    assert log.count("CPU threads for this run") == 1 and "trained on 2 CPU threads and continues on 1" in log


@pytest.mark.parametrize("batch_size, budget", [(256, None), (5, None), (256, 100), (4, 90), (256, 10)])
def test_decode_batches_sort_by_length_and_keep_the_frame_budget(batch_size, budget):
    """Every motion once; lengths ascending; at most batch_size motions and budget padded frames a pass (a
    longer motion alone); without a budget, full batches of batch_size."""
    from lsgan.generation import decode_batches

    frames = [int(f) for f in np.random.default_rng(0).integers(1, 60, 37)]
    batches = decode_batches(frames, batch_size, budget)
    flat = [i for b in batches for i in b]
    assert sorted(flat) == list(range(37))
    assert [frames[i] for i in flat] == sorted(frames)
    for b in batches:
        assert len(b) <= batch_size
        assert budget is None or len(b) == 1 or len(b) * max(frames[i] for i in b) <= budget
    if budget is None:
        assert [len(b) for b in batches[:-1]] == [batch_size] * (len(batches) - 1)


def test_decoding_in_frame_budget_batches_gives_the_same_features():
    """A motion's features do not depend on the pass it was decoded in (padding masked)."""
    from lsgan.generation import decode_batches

    torch.manual_seed(0)
    vae = MotionVAE(VAEConfig(d_model=32, num_heads=4, ff_size=64, num_layers=3)).eval()
    frames = [40, 7, 33, 40, 12, 25]
    z = torch.randn(len(frames), 256)
    with torch.no_grad():
        alone = [vae.decode(z[i:i + 1], torch.ones(1, f, dtype=torch.bool))[0] for i, f in enumerate(frames)]
        for idx in decode_batches(frames, 256, 80):
            lengths = torch.tensor([frames[i] for i in idx])
            out = vae.decode(z[idx], torch.arange(int(lengths.max()))[None] < lengths[:, None])
            for j, i in enumerate(idx):
                torch.testing.assert_close(out[j, :frames[i]], alone[i], atol=1e-5, rtol=0)
