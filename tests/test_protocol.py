"""T2M's protocol to the token: caption tokens kept and fed to the evaluator, time tags turned into frames with
T2M's rule (NaN included), old shards still read, and FID's real set as T2M (separate pass) or MLD (same draw).

Captions are written in HumanML3D's ``caption#word/POS ...#start#end`` line format; the first four lines are the
examples of HumanML3D's README. The T2M evaluator is a stand-in: random weights in the official checkpoint layout.
"""
from __future__ import annotations

import json
import pickle
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from torch.nn.utils.rnn import pack_padded_sequence

import lsgan.eval.evaluate as evaluate_module
from lsgan.data.captions import span_frames
from lsgan.data.dataset import MotionDataset
from lsgan.data.preprocess import preprocess
from lsgan.data.shards import FORMAT_VERSION, Shard
from lsgan.data.sources.humanml3d import HumanML3DSource, parse_caption_line
from lsgan.data.sources.synthetic import SyntheticSource
from lsgan.data.tokens import tokenize
from lsgan.models.evaluator import load_evaluator
from lsgan.models.t2m_modules import MotionEncoderBiGRUCo, MovementConvEncoder, TextEncoderBiGRUCo
from lsgan.models.word_vectorizer import POS_ENUMERATOR

README_LINES = [  # HumanML3D's README (EricGuo5513/HumanML3D): texts/ID.txt as the dataset ships it
    "a man kicks something or someone with his left leg.#a/DET man/NOUN kick/VERB something/PRON or/CCONJ "
    "someone/PRON with/ADP his/DET left/ADJ leg/NOUN#0.0#0.0",
    "the standing person kicks with their left foot before going back to their original stance.#the/DET "
    "stand/VERB person/NOUN kick/VERB with/ADP their/DET left/ADJ foot/NOUN before/ADP go/VERB back/ADV to/ADP "
    "their/DET original/ADJ stance/NOUN#0.0#0.0",
    "a man kicks with something or someone with his left leg.#a/DET man/NOUN kick/VERB with/ADP something/PRON "
    "or/CCONJ someone/PRON with/ADP his/DET left/ADJ leg/NOUN#0.0#0.0",
    "he is flying kick with his left leg#he/PRON is/AUX fly/VERB kick/NOUN with/ADP his/DET left/ADJ leg/NOUN#0.0#0.0",
]
VOCAB = ["unk", "sos", "eos", "a", "man", "kick", "something", "or", "someone", "with", "his", "left", "leg", "the",
         "stand", "person", "their", "foot", "before", "go", "back", "to", "original", "stance", "he", "is", "fly",
         "walk", "forward", "wave", "hand", "turn", "around"]


def t2m_frames(length: int, line: str) -> tuple[int, int] | None:
    """T2M's loader (data/dataset.py, Text2MotionDatasetV2 of EricGuo5513/text-to-motion) written out for one
    line: None for a whole-clip caption, else the (first, stop) frames of its slice of the motion ((0, 0): empty,
    which T2M skips)."""
    line_split = line.strip().split("#")
    f_tag = float(line_split[2])
    to_tag = float(line_split[3])
    f_tag = 0.0 if np.isnan(f_tag) else f_tag
    to_tag = 0.0 if np.isnan(to_tag) else to_tag
    if f_tag == 0.0 and to_tag == 0.0:
        return None
    n_motion = np.arange(length)[int(f_tag * 20): int(to_tag * 20)]
    return (int(n_motion[0]), int(n_motion[-1]) + 1) if len(n_motion) else (0, 0)


def write_hml(root: Path, clips: dict[str, tuple[int, list[str]]], split: str = "test", seed: int = 0) -> Path:
    """A processed-HumanML3D folder: per clip id (frames, caption lines), random features, one split file."""
    rng = np.random.default_rng(seed)
    for sub in ("new_joint_vecs", "texts"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    for name, (frames, lines) in clips.items():
        np.save(root / "new_joint_vecs" / f"{name}.npy", rng.normal(0, 1, (frames, 263)).astype(np.float32))
        (root / "texts" / f"{name}.txt").write_text("".join(line + "\n" for line in lines), encoding="utf-8")
    (root / f"{split}.txt").write_text("".join(f"{n}\n" for n in clips))
    return root


def windows_by_line(shard_path: Path, lines: list[str]) -> dict[str, tuple[int, int]]:
    """Each caption line of a one-clip shard -> its window's frames ((0, 0): it has none)."""
    ds = MotionDataset(shard_path, None, min_frames=1, max_frames=10_000, crop_long=False)
    out = {line: (0, 0) for line in lines}
    for w in ds.windows:
        for k in w.captions:
            out[lines[k]] = (w.start, w.stop)
    return out


def t2m_window(length: int, line: str) -> tuple[int, int]:
    """:func:`t2m_frames` as a window: a whole-clip caption's is the whole clip."""
    span = t2m_frames(length, line)
    return (0, length) if span is None else span


def _tags(line: str) -> tuple[float, float]:
    c = parse_caption_line(line)
    return c.start, c.end


# ------------------------------------------------------------------------------------------------------------------
# Time tags -> frames


def test_frames_follow_t2ms_rule_for_every_one_decimal_tag(tmp_path):
    tags = [f"{i / 10:.1f}" for i in range(1, 101)]
    lines = [f"up to {t}#up/ADP#0.0#{t}" for t in tags] + [f"from {t}#from/ADP#{t}#12.0" for t in tags]
    write_hml(tmp_path / "hml", {"000001": (250, lines)})
    preprocess(HumanML3DSource(root=str(tmp_path / "hml")), tmp_path / "s.h5")
    got = windows_by_line(tmp_path / "s.h5", lines)
    for line in lines:
        assert got[line] == t2m_window(250, line), line
    # 9.2 s: float("9.2") * 20 is 184.0, so T2M cuts 184 frames; the float32 tags of old shards gave 183
    assert got["up to 9.2#up/ADP#0.0#9.2"] == (0, 184) and int(9.2 * 20) == 184
    assert int(float(np.float32(9.2)) * 20) == 183
    moved = [t for t in tags if int(float(t) * 20) != int(float(np.float32(t)) * 20)]
    assert len(moved) == 38  # the share of one-decimal tags a float32 store moved by a frame


def test_span_frames_is_t2ms_rule_on_finer_tags():
    for i in range(0, 2001):
        for start in ("0.0", "1.35", "nan"):
            line = f"x#x/NOUN#{start}#{i / 100:.2f}"
            ours = span_frames(*_tags(line), 300)
            assert (ours if ours is None or ours[1] > ours[0] else (0, 0)) == t2m_frames(300, line), line


def test_nan_tags_as_t2m(tmp_path):
    lines = ["both nan#both/DET nan/NOUN#nan#nan", "start nan#start/NOUN nan/NOUN#nan#5.0",
             "end nan#end/NOUN nan/NOUN#2.0#nan", "zero and nan#zero/NOUN#0.0#nan", "plain#plain/ADJ#1.0#4.0"]
    write_hml(tmp_path / "hml", {"000001": (160, lines)})
    preprocess(HumanML3DSource(root=str(tmp_path / "hml")), tmp_path / "s.h5")
    with Shard(tmp_path / "s.h5") as shard:
        caps = shard.captions(0)
    assert np.isnan(caps[0].start) and np.isnan(caps[1].start) and caps[1].end == 5.0  # kept as the text gives them
    got = windows_by_line(tmp_path / "s.h5", lines)
    assert got == {line: t2m_window(160, line) for line in lines}
    assert got == {lines[0]: (0, 160), lines[1]: (0, 100), lines[2]: (0, 0), lines[3]: (0, 160), lines[4]: (20, 80)}
    ds = MotionDataset(tmp_path / "s.h5", None, min_frames=1)
    assert sorted(w.captions for w in ds.windows) == [(0, 3), (1,), (4,)]  # whole-clip captions share one window
    # written back in HumanML3D's layout, the tags read back the same (T2M parses 'nan' too)
    with Shard(tmp_path / "s.h5") as shard:
        out = tmp_path / "back"
        from lsgan.data.humanml3d_format import write_humanml3d_folder
        from lsgan.data.shards import ClipRecord

        write_humanml3d_folder(out, [ClipRecord("000001", shard.features(0), "test", captions=shard.captions(0))])
    back = (out / "texts" / "000001.txt").read_text().splitlines()
    assert [t2m_frames(160, line) for line in back] == [t2m_frames(160, line) for line in lines]


def test_shard_format_version_and_old_shards(tmp_path):
    tags = [f"{i / 10:.1f}" for i in range(1, 101)]
    lines = [f"up to {t}#up/ADP#0.0#{t}" for t in tags] + ["a person walks forward##0.0#0.0"]
    write_hml(tmp_path / "hml", {"000001": (250, lines)})
    preprocess(HumanML3DSource(root=str(tmp_path / "hml")), tmp_path / "v2.h5")
    new = windows_by_line(tmp_path / "v2.h5", lines)
    with h5py.File(tmp_path / "v2.h5", "r") as f:
        assert FORMAT_VERSION == 2 and f.attrs["format_version"] == 2 and f["captions/start"].dtype == np.float64
    # the same shard as version 1 wrote it: float32 tags, no tokens for a caption that had none
    with h5py.File(tmp_path / "v2.h5", "a") as f:
        for key in ("start", "end"):
            values = f[f"captions/{key}"][()].astype(np.float32)
            del f[f"captions/{key}"]
            f.create_dataset(f"captions/{key}", data=values)
        tokens = f["captions/tokens"][()]
        tokens[-1] = b""
        del f["captions/tokens"]
        f.create_dataset("captions/tokens", data=tokens, dtype=h5py.string_dtype("utf-8"))
        f.attrs["format_version"] = 1
    with Shard(tmp_path / "v2.h5") as shard:
        caps = shard.captions(0)
    assert [c.end for c in caps[:-1]] == [float(t) for t in tags]  # each tag is float() of its text again
    assert caps[-1].tokens == tokenize("a person walks forward") == "a/DET person/NOUN walk/VERB forward/ADV"
    assert windows_by_line(tmp_path / "v2.h5", lines) == new


# ------------------------------------------------------------------------------------------------------------------
# Tokens


def test_shards_keep_humanml3ds_tokens_and_importers_tag_the_rest(tmp_path):
    lines = README_LINES + ["a person walks forward", "a person waves#  #0.0#0.0"]
    write_hml(tmp_path / "hml", {"000001": (80, lines)})
    preprocess(HumanML3DSource(root=str(tmp_path / "hml")), tmp_path / "h.h5")
    with Shard(tmp_path / "h.h5") as shard:
        tokens = [c.tokens for c in shard.captions(0)]
    assert tokens[:4] == [line.split("#")[1] for line in README_LINES]  # verbatim, not re-tagged
    assert tokens[4:] == [tokenize("a person walks forward"), tokenize("a person waves")]
    preprocess(SyntheticSource(num_clips=3), tmp_path / "synth.h5")
    with Shard(tmp_path / "synth.h5") as shard:
        caps = [c for i in range(len(shard)) for c in shard.captions(i)]
    assert caps and all(c.tokens and c.tokens == tokenize(c.text) for c in caps)


def test_tagger_follows_humanml3ds_tagging():
    for line in README_LINES[:3]:
        text, tokens = line.split("#")[:2]
        assert tokenize(text) == tokens
    ours, theirs = tokenize(README_LINES[3].split("#")[0]).split(), README_LINES[3].split("#")[1].split()
    assert [(a, b) for a, b in zip(ours, theirs) if a != b] == [("kick/VERB", "kick/NOUN")]  # spaCy's reading
    # process_text's rules: hyphens removed, only alphabetic words, nouns and verbs lemmatised
    assert tokenize("A person's full-body stretch, 2 times") == "a/DET person/NOUN fullbody/NOUN stretch/VERB time/NOUN"
    assert tokenize("raises both hands") == "raise/VERB both/DET hand/NOUN"


# ------------------------------------------------------------------------------------------------------------------
# lsgan evaluate on a stand-in T2M evaluator


def write_t2m(root: Path) -> dict:
    """The official evaluator's files (t2m/..., glove/...) with small random modules of the official classes."""
    torch.manual_seed(0)
    text = TextEncoderBiGRUCo(300, len(POS_ENUMERATOR), 32, 16)
    movement = MovementConvEncoder(259, 32, 32)
    motion = MotionEncoderBiGRUCo(32, 32, 16)
    with torch.no_grad():
        for m in (text, movement, motion):
            for p in m.parameters():
                p.add_(0.05 * torch.randn_like(p))
    (root / "t2m/text_mot_match/model").mkdir(parents=True)
    torch.save({"text_encoder": text.state_dict(), "movement_encoder": movement.state_dict(),
                "motion_encoder": motion.state_dict(), "epoch": 1},
               root / "t2m/text_mot_match/model/finest.tar")
    (root / "t2m/Comp_v6_KLD01/meta").mkdir(parents=True)
    np.save(root / "t2m/Comp_v6_KLD01/meta/mean.npy", np.zeros(263, np.float32))
    np.save(root / "t2m/Comp_v6_KLD01/meta/std.npy", np.ones(263, np.float32))
    (root / "glove").mkdir()
    vectors = np.random.default_rng(0).normal(size=(len(VOCAB), 300))
    np.save(root / "glove/our_vab_data.npy", vectors)
    with open(root / "glove/our_vab_idx.pkl", "wb") as f:
        pickle.dump({w: i for i, w in enumerate(VOCAB)}, f)
    with open(root / "glove/our_vab_words.pkl", "wb") as f:
        pickle.dump(list(VOCAB), f)
    return {"text": text.eval(), "vectors": vectors}


def reference_text(m: dict, tokens: str) -> np.ndarray:
    """T2M's text side for one caption: Text2MotionDatasetV2's token handling + WordVectorizer + the encoder."""
    vip = {"left": "Loc_VIP", "back": "Loc_VIP", "forward": "Loc_VIP", "leg": "Body_VIP", "foot": "Body_VIP",
           "hand": "Body_VIP", "kick": "Act_VIP", "walk": "Act_VIP", "turn": "Act_VIP", "stand": "Act_VIP"}
    toks = tokens.split(" ")
    toks = ["sos/OTHER", *toks[:20], "eos/OTHER"]
    sent_len = len(toks)
    toks += ["unk/OTHER"] * (22 - sent_len)
    words, poses = [], []
    for t in toks:
        w, p = t.split("/")
        pos = np.zeros(15)
        known = w in VOCAB
        words.append(m["vectors"][VOCAB.index(w if known else "unk")])
        pos[POS_ENUMERATOR[(vip.get(w) or (p if p in POS_ENUMERATOR else "OTHER")) if known else "OTHER"]] = 1
        poses.append(pos)
    te = m["text"]
    with torch.no_grad():
        x = torch.tensor(np.array(words)).float()[None] + te.pos_emb(torch.tensor(np.array(poses)).float()[None])
        packed = pack_padded_sequence(te.input_emb(x), [sent_len], batch_first=True)
        _, last = te.gru(packed, te.hidden)
        return te.output_net(torch.cat([last[0], last[1]], -1))[0].numpy()


EXTRA_LINES = [  # tokens that the tagger would not give, so that a re-tagged caption shows
    "a person walks forward#a/DET person/NOUN walk/NOUN forward/ADJ#0.0#0.0",
    "someone waves a hand#someone/NOUN wave/VERB a/DET hand/NOUN#0.0#0.0",
    "the man turns around#the/DET man/PROPN turn/VERB around/ADV#1.0#4.5",
]


@pytest.fixture(scope="module")
def t2m_setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("protocol")
    stand_in = write_t2m(d / "t2m")
    lines = README_LINES + EXTRA_LINES
    clips = {f"{i:06d}": (60 + 3 * i, [lines[i % len(lines)], lines[(i + 3) % len(lines)]]) for i in range(36)}
    write_hml(d / "hml", clips)
    preprocess(HumanML3DSource(root=str(d / "hml")), d / "data.h5")
    return d, stand_in, {line.split("#")[0]: line.split("#")[1] for line in lines}


def record_and_copy(monkeypatch) -> dict:
    """Record what evaluate gives the evaluator; a stand-in generator that returns the real motions of the draw
    whose captions and lengths it is asked for (a perfect copy model)."""
    seen: dict = {"texts": [], "draws": []}
    real_draw = evaluate_module._draw

    def recording_draw(dataset, seed):
        out = real_draw(dataset, seed)
        seen["draws"].append(out)
        return out

    def loader(path, device="cpu"):
        ev = load_evaluator(path, device=device)
        embed = ev.embed_texts

        def embed_texts(captions, *, tokens=None, batch_size=256):
            out = embed(captions, tokens=tokens, batch_size=batch_size)
            seen["texts"].append((list(captions), list(tokens), out))
            return out
        ev.embed_texts = embed_texts
        return ev

    def copy_model(gan, vae, requests, *, num=1, seed=0, device="cpu", **kwargs):
        assert num == 1
        want = ([r.text for r in requests], [r.frames for r in requests])
        match = [d for d in seen["draws"] if (d.captions, [len(m) for m in d.motions]) == want]
        assert match and all(np.array_equal(np.concatenate(d.motions), np.concatenate(match[0].motions)) for d in match)
        return SimpleNamespace(motions=[SimpleNamespace(features=m) for m in match[0].motions])

    monkeypatch.setattr(evaluate_module, "_draw", recording_draw)
    monkeypatch.setattr("lsgan.models.evaluator.load_evaluator", loader)
    monkeypatch.setattr("lsgan.generate.generate", copy_model)
    return seen


def run_table(d: Path, **kwargs):
    return evaluate_module.evaluate_text_to_motion({"copy": str(d / "hml")}, d / "hml", d / "data.h5", d / "t2m",
                                                   replications=2, mm_captions=0, device="cpu", **kwargs)


def test_evaluate_feeds_the_stored_tokens_to_the_t2m_evaluator(t2m_setup, monkeypatch, one_thread):
    d, stand_in, tokens_of = t2m_setup
    seen = record_and_copy(monkeypatch)
    run_table(d)
    assert len(seen["texts"]) == 2
    for captions, tokens, emb in seen["texts"]:
        assert len(captions) >= 32 and tokens == [tokens_of[c] for c in captions]
        for k in range(len(captions)):
            np.testing.assert_allclose(emb[k], reference_text(stand_in, tokens[k]), rtol=1e-4, atol=1e-5)
    differs = [c for c in tokens_of if tokenize(c) != tokens_of[c]]
    assert len(differs) >= 4  # the token path matters: re-tagging would change these captions' encoder input
    ev = load_evaluator(d / "t2m")
    assert not np.allclose(ev.embed_texts(differs), ev.embed_texts(differs, tokens=[tokens_of[c] for c in differs]))


def test_fid_reference_separate_and_same(t2m_setup, monkeypatch, one_thread):
    d, _, _ = t2m_setup
    record_and_copy(monkeypatch)
    default, separate, same = run_table(d), run_table(d, fid_reference="separate"), run_table(d, fid_reference="same")
    assert default.rows == separate.rows and default.info["fid_reference"] == "separate"
    real, copy = separate.rows["Real"]["fid"], separate.rows["copy"]["fid"]
    assert min(real) > 0.01
    # separate (T2M, MDM): every row against a second real pass, so a perfect copy scores as Real does
    np.testing.assert_allclose(copy, real, rtol=1e-6)
    # same (MLD): model rows against the draw that gave their captions and lengths: a perfect copy scores 0
    assert same.rows["Real"]["fid"] == real and max(same.rows["copy"]["fid"]) < 1e-3 * min(real)
    assert same.info["fid_reference"] == "same"
    assert "FID reference: each row against a separate pass" in separate.to_markdown()
    assert "FID reference: model rows against the real draw" in same.to_markdown()
    assert same.to_json()["info"]["fid_reference"] == "same" and same.to_json()["notes"] == same.notes
    with pytest.raises(ValueError, match="fid_reference"):
        run_table(d, fid_reference="mld")


def test_cli_fid_reference_option(tmp_path, monkeypatch):
    from lsgan.cli import main
    from lsgan.eval.evaluate import Table

    for name in ("gan", "vae", "data.h5", "ev"):
        (tmp_path / name).mkdir() if "." not in name else (tmp_path / name).write_bytes(b"")
    given = {}

    def fake(models, vae, data, evaluator, **kwargs):
        given.update(kwargs)
        return Table("text-to-motion", ("fid",), rows={"Real": {"fid": [1.0]}}, notes=["note"])
    monkeypatch.setattr(evaluate_module, "evaluate_text_to_motion", fake)
    args = ["evaluate", "--gan", str(tmp_path / "gan"), "--vae", str(tmp_path / "vae"), "--data",
            str(tmp_path / "data.h5"), "--evaluator", str(tmp_path / "ev"), "-o", str(tmp_path / "t")]
    out = CliRunner().invoke(main, args)
    assert out.exit_code == 0, out.output
    assert given["fid_reference"] == "separate"
    out = CliRunner().invoke(main, [*args, "--fid-reference", "same", "--force"])
    assert out.exit_code == 0, out.output
    assert given["fid_reference"] == "same" and json.loads((tmp_path / "t.json").read_text())["notes"] == ["note"]
    out = CliRunner().invoke(main, [*args, "--vae-only", "--fid-reference", "same"])
    assert out.exit_code == 2 and "text-to-motion table only" in out.output
