"""Evaluators: the official T2M loader (on a random state dict in the official layout), our own text-motion
evaluator trained on a tiny synthetic shard, and the action-recognition GRU."""
from __future__ import annotations

import csv
import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lsgan.outputs import OutputError
import torch
from torch.nn.utils.rnn import pack_padded_sequence

from lsgan.data.preprocess import preprocess
from lsgan.data.sources.synthetic import SyntheticSource
from lsgan.data.tokens import tokenize
from lsgan.models.evaluator import (
    ActionClassifier,
    ActionClassifierConfig,
    ActionRecognitionGRU,
    EvaluatorConfig,
    load_action_classifier,
    load_evaluator,
    prepare_joints,
)
from lsgan.models.t2m_modules import MotionEncoderBiGRUCo, MovementConvEncoder, TextEncoderBiGRUCo, contrastive_loss
from lsgan.models.word_vectorizer import POS_ENUMERATOR, WordVectorizer
from lsgan.recipes import build, load_recipe, section
from lsgan.train.evaluator import (
    ActionTrainConfig,
    EvaluatorTrainConfig,
    heldout_pairs,
    train_action_classifier,
    train_evaluator,
)

# ------------------------------------------------------------------------------------------------------------------
# The official T2M evaluator: modules with the official sizes, randomly initialised, in the official files

VOCAB = ["unk", "sos", "eos", "a", "person", "walk", "forward", "and", "wave", "his", "left", "hand", "slowly", "the"]


class Boom:
    """A pickle payload that runs code when loaded (it must be refused)."""

    def __reduce__(self):
        return (os.system, (f"touch {BOOM_FILE}",))


BOOM_FILE = Path("/tmp/lsgan-test-evaluator-pwned")


def _write_official(root: Path, prefix: str = "") -> dict:
    torch.manual_seed(0)
    text = TextEncoderBiGRUCo(300, len(POS_ENUMERATOR), 512, 512)
    movement = MovementConvEncoder(259, 512, 512)
    motion = MotionEncoderBiGRUCo(512, 1024, 512)
    with torch.no_grad():  # move every parameter off its init (zero biases...) so that a mis-mapped key shows
        for m in (text, movement, motion):
            for p in m.parameters():
                p.add_(0.05 * torch.randn_like(p))
    ckpt = {
        "text_encoder": text.state_dict(), "motion_encoder": motion.state_dict(),
        "movement_encoder": movement.state_dict(),
        "opt_text_encoder": torch.optim.Adam(text.parameters(), lr=1e-4).state_dict(),
        "opt_motion_encoder": torch.optim.Adam(motion.parameters(), lr=1e-4).state_dict(),
        "epoch": 1, "iter": 10,
    }
    base = root / prefix
    (base / "t2m/text_mot_match/model").mkdir(parents=True)
    torch.save(ckpt, base / "t2m/text_mot_match/model/finest.tar")
    rng = np.random.default_rng(0)
    (base / "t2m/Comp_v6_KLD01/meta").mkdir(parents=True)
    mean = rng.normal(0, 0.1, 263).astype(np.float32)
    std = rng.uniform(0.5, 1.5, 263).astype(np.float32)
    np.save(base / "t2m/Comp_v6_KLD01/meta/mean.npy", mean)
    np.save(base / "t2m/Comp_v6_KLD01/meta/std.npy", std)
    (root / "glove").mkdir()
    vectors = rng.normal(size=(len(VOCAB), 300))  # float64, as the official file
    np.save(root / "glove/our_vab_data.npy", vectors)
    with open(root / "glove/our_vab_idx.pkl", "wb") as f:
        pickle.dump({w: i for i, w in enumerate(VOCAB)}, f)
    with open(root / "glove/our_vab_words.pkl", "wb") as f:
        pickle.dump(list(VOCAB), f)
    return {"text": text.eval(), "movement": movement.eval(), "motion": motion.eval(), "mean": mean, "std": std,
            "vectors": vectors}


@pytest.fixture(scope="module")
def official(tmp_path_factory):
    root = tmp_path_factory.mktemp("t2m")
    return root, _write_official(root)


def _reference_text(m: dict, tokens: list[str]) -> np.ndarray:
    """T2M's text pipeline written out for one caption (Text2MotionDatasetV2 + WordVectorizer + the module)."""
    vip = {"left": "Loc_VIP", "forward": "Loc_VIP", "hand": "Body_VIP", "walk": "Act_VIP",
           "slowly": "Desc_VIP"}
    tokens = ["sos/OTHER", *tokens[:20], "eos/OTHER"]
    sent_len = len(tokens)
    tokens += ["unk/OTHER"] * (22 - sent_len)
    words, poses = [], []
    for t in tokens:
        w, p = t.split("/")
        pos = np.zeros(15)
        if w in VOCAB:
            words.append(m["vectors"][VOCAB.index(w)])
            pos[POS_ENUMERATOR[vip.get(w, p if p in POS_ENUMERATOR else "OTHER")]] = 1
        else:
            words.append(m["vectors"][VOCAB.index("unk")])
            pos[POS_ENUMERATOR["OTHER"]] = 1
        poses.append(pos)
    te = m["text"]
    with torch.no_grad():
        x = torch.tensor(np.array(words)).float()[None] + te.pos_emb(torch.tensor(np.array(poses)).float()[None])
        packed = pack_padded_sequence(te.input_emb(x), [sent_len], batch_first=True)
        _, last = te.gru(packed, te.hidden.repeat(1, 1, 1))
        return te.output_net(torch.cat([last[0], last[1]], -1))[0].numpy()


def _reference_motion(m: dict, features: np.ndarray) -> np.ndarray:
    """T2M's motion pipeline for one motion: crop to a multiple of 4, normalise, pad to 196, drop the contacts."""
    n = len(features) // 4 * 4
    x = (features[:n] - m["mean"]) / m["std"]
    if n < 196:
        x = np.concatenate([x, np.zeros((196 - n, 263))], 0)
    with torch.no_grad():
        mov = m["movement"](torch.tensor(x).float()[None, :, :-4])
        mo = m["motion"]
        packed = pack_padded_sequence(mo.input_emb(mov), [n // 4], batch_first=True)
        _, last = mo.gru(packed, mo.hidden.repeat(1, 1, 1))
        return mo.output_net(torch.cat([last[0], last[1]], -1))[0].numpy()


def _motions(lengths, seed=0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.normal(0, 1, (n, 263)).astype(np.float32) for n in lengths]


def test_official_loader_matches_the_t2m_pipeline(official, one_thread):
    root, m = official
    ev = load_evaluator(root)
    assert ev.id.startswith("t2m-official:") and ev.dim == 512
    caption = "A person walks forward and waves his left hand slowly."
    tokens = tokenize(caption)
    assert tokens.split()[2] == "walk/VERB"
    want = _reference_text(m, tokens.split())
    got = ev.embed_texts([caption, "the person"])  # tagged here, as the caption comes without tokens
    np.testing.assert_allclose(got[0], want, rtol=1e-4, atol=1e-5)
    # explicit (e.g. spaCy) tokens are used as given; an unknown word maps to unk/OTHER
    spacy = "a/DET person/NOUN stroll/VERB forward/ADV"
    np.testing.assert_allclose(ev.embed_texts(["x"], tokens=[spacy])[0], _reference_text(m, spacy.split()),
                               rtol=1e-4, atol=1e-5)

    # motions: shorter than 196 (padded), exactly 196 (no padding), longer, not a multiple of 4
    feats = _motions([61, 196, 120, 203, 40])
    got = ev.embed_motions(feats)
    for x, g in zip(feats, got):
        np.testing.assert_allclose(g, _reference_motion(m, x), rtol=1e-4, atol=1e-5)
    # a motion's embedding does not depend on the rest of the batch (up to rounding), and repeats are identical
    np.testing.assert_allclose(ev.embed_motions(feats[:1]), got[:1], rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(ev.embed_motions(feats), got)


def test_official_layout_under_checkpoints(tmp_path, one_thread):
    _write_official(tmp_path, prefix="checkpoints")  # the T2M repository: checkpoints/t2m/... beside glove/
    ev = load_evaluator(tmp_path)
    assert ev.embed_texts(["a person walks"]).shape == (1, 512)


@pytest.mark.parametrize("missing", ["t2m/Comp_v6_KLD01/meta/std.npy", "glove/our_vab_idx.pkl",
                                     "glove/our_vab_words.pkl", "t2m/text_mot_match/model/finest.tar"])
def test_a_missing_official_file_is_named(official, tmp_path, missing):
    root, _ = official
    import shutil

    shutil.copytree(root, tmp_path / "t2m-copy")
    (tmp_path / "t2m-copy" / missing).unlink()
    with pytest.raises(FileNotFoundError, match=Path(missing).name):
        load_evaluator(tmp_path / "t2m-copy")


def test_a_pickle_with_code_is_refused(official, tmp_path):
    root, _ = official
    import shutil

    shutil.copytree(root, tmp_path / "t2m-copy")
    BOOM_FILE.unlink(missing_ok=True)
    with open(tmp_path / "t2m-copy/glove/our_vab_idx.pkl", "wb") as f:
        pickle.dump({"unk": Boom()}, f)
    with pytest.raises(ValueError, match="our_vab_idx.pkl.*refus"):
        load_evaluator(tmp_path / "t2m-copy")
    assert not BOOM_FILE.exists()


def test_word_vectorizer_rules(official):
    root, m = official
    wv = WordVectorizer(root / "glove")
    vec, pos = wv["left/ADJ"]  # a VIP word gets its VIP category
    assert pos.argmax() == POS_ENUMERATOR["Loc_VIP"]
    np.testing.assert_allclose(vec, m["vectors"][VOCAB.index("left")].astype(np.float32))
    vec, pos = wv["zebra/NOUN"]  # unknown: unk with OTHER
    assert pos.argmax() == POS_ENUMERATOR["OTHER"]
    words, poses, n = wv.encode(["a/DET"] * 30)
    assert words.shape == (22, 300) and poses.shape == (22, 15) and n == 22  # 20 tokens + sos + eos
    assert wv.encode(["a/DET", "person/NOUN"])[2] == 4


def test_contrastive_loss_is_t2ms():
    a, b = torch.zeros(2, 3), torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 12.0]])
    assert contrastive_loss(a, b, False, 10.0).item() == pytest.approx((25 + 144) / 2, rel=1e-5)
    assert contrastive_loss(a, b, True, 10.0).item() == pytest.approx((25 + 0) / 2, rel=1e-5)


def test_no_evaluator_here(tmp_path):
    with pytest.raises(FileNotFoundError, match="finest.tar"):
        load_evaluator(tmp_path)


# ------------------------------------------------------------------------------------------------------------------
# Our own evaluator and the action classifier on a tiny synthetic shard

TINY_MODEL = {"movement_hidden": 64, "movement_latent": 64, "motion_hidden": 64, "embed_dim": 64, "text_hidden": 64}
TINY_TRAIN = {"lr": 2e-3, "batch_size": 32, "max_steps": 50, "val_every": 25, "ckpt_every": 25, "log_every": 5}


@pytest.fixture(scope="module")
def shard(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("evaluator-data") / "synth.h5"
    preprocess(SyntheticSource(num_clips=360, seed=1), path)
    return path


@pytest.fixture(scope="module")
def text_run(shard, tmp_path_factory):
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("runs") / "evaluator"
    result = train_evaluator(shard, out, config=EvaluatorConfig(**TINY_MODEL),
                             train_config=EvaluatorTrainConfig(**TINY_TRAIN), device="cpu", progress=False)
    return out, result


def test_evaluator_learns(text_run):
    out, result = text_run
    with open(out / "log.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    losses = [float(r["loss"]) for r in rows if r.get("loss")]
    assert np.mean(losses[-3:]) < 0.7 * np.mean(losses[:2]), losses
    h = result["heldout"]
    print("held-out:", json.dumps(h))
    assert h["split"] == "test" and h["group_size"] == 32 and h["pairs"] >= 32
    assert h["r_precision_top3"] > 3 * h["chance_top3"], h  # chance is 3/32
    assert h["r_precision_top1"] <= h["r_precision_top2"] <= h["r_precision_top3"]
    assert json.loads((out / "heldout.json").read_text()) == h


def test_evaluator_reloads_to_identical_embeddings(text_run, shard, one_thread):
    out, result = text_run
    feats, caps, _ = heldout_pairs(shard, "test")
    ev = load_evaluator(out)
    again = load_evaluator(out / "best")
    assert ev.id == again.id == result["heldout"]["evaluator"]
    m, t = ev.embed_motions(feats), ev.embed_texts(caps)
    assert m.shape == (len(feats), 64) and t.shape == (len(caps), 64)
    np.testing.assert_array_equal(m, again.embed_motions(feats))
    np.testing.assert_array_equal(t, again.embed_texts(caps))
    np.testing.assert_allclose(m[:3], ev.embed_motions(feats[:3]), rtol=1e-4, atol=1e-5)  # nor does the batch
    # the reported figures are those of the saved checkpoint
    from lsgan.train.evaluator import retrieval_report

    rep = retrieval_report(t, m, group_size=32, repeats=10, seed=0)
    assert rep["r_precision_top3"] == pytest.approx(result["heldout"]["r_precision_top3"])
    meta = json.loads((out / "best" / "config.json").read_text())
    assert meta["kind"] == "evaluator" and len(meta["extra"]["mean"]) == 263


def test_resume_continues_exactly(shard, tmp_path, one_thread):
    cfg = EvaluatorConfig(**{**TINY_MODEL, "motion_hidden": 32})
    short = dict(TINY_TRAIN, val_every=3, ckpt_every=3, log_every=3, max_steps=6, eval_repeats=1)
    train_evaluator(shard, tmp_path / "a", config=cfg, train_config=EvaluatorTrainConfig(**short), device="cpu",
                    progress=False)
    train_evaluator(shard, tmp_path / "b", config=cfg, train_config=EvaluatorTrainConfig(**{**short, "max_steps": 3}),
                    device="cpu", progress=False)
    with pytest.raises(OutputError, match="--resume"):
        train_evaluator(shard, tmp_path / "b", config=cfg, train_config=EvaluatorTrainConfig(**short), device="cpu",
                        progress=False)
    train_evaluator(shard, tmp_path / "b", config=cfg, train_config=EvaluatorTrainConfig(**short), device="cpu",
                    progress=False, resume=True)
    from safetensors.torch import load_file

    wa, wb = load_file(tmp_path / "a/last/model.safetensors"), load_file(tmp_path / "b/last/model.safetensors")
    for k in wa:
        torch.testing.assert_close(wa[k], wb[k], rtol=0, atol=0)


def test_cli_trains_and_reports(shard, tmp_path):
    (tmp_path / "tiny.yaml").write_text(
        "evaluator:\n"
        f"  text:\n    model: {json.dumps(TINY_MODEL)}\n    train: {json.dumps({**TINY_TRAIN, 'eval_repeats': 2})}\n"
        "  action:\n    model: {hidden_size: 16}\n    train: {batch_size: 32, val_every: 2, ckpt_every: 2}\n")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-m", "lsgan.cli", "train-evaluator", "--data", shard, "--recipe", "tiny.yaml",
                          "--out", "ev", "--max-steps", "3"], capture_output=True, text=True, cwd=tmp_path, env=env, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "R-precision top-1" in out.stdout and "MM-Dist" in out.stdout
    assert (tmp_path / "ev/best/model.safetensors").exists()
    out = subprocess.run([sys.executable, "-m", "lsgan.cli", "train-evaluator", "--data", shard, "--recipe", "tiny.yaml",
                          "--kind", "action", "--out", "clf", "--max-steps", "2"], capture_output=True, text=True,
                         cwd=tmp_path, env=env, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "accuracy" in out.stdout
    out = subprocess.run([sys.executable, "-m", "lsgan.cli", "train-evaluator", "--data", shard, "--out", "ev"],
                         capture_output=True, text=True, cwd=tmp_path, env=env, check=False)
    assert out.returncode != 0 and "already holds a run" in out.stderr


def test_action_classifier_learns(shard, tmp_path, one_thread):
    result = train_action_classifier(
        shard, tmp_path / "clf", config=ActionClassifierConfig(hidden_size=64),
        train_config=ActionTrainConfig(lr=3e-3, batch_size=32, max_steps=120, val_every=40, ckpt_every=40,
                                       log_every=10, max_frames=120),
        device="cpu", progress=False)
    h = result["heldout"]
    print("held-out:", json.dumps(h))
    assert h["split"] == "test" and h["clips"] >= 20
    assert h["accuracy"] > 3 * h["chance"], h  # 13 classes
    clf = load_action_classifier(tmp_path / "clf")
    assert clf.action_names[0] == "jump" and len(clf.action_names) == 13
    from lsgan.data.features import recover_from_ric
    from lsgan.data.shards import Shard

    with Shard(shard) as s:
        joints = [recover_from_ric(s.features(i)) for i in s.indices("test")[:4]]
    f = clf.features(joints)
    assert f.shape == (4, 30) and np.abs(f).max() <= 1.0
    np.testing.assert_allclose(f[1:2], clf.features(joints[1:2]), atol=1e-5)  # padding in a batch changes nothing
    assert clf.predict(joints).shape == (4,)


def test_action_features_ignore_position_and_padding():
    torch.manual_seed(0)
    clf = ActionClassifier(ActionRecognitionGRU(ActionClassifierConfig(hidden_size=16, num_classes=3)), "abc", id="t")
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(30, 22, 3)), rng.normal(size=(50, 22, 3))
    np.testing.assert_allclose(prepare_joints(a + [1.0, 0.0, 2.0]), prepare_joints(a), atol=1e-6)
    both = clf.features([a, b])
    np.testing.assert_allclose(both[0], clf.features([a])[0], atol=1e-6)
    np.testing.assert_allclose(both[0], clf.features([a + 5.0])[0], atol=1e-5)


def test_recipes_have_buildable_evaluator_sections():
    kinds = {"text": (EvaluatorConfig, EvaluatorTrainConfig), "action": (ActionClassifierConfig, ActionTrainConfig)}
    want = {"demo": {"text", "action"}, "bandai": {"text", "action"}, "humanml3d": {"text"}, "humanact12": {"action"}}
    for name, expected in want.items():
        sections = section(load_recipe(name), "evaluator")
        assert set(sections) == expected, name
        for kind in sections:
            model, train = kinds[kind]
            build(model, section(sections[kind], "model"), f"{name}.evaluator.{kind}.model")
            t = build(train, section(sections[kind], "train"), f"{name}.evaluator.{kind}.train")
            if kind == "text":
                assert t.max_frames <= build(model, section(sections[kind], "model")).max_motion_length
    hml = section(section(load_recipe("humanml3d"), "evaluator"), "text")
    assert hml["train"]["lr"] == 1e-4 and hml["train"]["batch_size"] == 32 and hml["train"]["margin"] == 10.0
    assert hml["model"]["motion_hidden"] == 1024 and hml["model"]["embed_dim"] == 512
